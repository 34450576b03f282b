"""Floating-frame-of-reference (FFRF) data: the inertia invariants of theory.md §6.

A multibody code moves the body with a reference frame (origin O, rotation A) plus a
small elastic deflection in that frame, u(x) = Psi(x) q, q the n elastic coordinates.
Its kinetic energy needs, besides the reduced mass and stiffness, a few integrals over
the body ("inertia invariants"). With the consistent mass matrix M = M_s (x) I_3 they
are evaluated as bilinear forms: ``int rho a(x) . b(x) dV`` is ``a^T M b`` for nodal
fields a, b; cross products are taken node by node inside the same form
(``int rho a x b dV`` = sum_ij M_s,ij a_i x b_j). x_j are the node positions relative
to O, psi_k the k-th column of Psi, and ~ the skew (cross-product) matrix.

==============================  ==========================  ===========  =======================
term                            definition                  shape        Exudyn name
==============================  ==========================  ===========  =======================
mass m                          int rho dV                  ()           totalMass
first_moment                    int rho x dV = m c          (3,)         totalMass * chiU
center_of_mass c                first_moment / m            (3,)         chiU
inertia J0 (about O)            -int rho x~ x~ dV           (3, 3)       inertiaLocal
translational_coupling C_t      int rho psi_k dV            (3, n)       mPhitTPsi
rotational_coupling C_r         int rho x x psi_k dV        (3, n)       -mXRefTildePsi
modal_mass                      Psi^T M Psi                 (n, n)       massMatrixReduced
modal_stiffness                 Psi^T K Psi                 (n, n)       stiffnessMatrixReduced
inertia_first_order J1_k        -int rho (x~ psi_k~ +       (n, 3, 3)    X_k + X_k^T, X_k the
                                psi_k~ x~) dV                            k-th 3x3 block of
                                                                         mXRefTildePsiTilde
inertia_second_order J2_kl      -int rho psi_k~ psi_l~ dV   (n, n, 3, 3) block (k, l) of
                                                                         mPsiTildePsiTilde
gyroscopic_coupling G_kl        int rho psi_k x psi_l dV    (n, n, 3)    -(block k, column l of
                                                                         mPsiTildePsi)
==============================  ==========================  ===========  =======================

How they enter the equations of motion:

- [C_t; C_r] = R_O^T M Psi is the 6 x n coupling of the elastic coordinates with the
  rigid-body translation and rotation of the frame (zero for every column when Psi holds
  free-free modes with O at the centre of mass: the modes carry no momentum).
- the inertia tensor about O of the deflected body is
  J(q) = J0 + sum_k J1_k q_k + sum_kl J2_kl q_k q_l;
- the angular momentum of the elastic motion about O is (C_r + sum_k G_k. q_k) q', with
  G_k. the (3, n) slice G[k]: this gives the Coriolis and gyroscopic terms;
- the rigid-elastic rotational coupling of the deflected body is C_r + sum_k q_k G_k.

Bases (:func:`free_free_basis`, :func:`craig_bampton_basis`, or any (n_dofs, n) array):
free-free modes without the rigid-body modes; Craig-Bampton modes without the static
modes of the reference interface (the frame moves with it: Exudyn's convention); or the
modes clamped at a connection point (the frame is the clamp).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from pipeline.fe.body import rigid_body_modes

MODAL_UNIT = "m kg^1/2"

__all__ = ["FFRFInvariants", "ffrf_invariants", "invariants_from_products", "free_free_basis",
           "craig_bampton_basis", "craig_bampton_columns", "craig_bampton_kind",
           "modes_basis_labels", "skew_columns", "build_ffrf"]


@dataclass(frozen=True)
class FFRFInvariants:
    """The inertia invariants of the module docstring for one basis Psi (n_dofs x n)."""

    origin: np.ndarray
    mass: float
    first_moment: np.ndarray
    center_of_mass: np.ndarray
    inertia: np.ndarray
    translational_coupling: np.ndarray
    rotational_coupling: np.ndarray
    modal_mass: np.ndarray
    modal_stiffness: np.ndarray | None
    inertia_first_order: np.ndarray
    inertia_second_order: np.ndarray
    gyroscopic_coupling: np.ndarray
    basis: np.ndarray
    basis_kind: str
    coordinate_names: tuple[str, ...]
    coordinate_units: tuple[str, ...]

    @property
    def n(self) -> int:
        return int(self.basis.shape[1])

    def inertia_at(self, q: np.ndarray) -> np.ndarray:
        """J(q) (3, 3) kg m^2: inertia about O of the body deflected by q (n,)."""
        q = np.asarray(q, dtype=float)
        return (self.inertia + np.einsum("k,kab->ab", q, self.inertia_first_order)
                + np.einsum("k,l,klab->ab", q, q, self.inertia_second_order))


def skew_columns(V: np.ndarray) -> np.ndarray:
    """(3 n_nodes, 3 n) matrix whose 3x3 block (node j, column k) is skew(v_jk), for
    V (3 n_nodes, n) nodal vector fields (node-major DOF order)."""
    n_nodes = V.shape[0] // 3
    v = V.reshape(n_nodes, 3, -1)  # (j, c, k)
    out = np.zeros((n_nodes, 3, V.shape[1], 3))  # (j, row, k, col)
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    out[:, 0, :, 1], out[:, 0, :, 2] = -z, y
    out[:, 1, :, 0], out[:, 1, :, 2] = z, -x
    out[:, 2, :, 0], out[:, 2, :, 1] = -y, x
    return out.reshape(3 * n_nodes, 3 * V.shape[1])


def ffrf_invariants(M_full: sp.spmatrix, node_points: np.ndarray, basis: np.ndarray,
                    K_full: sp.spmatrix | None = None, origin=(0.0, 0.0, 0.0),
                    basis_kind: str = "", coordinate_names: Sequence[str] | None = None,
                    coordinate_units: Sequence[str] | None = None) -> FFRFInvariants:
    """Inertia invariants of ``basis`` (n_dofs, n) about ``origin`` (m).

    ``M_full`` (and ``K_full`` for the modal stiffness): (n_dofs x n_dofs) matrices of
    the unsupported body, DOF 3*node + component. ``node_points`` (n_nodes, 3) m.
    ``coordinate_units``: unit u_k of each elastic coordinate (default ``m kg^1/2``, the
    unit of M-orthonormal modal coordinates; Craig-Bampton static modes have m or rad).
    """
    O = np.asarray(origin, dtype=float).reshape(3)
    x = np.asarray(node_points, dtype=float) - O
    Psi = np.asarray(basis, dtype=float)
    R = rigid_body_modes(x)  # rows [I, -skew(x_j)]
    D = R.T @ (M_full @ R)
    MPsi = np.asarray(M_full @ Psi)
    modal_stiffness = None if K_full is None else Psi.T @ np.asarray(K_full @ Psi)
    PsiT = skew_columns(Psi)  # (3 n_nodes, 3 n)
    MPsiT = np.asarray(M_full @ PsiT)
    XT = skew_columns(x.reshape(-1, 1))  # (3 n_nodes, 3): skew(x_j) blocks
    return invariants_from_products(
        O, D, R.T @ MPsi, Psi.T @ MPsi, modal_stiffness, XT.T @ MPsiT, PsiT.T @ MPsiT,
        PsiT.T @ MPsi, Psi, basis_kind, coordinate_names, coordinate_units)


def invariants_from_products(O: np.ndarray, D: np.ndarray, coupling: np.ndarray,
                             modal_mass: np.ndarray, modal_stiffness: np.ndarray | None,
                             x_psi: np.ndarray, psi_psi: np.ndarray, psi_m_psi: np.ndarray,
                             basis, basis_kind: str = "",
                             coordinate_names: Sequence[str] | None = None,
                             coordinate_units: Sequence[str] | None = None) -> FFRFInvariants:
    """The :class:`FFRFInvariants` from the bilinear forms they are made of (n basis
    columns, x~ and Psi~ the :func:`skew_columns` of the node positions about ``O`` and of
    Psi): D = R_O^T M R_O (6, 6); coupling = R_O^T M Psi (6, n); modal_mass Psi^T M Psi
    and modal_stiffness Psi^T K Psi (n, n; None: no K); x_psi = x~^T M Psi~ (3, 3 n);
    psi_psi = Psi~^T M Psi~ (3 n, 3 n); psi_m_psi = Psi~^T M Psi (3 n, n)."""
    n = modal_mass.shape[0]
    D = 0.5 * (D + D.T)
    m = float(D[0, 0])
    S = -D[0:3, 3:6]  # R_t^T M R_r = -skew(m c)
    first = np.array([S[2, 1], S[0, 2], S[1, 0]])
    J0 = D[3:6, 3:6]
    if modal_stiffness is not None:
        modal_stiffness = 0.5 * (modal_stiffness + modal_stiffness.T)
    # skew(a)^T = -skew(a), so a block of A~^T M B~ is -int rho a~ b~:
    # X_k = -int rho x~ psi_k~  (3 x 3 per k)
    Xk = x_psi.reshape(3, n, 3).transpose(1, 0, 2)
    J1 = Xk + Xk.transpose(0, 2, 1)
    # J2_kl = -int rho psi_k~ psi_l~
    J2 = psi_psi.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)
    # G_kl = int rho psi_k x psi_l = int rho psi_k~ psi_l = -(psi_k~^T M psi_l)
    G = -psi_m_psi.reshape(n, 3, n).transpose(0, 2, 1)
    names = tuple(coordinate_names) if coordinate_names is not None else tuple(
        f"q_{i + 1}" for i in range(n))
    units = (tuple(coordinate_units) if coordinate_units is not None
             else (MODAL_UNIT,) * n)
    return FFRFInvariants(O, m, first, first / m, 0.5 * (J0 + J0.T), coupling[0:3],
                          coupling[3:6], 0.5 * (modal_mass + modal_mass.T), modal_stiffness,
                          J1, J2, G, basis, basis_kind, names, units)


def free_free_basis(shapes: np.ndarray, omega2: np.ndarray, n_rigid: int | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Elastic free-free modes: drop the rigid-body modes (the first ``n_rigid``, or those
    with omega2 == 0). ``shapes`` (n_dofs, n_m) or (n_points, 3, n_m). Returns
    (basis (n_dofs, n), kept mode indices)."""
    S = np.asarray(shapes)
    if S.ndim == 3:
        S = S.reshape(-1, S.shape[2])
    omega2 = np.asarray(omega2, dtype=float)
    if n_rigid is None:
        keep = np.flatnonzero(omega2 > 0)
    else:
        keep = np.arange(int(n_rigid), omega2.size)
    return S[:, keep], keep


