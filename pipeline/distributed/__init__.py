"""One body on many MPI processes: PETSc distributed matrices and SLEPc's eigensolver
(``modes.solver: slepc``).

Rank 0 meshes the body and evaluates what needs the whole mesh (regions, supports,
ports, materials); the free DOFs are split into parts of whole points (PT-Scotch, or
slabs along the body's longest extent: :mod:`~pipeline.distributed.partition`), rank 0
sends each rank its part of the mesh (:mod:`~pipeline.distributed.submesh`), each
rank assembles only the rows of K and M it owns (:mod:`~pipeline.distributed.assemble`,
from the elements that touch its nodes) and hands them to PETSc as an MPIAIJ matrix, and SLEPc's shift-invert
Krylov-Schur on MUMPS' distributed factor finds the modes
(:mod:`~pipeline.distributed.eigen`). No rank holds the whole K, M or factor, and no
rank but 0 the whole mesh.

The small quantities the reduce stage and the writer need are made collectively:
:class:`~pipeline.distributed.operators.RowMatrix` stands in for K and M (a product
with a replicated block gathers every rank's rows), the kept factor solves K x = F for
the static correction, and rank 0 writes the file with the one atomic writer.

petsc4py, slepc4py and mpi4py are imported only when this path runs (`make mpi-env`).
"""
