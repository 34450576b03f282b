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
element), built once with a counting sort; element values are summed into it with
``np.bincount``. K is returned in CSR with full 3x3 node blocks, M with only the
u_i.v_i entries (a third of the non-zeros: M couples equal components only); both
have 32-bit indices where they fit. The result equals ``skfem.asm`` of the same forms
to round-off (``tests/test_assemble.py``), without ever holding basis values for the
whole mesh.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pipeline.config import Material
from pipeline.errors import SolverError
from pipeline.fe.space import FESpace

log = logging.getLogger(__name__)

INT32_MAX = 2**31 - 1


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
    slots: (nb * nb, n_t) block index of every element node pair (a, b) (pair
    a * nb + b first, then element), the layout the assembly GEMM produces.
    """

    indptr: np.ndarray
    indices: np.ndarray
    slots: np.ndarray
    n_nodes: int

    @property
    def n_blocks(self) -> int:
        return int(self.indices.size)


def block_pattern(space: FESpace) -> BlockPattern:
    """The node-pair pattern of ``space`` (every pair of nodes sharing an element).

    A counting sort by row (scipy's linear-time COO to CSR conversion, which keeps
    duplicates), small per-row sorts by column, then one pass marking the first of
    every run of equal (row, column) pairs: about twice as fast as ``np.unique`` on
    the 100 n_t pair keys, and in 32-bit integers.
    """
    en = np.ascontiguousarray(space.element_nodes)
    n_t, nb = en.shape
    n = space.n_nodes
    count = n_t * nb * nb
    itype = _index_dtype(max(count, n))
    ia = np.repeat(np.arange(nb), nb)
    ib = np.tile(np.arange(nb), nb)
    rows = np.ascontiguousarray(en[:, ia].T, dtype=itype).reshape(-1)
    cols = np.ascontiguousarray(en[:, ib].T, dtype=itype).reshape(-1)
    try:
        from scipy.sparse import _sparsetools

        ids = np.arange(count, dtype=itype)
        Bp = np.empty(n + 1, dtype=itype)
        Bj = np.empty(count, dtype=itype)
        Bx = np.empty(count, dtype=itype)
        _sparsetools.coo_tocsr(n, n, count, rows, cols, ids, Bp, Bj, Bx)
        del ids
        _sparsetools.csr_sort_indices(n, Bp, Bj, Bx)
        row_of = np.repeat(np.arange(n, dtype=itype), np.diff(Bp))
        first = np.empty(count, dtype=bool)
        first[0] = True
        np.not_equal(Bj[1:], Bj[:-1], out=first[1:])
        first[1:] |= row_of[1:] != row_of[:-1]
        block_id = np.cumsum(first, dtype=itype)
        block_id -= 1
        slots = np.empty(count, dtype=itype)
        slots[Bx] = block_id
        del Bx, block_id
        indices = Bj[first]
        per_row = np.bincount(row_of[first], minlength=n)
        del Bj, row_of, first
    except (ImportError, AttributeError, TypeError):  # private scipy API changed: np.unique
        keys = rows.astype(np.int64) * n + cols
        unique, slots = np.unique(keys, return_inverse=True)
        del keys
        per_row = np.bincount(unique // n, minlength=n)
        indices = (unique % n).astype(itype)
        slots = slots.astype(itype)
    del rows, cols
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(per_row, out=indptr[1:])
    btype = _index_dtype(int(indptr[-1]))
    return BlockPattern(indptr.astype(btype), indices.astype(btype, copy=False),
                        slots.reshape(nb * nb, n_t), n)


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


def _element_factors(space: FESpace, lam: float, mu: float, elems: slice):
    """Q (9, 9, n) with K_e[ab, c] = R[ab, :] @ Q[c, :, e] for component c = 3 i + j of
    the 3x3 block (row DOF i of node a, column DOF j of node b), and |det J| (n,)."""
    v = space.body.vertices
    t = space.body.tetrahedra[elems]
    a = v[t[:, 0]]
    J = np.stack([v[t[:, 1]] - a, v[t[:, 2]] - a, v[t[:, 3]] - a], axis=2)  # columns
    det = np.linalg.det(J)
    G = np.linalg.inv(J)  # G[k, i] = d xi_k / d x_i
    vol = np.abs(det)
    # P[ij, kl] = G[k, i] G[l, j]; Q = lam P + mu P^(ij swapped) + mu delta_ij (G G^T)[k, l]
    P = np.einsum("nki,nlj->ijkln", G, G, optimize=True)
    Q = lam * P + mu * P.transpose(1, 0, 2, 3, 4)
    del P
    GG = np.einsum("nkm,nlm->kln", G, G)
    for i in range(3):
        Q[i, i] += mu * GG
    Q *= vol
    return Q.reshape(9, 9, -1), vol


def _scatter_add(slots: np.ndarray, values: np.ndarray, out: np.ndarray) -> None:
    """out[slots[r], :] += values[r, :] for every row r of ``values`` (m, k).

    scipy's C++ sparse (CSC, one entry per column) times dense product with unit
    weights, which accumulates into ``out`` (n_blocks, k) in place: one pass over the
    element values, k contiguous columns per entry. Falls back to one ``np.bincount``
    per column if scipy's private kernel is not there.
    """
    m, k = values.shape
    try:
        from scipy.sparse import _sparsetools

        itype = slots.dtype
        _sparsetools.csc_matvecs(out.shape[0], m, k, np.arange(m + 1, dtype=itype), slots,
                                 np.ones(m), values.reshape(-1), out.reshape(-1))
    except (ImportError, AttributeError, TypeError, ValueError):
        index = slots.astype(np.intp)
        for c in range(k):
            out[:, c] += np.bincount(index, weights=values[:, c], minlength=out.shape[0])


def assemble_blocks(space: FESpace, material: Material, chunk_size: int = 4096,
                    pattern: BlockPattern | None = None, progress=None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Node-block values of K and M on ``pattern`` (default: :func:`block_pattern`).

    Returns (kcomp (9, n_blocks) N/m, component c = 3 i + j of every 3x3 stiffness block,
    the transpose of a C-ordered (n_blocks, 9) array; mblock (n_blocks,) kg, the mass
    block is mblock * I_3).
    ``progress``, if given, is called with the number of elements done after each chunk.

    Per chunk of ``chunk_size`` elements, one batched GEMM gives every element's nb^2
    node pairs x (9 stiffness components + mass): [R | m_ref] (nb^2 x 10) @ F_e (10 x 10)
    with F_e = [[Q_e, 0], [0, rho |det J_e|]], laid out element by element so that each
    (element, pair) row has its 10 values side by side and one element's rows fall into
    the same few node rows of the pattern; one scatter-add (:func:`_scatter_add`) sums them
    into the blocks. Measured at 314k DOFs against 9 + 1 ``np.bincount`` passes over
    component-major whole-mesh arrays: about 2.5x faster (docs/performance.md).
    """
    lam, mu = lame_parameters(material)
    if pattern is None:
        pattern = block_pattern(space)
    R, mass_ref = _reference_data(space.order)
    R_aug = np.concatenate([R, material.rho * mass_ref.reshape(-1, 1)], axis=1)  # (nb^2, 10)
    n_t = space.body.n_tetrahedra
    chunk_size = max(1, int(chunk_size))
    values = np.zeros((pattern.n_blocks, 10))
    factors = np.zeros((min(chunk_size, max(n_t, 1)), 10, 10))  # F_e[kl, c]
    for start in range(0, n_t, chunk_size):
        sl = slice(start, min(start + chunk_size, n_t))
        m = sl.stop - sl.start
        Q, vol = _element_factors(space, lam, mu, sl)  # Q[c, kl, e]
        F = factors[:m]
        F[:, :9, :9] = Q.transpose(2, 1, 0)
        F[:, 9, 9] = vol
        del Q
        block = np.matmul(R_aug, F)  # (m, nb^2, 10): [element, pair, c]
        slots = np.ascontiguousarray(pattern.slots[:, sl].T).reshape(-1)
        _scatter_add(slots, block.reshape(-1, 10), values)
        del block
        if progress is not None:
            progress(m)
    mblock = values[:, 9].copy()
    kblocks = np.ascontiguousarray(values[:, :9])  # (n_blocks, 9): row gathers stay fast
    del values
    return kblocks.T, mblock


