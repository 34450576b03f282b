"""Assembly stage: linear-elasticity stiffness K and consistent mass M.

scikit-fem is the finite-element engine: its mesh numbers the edges, its Lagrange
elements give the reference shape functions and its quadrature rules the points and
weights. On straight-sided tetrahedra the Jacobian J is constant per element, so the
element matrices are one matrix product for the whole mesh:

- stiffness: with R[ab, kl] = int_ref dphi_a/dxi_k dphi_b/dxi_l (exact with the degree
  2(p-1) rule: 4 points for P2), K_e[ab, ij] = sum_kl R[ab, kl] Q_e[kl, ij], where the
  9x9 matrix Q_e holds the element's J^-1, |det J| and the Lame parameters. One GEMM
  (nb^2 x 9) @ (9 x n_elements) per stiffness component;
- mass: one reference mass matrix (degree 2p rule) times each element's |det J|.

Both matrices use one node-block sparsity pattern (every pair of nodes sharing an
element), built once as the pattern of E^T E (E: element-node incidence); element values
are scatter-added straight into K's CSR values by 3-value rows. The index steps (every
pair's block, K's and M's CSR structure) run by chunks on two cores: on this project's
VMs their cost is mostly the first write of fresh memory, which two cores share
(docs/performance.md). K is returned in CSR with full 3x3 node blocks, M with only the
u_i.v_i entries (a third of the non-zeros: M couples equal components only); both
have 32-bit indices where they fit. The result equals ``skfem.asm`` of the same forms
to round-off (``tests/test_assemble.py``), without ever holding basis values for the
whole mesh.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
import scipy.sparse as sp

from pipeline._util.resources import release_free_heap, usable_cores
from pipeline.config import Material
from pipeline.errors import SolverError
from pipeline.fe.space import FESpace

log = logging.getLogger(__name__)

INT32_MAX = 2**31 - 1
# work sizes of the index steps run side by side (module constants so that the tests can
# make a small body take the chunked, threaded paths): node-row chunks of about this many
# blocks (:func:`_row_chunks`), and at least this many elements per slot look-up chunk
LAYOUT_CHUNK_BLOCKS = 1 << 20
SLOT_CHUNK_ELEMENTS = 1024


def check_material(material: Material) -> None:
    """Refuse a material whose stiffness or mass matrix would not be positive definite.

    A config's material was checked when the config was read (:mod:`pipeline.config`);
    this guards library callers that build a :class:`~pipeline.config.Material` themselves
    (the record does not validate itself)."""
    E, nu, rho = material.E, material.nu, material.rho
    if not (np.isfinite(E) and E > 0 and np.isfinite(nu) and -1.0 < nu < 0.5
            and np.isfinite(rho) and rho > 0):
        raise SolverError(f"material E = {E:g} Pa, nu = {nu:g}, rho = {rho:g} kg/m^3: the "
                          "stiffness or mass matrix would not be positive definite; expected "
                          "E > 0, -1 < nu < 0.5 and rho > 0", key="material",
                          value={"E": E, "nu": nu, "rho": rho},
                          expected="E > 0, -1 < nu < 0.5 and rho > 0")


def lame_parameters(material: Material) -> tuple[float, float]:
    """(lambda, mu) in Pa from Young's modulus and Poisson's ratio."""
    check_material(material)
    E, nu = material.E, material.nu
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def _index_dtype(size: int):
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


def block_pattern(space: FESpace, threads: int | None = None) -> BlockPattern:
    """The node-pair pattern of ``space`` (every pair of nodes sharing an element).

    The node graph is the pattern of E^T E, E the (n_t, n_nodes) boolean incidence of
    elements and nodes: scipy's sparse product counts each row's distinct columns, so
    only the result is ever held (no array of the 100 n_t pairs). Every pair's block
    index is then looked up in the sorted rows by element chunks (:func:`_lookup_slots`),
    on ``threads`` cores (default: the usable ones). At 1M DOFs on this project's VMs:
    0.7-0.9 s and 0.15 GB written, against 1.6-1.8 s and 0.7 GB for a counting sort of
    all pairs (most of it the first write of fresh memory, docs/performance.md).
    """
    en = np.ascontiguousarray(space.element_nodes)
    n_t, nb = en.shape
    n = space.n_nodes
    # boolean data: the product's sums are logical ors, so no count can wrap to zero
    # (scipy drops the zeros of a product)
    E = sp.csr_matrix((np.ones(en.size, dtype=bool), en.reshape(-1),
                       np.arange(0, en.size + 1, nb, dtype=np.int64)), shape=(n_t, n))
    graph = (E.T.tocsr() @ E).tocsr()
    del E
    graph.sort_indices()
    btype = _index_dtype(max(int(graph.nnz), n))
    indptr = graph.indptr.astype(btype, copy=False)
    indices = graph.indices.astype(btype, copy=False)
    del graph
    slots = _lookup_slots(indptr, indices, en.astype(btype, copy=False), n,
                          usable_cores() if threads is None else threads)
    return BlockPattern(indptr, indices, slots, n)


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


def stiffness_layout(pattern: BlockPattern, nodes: np.ndarray | None = None,
                     threads: int | None = None) -> StiffnessLayout:
    """:class:`StiffnessLayout` of K on the sorted ``nodes`` (all three DOFs of each;
    None: every node). Dropping a clamped body's fixed nodes here means the full K is
    never built: K is assembled straight onto the free DOFs.

    Every output is positional in the node rows, so it is written by chunks of node
    rows on ``threads`` cores (default: the usable ones): the kept blocks and where
    each block's values go (:func:`_kept_blocks`, by rows of the full pattern), then K's
    and M's column indices (:func:`_layout_rows`, by rows of the kept one). The
    temporaries stay a chunk's size and the first write of K's 0.3 GB of indices is
    shared by two cores (at 1M DOFs on this project's VMs: 0.8-1.0 s against 1.7-2.2 s
    in one pass, most of it page faults on fresh memory, docs/performance.md).
    """
    threads = usable_cores() if threads is None else threads
    n_nodes = pattern.n_nodes
    # one integer type for every index below: K's nnz and the element rows must fit
    itype = _index_dtype(max(9 * pattern.n_blocks + 3, 3 * pattern.slots.size + 1))
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


def side_by_side(tasks: list, threads: int) -> None:
    """Run the callables ``tasks`` (no arguments) on two threads when ``threads`` >= 2
    and there is more than one, else one after the other; the first failure is raised
    once both have ended. For numpy and scipy kernels that release the GIL: on this
    project's VMs the first write of fresh memory costs about 2.3 s/GiB on one core and
    1.2-1.5 s/GiB on two (docs/performance.md)."""
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


def _reference_data(order: int):
    """Reference stiffness tensor R (nb*nb, 9) and mass matrix (nb, nb) on the unit tet.

    R[a * nb + b, 3 k + l] = int dphi_a/dxi_k dphi_b/dxi_l over the reference
    tetrahedron (volume 1/6), with the degree 2(p-1) rule (exact).
    """
    from skfem import ElementTetP1, ElementTetP2
    from skfem.quadrature import get_quadrature
    from skfem.refdom import RefTet

    elem = ElementTetP2() if order == 2 else ElementTetP1()
    nb = elem.doflocs.shape[0]
    Xk, Wk = get_quadrature(RefTet, max(2 * (order - 1), 1))
    dphi = np.stack([elem.lbasis(Xk, i)[1] for i in range(nb)])  # (nb, 3, n_q)
    R = np.einsum("akq,blq,q->abkl", dphi, dphi, Wk).reshape(nb * nb, 9)
    Xm, Wm = get_quadrature(RefTet, 2 * order)
    phi = np.stack([elem.lbasis(Xm, i)[0] for i in range(nb)])  # (nb, n_q)
    mass_ref = (phi * Wm) @ phi.T
    return R, mass_ref


def inverse_jacobians(space: FESpace, elements: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(G (n, 3, 3), |det J| (n,)) of the straight-sided tetrahedra ``elements``:
    G[e, k, i] = d xi_k / d x_i (1/m), |det J| = 6 x volume (m^3)."""
    v = space.body.vertices
    t = space.body.tetrahedra[elements]
    a = v[t[:, 0]]
    J = np.stack([v[t[:, 1]] - a, v[t[:, 2]] - a, v[t[:, 3]] - a], axis=2)  # columns
    return np.linalg.inv(J), np.abs(np.linalg.det(J))


