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
#: elements (edges) a chunk of :func:`edge_numbering`'s keys (of :func:`build_space`'s
#: midpoints): a chunk's keys and their temporaries are about 230 bytes an element, 1 MB
EDGE_CHUNK = 1 << 12


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
    """Create the vector Lagrange space of ``order`` on ``body``.

    Memory: what the space keeps (scikit-fem's mesh, for order 2 the nodes, the int64
    element nodes and the edges) plus, at the peak, the edge numbering's int64 keys and
    their sort permutation (96 bytes an element; :func:`_number_edges`); the element nodes
    and the midpoints are written in place a chunk at a time (:data:`EDGE_CHUNK` elements
    or edges)."""
    from skfem import MeshTet

    # int32 and C order are what MeshTet stores: no int64 copy in between
    mesh = MeshTet(body.vertices.T.copy(), np.ascontiguousarray(body.tetrahedra.T, np.int32),
                   validate=False, sort_t=False)
    if order == 1:
        return FESpace(mesh, 1, body.vertices, body.tetrahedra, np.zeros((0, 2), np.int64), body)
    n_v, n_t = body.n_vertices, body.n_tetrahedra
    if edge_numbering_matches_skfem():
        element_nodes = np.empty((n_t, 10), dtype=np.int64)
        element_nodes[:, :4] = body.tetrahedra
        edges = _number_edges(body.tetrahedra, n_v, element_nodes.reshape(-1), 10, 4, n_v)
    else:  # the nodes must be numbered as scikit-fem's basis numbers its DOFs
        log.warning("scikit-fem numbers edges differently from pipeline.fe.space."
                    "edge_numbering: using its own (slower) numbering")
        edges = mesh.edges.T.astype(np.int64)
        element_nodes = np.hstack([body.tetrahedra, n_v + mesh.t2e.T.astype(np.int64)])
    nodes = np.empty((n_v + edges.shape[0], 3))
    nodes[:n_v] = body.vertices
    for start in range(0, edges.shape[0], EDGE_CHUNK):
        pair = edges[start:start + EDGE_CHUNK]
        mid = nodes[n_v + start:n_v + start + pair.shape[0]]
        np.add(body.vertices[pair[:, 0]], body.vertices[pair[:, 1]], out=mid)
        mid *= 0.5
    return FESpace(mesh, 2, nodes, element_nodes, edges, body)


def sub_space(order: int, node_points: np.ndarray, element_nodes: np.ndarray,
              n_vertices: int) -> FESpace:
    """The space of a part of a mesh (one MPI rank's elements, :mod:`pipeline.distributed`).

    node_points (n, 3) m: the part's nodes, its ``n_vertices`` vertices first, then (order
    2) its edge midpoints; element_nodes (n_t, 4 | 10): local node indices, meshio order.
    It holds what the element kernels and the nodal recovery read (the corner vertices,
    the element nodes), no scikit-fem mesh and no edge table (nothing a region needs)."""
    body = BodyMesh(node_points[:n_vertices], element_nodes[:, :4])
    return FESpace(None, order, node_points, element_nodes, np.zeros((0, 2), np.int64), body)


