"""The finite-element stack: the only subpackage that imports gmsh, meshio and scikit-fem.

config -> mesh (gmsh or a mesh file) -> space (P1/P2 vector tetrahedra) -> regions and
supports -> assemble K, M (N/m, kg) -> body properties -> ports (F, T).
"""