def _element_factors(space: FESpace, lam: float, mu: float, elems: np.ndarray):
    """F (n, 9, 9) with K_e[ab, c] = R[ab, :] @ F[e, :, c] for component c = 3 i + j of
    the 3x3 block (row DOF i of node a, column DOF j of node b), and |det J| (n,)."""
    G, vol = inverse_jacobians(space, elems)  # G[e, k, i] = d xi_k / d x_i
    # P[kl, ij] = G[k, i] G[l, j]; F = lam P + mu P^(ij swapped) + mu delta_ij (G G^T)[k, l]
    P = np.einsum("nki,nlj->nklij", G, G, optimize=True)
    F = lam * P + mu * P.transpose(0, 1, 2, 4, 3)
    del P
    GG = np.einsum("nkm,nlm->nkl", G, G)
    for i in range(3):
        F[:, :, :, i, i] += mu * GG
    F *= vol[:, None, None, None, None]
    return F.reshape(-1, 9, 9), vol


def scatter_add(rows: np.ndarray, values: np.ndarray, out: np.ndarray) -> None:
    """out[rows[r], :] += values[r, :] for every row r of ``values`` (m, k).

    scipy's C++ sparse (CSC, one entry per column) times dense product with unit
    weights, which accumulates into ``out`` (n_out, k) in place: one pass over the
    element values, k contiguous columns per entry; it releases the GIL, so threads that
    write disjoint rows of ``out`` run side by side. Falls back to ``np.add.at`` if that private
    kernel is not there.
    """
    m, k = values.shape
    try:
        from scipy.sparse import _sparsetools

        _sparsetools.csc_matvecs(out.shape[0], m, k, np.arange(m + 1, dtype=rows.dtype), rows,
                                 np.ones(m), values.reshape(-1), out.reshape(-1))
    except (ImportError, AttributeError, TypeError, ValueError):
        np.add.at(out, rows.astype(np.intp), values)


