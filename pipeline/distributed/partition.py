"""Row partition of the free DOFs over the ranks: contiguous slabs along the body's
longest extent, or the parts of a graph partitioner (PT-Scotch through PETSc's
MatPartitioning, :func:`graph_partition`).

The free DOFs are renumbered for PETSc: sorted by the coordinate of their mesh point
along the longest extent (stable, so a point's three DOFs stay together and in order),
then split into ``size`` ranges of (nearly) equal length. Rank r owns PETSc rows
``starts[r]:starts[r + 1]``; ``order[i]`` is the free-DOF index of PETSc row i. A slab
touches at most two neighbours, so the off-rank columns of a rank's rows are the
nodes of one element layer per neighbour; on a compact body the slab interfaces are
whole cross-sections, where a graph partitioner cuts less (:func:`graph_partition`).

>>> import numpy as np
>>> points = np.array([[3.0, 0, 0], [0.0, 0, 0], [2.0, 0, 0], [1.0, 0, 0]])
>>> part = slab_partition(points, np.arange(12), 2)
>>> part.order.tolist()
[3, 4, 5, 9, 10, 11, 6, 7, 8, 0, 1, 2]
>>> part.starts.tolist()
[0, 6, 12]
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class RowPartition:
    """The PETSc rows of each rank: ``starts`` (size + 1,) the first row of each rank
    (starts[-1] = n_free); ``order`` the free-DOF index (serial order) of each row and
    ``dofs`` the DOF (3 p + c of point p) of each row, or None where the rows are not
    DOFs (a constraint's coordinates). The whole partition (``rank`` None) holds every
    row's, (n_free,) each, as rank 0 makes it; a rank's own partition
    (:meth:`local`, ``rank`` its number) holds only its rows' (hi - lo,), which is what
    every rank keeps (16 bytes a row of its own); :meth:`whole` gathers the rest where
    a step needs every row's (collective)."""

    order: np.ndarray
    starts: np.ndarray
    dofs: np.ndarray | None = None
    rank: int | None = None

    @property
    def n_free(self) -> int:
        """Rows over all ranks (free DOFs)."""
        return int(self.starts[-1])

    def rows(self, rank: int) -> tuple[int, int]:
        """[lo, hi): the PETSc rows rank ``rank`` owns."""
        return int(self.starts[rank]), int(self.starts[rank + 1])

    def _own(self, values: np.ndarray | None, rank: int) -> np.ndarray | None:
        if self.rank is None:
            lo, hi = self.rows(rank)
            return None if values is None else values[lo:hi]
        if rank != self.rank:
            raise ValueError(f"the partition of rank {self.rank} holds its own rows only, "
                             f"not rank {rank}'s")
        return values

    def owned_free(self, rank: int) -> np.ndarray:
        """Free-DOF indices of the rows rank ``rank`` owns, in PETSc order."""
        return self._own(self.order, rank)

    def owned_dofs(self, rank: int) -> np.ndarray:
        """The DOF (3 p + c) of each row rank ``rank`` owns, in PETSc order."""
        if self.dofs is None:
            raise ValueError("the rows of this partition are not DOFs")
        return self._own(self.dofs, rank)

    def local(self, rank: int) -> "RowPartition":
        """Rank ``rank``'s own partition: its rows' order and DOFs only."""
        return RowPartition(self.owned_free(rank), self.starts,
                            None if self.dofs is None else self.owned_dofs(rank), rank)

    def whole(self, comm, root: int | None = None) -> "RowPartition | None":
        """The whole partition: itself if whole; else gathered from every rank's own rows
        (collective), on every rank (``root`` None: O(n_free) on each for as long as the
        caller keeps it) or on ``root`` only (None elsewhere)."""
        if self.rank is None:
            return self if root is None or comm.rank == root else None
        if root is None:
            parts = [comm.allgather(self.order), comm.allgather(self.dofs)]
        else:
            parts = [comm.gather(self.order, root=root), comm.gather(self.dofs, root=root)]
            if comm.rank != root:
                return None
        order, dofs = parts
        return RowPartition(np.concatenate(order), self.starts,
                            None if self.dofs is None else np.concatenate(dofs))

    def free_dofs(self) -> np.ndarray:
        """(n_free,) the free DOFs, ascending (the serial ``free``), of a whole partition."""
        if self.rank is not None or self.dofs is None:
            raise ValueError("free_dofs needs the whole partition of DOF rows")
        free = np.empty_like(self.dofs)
        free[self.order] = self.dofs
        return free


@dataclass(frozen=True)
class FreeDofs:
    """The free DOFs as a rank of the distributed path holds them: their count only
    (``size``, as the serial path's (n_free,) array has), nothing per DOF. The DOFs of
    a rank's own rows are its partition's (:meth:`RowPartition.owned_dofs`); a step that
    needs every free DOF gathers them (:meth:`RowPartition.whole`, collective)."""

    size: int

    def __array__(self, *args, **kwargs):
        raise TypeError("the free DOFs are not held on every rank: use the partition's own "
                        "rows (RowPartition.owned_dofs) or RowPartition.whole(comm)")


def slab_partition(node_points: np.ndarray, free: np.ndarray, size: int) -> RowPartition:
    """The slab partition of the sorted ``free`` DOFs (DOF 3 p + c of point p) of a body
    with (n_points, 3) ``node_points`` over ``size`` ranks."""
    points = np.asarray(node_points, dtype=float)
    axis = int(np.argmax(np.ptp(points, axis=0))) if points.shape[0] else 0
    key = points[np.asarray(free) // 3, axis]
    order = np.argsort(key, kind="stable").astype(np.int64)
    n = order.size
    free = np.asarray(free)
    # whole points (every point's three DOFs free) stay on one rank: K and M then go to
    # PETSc with block size 3 (pipeline.distributed.eigen.petsc_matrix)
    step = 3 if n % 3 == 0 and np.array_equal(free[order] % 3, np.tile(np.arange(3), n // 3)) \
        else 1
    starts = np.array([step * (((n // step) * r) // size) for r in range(size + 1)],
                      dtype=np.int64)
    return RowPartition(order=order, starts=starts, dofs=free[order])


def graph_partition(PETSc, comm, element_nodes: np.ndarray | None,
                    node_points: np.ndarray | None, free: np.ndarray | None,
                    kind: str = "ptscotch", parts: int | None = None) -> RowPartition:
    """A partition of whole points by PETSc's MatPartitioning (``kind``: ``ptscotch``;
    Debian's PETSc has no ParMETIS), collectively. Only rank 0 needs the mesh (the others
    may pass None): it builds the graph rows of each rank's slab (the initial
    distribution) and sends them, the other ranks' first, so that only its own slab's
    rows are alive when its part of PETSc's graph is made; PETSc moves the graph's
    vertices to ``parts`` parts of nearly equal weight with few cut edges, rank 0 gathers
    each vertex's part and makes the partition (the whole one, on rank 0; None
    elsewhere: each rank receives its own, :meth:`RowPartition.local`). Within a part
    the rows keep the slab order, a point's DOFs together; rank r owns part r.

    The graph: for quadratic elements the mesh vertices, adjacent along the mesh's
    edges, each weighted by the free DOFs at home there (its own and its edges'
    midpoints', :func:`vertex_graph_rows`), about 14 times fewer entries than the point
    graph; for linear elements, or where PETSc's vertex weights cannot be set
    (:func:`_petsc_weight_calls`), the point graph (two points adjacent when an element
    holds both, :func:`slab_graph_rows`), every point weighing the same; the PETSc
    option ``-pipeline_partition_graph points`` asks for the point graph always.

    ``comm``: COMM_WORLD's mpi4py communicator (:func:`pipeline.distributed.mpi.world`)
    or, on one process, COMM_SELF's (PETSc's objects live on the matching PETSc
    communicator); ``parts``: the number of parts, ``comm.size`` (None) or, on one
    process, any count (the partition a later run on ``parts`` ranks reads, ``python -m
    pipeline partition``): PETSc's option ``mat_partitioning_nparts`` is set then under
    this call's own options prefix (:data:`NPARTS_PREFIX`, so that no option of the host
    process changes and the host's ``-mat_partitioning_*`` options do not apply) and
    removed after."""
    size, rank = comm.size, comm.rank
    n_parts = size if parts is None else int(parts)
    if n_parts != size and size != 1:
        raise ValueError(f"{n_parts} parts on {size} processes: expected {size}, or any "
                         "count on one process")
    graph = PETSc.Options().getString("pipeline_partition_graph", "vertices")
    if graph not in ("vertices", "points"):
        raise ConfigError(f"PETSc option -pipeline_partition_graph: {graph!r}; expected "
                          "vertices or points", key="-pipeline_partition_graph",
                          value=graph, expected="vertices or points")
    quadratic = comm.bcast(None if rank else element_nodes.shape[1] == 10, root=0)
    weighted = graph == "vertices" and bool(quadratic) and \
        all(comm.allgather(_petsc_weight_calls() is not None))
    home = None
    if rank == 0:
        if weighted:
            home, vertex, vorder, rows = vertex_graph_rows(element_nodes, node_points, free,
                                                           size)
        else:
            vertex, vorder, rows = slab_graph_rows(element_nodes, node_points, free, size)
        for r in range(1, size):
            comm.send(rows(r), dest=r, tag=39)
        mine = rows(0)
        del rows  # the incidence or the edges it reads
    else:
        mine = comm.recv(source=0, tag=39)
    indptr, indices = mine[0], mine[1]
    weights = mine[2] if weighted else None
    del mine
    n_rows, n_v = indptr.size - 1, comm.allreduce(indptr.size - 1)
    # PETSc's objects on COMM_WORLD (every rank of the run) or, on one process, COMM_SELF
    pcomm = PETSc.COMM_SELF if size == 1 else PETSc.COMM_WORLD
    # every edge weighs 1 (PT-Scotch reads the values only with
    # -mat_partitioning_use_edge_weights); PETSc copies the arrays
    G = PETSc.Mat().createAIJ(size=((n_rows, n_v), (n_rows, n_v)),
                              csr=(np.asarray(indptr, dtype=PETSc.IntType),
                                   np.asarray(indices, dtype=PETSc.IntType),
                                   np.ones(indices.size)),
                              comm=pcomm)
    del indptr, indices
    G.assemble()
    mp = PETSc.MatPartitioning().create(comm=pcomm)
    mp.setType(kind)
    mp.setAdjacency(G)
    if weighted:
        set_weights(PETSc, mp, weights)
    options = PETSc.Options()
    if n_parts != size:
        mp.setOptionsPrefix(NPARTS_PREFIX)
        options.setValue(f"{NPARTS_PREFIX}mat_partitioning_nparts", n_parts)
    try:
        mp.setFromOptions()  # -mat_partitioning_* options override (without the prefix)
    finally:
        if n_parts != size:
            options.delValue(f"{NPARTS_PREFIX}mat_partitioning_nparts")
    owned = PETSc.IS()
    mp.apply(owned)
    owner = comm.gather(np.asarray(owned.getIndices(), dtype=np.int64), root=0)
    for obj in (owned, mp, G):
        obj.destroy()
    part = None
    if rank == 0:
        owner = np.concatenate(owner)
        free = np.asarray(free)
        points = free // 3
        v_of_dof = vertex[points if home is None else home[points]]
        del points
        order = np.lexsort((np.arange(free.size), v_of_dof, owner[v_of_dof])).astype(np.int64)
        counts = np.bincount(owner[v_of_dof], minlength=n_parts)
        part = RowPartition(order=order, starts=np.concatenate([[0], np.cumsum(counts)]),
                            dofs=free[order])
    return part


#: the options prefix of a partition into another count of parts than processes
#: (:func:`graph_partition`)
NPARTS_PREFIX = "pipeline_parts_"


#: element-node pairs whose rows :func:`slab_graph_rows` makes at a time: the chunk's
#: product rows (about 0.4 entries a pair, 30 bytes each with their keys and sort) and
#: the pairs themselves (5 bytes each), about 8 MB whatever the mesh
GRAPH_CHUNK_PAIRS = 1 << 19


def point_elements(element_nodes: np.ndarray, n_points: int):
    """(the (n_el, n_points) element-node incidence, CSR of bool with int32 indices; the
    elements of every point: (indptr (n_points + 1,), elements (n_el nb,) int32), point
    p's ascending in ``elements[indptr[p]:indptr[p + 1]]``), 5 and 4 bytes a node of an
    element."""
    import scipy.sparse as sp

    n_el, nb = element_nodes.shape
    incidence = sp.csr_matrix((np.ones(n_el * nb, dtype=bool), element_nodes.ravel(),
                               np.arange(0, n_el * nb + 1, nb)), shape=(n_el, n_points))
    by_point = incidence.tocsc()  # each column's rows (elements) ascending
    return incidence, (by_point.indptr, by_point.indices)


def slab_graph_rows(element_nodes: np.ndarray, node_points: np.ndarray, free: np.ndarray,
                    size: int, chunk_pairs: int = GRAPH_CHUNK_PAIRS):
    """The point graph's rows by slabs: (vertex (n_points,) int32, the graph vertex of
    each point, -1 without a free DOF; vorder (n_v,), the point of each vertex, sorted
    along the longest extent; ``rows(r)``: slab r's rows, (indptr (n_r + 1,) int64,
    indices int32), each vertex's adjacent vertices ascending, no self loops).

    Vertices v and w are adjacent when an element holds both their points. A slab's rows
    are made a chunk of its points at a time, about ``chunk_pairs`` element-node pairs
    (the incidence's rows of the chunk's points' elements times the incidence, a
    boolean sparse product, its columns mapped to vertices and sorted as int64 keys
    row n_v + column), so that the transient arrays stay bounded by the chunk; between
    calls ``rows`` holds the incidence both ways (:func:`point_elements`, 9 bytes a
    node of an element) and the two maps."""
    import scipy.sparse as sp

    free = np.asarray(free)
    points = np.asarray(node_points, dtype=float)
    axis = int(np.argmax(np.ptp(points, axis=0))) if points.shape[0] else 0
    up = np.unique(free // 3)  # the points with a free DOF: the graph's vertices
    vorder = up[np.argsort(points[up, axis], kind="stable")]  # vertex v is point vorder[v]
    del up
    n_v = vorder.size
    vertex = np.full(points.shape[0], -1, dtype=np.int32)
    vertex[vorder] = np.arange(n_v, dtype=np.int32)
    vs = [(n_v * r) // size for r in range(size + 1)]
    incidence, (ptr, elements) = point_elements(element_nodes, points.shape[0])
    pairs = np.diff(ptr) * element_nodes.shape[1]  # element-node pairs of each point

    def rows(r: int) -> tuple[np.ndarray, np.ndarray]:
        mine = vorder[vs[r]:vs[r + 1]]
        ends = np.cumsum(pairs[mine])
        counts, pieces = [], []
        a = 0
        while a < mine.size:
            done = ends[a - 1] if a else 0
            b = max(a + 1, int(np.searchsorted(ends, done + chunk_pairs, side="right")))
            lo = ptr[mine[a:b]]
            n_e = ptr[mine[a:b] + 1] - lo  # each point's elements
            at = np.arange(int(n_e.sum())) + np.repeat(lo - (np.cumsum(n_e) - n_e), n_e)
            chunk = sp.csr_matrix((np.ones(at.size, dtype=bool), elements[at],
                                   np.concatenate([[0], np.cumsum(n_e)])),
                                  shape=(b - a, incidence.shape[0]))
            del at
            shared = chunk @ incidence  # (chunk, n_points): the points sharing an element
            del chunk
            row = np.repeat(np.arange(b - a, dtype=np.int64), np.diff(shared.indptr))
            cols = vertex[shared.indices]
            del shared
            keep = (cols >= 0) & (cols != vs[r] + a + row)  # free points, no self loops
            key = (row * n_v + cols)[keep]
            del row, cols, keep
            key.sort()  # row-major, each row's vertices ascending
            row = key // n_v
            pieces.append((key - row * n_v).astype(np.int32))
            counts.append(np.bincount(row, minlength=b - a))
            a = b
        indptr = np.zeros(mine.size + 1, dtype=np.int64)
        if counts:
            np.cumsum(np.concatenate(counts), out=indptr[1:])
        return indptr, (np.concatenate(pieces) if pieces else np.zeros(0, np.int32))

    return vertex, vorder, rows


#: elements of a chunk of :func:`vertex_homes` (six edges each, about 100 bytes an
#: element of temporaries, 3 MB)
HOME_CHUNK = 1 << 15


def vertex_homes(element_nodes: np.ndarray, n_points: int):
    """Quadratic tetrahedra (meshio's tetra10 order: four corners, then the midpoints of
    the edges 01, 12, 02, 03, 13, 23; every vertex numbered below every midpoint):
    (home (n_points,) int32, the home vertex of each point: a vertex itself, an edge's
    midpoint the lower-numbered end of its edge; far (n_points - n_v,) int32, the other
    end of each midpoint's edge; n_v), made a chunk of ``HOME_CHUNK`` elements at a time.
    The mesh's edges are the pairs (home[m], far[m - n_v]) of its midpoints m: two
    vertices share an element exactly when they share an edge, so these pairs are the
    vertex graph."""
    from pipeline.fe.space import TET_EDGES

    en = element_nodes
    n_v = int(en[:, :4].max()) + 1 if en.size else 0
    n_e = max(n_points - n_v, 0)
    home = np.arange(n_points, dtype=np.int32)
    far = np.zeros(n_e, dtype=np.int32)
    for start in range(0, en.shape[0], HOME_CHUNK):
        chunk = en[start:start + HOME_CHUNK]
        for k, (a, b) in enumerate(TET_EDGES):
            mid, ea, eb = chunk[:, 4 + k], chunk[:, a], chunk[:, b]
            home[mid] = np.minimum(ea, eb)
            far[mid - n_v] = np.maximum(ea, eb)
    return home, far, n_v


def vertex_graph_rows(element_nodes: np.ndarray, node_points: np.ndarray, free: np.ndarray,
                      size: int):
    """The partitioner's graph on the mesh vertices of a quadratic mesh, by slabs:
    (home (n_points,) int32 of :func:`vertex_homes`; vertex (n_v,) int32, the graph
    vertex of each mesh vertex, -1 for one that is home to no free DOF; vorder (n_g,),
    the mesh vertex of each graph vertex, sorted along the longest extent; ``rows(r)``:
    slab r's (indptr (n_r + 1,) int64; indices int32, each vertex's neighbours along the
    mesh edges, ascending, no self loops; weights (n_r,) int64, the free DOFs at home
    there)).

    A point's DOFs go where its home vertex goes, so the weights (its own free DOFs and
    those of the midpoints it is home to) balance the free DOFs. The graph has about 14
    entries a vertex, 1.6 a point and 0.6 a free DOF, where the point graph of
    :func:`slab_graph_rows` has 8.5 a free DOF; its CSR of the mesh edges both ways is
    about 16 bytes a point while the slabs are made."""
    import scipy.sparse as sp

    free = np.asarray(free)
    points = np.asarray(node_points, dtype=float)
    home, far, n_v = vertex_homes(element_nodes, points.shape[0])
    per_point = np.bincount(free // 3, minlength=points.shape[0])
    weight = np.bincount(home, weights=per_point, minlength=n_v).astype(np.int64)
    del per_point
    axis = int(np.argmax(np.ptp(points[:n_v], axis=0))) if n_v else 0
    up = np.flatnonzero(weight > 0)
    vorder = up[np.argsort(points[up, axis], kind="stable")]
    del up
    n_g = vorder.size
    vertex = np.full(n_v, -1, dtype=np.int32)
    vertex[vorder] = np.arange(n_g, dtype=np.int32)
    ends = (home[n_v:], far)
    adjacency = sp.csr_matrix((np.ones(2 * far.size, dtype=bool),
                               (np.concatenate(ends), np.concatenate(ends[::-1]))),
                              shape=(n_v, n_v))
    del ends, far
    vs = [(n_g * r) // size for r in range(size + 1)]

    def rows(r: int):
        mine = vorder[vs[r]:vs[r + 1]]
        block = adjacency[mine]
        cols = vertex[block.indices]
        row = np.repeat(np.arange(mine.size, dtype=np.int64), np.diff(block.indptr))
        keep = cols >= 0
        key = row[keep] * n_g + cols[keep]
        del block, cols, row, keep
        key.sort()  # row-major, each row's vertices ascending
        row = key // n_g
        indptr = np.zeros(mine.size + 1, dtype=np.int64)
        np.cumsum(np.bincount(row, minlength=mine.size), out=indptr[1:])
        return indptr, (key - row * n_g).astype(np.int32), weight[mine]

    return home, vertex, vorder, rows


@functools.lru_cache(maxsize=1)
def _petsc_weight_calls():
    """(MatPartitioningSetVertexWeights, PETSc's allocator) from the PETSc library this
    process has loaded, or None where it or its symbols are not found: petsc4py 3.18 has
    no binding for the vertex weights, so they are set through ctypes."""
    import ctypes

    try:
        with open("/proc/self/maps") as maps:
            path = next((line.split()[-1] for line in maps
                         if "libpetsc" in line and ".so" in line), None)
        if path is None:
            return None
        lib = ctypes.CDLL(path)
        vertex_weights = lib.MatPartitioningSetVertexWeights
        vertex_weights.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        vertex_weights.restype = ctypes.c_int
        allocate = ctypes.CFUNCTYPE(
            ctypes.c_int, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_char_p,
            ctypes.c_char_p, ctypes.POINTER(ctypes.c_void_p))(
            ctypes.c_void_p.in_dll(lib, "PetscTrMalloc").value)
    except (OSError, AttributeError, ValueError, TypeError):
        return None
    return vertex_weights, allocate


def set_weights(PETSc, partitioning, weights: np.ndarray) -> None:
    """Give PETSc's ``partitioning`` this rank's vertex weights (n_rows,), in an array
    from PETSc's own allocator, which the partitioning owns and frees (PETSc's rule for
    ``MatPartitioningSetVertexWeights``). Needs :func:`_petsc_weight_calls`."""
    import ctypes

    vertex_weights, allocate = _petsc_weight_calls()
    values = np.ascontiguousarray(weights, dtype=PETSc.IntType)
    memory = ctypes.c_void_p()
    if allocate(max(values.nbytes, 1), 0, 0, b"set_weights", b"partition.py",
                ctypes.byref(memory)) or not memory.value:
        raise MemoryError(f"PETSc could not allocate {values.nbytes} bytes of vertex weights")
    ctypes.memmove(memory, values.ctypes.data, values.nbytes)
    if vertex_weights(partitioning.handle, memory):
        raise RuntimeError("PETSc refused the partitioner graph's vertex weights")


def cut_measures(local_K, lo: int, hi: int) -> tuple[int, int]:
    """(cut entries, halo columns) of one rank's rows (CSR with global columns): the
    stored entries whose column another rank owns (the edge cut, doubled over the two
    sides) and the distinct such columns (the vector entries it receives per product)."""
    cols = np.asarray(local_K.indices)
    off = cols[(cols < lo) | (cols >= hi)]
    return int(off.size), int(np.unique(off).size)


def partition_kind(PETSc) -> str:
    """``graph`` or ``slab``: the PETSc option ``-pipeline_partition`` (default graph)."""
    kind = PETSc.Options().getString("pipeline_partition", "graph")
    if kind not in ("graph", "slab"):
        raise ConfigError(f"PETSc option -pipeline_partition: {kind!r}; expected graph or "
                          "slab", key="-pipeline_partition", value=kind,
                          expected="graph or slab")
    return kind