def edge_numbering(tetrahedra: np.ndarray, n_vertices: int, chunk: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """skfem's edge numbering of a tetrahedral mesh, computed on integer keys.

    tetrahedra (n_t, 4) vertex indices. Returns (edges (n_e, 2), t2e (n_t, 6)), int64: the
    vertex pairs, smaller first, in lexicographic order, and each element's edge numbers
    in the local order ``TET_EDGES``; the same arrays as ``MeshTet.edges.T`` and
    ``MeshTet.t2e.T`` (:func:`_number_edges`, ``chunk`` elements at a time)."""
    t2e = np.empty((np.shape(tetrahedra)[0], 6), dtype=np.int64)
    edges = _number_edges(tetrahedra, n_vertices, t2e.reshape(-1), 6, 0, 0, chunk)
    return edges, t2e


def _number_edges(tetrahedra: np.ndarray, n_vertices: int, flat: np.ndarray, width: int,
                  column: int, offset: int, chunk: int | None = None) -> np.ndarray:
    """The edges (n_e, 2) int64 of :func:`edge_numbering`; the number of local edge j of
    element e, plus ``offset``, goes to ``flat[width * e + column + j]`` (``flat``: a
    C-ordered (n_t, width) int64 array's flat view, say the element nodes').

    Each element edge's key v0 * n_v + v1 (v0 < v1) goes into one int64 array; its sort
    permutation is taken, then the keys are sorted in place: their distinct values are the
    edges in lexicographic order, and the running count of distinct values, scattered back
    through the permutation, is each element edge's number. The peak is the keys and the
    permutation (96 bytes an element) and the distinct keys (8 bytes an edge); the keys
    are made and the numbers written ``chunk`` elements at a time (default
    :data:`EDGE_CHUNK`). ``np.unique(..., return_inverse=True)`` holds besides a sorted
    copy of the keys, the inverse and its scatter. Sorting integer keys is about ten
    times faster than skfem's ``np.unique(..., axis=1)``, which sorts the vertex pairs as
    rows (a test compares the two edge for edge)."""
    t = np.asarray(tetrahedra)
    n_t = t.shape[0]
    chunk = max(1, int(chunk or EDGE_CHUNK))
    keys = np.empty(6 * n_t, dtype=np.int64)
    for start in range(0, n_t, chunk):
        sel = t[start:start + chunk]
        keys[6 * start:6 * (start + sel.shape[0])] = _edge_keys(sel, n_vertices).ravel()
    order = np.argsort(keys)  # element edge order[i] = 6 e + j has the i-th smallest key
    keys.sort()
    first = np.empty(keys.size, dtype=bool)  # the first of each run of equal keys
    first[:1] = True
    np.not_equal(keys[1:], keys[:-1], out=first[1:])
    unique = keys[first]
    rank = np.cumsum(first, out=keys)  # 1 + the edge number of the i-th smallest key
    del first
    for start in range(0, rank.size, 6 * chunk):
        at = order[start:start + 6 * chunk]
        where = at + column
        if width != 6:
            where += (at // 6) * (width - 6)
        flat[where] = rank[start:start + at.size] + (offset - 1)
    del order, rank, keys
    edges = np.empty((unique.size, 2), dtype=np.int64)
    np.floor_divide(unique, n_vertices, out=edges[:, 0])
    np.remainder(unique, n_vertices, out=edges[:, 1])
    return edges


def _edge_keys(tetrahedra: np.ndarray, n_vertices: int) -> np.ndarray:
    """(n, 6) int64 keys v0 * n_vertices + v1 (v0 < v1) of the edges of ``tetrahedra``
    (n, 4), local order ``TET_EDGES``."""
    t = np.asarray(tetrahedra, dtype=np.int64)
    a, b = t[:, TET_EDGES[:, 0]], t[:, TET_EDGES[:, 1]]
    key = np.minimum(a, b)
    key *= n_vertices
    key += np.maximum(a, b)
    return key


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


#: region dimension -> (what it is made of, the unit of its measure)
REGION_KINDS = {2: ("face", "m^2"), 1: ("line", "m"), 0: ("point", "1")}


def region_dimension(cells: np.ndarray) -> int:
    """Dimension of a region given by its vertex ``cells`` (n, k): k = 3 triangles (2, a
    face), k = 2 edges (1, a line), k = 1 vertices (0, a point or node set)."""
    return int(np.asarray(cells).shape[1]) - 1


@dataclass(frozen=True)
class WeightedRegion:
    """A region (face, line or point set) as the FE space sees it.

    dimension: 2 face, 1 line, 0 point (node set).
    nodes: (n_r,) node indices on the region.
    weights: (n_r,) integral of each node's shape function over the region, in m^2 for a
        face, m for a line, 1 per node for a point set (sum = measure; a uniform load per
        unit measure t gives nodal forces weights * t).
    measure: area (m^2), length (m) or node count; centroid: (3,) m.
    """

    name: str
    dimension: int
    nodes: np.ndarray
    weights: np.ndarray
    measure: float
    centroid: np.ndarray


def boundary_triangles(space: FESpace) -> np.ndarray:
    """(n_bf, 3) vertex indices of the boundary facets of the mesh."""
    mesh = space.skfem_mesh
    return mesh.facets[:, mesh.boundary_facets()].T.astype(np.int64)


def boundary_edges(space: FESpace) -> np.ndarray:
    """(n_be, 2) vertex pairs (smaller first) of the edges of the boundary facets."""
    pairs = np.sort(boundary_triangles(space)[:, TRI_EDGES].reshape(-1, 2), axis=1)
    return np.unique(pairs, axis=0)


def weighted_region(space: FESpace, name: str, cells: np.ndarray) -> WeightedRegion:
    """Nodes and consistent weights of the region made of ``cells`` (n, 3 | 2 | 1).

    The weights are exact integrals of the Lagrange shape functions on straight cells:
    triangles (area A): A/3 per vertex for order 1, 0 per vertex and A/3 per edge midpoint
    for order 2; edges (length L): L/2 per vertex for order 1, L/6 per vertex and 2L/3 per
    midpoint for order 2; vertices: 1 each.
    """
    cells = np.asarray(cells, dtype=np.int64)
    dim = region_dimension(cells)
    what, unit = REGION_KINDS[dim]
    if cells.shape[0] == 0:
        raise RegionError(f"region '{name}': has no {what} cells; expected a non-empty region")
    v = space.body.vertices
    if dim == 0:
        nodes = np.unique(cells)
        return WeightedRegion(name, 0, nodes, np.ones(nodes.size), float(nodes.size),
                              v[nodes].mean(axis=0))
    if dim == 2:
        a, b, c = (v[cells[:, i]] for i in range(3))
        sizes = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        centres = (a + b + c) / 3.0
    else:
        a, b = v[cells[:, 0]], v[cells[:, 1]]
        sizes = np.linalg.norm(b - a, axis=1)
        centres = 0.5 * (a + b)
    measure = float(sizes.sum())
    if not measure > 0:
        raise RegionError(f"region '{name}': has zero {'area' if dim == 2 else 'length'}")
    centroid = (centres * sizes[:, None]).sum(axis=0) / measure
    if dim == 2:
        corner_w = np.zeros(0) if space.order == 2 else np.repeat(sizes / 3.0, 3)
        pairs = cells[:, TRI_EDGES].reshape(-1, 2)
        mid_w = np.repeat(sizes / 3.0, 3)
    else:
        corner_w = np.repeat(sizes / (6.0 if space.order == 2 else 2.0), 2)
        pairs = cells
        mid_w = 2.0 * sizes / 3.0
    parts, w = [], []
    if corner_w.size:
        parts.append(cells.ravel())
        w.append(corner_w)
    if space.order == 2:
        eid = _edge_ids(space, pairs)
        if (eid < 0).any():
            raise RegionError(f"region '{name}': has {what} cells whose edges are not edges of "
                              "the mesh")
        parts.append(space.body.n_vertices + eid)
        w.append(mid_w)
    nodes, inverse = np.unique(np.concatenate(parts), return_inverse=True)
    weights = np.bincount(inverse, weights=np.concatenate(w), minlength=nodes.size)
    return WeightedRegion(name, dim, nodes, weights, measure, centroid)


def region_nodes(space: FESpace, cells: np.ndarray) -> np.ndarray:
    """All node indices of a region of any dimension, given by its vertex ``cells``
    (n, 3 | 2 | 1): the vertices, and for order 2 the midpoints of the cells' edges (a
    line region's mid-edge nodes belong to it; a point region is its vertex nodes)."""
    cells = np.asarray(cells, dtype=np.int64)
    verts = np.unique(cells)
    dim = region_dimension(cells)
    if space.order == 1 or dim == 0:
        return verts
    pairs = cells[:, TRI_EDGES].reshape(-1, 2) if dim == 2 else cells
    eid = _edge_ids(space, pairs)
    return np.concatenate([verts, space.body.n_vertices + np.unique(eid[eid >= 0])])


def triangle_nodes(space: FESpace, triangles: np.ndarray) -> np.ndarray:
    """(n_f, 3 | 6) node indices of every triangle: its vertices, then (order 2) the
    nodes of its edges 01, 12, 02; -1 where an edge is not an edge of the mesh."""
    if space.order == 1:
        return np.asarray(triangles)
    eid = _edge_ids(space, triangles[:, TRI_EDGES].reshape(-1, 2)).reshape(-1, 3)
    return np.concatenate([triangles, np.where(eid >= 0, space.body.n_vertices + eid, -1)],
                          axis=1)
