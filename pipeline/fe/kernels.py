"""Element kernels of the assembly: the material's Lame parameters, the reference
element data, each element's geometric factors and the scatter-add of element values.

scikit-fem's Lagrange elements give the reference shape functions and its quadrature
rules the points and weights. On straight-sided tetrahedra the Jacobian J is constant per
element, so the element matrices are one matrix product for the whole mesh:

- stiffness: with R[ab, kl] = int_ref dphi_a/dxi_k dphi_b/dxi_l (exact with the degree
  2(p-1) rule: 4 points for P2), K_e[ab, ij] = sum_kl R[ab, kl] Q_e[kl, ij], where the
  9x9 matrix Q_e holds the element's J^-1, |det J| and the Lame parameters. One GEMM
  (nb^2 x 9) @ (9 x n_elements) per stiffness component (:func:`element_factors`);
- mass: one reference mass matrix (degree 2p rule) times each element's |det J|.

Used by :mod:`pipeline.fe.assemble` (K and M) and :mod:`pipeline.fe.strain` (stress modes).
"""

from __future__ import annotations

import numpy as np

from pipeline.config import Material
from pipeline.errors import SolverError
from pipeline.fe.space import FESpace

__all__ = ["check_material", "lame_parameters", "reference_data", "inverse_jacobians",
           "element_factors", "element_factors_general", "scatter_add"]


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


def reference_data(order: int):
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


def element_factors(space: FESpace, lam: float, mu: float, elems: np.ndarray):
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


def element_factors_general(space: FESpace, C: np.ndarray, elems: np.ndarray):
    """F (n, 9, 9) as :func:`element_factors` for a general stiffness tensor per element,
    C (n, 3, 3, 3, 3) Pa (sigma_ij = C_ijpq eps_pq):

        F[e, kl, ij] = |det J| sum_pq G[k, p] G[l, q] C[i, p, j, q]

    (K_e[ai, bj] = int dphi_a/dx_p C_ipjq dphi_b/dx_q); for an isotropic C it equals
    :func:`element_factors` to round-off."""
    G, vol = inverse_jacobians(space, elems)
    T = np.einsum("nkp,nipjq->nkijq", G, C, optimize=True)
    F = np.einsum("nlq,nkijq->nklij", G, T, optimize=True)
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
