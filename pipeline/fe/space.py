"""The finite-element space: nodes, degrees of freedom and region data of a mesh.

scikit-fem is the finite-element engine: its :class:`skfem.MeshTet` numbers the
edges, and the vector Lagrange elements ``ElementVector(ElementTetP1|P2)`` fix the
DOF order, which this module reproduces without building a global ``Basis`` (that
would hold every basis function at every quadrature point):

- nodes are the mesh vertices, then (order 2) the edge midpoints in skfem's edge order;
- DOF ``3 * node + c`` is displacement component ``c`` (0 = x, 1 = y, 2 = z) of ``node``;
- element nodes follow skfem's local order, which is also meshio's ``tetra10`` order
  (corners, then edges 01, 12, 02, 03, 13, 23).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.errors import RegionError
from pipeline.fe.mesh.common import BodyMesh

log = logging.getLogger(__name__)

# local edges of a tetrahedron in skfem's (and VTK's tetra10) order
TET_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
# local edges of a triangle
TRI_EDGES = np.array([[0, 1], [1, 2], [0, 2]])


@dataclass(frozen=True)
class FESpace:
    """Vector Lagrange space of ``order`` 1 or 2 on a tetrahedral mesh.

    skfem_mesh: the :class:`skfem.MeshTet` (vertices and edge numbering).
    node_points: (n_nodes, 3) m, vertices then edge midpoints.
    element_nodes: (n_t, 4 | 10) node indices per element, meshio order.
    edges: (n_e, 2) vertex pairs of the edges (order 2; empty for order 1).
    """

    skfem_mesh: Any
    order: int
    node_points: np.ndarray
    element_nodes: np.ndarray
    edges: np.ndarray
    body: BodyMesh

    @property
    def n_nodes(self) -> int:
        return int(self.node_points.shape[0])

    @property
    def n_dofs(self) -> int:
        return 3 * self.n_nodes

    @property
    def cell_type(self) -> str:
        return "tetra10" if self.order == 2 else "tetra"

    def skfem_element(self):
        from skfem import ElementTetP1, ElementTetP2, ElementVector

        return ElementVector(ElementTetP2() if self.order == 2 else ElementTetP1())


def build_space(body: BodyMesh, order: int) -> FESpace:
    """Create the vector Lagrange space of ``order`` on ``body``."""
    from skfem import MeshTet

    mesh = MeshTet(body.vertices.T.copy(), body.tetrahedra.T.copy(), validate=False,
                   sort_t=False)
    if order == 1:
        return FESpace(mesh, 1, body.vertices, body.tetrahedra, np.zeros((0, 2), np.int64), body)
    if edge_numbering_matches_skfem():
        edges, t2e = edge_numbering(body.tetrahedra, body.n_vertices)
    else:  # the nodes must be numbered as scikit-fem's basis numbers its DOFs
        log.warning("scikit-fem numbers edges differently from pipeline.fe.space."
                    "edge_numbering: using its own (slower) numbering")
        edges = mesh.edges.T.astype(np.int64)
        t2e = mesh.t2e.T.astype(np.int64)
    midpoints = 0.5 * (body.vertices[edges[:, 0]] + body.vertices[edges[:, 1]])
    nodes = np.vstack([body.vertices, midpoints])
    element_nodes = np.hstack([body.tetrahedra, body.n_vertices + t2e])
    return FESpace(mesh, 2, nodes, element_nodes, edges, body)


def edge_numbering(tetrahedra: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """skfem's edge numbering of a tetrahedral mesh, computed on integer keys.

    tetrahedra (n_t, 4) vertex indices. Returns (edges (n_e, 2), t2e (n_t, 6)): the
    vertex pairs, smaller first, in lexicographic order, and each element's edge numbers
    in the local order ``TET_EDGES``; the same arrays as ``MeshTet.edges.T`` and
    ``MeshTet.t2e.T``. One ``np.unique`` of the int64 keys v0 * n_v + v1 is about ten
    times faster than skfem's ``np.unique(..., axis=1)``, which sorts the vertex pairs as
    rows (a test compares the two edge for edge).
    """
    t = np.asarray(tetrahedra, dtype=np.int64)
    a, b = t[:, TET_EDGES[:, 0]], t[:, TET_EDGES[:, 1]]  # (n_t, 6)
    key = np.minimum(a, b) * n_vertices + np.maximum(a, b)
    unique, t2e = np.unique(key.ravel(), return_inverse=True)
    edges = np.stack([unique // n_vertices, unique % n_vertices], axis=1)
    return edges, t2e.reshape(t.shape[0], 6).astype(np.int64, copy=False)


@functools.lru_cache(maxsize=1)
def edge_numbering_matches_skfem() -> bool:
    """Whether :func:`edge_numbering` gives the installed scikit-fem's ``MeshTet.edges``
    and ``MeshTet.t2e`` (its public arrays) on a small mesh whose tetrahedra list their
    vertices in shuffled orders; checked once per process. :func:`build_space` uses
    scikit-fem's arrays where it does not, so that a release that numbers edges another way
    costs time, not a wrong numbering."""
    from skfem import MeshTet

    base = MeshTet().refined(1)
    t = base.t.T.copy()
    rng = np.random.default_rng(0)
    for row in t:
        rng.shuffle(row)  # unsorted vertex order, as a mesh file gives them
    mesh = MeshTet(base.p, t.T.copy(), validate=False, sort_t=False)
    edges, t2e = edge_numbering(t, base.p.shape[1])
    return bool(np.array_equal(edges, mesh.edges.T) and np.array_equal(t2e, mesh.t2e.T))


def _edge_ids(space: FESpace, pairs: np.ndarray) -> np.ndarray:
    """Edge numbers of vertex ``pairs`` (n, 2); -1 where no such edge exists."""
    n_v = space.body.n_vertices
    key = np.sort(space.edges, axis=1) @ np.array([n_v, 1], dtype=np.int64)
    order = np.argsort(key)
    sorted_keys = key[order]
    q = np.sort(pairs, axis=1) @ np.array([n_v, 1], dtype=np.int64)
    pos = np.searchsorted(sorted_keys, q).clip(max=len(sorted_keys) - 1)
    found = sorted_keys[pos] == q
    return np.where(found, order[pos], -1)


@dataclass(frozen=True)
class SurfaceRegion:
    """A boundary region as the FE space sees it.

    nodes: (n_r,) node indices on the region.
    weights: (n_r,) m^2, integral of each node's shape function over the region
        (sum = area; a uniform traction t gives nodal forces weights * t).
    area: m^2; centroid: (3,) m.
    """

    name: str
    nodes: np.ndarray
    weights: np.ndarray
    area: float
    centroid: np.ndarray


def boundary_triangles(space: FESpace) -> np.ndarray:
    """(n_bf, 3) vertex indices of the boundary facets of the mesh."""
    mesh = space.skfem_mesh
    return mesh.facets[:, mesh.boundary_facets()].T.astype(np.int64)


def surface_region(space: FESpace, name: str, triangles: np.ndarray) -> SurfaceRegion:
    """Nodes and consistent area weights of the region made of ``triangles`` (n_f, 3).

    The weights are exact integrals of the Lagrange shape functions on straight
    triangles: area/3 per vertex for order 1; 0 per vertex and area/3 per edge midpoint
    for order 2.
    """
    if triangles.shape[0] == 0:
        raise RegionError(f"region '{name}': has no boundary facets; expected a non-empty surface")
    v = space.body.vertices
    a, b, c = (v[triangles[:, i]] for i in range(3))
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    area = float(areas.sum())
    if not area > 0:
        raise RegionError(f"region '{name}': has zero area")
    centroid = ((a + b + c) / 3.0 * areas[:, None]).sum(axis=0) / area
    if space.order == 1:
        nodes_per_tri = triangles
    else:
        pairs = triangles[:, TRI_EDGES].reshape(-1, 2)
        eid = _edge_ids(space, pairs)
        if (eid < 0).any():
            raise RegionError(f"region '{name}': has triangles that are not faces of the mesh")
        nodes_per_tri = space.body.n_vertices + eid.reshape(-1, 3)
    w = np.repeat(areas / 3.0, 3)
    nodes, inverse = np.unique(nodes_per_tri.ravel(), return_inverse=True)
    weights = np.bincount(inverse, weights=w, minlength=nodes.size)
    return SurfaceRegion(name, nodes, weights, area, centroid)


def region_nodes(space: FESpace, triangles: np.ndarray) -> np.ndarray:
    """All node indices touching ``triangles`` (vertices, and edge midpoints for order 2)."""
    verts = np.unique(triangles)
    if space.order == 1:
        return verts
    eid = _edge_ids(space, triangles[:, TRI_EDGES].reshape(-1, 2))
    return np.concatenate([verts, space.body.n_vertices + np.unique(eid[eid >= 0])])


def triangle_nodes(space: FESpace, triangles: np.ndarray) -> np.ndarray:
    """(n_f, 3 | 6) node indices of every triangle: its vertices, then (order 2) the
    nodes of its edges 01, 12, 02; -1 where an edge is not an edge of the mesh."""
    if space.order == 1:
        return np.asarray(triangles)
    eid = _edge_ids(space, triangles[:, TRI_EDGES].reshape(-1, 2)).reshape(-1, 3)
    return np.concatenate([triangles, np.where(eid >= 0, space.body.n_vertices + eid, -1)],
                          axis=1)
