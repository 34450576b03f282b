"""Each rank's part of the mesh: rank 0 meshes the body, every rank gets only its elements.

Rank 0 holds the whole mesh until the parts are sent (then only the points and the
elements it writes to the file, :func:`compact_nodes`) and evaluates once what needs
the whole of it: regions, supports, ports, materials, added masses and the partition
of the free DOFs into the ranks' rows (:class:`~pipeline.distributed.partition.RowPartition`).
Then it cuts out the part of rank r (:func:`split_mesh`):

    P_r = {points p : r owns the PETSc rows of p's free DOFs}
    E_r = {elements e : e has a node in P_r, or r sums e's node mass (below)}
    N_r = the nodes of E_r, ascending (vertices first: every global vertex number is
          below every edge-midpoint number), local node i = global node N_r[i]

and sends r its :class:`RankMesh`: the coordinates of N_r, the elements of E_r renumbered
to local nodes, their materials, the PETSc row of every local DOF, the whole mesh's
element volume around each local node (the nodal recovery's denominator), the elements
whose node mass r sums (each element exactly once: owned by the lowest rank owning one
of its points; elements with no free point by rank 0), r's rows of the added mass and
r's rows of the elastic supports' stiffness (springs, bushings).
A rank assembles its rows of K and M from E_r with the serial kernels, in the element
order of the whole mesh, so its rows are those of the whole-mesh assembly bit for bit.

Memory per rank: O(|N_r| + |E_r|), its part plus one element layer, instead of the whole
mesh. What stays O(n_points) on every rank is listed in docs/distributed.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np
import scipy.sparse as sp

from pipeline.distributed.partition import RowPartition
from pipeline.fe.materials import ElementMaterials
from pipeline.fe.space import FESpace, sub_space
from pipeline.fe.strain import node_volumes


@dataclass(frozen=True)
class RankMesh:
    """One rank's part of the mesh (see the module).

    space: the FE space of the part (local node numbers). points: (n_loc,) the global
    node of each local node, ascending. dof_rows: (3 n_loc,) PETSc row of each local DOF
    (3 i + c), -1 for a fixed one. lo, hi: the PETSc rows this rank owns; n_free: all
    rows. node_volume: (n_loc,) m^3, the whole mesh's element volume around each local
    node. mass_elements: local indices of the elements whose node mass this rank sums.
    materials: the laws of the local elements. added: (hi - lo, n_free) CSR, kg, this
    rank's rows of the point and area masses (PETSc's column numbers), or None.
    springs: (hi - lo, n_free) CSR, N/m, this rank's rows of the springs and bushings
    (:func:`pipeline.fe.supports.support_stiffness`, PETSc's column numbers), or None.
    """

    space: FESpace
    points: np.ndarray
    dof_rows: np.ndarray
    lo: int
    hi: int
    n_free: int
    node_volume: np.ndarray
    mass_elements: np.ndarray
    materials: ElementMaterials
    added: sp.csr_matrix | None = None
    springs: sp.csr_matrix | None = None

    @property
    def owned_nodes(self) -> np.ndarray:
        """(n_loc,) bool: the local nodes with a DOF among this rank's rows."""
        rows = self.dof_rows.reshape(-1, 3)
        return ((rows >= self.lo) & (rows < self.hi)).any(axis=1)

    def local_nodes(self, global_nodes: np.ndarray) -> np.ndarray:
        """Local numbers of ``global_nodes`` (all of them in this part)."""
        return np.searchsorted(self.points, global_nodes)


@dataclass(frozen=True)
class MeshCounts:
    """The whole mesh's counts, on every rank."""

    n_tetrahedra: int
    n_vertices: int


@dataclass(frozen=True)
class DistributedSpace:
    """The FE space as the stages after the FE stage see it on a rank of the distributed
    path: the whole mesh's counts on every rank, its points and elements (the file's
    ``/mesh``) on rank 0 only ((0, 3) and (0, nb) elsewhere; the elements in the
    narrowest integer type that holds every node number, :func:`compact_nodes`: the
    writer stores them as int64), this rank's part (``local``), the port matrices rank 0
    made (None: no reduction) and (rank 0) the body's
    :class:`~pipeline.solve.labels.LabelFrame` of the mode labels (a few numbers a
    slice, made from every point before the whole FE space is dropped); a rotating
    body's added masses (rank 0's
    :func:`pipeline.distributed.prestress.rotation_masses`, on every rank) or None."""

    order: int
    n_nodes: int
    body: MeshCounts
    node_points: np.ndarray
    element_nodes: np.ndarray
    local: RankMesh
    ports: Any = None
    label_frame: Any = None
    rotation_masses: Any = None
    #: the interfaces of a connection model, parent first
    #: (:mod:`pipeline.distributed.connection`), or None
    connections: Any = None
    #: the unsupported body's part when the connection model's clamped pencil is not the
    #: run's (:class:`~pipeline.distributed.unsupported.Unsupported`), or None
    unsupported: Any = None

    @property
    def n_dofs(self) -> int:
        return 3 * self.n_nodes

    @property
    def cell_type(self) -> str:
        return self.local.space.cell_type  # the part's elements are the mesh's kind


def compact_nodes(element_nodes: np.ndarray, n_nodes: int) -> np.ndarray:
    """``element_nodes`` (n_el, nb) as int32 where every node number below ``n_nodes``
    fits (a copy: 4 bytes an entry instead of 8), else unchanged. Rank 0 keeps the whole
    mesh's elements this way from the hand-off to the writer, which widens them back
    (the same int64 values)."""
    if n_nodes <= np.iinfo(np.int32).max and element_nodes.dtype != np.int32:
        return element_nodes.astype(np.int32)
    return element_nodes


def petsc_numbering(n_dofs: int, part: RowPartition, dtype=np.int64) -> np.ndarray:
    """(n_dofs,) PETSc row of every DOF, -1 for a fixed one (``part``: the whole
    partition), as ``dtype`` (a signed integer type that holds n_free - 1)."""
    rows = np.full(n_dofs, -1, dtype=dtype)
    rows[part.dofs] = np.arange(part.n_free, dtype=dtype)
    return rows


def point_ranks(n_nodes: int, part: RowPartition, size: int, dtype=np.int64) -> np.ndarray:
    """(n_nodes,) the rank owning each point's free DOFs, ``size`` for a point without
    (``part``: the whole partition; a point whose DOFs several ranks own: the highest of
    them), as ``dtype`` (an integer type that holds ``size``)."""
    owner = np.full(n_nodes, size, dtype=dtype)
    for r in range(size):
        owner[part.owned_dofs(r) // 3] = r
    return owner


def _narrowest(largest: int) -> type:
    """The narrowest signed integer type that holds -1 and ``largest``."""
    for dtype in (np.int8, np.int16, np.int32):
        if largest <= np.iinfo(dtype).max:
            return dtype
    return np.int64


#: elements whose nodes' owners :func:`split_mesh` compares at a time: (chunk, nb) owner
#: ranks (1 byte each up to 127 ranks) and the comparison's booleans, 1.3 MB of quadratic
#: elements, with the node numbers of the elements compared per part (8 bytes each) 6.5 MB
SPLIT_CHUNK = 1 << 16


def element_owner_span(element_nodes: np.ndarray, owner: np.ndarray, size: int,
                       chunk: int = SPLIT_CHUNK) -> tuple[np.ndarray, np.ndarray]:
    """(lowest, highest) (n_el,) each, ``owner``'s dtype: the lowest and the highest rank
    owning a node of each element (``owner`` (n_nodes,) from :func:`point_ranks`, ``size``
    for a node without a free DOF); an element without such a node has lowest ``size`` and
    highest -1. Made ``chunk`` elements at a time."""
    n_el = element_nodes.shape[0]
    lowest = np.empty(n_el, dtype=owner.dtype)
    highest = np.empty(n_el, dtype=owner.dtype)
    for start in range(0, n_el, chunk):
        ranks = owner[element_nodes[start:start + chunk]]  # (chunk, nb)
        ranks.min(axis=1, out=lowest[start:start + ranks.shape[0]])
        ranks[ranks == size] = -1  # no owner: below every rank
        ranks.max(axis=1, out=highest[start:start + ranks.shape[0]])
    return lowest, highest


def split_mesh(space: FESpace, materials: ElementMaterials, free: np.ndarray,
               part: RowPartition, size: int, added: sp.spmatrix | None = None,
               springs: sp.spmatrix | None = None) -> Iterator[RankMesh]:
    """The :class:`RankMesh` of every rank in rank order (the module), from the whole
    ``space`` with its element ``materials``, the sorted ``free`` DOFs, the partition,
    the (n_dofs, n_dofs) added masses (kg) or None and the (n_dofs, n_dofs) spring
    stiffness (N/m) or None. One part is made at a time; the generator keeps no
    reference to a part once it has yielded it.

    Scratch beside the parts (n_el elements of nb nodes, n_nodes points, n_dofs DOFs;
    ``tests/test_submesh_split.py`` bounds it): the whole mesh's volume around each node
    (8 bytes a point), the PETSc row of every DOF (4 bytes a DOF below 2^31 rows), each
    point's rank and each element's lowest and highest rank (1 byte each up to 127
    ranks), the indices of the elements with a rank strictly between (8 bytes each: few
    on slabs), a local-number table and a marker over the points (4 and 1 bytes a
    point), and per part two boolean masks over the elements and the part's element
    indices (8 bytes each). An element is in part r if its lowest or highest rank is r; only an
    element with a rank strictly between (a node owned by neither end) has its nodes
    compared with r, :data:`SPLIT_CHUNK` elements at a time. The part's points are the
    marked ones, ascending, and its local element nodes the table's numbers of them:
    the same arrays as ``np.unique(..., return_inverse=True)``'s, without its sorted
    copy and permutation of the part's element nodes."""
    n_free = int(np.asarray(free).size)
    en = space.element_nodes
    n_nodes = space.n_nodes
    node_volume = node_volumes(space)  # before the rest: its chunks' scratch comes first
    owner = point_ranks(n_nodes, part, size, _narrowest(size))
    lowest, highest = element_owner_span(en, owner, size)
    # between the two ends: the only elements whose other nodes' ranks are unknown
    between = np.flatnonzero(highest.astype(np.int32) - lowest > 1)
    element_rank = lowest  # the mass-summing rank: the lowest, rank 0 with no free point
    element_rank[element_rank == size] = 0
    rows = petsc_numbering(space.n_dofs, part, _narrowest(n_free))
    local_of = np.empty(n_nodes, dtype=_narrowest(n_nodes))  # valid at the marked points
    marked = np.zeros(n_nodes, dtype=bool)
    added = None if added is None else sp.csr_matrix(added)
    springs = None if springs is None else sp.csr_matrix(springs)
    for r in range(size):
        member = element_rank == r
        member |= highest == r
        inner = between[(element_rank[between] < r) & (highest[between] > r)]
        for start in range(0, inner.size, SPLIT_CHUNK):
            some = inner[start:start + SPLIT_CHUNK]
            member[some[(owner[en[some]] == r).any(axis=1)]] = True
        del inner
        elements = np.flatnonzero(member)
        del member
        local = en[elements]  # global node numbers, renumbered in place below
        marked[local.ravel()] = True
        points = np.flatnonzero(marked).astype(en.dtype, copy=False)
        marked[points] = False
        local_of[points] = np.arange(points.size, dtype=local_of.dtype)
        for start in range(0, local.shape[0], SPLIT_CHUNK):
            block = local[start:start + SPLIT_CHUNK]
            block[...] = local_of[block]
        n_vertices = int(np.searchsorted(points, space.body.n_vertices))
        lo, hi = part.rows(r)
        owned = part.owned_dofs(r)
        mesh = RankMesh(
            space=sub_space(space.order, space.node_points[points], local, n_vertices),
            points=points,
            dof_rows=rows.reshape(-1, 3)[points].ravel().astype(np.int64, copy=False),
            lo=lo, hi=hi, n_free=n_free, node_volume=node_volume[points],
            mass_elements=np.flatnonzero(element_rank[elements] == r),
            materials=ElementMaterials(materials.names, materials.D, materials.law_rho,
                                       materials.index[elements], materials.rho[elements],
                                       materials.uniform),
            added=None if added is None else owned_rows(added, owned, rows, n_free),
            springs=None if springs is None else owned_rows(springs, owned, rows, n_free))
        del elements, local, points, owned
        yield mesh
        del mesh


def owned_rows(A: sp.csr_matrix, owned: np.ndarray, rows: np.ndarray,
               n_free: int) -> sp.csr_matrix:
    """(len(owned), n_free) CSR: the rows ``owned`` (global DOFs, in PETSc row order)
    of the (n_dofs, n_dofs) CSR ``A``, its columns renumbered to PETSc's (``rows``: the
    PETSc row of every DOF, -1 for a fixed one, whose columns are dropped); each row's
    columns ascending, duplicates summed (the canonical form). Made from the CSR slice
    of the rows, without a COO copy of it."""
    B = A[owned]
    cols = rows[B.indices]
    keep = cols >= 0
    kept = np.zeros(keep.size + 1, dtype=np.int64)  # kept entries before each entry
    np.cumsum(keep, out=kept[1:])
    indptr = kept[B.indptr]
    out = sp.csr_matrix((B.data[keep], cols[keep], indptr), shape=(owned.size, n_free))
    out.sum_duplicates()
    return out


def scatter_parts(comm, parts: Iterator[RankMesh] | None) -> RankMesh:
    """This rank's part: rank 0 sends part r to rank r as it makes it (``parts``: the
    iterator of :func:`split_mesh` on rank 0, None elsewhere) and keeps part 0. No name
    holds a sent part while the next is made (``enumerate``'s reused result tuple would:
    one part more at rank 0's peak)."""
    if comm.rank != 0:
        return comm.recv(source=0, tag=38)
    parts = iter(parts)
    mine = next(parts)
    for r in range(1, comm.size):
        comm.send(next(parts), dest=r, tag=38)
    return mine