def assemble_stiffness_mass(space: FESpace, material: Material, chunk_size: int = 4096,
                            pattern: BlockPattern | None = None, progress=None
                            ) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Assemble K (N/m) and M (kg), both (n_dofs x n_dofs) CSR, in the space's DOF order.

    :func:`assemble_blocks`, then :func:`stiffness_csr` and :func:`mass_csr`.
    """
    if pattern is None:
        pattern = block_pattern(space)
    kcomp, mblock = assemble_blocks(space, material, chunk_size, pattern, progress)
    K = stiffness_csr(pattern, kcomp)
    del kcomp
    return K, mass_csr(pattern, mblock)


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


def stiffness_csr(pattern: BlockPattern, kcomp: np.ndarray, free: np.ndarray | None = None
                  ) -> sp.csr_matrix:
    """K (N/m) in CSR with full 3x3 node blocks from the component arrays (9, n_blocks),
    restricted to the sorted ``free`` DOFs if given (``K[free][:, free]``).

    When ``free`` holds whole nodes (a clamped support), the blocks of fixed nodes are
    dropped before the expansion to CSR, so the full matrix is never built and the
    restriction pass over its 80M entries at 1M DOFs is not needed (0.3-0.5 s saved);
    otherwise the full matrix is built and restricted in place (:func:`restrict`).
    """
    n_nodes = pattern.n_nodes
    nodes = None if free is None else whole_nodes(free, n_nodes)
    if free is not None and nodes is None:
        return restrict(stiffness_csr(pattern, kcomp), free, overwrite=True)
    indptr = pattern.indptr.astype(np.int64)
    indices = pattern.indices
    if nodes is None or nodes.size == n_nodes:
        blocks = kcomp.T  # (n_blocks, 9), a view
    else:
        new_node = np.full(n_nodes, -1, dtype=np.int64)
        new_node[nodes] = np.arange(nodes.size)
        row_of = np.repeat(np.arange(n_nodes), np.diff(indptr))
        keep = (new_node[row_of] >= 0) & (new_node[indices] >= 0)
        del row_of
        kept = np.zeros(keep.size + 1, dtype=np.int64)
        np.cumsum(keep, out=kept[1:])
        indptr = kept[indptr[nodes]]
        indptr = np.append(indptr, kept[-1])
        indices = new_node[indices[keep]]
        blocks = kcomp.T[keep]  # one gather: restriction and transposition together
        del keep, kept
        n_nodes = nodes.size
    n = 3 * n_nodes
    itype = _index_dtype(max(9 * indices.size, n))
    K = sp.bsr_matrix((np.ascontiguousarray(blocks).reshape(-1, 3, 3),
                       indices.astype(itype, copy=False), indptr.astype(itype)),
                      shape=(n, n)).tocsr()
    del blocks
    itype = _index_dtype(max(K.nnz, n))
    K.indices = K.indices.astype(itype, copy=False)
    K.indptr = K.indptr.astype(itype, copy=False)
    return K


def mass_csr(pattern: BlockPattern, mblock: np.ndarray) -> sp.csr_matrix:
    """CSR of m_ab * I_3 for every node block: rows 3a+c hold columns 3b+c only."""
    n_nodes = pattern.n_nodes
    n = 3 * n_nodes
    ip = pattern.indptr.astype(np.int64)
    lens = np.diff(ip)
    nnz = 3 * pattern.n_blocks
    itype = _index_dtype(max(nnz, n))
    indptr = np.empty(n + 1, dtype=np.int64)
    indptr[0:n:3] = 3 * ip[:-1]
    indptr[1:n:3] = 3 * ip[:-1] + lens
    indptr[2:n:3] = 3 * ip[:-1] + 2 * lens
    indptr[n] = nnz
    # block k of node row a goes to positions k + 2 ip[a] + c len[a], c = 0, 1, 2
    row = np.repeat(np.arange(n_nodes, dtype=np.int64), lens)
    base = np.arange(pattern.n_blocks, dtype=np.int64) + 2 * ip[row]
    step = lens[row]
    del row
    indices = np.empty(nnz, dtype=itype)
    data = np.empty(nnz)
    col = 3 * pattern.indices.astype(itype)
    for c in range(3):
        pos = base + c * step
        indices[pos] = col + c
        data[pos] = mblock
    return sp.csr_matrix((data, indices, indptr.astype(itype)), shape=(n, n))


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
