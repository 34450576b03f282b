"""Assembly stage: linear-elasticity stiffness K and consistent mass M.

scikit-fem is the finite-element engine: its mesh numbers the edges, its Lagrange
elements give the reference shape functions and its quadrature rules the points and
weights. On straight-sided tetrahedra the Jacobian is constant per element, so the
element matrices are batched matrix products over element chunks:

- stiffness with the degree 2(p-1) rule (4 points for P2, exact for straight elements);
- consistent mass from one reference mass matrix times each element's volume.

Both matrices share one node-block sparsity pattern (3x3 blocks per node pair), built
once; element blocks are summed into it with ``np.bincount``. The result equals
``skfem.asm`` of the same forms to round-off (``tests/test_assemble.py``), without
ever holding basis values for the whole mesh.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .config import Material
from .fespace import FESpace

log = logging.getLogger(__name__)


def lame_parameters(material: Material) -> tuple[float, float]:
    """(lambda, mu) in Pa from Young's modulus and Poisson's ratio."""
    E, nu = material.E, material.nu
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


@dataclass(frozen=True)
class BlockPattern:
    """Node-pair sparsity pattern shared by K and M.

    indptr (n_nodes + 1,), indices (n_blocks,): CSR structure of the node graph.
    slots: (n_t, nb * nb) block index of every element node pair (a, b), row-major.
    """

    indptr: np.ndarray
    indices: np.ndarray
    slots: np.ndarray
    n_nodes: int

    @property
    def n_blocks(self) -> int:
        return int(self.indices.size)


def block_pattern(space: FESpace) -> BlockPattern:
    """The node-pair pattern of ``space`` (every pair of nodes sharing an element)."""
    en = space.element_nodes.astype(np.int64)
    n_t, nb = en.shape
    n = space.n_nodes
    keys = (en[:, :, None] * n + en[:, None, :]).reshape(n_t, nb * nb)
    unique, inverse = np.unique(keys, return_inverse=True)
    del keys
    itype = np.int32 if unique.size < 2**31 - 1 else np.int64
    rows = unique // n
    indices = (unique - rows * n).astype(itype)
    indptr = np.zeros(n + 1, dtype=np.int64)
    indptr[1:] = np.bincount(rows, minlength=n)
    indptr = np.cumsum(indptr).astype(itype)
    return BlockPattern(indptr, indices, inverse.reshape(n_t, nb * nb).astype(itype), n)


def _reference_data(order: int):
    """Reference-element gradients at the stiffness rule and the reference mass matrix.

    Returns dphi (n_q, nb, 3), weights (n_q,) and mass_ref (nb, nb) on the unit
    tetrahedron (volume 1/6).
    """
    from skfem import ElementTetP1, ElementTetP2
    from skfem.quadrature import get_quadrature
    from skfem.refdom import RefTet

    elem = ElementTetP2() if order == 2 else ElementTetP1()
    nb = elem.doflocs.shape[0]
    Xk, Wk = get_quadrature(RefTet, max(2 * (order - 1), 1))
    dphi = np.stack([elem.lbasis(Xk, i)[1] for i in range(nb)])  # (nb, 3, n_q)
    Xm, Wm = get_quadrature(RefTet, 2 * order)
    phi = np.stack([elem.lbasis(Xm, i)[0] for i in range(nb)])  # (nb, n_q)
    mass_ref = (phi * Wm) @ phi.T
    return np.ascontiguousarray(dphi.transpose(2, 0, 1)), Wk, mass_ref


def _jacobians(space: FESpace, elems: slice):
    v = space.body.vertices
    t = space.body.tetrahedra[elems]
    a = v[t[:, 0]]
    J = np.stack([v[t[:, 1]] - a, v[t[:, 2]] - a, v[t[:, 3]] - a], axis=2)  # (n, 3, 3) columns
    det = np.linalg.det(J)
    return J, det


def _to_csr(pattern: BlockPattern, data: np.ndarray) -> sp.csr_matrix:
    n = 3 * pattern.n_nodes
    bsr = sp.bsr_matrix((data, pattern.indices, pattern.indptr), shape=(n, n))
    csr = bsr.tocsr()
    if n < 2**31 // 40:  # 32-bit indices where they fit
        csr.indices = csr.indices.astype(np.int32, copy=False)
        csr.indptr = csr.indptr.astype(np.int32, copy=False)
    return csr


def assemble_stiffness_mass(space: FESpace, material: Material, chunk_size: int = 16384,
                            pattern: BlockPattern | None = None, progress=None
                            ) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Assemble K (N/m) and M (kg), both (n_dofs x n_dofs) CSR, in the space's DOF order.

    ``progress``, if given, is called with the number of elements done after each chunk.
    """
    lam, mu = lame_parameters(material)
    if pattern is None:
        pattern = block_pattern(space)
    dphi, wq, mass_ref = _reference_data(space.order)
    n_q, nb, _ = dphi.shape
    n_t = space.body.n_tetrahedra
    kdata = np.zeros((pattern.n_blocks, 3, 3))
    mdiag = np.zeros(pattern.n_blocks)
    eye = np.eye(3)
    for start in range(0, n_t, chunk_size):
        sl = slice(start, min(start + chunk_size, n_t))
        J, det = _jacobians(space, sl)
        vol = np.abs(det)
        invJ = np.linalg.inv(J)  # (n, 3, 3): d xi_k / d x_j = invJ[k, j]
        G = np.einsum("qbk,nkj->nqbj", dphi, invJ, optimize=True)  # (n, q, nb, 3)
        Gw = G * (vol[:, None] * wq)[:, :, None, None]
        n = G.shape[0]
        S = np.matmul(Gw.reshape(n, n_q, nb * 3).transpose(0, 2, 1), G.reshape(n, n_q, nb * 3))
        S = S.reshape(n, nb, 3, nb, 3).transpose(0, 1, 3, 2, 4)  # (n, a, b, i, j)
        trace = np.einsum("nabkk->nab", S)
        Ke = lam * S + mu * S.transpose(0, 1, 2, 4, 3) + mu * trace[..., None, None] * eye
        slots = pattern.slots[sl].ravel()
        Ke = Ke.reshape(-1, 9)
        for c in range(9):
            kdata[:, c // 3, c % 3] += np.bincount(slots, weights=Ke[:, c],
                                                   minlength=pattern.n_blocks)
        mdiag += np.bincount(slots, weights=(vol[:, None, None] * mass_ref).ravel(),
                             minlength=pattern.n_blocks)
        if progress is not None:
            progress(sl.stop - sl.start)
    K = _to_csr(pattern, kdata)
    del kdata
    mdata = (material.rho * mdiag)[:, None, None] * eye
    del mdiag
    M = _to_csr(pattern, mdata)
    return K, M


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


def restrict(A: sp.spmatrix, keep: np.ndarray) -> sp.csr_matrix:
    """A[keep][:, keep] (condensation of the supports) for sorted ``keep`` indices."""
    A = sp.csr_matrix(A)
    if keep.size == A.shape[0]:
        return A
    sub = A[keep]
    return sub[:, keep].tocsr()
