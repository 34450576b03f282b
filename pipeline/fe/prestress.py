"""Prestress: centrifugal loads, the spin-softening mass and the geometric stiffness.

A body spinning at the constant angular velocity omega (rad/s, a 3-vector in the body
frame) about a point p (m), seen in the frame that spins with it, carries the
centrifugal body force per unit volume

    b(x) = rho (|omega|^2 I - omega omega^T) (x + u - p)                      (N/m^3)

which is linear in the six entries W_ij = omega_i omega_j of the angular-velocity
tensor W = omega omega^T (|omega|^2 = tr W). Per unit W_ij (the pairs of
:data:`TENSOR_ENTRIES`, i <= j) the force density is rho A_ij (x - p) with

    A_ii = I - e_i e_i^T,      A_ij = -(e_i e_j^T + e_j e_i^T)  (i < j),

so that sum_{i<=j} W_ij A_ij = |omega|^2 I - omega omega^T. For a spin Omega about a
unit axis a, W = Omega^2 a a^T and the weights are a_i a_j (:func:`tensor_weights`).

Discretised with the consistent mass (the nodal interpolation of the linear field
x - p is exact in the P1 and P2 spaces):

- the load at the reference state, per unit W_ij: f_ij = M_ij r (N per rad^2/s^2),
  with r (n_dofs,) the nodal values of x - p and M_ij = m (x) A_ij the mass matrix of
  A_ij (m: the scalar node mass matrix, kg; DOF 3 a + c is component c of node a);
- the displacement-dependent part of b, rho (|omega|^2 I - omega omega^T) u, is the
  spin-softening term: it enters the stiffness as -sum W_ij M_ij (for a spin about a:
  -Omega^2 M_perp, M_perp = m (x) (I - a a^T));
- the static stress sigma of the supported body under f (K u = f) stiffens it by the
  geometric (initial-stress) stiffness

      K_G(sigma)[u, v] = int sigma_ij (du_k/dx_i) (dv_k/dx_j) dV              (N/m),

  linear in sigma, hence in W: K_G = sum W_ij K_G,ij.

The linearised motion about the spinning state (constant omega) is then

    M u'' + G u' + (K + sum_ij W_ij (K_G,ij - M_ij)) u = f_ext,

and the prestressed modes at a spin Omega about a solve
(K + Omega^2 (K_G1 - M_perp)) phi = w^2 M phi (the Coriolis matrix G is left out, as
in the classical rotating-blade results). A static preload F (the input ports) gives
K + lambda K_G(sigma(F)) the same way (no softening term).

With several materials m takes each element's density and sigma each element's law
(sigma = D_e gamma). A rigid mass M6 = diag(m I, J) at P tied by a distributing coupling
(six motions q = G u) adds G^T (.) G of its rigid-body terms per unit W_ij: the load
[m A (P - p); int r x A r dm], the softening blockdiag(m A, int [r]^T A [r] dm) and its
own initial-stress stiffness blockdiag(0, tr(A S) I - sym(A S)), S = int r r^T dm about
P (:func:`point_mass_prestress`; the second-order terms of its centrifugal potential).

Matrices are assembled with scikit-fem (``skfem.asm`` in element chunks; speed matters
less than for K and M), on every DOF of the space (n_dofs x n_dofs, CSR); the caller
restricts them to the free DOFs.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

from pipeline.config import Material
from pipeline.config.rotation import TENSOR_ENTRIES, TENSOR_NAMES, entry_matrix, tensor_weights
from pipeline.fe.kernels import lame_parameters
from pipeline.fe.materials import VOIGT_INDEX, ElementMaterials
from pipeline.fe.space import FESpace

log = logging.getLogger(__name__)

__all__ = ["TENSOR_ENTRIES", "TENSOR_NAMES", "entry_matrix", "tensor_weights",
           "node_mass_matrix", "tensor_mass", "centrifugal_loads", "geometric_stiffness",
           "point_mass_prestress", "rigid_mass_of", "rigid_centrifugal_load",
           "rigid_geometric_stiffness"]

def node_mass_matrix(space: FESpace, rho) -> sp.csr_matrix:
    """The scalar consistent mass m (n_nodes x n_nodes, kg): m_ab = int rho N_a N_b dV,
    so the vector mass matrix is m (x) I_3. ``rho``: one density (kg/m^3) or each
    element's, (n_e,). Assembled with scikit-fem's scalar Lagrange element of the space's
    order (its DOFs are the space's nodes, in the same order)."""
    from skfem import Basis, BilinearForm, ElementTetP1, ElementTetP2

    element = ElementTetP2() if space.order == 2 else ElementTetP1()
    basis = Basis(space.skfem_mesh, element, intorder=2 * space.order)
    if np.ndim(rho) == 0:
        @BilinearForm
        def mass(u, v, w):
            return rho * u * v

        return mass.assemble(basis).tocsr()

    @BilinearForm
    def mass_per_element(u, v, w):
        return w["rho"] * u * v

    rho_q = np.repeat(np.asarray(rho, dtype=float)[:, None], basis.X.shape[-1], axis=1)
    return mass_per_element.assemble(basis, rho=rho_q).tocsr()


def tensor_mass(node_mass: sp.spmatrix, A: np.ndarray) -> sp.csr_matrix:
    """The mass matrix of the 3 x 3 matrix A, m (x) A (n_dofs x n_dofs, kg): the
    spin-softening matrix of one tensor entry (A = A_ij) or of a spin about a unit axis
    a (A = I - a a^T: M_perp)."""
    return sp.kron(node_mass, sp.csr_matrix(np.asarray(A, dtype=float)), format="csr")


def centrifugal_loads(space: FESpace, node_mass: sp.spmatrix,
                      point: np.ndarray) -> np.ndarray:
    """(n_dofs, 6) the consistent centrifugal loads f_ij = (m (x) A_ij) r per unit W_ij
    (N per rad^2/s^2, columns in :data:`TENSOR_ENTRIES` order), r the nodal x - ``point``
    (m). The load of a spin Omega about the unit axis a is Omega^2 f @ tensor_weights(a)."""
    r = space.node_points - np.asarray(point, dtype=float)  # (n_nodes, 3)
    mr = node_mass @ r  # (n_nodes, 3): the consistent mass times each component
    out = np.empty((space.n_dofs, len(TENSOR_ENTRIES)))
    for col, (i, j) in enumerate(TENSOR_ENTRIES):
        out[:, col] = (mr @ entry_matrix(i, j).T).reshape(-1)
    return out


def _element_stress(D: np.ndarray, eps: np.ndarray) -> np.ndarray:
    """(3, 3, n_e, n_q) Pa: sigma = D_e gamma of the strain tensors eps (3, 3, n_e, n_q)
    with D (n_e, 6, 6) (Voigt order VOIGT_INDEX, engineering shear gamma_ij = 2 eps_ij)."""
    gamma = np.stack([eps[i, j] * (1.0 if i == j else 2.0) for i, j in VOIGT_INDEX])
    sig_v = np.einsum("eIJ,Jeq->Ieq", D, gamma)
    sig = np.empty_like(eps)
    for I, (i, j) in enumerate(VOIGT_INDEX):
        sig[i, j] = sig[j, i] = sig_v[I]
    return sig


def _chunks(n: int, size: int):
    for start in range(0, n, size):
        yield np.arange(start, min(n, start + size))


def geometric_stiffness(space: FESpace, material: "Material | ElementMaterials",
                        displacements: np.ndarray, chunk_size: int = 8000
                        ) -> list[sp.csr_matrix]:
    """The geometric stiffness K_G(sigma(u)) (n_dofs x n_dofs, CSR, N/m) of each column
    of ``displacements`` (n_dofs, k) (m): sigma = 2 mu eps(u) + lambda tr(eps(u)) I,
    eps = sym grad u (one isotropic ``material``), or sigma = D_e gamma(u) with each
    element's own law (``material`` an :class:`~pipeline.fe.materials.ElementMaterials`
    whose elements differ: Voigt order and engineering shear of pipeline.fe.materials),
    and K_G[u, v] = int sigma_ij du_k/dx_i dv_k/dx_j dV.

    The form couples equal components only, so K_G = g (x) I_3 with the scalar
    g_ab = int sigma_ij dN_a/dx_i dN_b/dx_j dV, assembled with scikit-fem's scalar
    Lagrange element (a ninth of the vector form's work), integrated exactly on straight
    elements (degree 3 for P2, 0 for P1), in chunks of ``chunk_size`` elements.
    """
    from skfem import BilinearForm, Basis, ElementTetP1, ElementTetP2
    from skfem.helpers import dot, grad, mul

    if isinstance(material, ElementMaterials) and material.uniform is not None:
        material = material.uniform  # one isotropic law: the single-material path
    per_element = isinstance(material, ElementMaterials)
    if not per_element:
        lam, mu = lame_parameters(material)
    U = np.asarray(displacements, dtype=float).reshape(space.n_dofs, -1)

    @BilinearForm
    def initial_stress(u, v, w):
        return dot(mul(w["sig"], grad(u)), grad(v))

    element = ElementTetP2() if space.order == 2 else ElementTetP1()
    n_t = space.element_nodes.shape[0]
    scalar = [sp.csr_matrix((space.n_nodes, space.n_nodes)) for _ in range(U.shape[1])]
    for elements in _chunks(n_t, chunk_size):
        basis = Basis(space.skfem_mesh, element, intorder=3 if space.order == 2 else 1,
                      elements=elements)
        for col in range(U.shape[1]):
            # du_c/dx_j of each component c: (3, 3, n_e, n_q)
            G = np.stack([basis.interpolate(U[c::3, col]).grad for c in range(3)])
            eps = 0.5 * (G + G.transpose(1, 0, 2, 3))
            if per_element:
                sig = _element_stress(material.element_D(elements), eps)
            else:
                sig = 2.0 * mu * eps + lam * np.einsum("ii...->...", eps) * np.eye(3)[:, :, None, None]
            scalar[col] = scalar[col] + initial_stress.assemble(basis, sig=sig).tocsr()
    eye = sp.identity(3, format="csr")
    return [sp.kron(g, eye, format="csr") for g in scalar]


# --------------------------------------------------------------------------- point masses
#: the Levi-Civita symbol eps_ijk
_LEVI_CIVITA = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI_CIVITA[_i, _j, _k], _LEVI_CIVITA[_i, _k, _j] = 1.0, -1.0


def second_moment(M6: np.ndarray) -> np.ndarray:
    """(3, 3) kg m^2: S = int r r^T dm about the point, of a rigid mass M6 = diag(m I, J)
    (J = tr(S) I - S, so S = tr(J)/2 I - J)."""
    J = M6[3:, 3:]
    return 0.5 * np.trace(J) * np.eye(3) - J


def rigid_mass_of(M6: np.ndarray, A: np.ndarray) -> np.ndarray:
    """(6, 6) the mass of the 3 x 3 matrix A for a rigid body (the rigid-body form of
    m (x) A): the field A (u_P + theta x r) summed over dm against v_P + delta x r,
    blockdiag(m A, int [r]^T A [r] dm) about the centre of mass P ([r] v = r x v)."""
    out = np.zeros((6, 6))
    out[:3, :3] = M6[0, 0] * np.asarray(A, dtype=float)
    out[3:, 3:] = np.einsum("cak,dbl,cd,kl->ab", _LEVI_CIVITA, _LEVI_CIVITA, A,
                            second_moment(M6))
    return out


def rigid_centrifugal_load(M6: np.ndarray, offset: np.ndarray, A: np.ndarray) -> np.ndarray:
    """(6,) [force N; moment N m about P] per unit W_ij of the density A (x - p) on a
    rigid body at P (``offset`` = P - p, m): m A (P - p) and int r x (A r) dm."""
    S = second_moment(M6)
    return np.concatenate([M6[0, 0] * (A @ offset),
                           np.einsum("ijk,kj->i", _LEVI_CIVITA, A @ S)])


def rigid_geometric_stiffness(M6: np.ndarray, A: np.ndarray) -> np.ndarray:
    """(6, 6) the rigid body's own initial-stress stiffness per unit W_ij: the second-order
    part of its centrifugal potential -1/2 int (x - p)^T A (x - p) dm in a rotation theta,
    beyond the softening theta^T (int [r]^T A [r] dm) theta:
    blockdiag(0, tr(A S) I - sym(A S)). With it, a rotation about the spin axis (or any
    rotation under A = I) leaves the potential unchanged, as it must."""
    AS = np.asarray(A, dtype=float) @ second_moment(M6)
    out = np.zeros((6, 6))
    out[3:, 3:] = np.trace(AS) * np.eye(3) - 0.5 * (AS + AS.T)
    return out


def point_mass_prestress(point_masses, point, n_dofs: int
                         ) -> tuple[np.ndarray, list[sp.csr_matrix], list[sp.csr_matrix]]:
    """The centrifugal loads (n_dofs, 6), spin-softening masses and own geometric
    stiffnesses (six n_dofs x n_dofs CSR each, per unit W_ij in TENSOR_ENTRIES order) of
    rigid masses tied by distributing couplings: ``point_masses`` of (dofs, G, M6, P)
    (:func:`pipeline.fe.added_mass.distributing_point_masses`), each term G^T (.) G."""
    loads = np.zeros((n_dofs, len(TENSOR_ENTRIES)))
    soft = [sp.csr_matrix((n_dofs, n_dofs)) for _ in TENSOR_ENTRIES]
    geo = [sp.csr_matrix((n_dofs, n_dofs)) for _ in TENSOR_ENTRIES]
    for dofs, G, M6, P in point_masses:
        offset = np.asarray(P, dtype=float) - np.asarray(point, dtype=float)
        rows, cols = np.meshgrid(dofs, dofs, indexing="ij")
        for col, (i, j) in enumerate(TENSOR_ENTRIES):
            A = entry_matrix(i, j)
            loads[dofs, col] += G.T @ rigid_centrifugal_load(M6, offset, A)
            for out, block in ((soft, rigid_mass_of(M6, A)),
                               (geo, rigid_geometric_stiffness(M6, A))):
                out[col] = out[col] + sp.csr_matrix(
                    ((G.T @ block @ G).ravel(), (rows.ravel(), cols.ravel())),
                    shape=(n_dofs, n_dofs))
    return loads, soft, geo
