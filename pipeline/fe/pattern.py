"""Index steps of the assembly: the node-block sparsity pattern that K and M share, K's
CSR structure on the kept nodes, and M's CSR from it.

The pattern holds every pair of nodes sharing an element, built once as the pattern of
E^T E (E: element-node incidence); each element's node pairs are looked up in it once
(:attr:`BlockPattern.slots`), so that the element values are scatter-added straight into
K's CSR values by 3-value rows (:class:`StiffnessLayout`). The steps write large fresh
index arrays, and the first write of fresh memory dominates their cost: they run by
chunks of node rows or elements on two cores (:func:`side_by_side`), which share that
cost, and keep their temporaries a chunk's size. Every index array is 32-bit where its
values fit (:func:`index_dtype`).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np
import scipy.sparse as sp

from pipeline._util.resources import release_free_heap, usable_cores
from pipeline.fe.space import FESpace

__all__ = ["INT32_MAX", "index_dtype", "BlockPattern", "block_pattern", "NodeGraph",
           "node_graph", "element_slots", "StiffnessLayout",
           "stiffness_layout", "mass_csr", "side_by_side"]

INT32_MAX = 2**31 - 1
# work sizes of the index steps run side by side (module constants so that the tests can
# make a small body take the chunked, threaded paths): node-row chunks of about this many
# blocks (:func:`_row_chunks`), and at least this many elements per slot look-up chunk
LAYOUT_CHUNK_BLOCKS = 1 << 20
SLOT_CHUNK_ELEMENTS = 1024


def index_dtype(size: int):
    """np.int32 for indices up to ``size``, where they fit; else np.int64."""
    return np.int32 if size <= INT32_MAX else np.int64


@dataclass(frozen=True)
class BlockPattern:
    """Node-pair sparsity pattern shared by K and M.

    indptr (n_nodes + 1,), indices (n_blocks,): CSR structure of the node graph,
    sorted, 32-bit where it fits.
    slots: (n_t, nb * nb) block index of every element node pair (a, b), pair
    a * nb + b of element e in row e: the order in which the assembly produces them.
    """

    indptr: np.ndarray
    indices: np.ndarray
    slots: np.ndarray
    n_nodes: int

    @property
    def n_blocks(self) -> int:
        return int(self.indices.size)

    @property
    def n_pairs(self) -> int:
        return int(self.slots.size)


@dataclass(frozen=True)
class NodeGraph:
    """The node-pair pattern alone, before any element's pairs are looked up in it
    (:func:`node_graph`): enough for K's structure (:func:`stiffness_layout`), so that
    the solver can analyse K's pattern while the slots and the values are computed.

    indptr (n_nodes + 1,), indices (n_blocks,): :class:`BlockPattern`'s.
    n_pairs: element node pairs the slots will hold (n_t nb^2).
    """

    indptr: np.ndarray
    indices: np.ndarray
    n_nodes: int
    n_pairs: int

    @property
    def n_blocks(self) -> int:
        return int(self.indices.size)


def node_graph(space: FESpace) -> NodeGraph:
    """The node graph of ``space`` (every pair of nodes sharing an element), sorted.

    The pattern of E^T E, E the (n_t, n_nodes) boolean incidence of elements and nodes:
    scipy's sparse product counts each row's distinct columns, so only the result is
    ever held (no array of the 100 n_t pairs).
    """
    en = space.element_nodes
    n_t, nb = en.shape
    n = space.n_nodes
    # boolean data: the product's sums are logical ors, so no count can wrap to zero
    # (scipy drops the zeros of a product)
    E = sp.csr_matrix((np.ones(en.size, dtype=bool), np.ascontiguousarray(en).reshape(-1),
                       np.arange(0, en.size + 1, nb, dtype=np.int64)), shape=(n_t, n))
    graph = (E.T.tocsr() @ E).tocsr()
    del E
    graph.sort_indices()
    btype = index_dtype(max(int(graph.nnz), n))
    return NodeGraph(graph.indptr.astype(btype, copy=False),
                     graph.indices.astype(btype, copy=False), n, n_t * nb * nb)


def element_slots(graph: NodeGraph, space: FESpace, threads: int | None = None
                  ) -> BlockPattern:
    """:class:`BlockPattern` of ``graph`` (:func:`node_graph` of ``space``): every
    element pair's block index looked up in the sorted rows by element chunks
    (:func:`_lookup_slots`), on ``threads`` cores (default: the usable ones)."""
    en = space.element_nodes.astype(graph.indices.dtype, copy=False)
    slots = _lookup_slots(graph.indptr, graph.indices, np.ascontiguousarray(en),
                          graph.n_nodes, usable_cores() if threads is None else threads)
    return BlockPattern(graph.indptr, graph.indices, slots, graph.n_nodes)


def block_pattern(space: FESpace, threads: int | None = None) -> BlockPattern:
    """The node-pair pattern of ``space`` (every pair of nodes sharing an element) and
    every element pair's place in it: :func:`node_graph`, then :func:`element_slots`.
    This writes about a fifth of the memory of a counting sort of all pairs, and the
    first write of fresh memory is most of either's cost (docs/performance.md has the
    figures).
    """
    return element_slots(node_graph(space), space, threads)


def _lookup_slots(indptr: np.ndarray, indices: np.ndarray, en: np.ndarray, n: int,
                  threads: int) -> np.ndarray:
    """(n_t, nb^2) block index of every element node pair (a, b), pair a nb + b of
    element e in row e, found in the sorted CSR rows (``indptr``, ``indices``).

    scipy's CSR sampling (``A[rows, cols]``) on the matrix of block numbers, by element
    chunks so that the pair arrays stay small: chunks hold more than a tenth of the
    pattern's blocks as samples, where scipy binary-searches each row (below, it scans
    the whole row). The sampling releases the GIL: element halves run side by side.
    """
    n_t, nb = en.shape
    positions = sp.csr_array((np.arange(indices.size, dtype=indices.dtype), indices, indptr),
                             shape=(n, n))
    positions.has_canonical_format = True
    slots = np.empty((n_t, nb * nb), dtype=indices.dtype)
    chunk = max(SLOT_CHUNK_ELEMENTS, indices.size // (8 * nb * nb) + 1)

    def sample(rows: np.ndarray, cols: np.ndarray, out: np.ndarray) -> None:
        try:
            from scipy.sparse._sparsetools import csr_sample_values

            csr_sample_values(n, n, indptr, indices, positions.data, rows.size, rows, cols,
                              out)
        except (ImportError, TypeError):  # private scipy API changed: public indexing
            out[:] = positions[rows, cols]

    def run(lo: int, hi: int) -> None:
        for s in range(lo, hi, chunk):
            e = en[s:min(hi, s + chunk)]
            sample(np.repeat(e, nb, axis=1).reshape(-1), np.tile(e, (1, nb)).reshape(-1),
                   slots[s:s + e.shape[0]].reshape(-1))

    half = n_t // 2 if n_t >= 4 * chunk else n_t
    side_by_side([lambda: run(0, half), (lambda: run(half, n_t)) if half < n_t else None],
                 threads)
    return slots


@dataclass(frozen=True)
class StiffnessLayout:
    """K's CSR structure on the kept nodes, and where every node block's values go.

    The kept nodes' 3x3 blocks expand to CSR rows 3 a' + i (a' the kept node's new
    number): row 3 a' + i holds, for each block k' of node row a', the three values
    (i, 0..2) at data[3 r : 3 r + 3] with r = k' + 2 ip'[a'] + i L'[a'] (ip', L': start
    and length of node row a' in the kept pattern).

    indptr (3 n_kept + 1,), indices (nnz,): K's CSR structure, sorted.
    base, step (n_blocks,): for block s of the full pattern, its row i lands at
    r = base[s] + i step[s]; blocks touching a dropped node have base = nnz // 3 (one
    spare row, discarded) and step 0.
    block_indptr (n_kept + 1,): ip', the kept pattern's node rows (:func:`_row_blocks`).
    mass_indices (nnz // 3,): M's CSR column indices, 3 b' + i for 3-value row i of
    block (a', b') (:func:`mass_csr`). They come out of the gather that builds
    ``indices``, so M's structure needs no second pass over the pattern.
    """

    indptr: np.ndarray
    indices: np.ndarray
    base: np.ndarray
    step: np.ndarray
    block_indptr: np.ndarray
    mass_indices: np.ndarray

    @property
    def nnz(self) -> int:
        return int(self.indices.size)

    @property
    def n(self) -> int:
        return int(self.indptr.size - 1)


def stiffness_layout(pattern: BlockPattern | NodeGraph, nodes: np.ndarray | None = None,
                     threads: int | None = None) -> StiffnessLayout:
    """:class:`StiffnessLayout` of K on the sorted ``nodes`` (all three DOFs of each;
    None: every node). Dropping a clamped body's fixed nodes here means the full K is
    never built: K is assembled straight onto the free DOFs.

    Every output is positional in the node rows, so it is written by chunks of node
    rows on ``threads`` cores (default: the usable ones): the kept blocks and where
    each block's values go (:func:`_kept_blocks`, by rows of the full pattern), then K's
    and M's column indices (:func:`_layout_rows`, by rows of the kept one). The
    temporaries stay a chunk's size and the first write of K's indices (page faults on
    fresh memory, most of this step's cost) is shared by two cores.
    """
    threads = usable_cores() if threads is None else threads
    n_nodes = pattern.n_nodes
    # one integer type for every index below: K's nnz and the element rows must fit
    itype = index_dtype(max(9 * pattern.n_blocks + 3, 3 * pattern.n_pairs + 1))
    indptr = pattern.indptr.astype(itype, copy=False)
    indices = pattern.indices.astype(itype, copy=False)
    new_node = None
    if nodes is not None and nodes.size != n_nodes:
        new_node = np.full(n_nodes, -1, dtype=itype)
        new_node[nodes] = np.arange(nodes.size, dtype=itype)
    blocks = _kept_blocks(indptr, indices, new_node, threads)
    n_kept = n_nodes if new_node is None else nodes.size
    kept_indptr = blocks.start if new_node is None else np.append(blocks.start[nodes],
                                                                  blocks.start[-1])
    nnz = 9 * int(kept_indptr[-1])
    n = 3 * n_kept
    lens = np.diff(kept_indptr)
    # scalar rows: row 3 a' + i starts at 9 ip'[a'] + 3 i L'[a']
    k_indptr = np.empty(n + 1, dtype=itype)
    for i in range(3):
        k_indptr[i:n:3] = 9 * kept_indptr[:-1] + 3 * i * lens
    k_indptr[n] = nnz
    k_indices = np.empty((nnz // 3, 3), dtype=itype)
    mass_indices = np.empty(nnz // 3, dtype=itype)
    side_by_side([lambda part=part: [_layout_rows(kept_indptr, blocks.indices, a0, a1,
                                                  k_indices, mass_indices)
                                     for a0, a1 in part]
                  for part in _row_chunks(kept_indptr)], threads)
    return StiffnessLayout(k_indptr, k_indices.reshape(-1), blocks.base, blocks.step,
                           kept_indptr, mass_indices)


@dataclass(frozen=True)
class _KeptBlocks:
    """The blocks of the pattern on the kept nodes (:func:`_kept_blocks`).

    start (n_nodes + 1,): kept blocks in the node rows before each full node row (a
    dropped row keeps none), so that a kept node a has ip' = start[a]; indices
    (n_blocks_kept,): the kept blocks' columns in the kept nodes' numbering.
    base, step (n_blocks,): :class:`StiffnessLayout`'s.
    """

    start: np.ndarray
    indices: np.ndarray
    base: np.ndarray
    step: np.ndarray


def _kept_blocks(indptr: np.ndarray, indices: np.ndarray, new_node: np.ndarray | None,
                 threads: int) -> _KeptBlocks:
    """Which blocks of the pattern (``indptr``, ``indices``) touch only kept nodes
    (``new_node``: each node's new number, -1 dropped; None: every node kept), their
    columns renumbered, and where each block's 3-value rows go (:class:`StiffnessLayout`):
    two passes by chunks of node rows (count the kept blocks per row; write), side by side.
    """
    itype = indices.dtype
    n_nodes = indptr.size - 1
    chunks = _row_chunks(indptr)
    keep = None
    start = indptr
    if new_node is not None:
        keep = np.empty(indices.size, dtype=bool)
        counts = np.zeros(n_nodes + 1, dtype=itype)

        def count(part: list[tuple[int, int]]) -> None:
            for a0, a1 in part:
                b0, b1 = int(indptr[a0]), int(indptr[a1])
                k = keep[b0:b1]
                np.greater_equal(new_node[indices[b0:b1]], 0, out=k)
                k &= np.repeat(new_node[a0:a1] >= 0, np.diff(indptr[a0:a1 + 1]))
                before = np.zeros(b1 - b0 + 1, dtype=itype)
                np.cumsum(k, out=before[1:])
                local = indptr[a0:a1 + 1] - b0
                counts[a0 + 1:a1 + 1] = np.diff(before[local])

        side_by_side([lambda part=part: count(part) for part in chunks], threads)
        start = np.cumsum(counts, out=counts)
    n_blocks_kept = int(start[-1])
    spare = 3 * n_blocks_kept  # K's 3-value row count: the dropped blocks' row
    kept_indices = indices if keep is None else np.empty(n_blocks_kept, dtype=itype)
    base = np.empty(indices.size, dtype=itype)
    step = np.empty(indices.size, dtype=itype)

    def write(part: list[tuple[int, int]]) -> None:
        for a0, a1 in part:
            b0, b1 = int(indptr[a0]), int(indptr[a1])
            lens = np.diff(indptr[a0:a1 + 1])
            # kept block at kept position p of node row a (kept start s = start[a],
            # length L' = start[a + 1] - s): 3-value rows 3 s + p + i L' = 2 s + (s + p)
            # + i L', (s + p) its number among all kept blocks
            s = start[a0:a1]
            length = np.diff(start[a0:a1 + 1])
            b, t = base[b0:b1], step[b0:b1]
            b[:] = np.repeat(2 * s, lens)
            t[:] = np.repeat(length, lens)
            if keep is None:
                b += np.arange(b0, b1, dtype=itype)
                continue
            k = keep[b0:b1]
            number = np.cumsum(k, dtype=itype)
            number += int(start[a0]) - 1
            b += number
            drop = ~k
            b[drop] = spare
            t[drop] = 0
            kept_indices[int(start[a0]):int(start[a1])] = new_node[indices[b0:b1][k]]

    side_by_side([lambda part=part: write(part) for part in chunks], threads)
    return _KeptBlocks(start, kept_indices, base, step)


def _layout_rows(indptr: np.ndarray, indices: np.ndarray, a0: int, a1: int,
                 k_indices: np.ndarray, mass_indices: np.ndarray) -> None:
    """K's and M's column indices (:class:`StiffnessLayout`) for kept node rows a0..a1-1
    of the kept pattern (``indptr``, ``indices``): 3-value rows 3 ip'[a0] .. 3 ip'[a1]
    of ``k_indices`` (nnz // 3, 3) and ``mass_indices`` (nnz // 3,)."""
    itype = indptr.dtype
    r0, r1 = 3 * int(indptr[a0]), 3 * int(indptr[a1])
    lens = np.diff(indptr[a0:a1 + 1])
    # 3-value row r holds columns 3 b + (0, 1, 2) of its kept block: one gather (twice
    # as fast as scattering every block three times)
    col = indices[_row_blocks(indptr, a0, a1)]  # (take: a 64-bit copy of the index first)
    col *= 3
    np.add(col[:, None], np.arange(3, dtype=itype), out=k_indices[r0:r1])
    # M's entry for 3-value row r (component i) is column 3 b' + i
    np.add(col, np.repeat(np.tile(np.arange(3, dtype=np.int8), a1 - a0), np.repeat(lens, 3)),
           out=mass_indices[r0:r1])


def _row_chunks(indptr: np.ndarray) -> list[list[tuple[int, int]]]:
    """Ranges (a0, a1) of node rows of about LAYOUT_CHUNK_BLOCKS blocks each (CSR ``indptr``),
    dealt alternately to two lists (the two threads of :func:`side_by_side`; a list
    may be empty)."""
    n_rows, n_blocks = indptr.size - 1, int(indptr[-1])
    bounds = np.searchsorted(indptr, np.arange(0, n_blocks, LAYOUT_CHUNK_BLOCKS), side="right") - 1
    bounds = np.unique(np.concatenate([[0], np.clip(bounds, 0, n_rows), [n_rows]]))
    ranges = [(int(a0), int(a1)) for a0, a1 in pairwise(bounds.tolist())]
    return [ranges[0::2], ranges[1::2]]


def _row_blocks(indptr: np.ndarray, a0: int, a1: int) -> np.ndarray:
    """The kept block of every 3-value row of node rows a0..a1-1 (:class:`StiffnessLayout`,
    3-value rows 3 ip'[a0] .. 3 ip'[a1]): r - (2 ip'[a'] + i L'[a']) for row r of node
    row a', component i."""
    ip = indptr[a0:a1 + 1]
    lens = np.diff(ip)
    offsets = (2 * ip[:-1])[:, None] + np.arange(3, dtype=ip.dtype) * lens[:, None]
    block = np.arange(3 * ip[0], 3 * ip[-1], dtype=ip.dtype)
    block -= np.repeat(offsets.reshape(-1), np.repeat(lens, 3))
    return block


def mass_csr(layout: StiffnessLayout, mblock: np.ndarray, threads: int | None = None
             ) -> sp.csr_matrix:
    """M (kg) on ``layout``'s kept nodes from the mass of every block of the pattern
    (n_blocks,): the CSR of m_ab I_3, rows 3 a' + c holding columns 3 b' + c only.

    M's row 3 a' + c has one entry per block k' of node row a', at position
    k' + 2 ip'[a'] + c L'[a']: the place of K's 3-value row i = c. So M has K's
    structure divided by three (indptr / 3; the column of entry r is K's 3-value row r's
    first column 3 b' plus c: ``layout.mass_indices``), and its values are one gather
    of the block masses by :func:`_row_blocks`, without another pass over the pattern.
    """
    spare = layout.nnz // 3
    if layout.base.size == spare // 3:  # no node dropped: every block is kept
        masses = mblock
    else:  # kept blocks, in the pattern's order
        masses = mblock[layout.base < spare]
    data = np.empty(spare)
    ip = layout.block_indptr

    def gather(part: list[tuple[int, int]]) -> None:
        for a0, a1 in part:
            data[3 * ip[a0]:3 * ip[a1]] = masses[_row_blocks(ip, a0, a1)]

    side_by_side([lambda part=part: gather(part) for part in _row_chunks(ip)],
                 usable_cores() if threads is None else threads)
    M = sp.csr_matrix((data, layout.mass_indices, layout.indptr // 3),
                      shape=(layout.n, layout.n))
    M.has_sorted_indices = True
    return M


def side_by_side(tasks: list, threads: int) -> None:
    """Run the callables ``tasks`` (no arguments) on two threads when ``threads`` >= 2
    and there is more than one, else one after the other; the first failure is raised
    once both have ended. For numpy and scipy kernels that release the GIL, whose cost
    is mostly the first write of fresh memory: two cores fault pages in about twice as
    fast as one (docs/performance.md)."""
    tasks = [t for t in tasks if t is not None]
    if threads < 2 or len(tasks) < 2:
        for task in tasks:
            task()
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        futures = [pool.submit(task) for task in tasks]
    for f in futures:
        f.result()
    release_free_heap()  # the worker's malloc arena keeps its temporaries' pages