def craig_bampton_basis(cb, reference: int | str = 0
                        ) -> tuple[np.ndarray, list[str], list[str]]:
    """The Craig-Bampton basis without the six static modes of the reference interface
    (index or name): the floating frame follows that interface. Returns (basis, names,
    units)."""
    keep, names, units = craig_bampton_columns(cb, reference)
    return cb.shapes[:, keep], names, units


def craig_bampton_columns(cb, reference: int | str = 0
                          ) -> tuple[list[int], list[str], list[str]]:
    """(kept column indices, names, units) of :func:`craig_bampton_basis`."""
    sl = (cb.interface_columns(reference) if isinstance(reference, str)
          else slice(6 * reference, 6 * reference + 6))
    keep = [i for i in range(len(cb.coordinate_names)) if not sl.start <= i < sl.stop]
    return (keep, [cb.coordinate_names[i] for i in keep],
            [cb.coordinate_units[i] for i in keep])


def craig_bampton_kind(cb, reference: int = 0) -> str:
    """The basis kind of :func:`craig_bampton_basis` (the frame follows the reference)."""
    return f"craig_bampton (frame follows interface '{cb.interfaces[reference].name}')"


def modes_basis_labels(keep: np.ndarray, supported: bool) -> tuple[str, list[str]]:
    """(basis kind, coordinate names) of a basis of the run's modes ``keep`` (indices)."""
    kind = "supported modes (frame = support)" if supported else "free-free elastic modes"
    return kind, [f"mode_{i + 1}" for i in keep]