@dataclass(frozen=True)
class Assembled:
    """K and M on the kept nodes, and the node-level mass of the whole body.

    K: (3 n_kept, 3 n_kept) CSR stiffness (N/m), full 3x3 node blocks.
    M: (3 n_kept, 3 n_kept) CSR mass (kg), only the u_i.v_i entries (M couples equal
    components: a third of K's non-zeros).
    node_mass: (n_nodes, n_nodes) CSR of the scalar m_ab of every node pair of the
    whole body (kg), so that the unsupported mass is node_mass (x) I_3; it shares the
    pattern's index arrays.
    """

    K: sp.csr_matrix
    M: sp.csr_matrix
    node_mass: sp.csr_matrix


def element_groups(space: FESpace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three groups of element indices (each sorted): the elements whose nodes all lie
    below the median node coordinate along the mesh's longest extent, those whose nodes
    all lie at or above it, and the rest (the elements the plane cuts).

    The first two groups touch disjoint node rows of K and M, so they can be summed
    into the same arrays side by side without a race; the third, a layer one element
    thick, is summed after them.
    """
    x = space.node_points
    axis = int(np.argmax(np.ptp(x, axis=0))) if x.shape[0] else 0
    upper = x[:, axis] >= np.median(x[:, axis]) if x.shape[0] else np.zeros(0, bool)
    side = upper[space.element_nodes]
    lower_all = ~side.any(axis=1)
    upper_all = side.all(axis=1)
    return (np.flatnonzero(lower_all), np.flatnonzero(upper_all),
            np.flatnonzero(~(lower_all | upper_all)))


def _assemble_elements(space: FESpace, R: np.ndarray, mass_ref: np.ndarray, lam: float,
                       mu: float, rho: float, pattern: BlockPattern, layout: StiffnessLayout,
                       elements: np.ndarray, spare: int, chunk_size: int, kdata: np.ndarray,
                       mblock: np.ndarray, progress, stop) -> None:
    """Add ``elements`` into kdata (n_rows, 3) and mblock (n_blocks,); the dropped
    nodes' blocks go to kdata's row ``spare`` (one per concurrent caller). Returns early
    once the event ``stop`` is set (checked before each chunk)."""
    offsets = np.arange(3, dtype=layout.base.dtype)
    m_ref = rho * mass_ref.reshape(-1)
    first_spare = layout.nnz // 3
    for start in range(0, elements.size, chunk_size):
        if stop.is_set():
            return
        chunk = elements[start:start + chunk_size]
        F, vol = _element_factors(space, lam, mu, chunk)
        block = np.matmul(R, F)  # (m, nb^2, 9): [element, pair, 3 i + j]
        del F
        slots = pattern.slots[chunk].reshape(-1)
        rows = layout.base[slots][:, None] + layout.step[slots][:, None] * offsets
        if spare != first_spare:
            rows[rows == first_spare] = spare
        scatter_add(rows.reshape(-1), block.reshape(-1, 3), kdata)
        del block, rows
        scatter_add(slots, np.outer(vol, m_ref).reshape(-1, 1), mblock.reshape(-1, 1))
        if progress is not None:
            progress(chunk.size)


def assemble_on_nodes(space: FESpace, material: Material, nodes: np.ndarray | None = None,
                      pattern: BlockPattern | None = None, chunk_size: int = 2048,
                      progress=None, threads: int | None = None,
                      on_layout=None) -> Assembled:
    """K (N/m) and M (kg) on the sorted ``nodes`` (all three DOFs of each; None: every
    node), and the whole body's node-level mass (:class:`Assembled`); CSR, sorted, 32-bit
    indices where they fit. ``pattern`` defaults to :func:`block_pattern`.
    ``progress``, if given, is called with the number of elements done after each chunk.
    ``on_layout(indptr, indices)``, if given, is called with K's CSR structure as soon as
    it is known, before any value is summed (the solver can analyse the pattern
    meanwhile: :class:`pipeline.solve.factorize.PatternAnalysis`).

    Per chunk of ``chunk_size`` elements: the element factors F_e (9 x 9), one batched
    GEMM R (nb^2 x 9) @ F_e giving each (element, pair) row its 9 values (i, j), and one
    scatter-add of 3-value rows (i, 0..2) straight into K's CSR data
    (:class:`StiffnessLayout`), so no node-block array and no BSR-to-CSR expansion
    exist. The two halves of :func:`element_groups` touch disjoint rows: with ``threads``
    >= 2 (default: the usable cores) they are summed side by side in two threads (the
    GEMM, numpy's kernels and scipy's scatter release the GIL) into the same arrays, then
    the cut layer. Every entry is summed in the same order whatever the thread count, so
    K does not depend on the machine to the last bit.
    """
    lam, mu = lame_parameters(material)
    if threads is None:
        threads = usable_cores()
    if pattern is None:
        pattern = block_pattern(space, threads)
    layout = stiffness_layout(pattern, nodes, threads)
    if on_layout is not None:
        on_layout(layout.indptr, layout.indices)
    R, mass_ref = _reference_data(space.order)
    chunk_size = max(1, int(chunk_size))
    lower, upper, cut = element_groups(space)
    # three spare 3-value rows at the end take the dropped nodes' blocks, one per group
    held = [np.zeros(layout.nnz + 9)]
    kdata = held[0].reshape(-1, 3)
    mblock = np.zeros(pattern.n_blocks)
    args = (space, R, mass_ref, lam, mu, material.rho, pattern, layout)

    stop = threading.Event()

    def run(group: int, elements: np.ndarray, kdata: np.ndarray = kdata) -> None:
        _assemble_elements(*args, elements, layout.nnz // 3 + group, chunk_size, kdata,
                           mblock, progress, stop)

    # threads pay off from a few chunks per half; below that (about 150k DOFs at the
    # default chunk) the worker's malloc arena would only add to the peak (~45 MB kept)
    if threads < 2 or min(lower.size, upper.size) < 8 * chunk_size:
        run(0, lower)
        run(1, upper)
    else:
        from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait

        if progress is not None:  # one caller at a time: progress counters are not atomic
            lock, report = threading.Lock(), progress

            def progress(n: int) -> None:
                with lock:
                    report(n)

        with ThreadPoolExecutor(2) as pool:
            futures = [pool.submit(run, 0, lower), pool.submit(run, 1, upper)]
            try:
                done, _ = wait(futures, return_when=FIRST_EXCEPTION)
                for f in list(done) + futures:  # a failed half raises here at once
                    f.result()
            except BaseException:  # an interrupt or a failed half: stop the other at its
                stop.set()         # next chunk instead of finishing the body
                raise
        release_free_heap()  # the threads' malloc arenas keep their temporaries' pages
    run(2, cut)
    del kdata, run  # only ``held`` refers to the values now: cut the spare rows in place
    K = sp.csr_matrix((_shrink(held, layout.nnz), layout.indices, layout.indptr),
                      shape=(layout.n, layout.n))
    K.has_sorted_indices = True
    node_mass = sp.csr_matrix((mblock, pattern.indices, pattern.indptr),
                              shape=(pattern.n_nodes, pattern.n_nodes))
    return Assembled(K, mass_csr(layout, mblock, threads), node_mass)


def assemble_stiffness_mass(space: FESpace, material: Material, chunk_size: int = 2048,
                            pattern: BlockPattern | None = None, progress=None
                            ) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Assemble K (N/m) and M (kg), both (n_dofs x n_dofs) CSR, in the space's DOF order.

    :func:`assemble_on_nodes` on every node.
    """
    assembled = assemble_on_nodes(space, material, None, pattern, chunk_size, progress)
    return assembled.K, assembled.M


def whole_nodes(free: np.ndarray, n_nodes: int) -> np.ndarray | None:
    """The free nodes (sorted) when the sorted ``free`` DOFs are all three DOFs of each
    of them (supports that clamp whole nodes); else None."""
    free = np.asarray(free)
    if free.size % 3:
        return None
    triples = free.reshape(-1, 3)
    nodes = triples[:, 0] // 3
    if np.array_equal(triples, 3 * nodes[:, None] + np.arange(3)) and (
            nodes.size == 0 or nodes[-1] < n_nodes):
        return nodes
    return None


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


def assemble_reference(space: FESpace, material: Material) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Plain scikit-fem assembly (``form.assemble(basis)``), the reference for tests.

    Holds basis values for the whole mesh at once: keep it for small meshes and the
    benchmark's "straightforward stack".
    """
    from skfem import Basis, BilinearForm
    from skfem.helpers import ddot, dot, sym_grad, trace

    lam, mu = lame_parameters(material)
    rho = material.rho

    @BilinearForm
    def stiffness(u, v, w):
        eu, ev = sym_grad(u), sym_grad(v)
        return 2.0 * mu * ddot(eu, ev) + lam * trace(eu) * trace(ev)

    @BilinearForm
    def mass(u, v, w):
        return rho * dot(u, v)

    basis = Basis(space.skfem_mesh, space.skfem_element())
    return stiffness.assemble(basis).tocsr(), mass.assemble(basis).tocsr()


def restrict(A: sp.spmatrix, keep: np.ndarray, overwrite: bool = False) -> sp.csr_matrix:
    """A[keep][:, keep] (condensation of the supports) for sorted ``keep`` indices.

    One pass over A's entries, in row chunks (scipy's A[keep][:, keep] copies the
    matrix twice). ``overwrite=True`` compacts A's own arrays in place and shrinks
    them, so a second copy of A never exists: A is emptied and must not be used
    afterwards (``K = restrict(K, free, overwrite=True)``).
    """
    A = A if sp.isspmatrix_csr(A) else sp.csr_matrix(A)
    n = A.shape[0]
    keep = np.asarray(keep)
    if keep.size == n:
        return A
    m = keep.size
    itype = A.indices.dtype if m <= INT32_MAX else np.int64
    new_index = np.full(n, -1, dtype=itype)
    new_index[keep] = np.arange(m, dtype=itype)
    row_kept = new_index >= 0
    indptr = A.indptr.astype(np.int64, copy=False)
    new_counts = np.zeros(m + 1, dtype=np.int64)
    src_data, src_indices = A.data, A.indices
    if overwrite:  # write into the source arrays (never ahead of the reading position)
        data, indices = src_data, src_indices
        A.data, A.indices = np.empty(0), np.empty(0, dtype=A.indices.dtype)
    else:
        bound = int((indptr[keep + 1] - indptr[keep]).sum())
        data = np.empty(bound, dtype=A.data.dtype)
        indices = np.empty(bound, dtype=itype)
    write = 0
    done = 0  # kept rows written so far
    step = 1 << 16  # rows per chunk
    for r0 in range(0, n, step):
        r1 = min(n, r0 + step)
        lo, hi = int(indptr[r0]), int(indptr[r1])
        sel = np.repeat(row_kept[r0:r1], np.diff(indptr[r0:r1 + 1]))
        cols = new_index[src_indices[lo:hi]]
        sel &= cols >= 0
        cs = np.zeros(hi - lo + 1, dtype=np.int64)
        np.cumsum(sel, out=cs[1:])
        local = indptr[r0:r1 + 1] - lo
        per_row = (cs[local[1:]] - cs[local[:-1]])[row_kept[r0:r1]]
        new_counts[done + 1:done + 1 + per_row.size] = per_row
        done += per_row.size
        k = int(cs[-1])
        vals = src_data[lo:hi][sel]  # copies first: safe when writing in place below
        data[write:write + k] = vals
        indices[write:write + k] = cols[sel]
        write += k
    new_indptr = np.cumsum(new_counts)
    del src_data, src_indices
    if overwrite:
        held = [data]
        del data
        data = _shrink(held, write)
        held = [indices]
        del indices
        indices = _shrink(held, write).astype(itype, copy=False)
    else:
        data, indices = data[:write], indices[:write]
    return sp.csr_matrix((data, indices, new_indptr.astype(_index_dtype(max(write, m)))),
                         shape=(m, m))


def _shrink(holder: list, size: int) -> np.ndarray:
    """``arr[:size]`` of the array in ``holder``, in place when nothing else holds it."""
    arr = holder.pop()
    try:
        arr.resize(size, refcheck=True)
        return arr
    except ValueError:  # referenced elsewhere: copy the part we keep
        return arr[:size].copy()