#: units of each invariant for M-orthonormal modal coordinates (u = m kg^1/2), and the
#: general rule in terms of the coordinate units u_k, u_l
def build_ffrf(M_full: sp.spmatrix, K_full: sp.spmatrix | None, node_points: np.ndarray, *,
               cb=None, shapes: np.ndarray | None = None, omega2: np.ndarray | None = None,
               n_rigid: int = 0, supported: bool = False, origin=(0.0, 0.0, 0.0)
               ) -> FFRFInvariants:
    """Everything for ``/ffrf``, in one call, from the best basis available:

    - ``cb`` (a :class:`pipeline.reduce.craig_bampton.CraigBamptonModel`): its basis without the
      first interface's static modes;
    - else ``shapes`` (n_dofs, n_m) or (n_points, 3, n_m) and ``omega2`` of the run's
      modes: without the ``n_rigid`` rigid-body modes; ``supported`` says whether they
      are modes of a supported body (the frame is then the support).
    """
    if cb is not None:
        Psi, names, units = craig_bampton_basis(cb, 0)
        inv = ffrf_invariants(M_full, node_points, Psi, K_full, origin,
                              craig_bampton_kind(cb), names, units)
    else:
        if shapes is None or omega2 is None:
            raise ValueError("build_ffrf: give cb, or shapes and omega2")
        Psi, keep = free_free_basis(shapes, omega2, n_rigid)
        inv = ffrf_invariants(M_full, node_points, Psi, K_full, origin,
                              *modes_basis_labels(keep, supported))
    return inv
