"""Connection points of a flexible body: the hybrid-cantilever (6x6) model of theory.md
section 5 at a parent point, with optional child points.

Notation (SI; twist order [v; omega], wrench order [F; T]; ``R_P``, ``D_P``): as in
:mod:`pipeline.reduce.interfaces`.

Interfaces (RBE2 / RBE3 couplings, the clamping change of coordinates) are built by
:mod:`pipeline.reduce.interfaces`.

Hybrid-cantilever model (one parent point P, optional child points C_k)
-----------------------------------------------------------------------
With the parent interface clamped (q_P = 0) and the child interfaces free, the modes of
(K_c, M_c) are the clamped modes Phi_c (M-orthonormal, N of them). The body's motion is
s = R_P q_P + Phi_c eta, exactly (K R_P = 0 for an unsupported body), so

    [D_P  L_P^T] [a_P ]   [0          ]   [W_P + sum_k tau_k^T W_k]
    [L_P  I    ] [eta''] + [Omega2 eta ] = [Phi_k^T W_k            ]

with L_P = Phi_c^T M R_P (N x 6), tau_k = [[I, skew(P - C_k)], [0, I]] (twist at P to
twist at C_k), Phi_k the rows of the clamped modes at the child coordinates q_k (6 x N)
and W_k the wrench applied to the body at C_k. Eliminating eta'' gives the state-space
model of :func:`connection_statespace` (inputs [a_P; W_1; ...], outputs [W_P; a_1; ...],
states [eta; eta']):

    A = [[0, I], [-Omega2, -2 Xi Omega]]
    B = [[0, 0], [-L_P, Phi_C^T]]
    C = [[-L_P^T Omega2, -L_P^T 2 Xi Omega], [-Phi_C Omega2, -Phi_C 2 Xi Omega]]
    D = [[D_P0, L_P^T Phi_C^T - tau^T], [tau - Phi_C L_P, Phi_C Phi_C^T]]

D_P0 = D_P - L_P^T L_P is the residual (interface) mass. W_P is the wrench the parent
exerts on the body at P (the body exerts -W_P on the parent); at zero frequency
W_P = D_P a_P: the body moves as a rigid body. Without child points this is exactly
theory.md §5.

Effective modal masses: m_eff[i, d] = L_P[i, d]^2 (kg for d = x, y, z translations,
kg m^2 for rotations about P). Summed over all modes they reach D_P - D_P0, where D_P0
is the mass the interface carries itself (for a lumped mass matrix and rigid coupling,
exactly the rigid mass of the region nodes). The cumulative fraction per direction is
sum_{j <= i} m_eff[j, d] / D_P[d, d], the "90% of the mass" criterion.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from pipeline.fe.body import rigid_body_modes
from pipeline.errors import RegionError, SolverError
from pipeline.reduce.interfaces import (DIRECTIONS, Interface, RigidProperties,
                                        check_interfaces, interface_transformation,
                                        make_interfaces, project, rigid_properties_at,
                                        twist_transform)
from pipeline.reduce.statespace import StateSpace
from pipeline.solve import eigen  # module: solve_modes is looked up at call time

log = logging.getLogger(__name__)

__all__ = [
    "clamped_modes",
    "connection_model_from_modes",
    "model_from_clamped",
    "check_residual_mass",
    "ConnectionModel",
    "connection_model",
    "connection_statespace",
    "effective_mass_table",
    "build_connection_model",
]


# --------------------------------------------------------------------------- 6x6 model
@dataclass(frozen=True)
class ConnectionModel:
    """Hybrid-cantilever model of the body at its parent point (see module docstring).

    parent: the parent interface; children: child interfaces (may be empty).
    rigid: RigidProperties at the parent point (D_P = rigid.D_P).
    omega2 (N,) rad^2/s^2 clamped modes; L_P (N, 6) (kg^1/2 | kg^1/2 m); D_P0 (6, 6).
    shapes: (n_dofs, N) clamped mode shapes on every DOF, kg^-1/2.
    Phi_C: (6 n_c, N) clamped modes at the child coordinates (m kg^-1/2 | rad kg^-1/2).
    tau_C: (6 n_c, 6) rigid transport of a twist from P to each child point.
    residuals: (N,) eigen-residuals of the clamped solve.
    """

    parent: Interface
    children: tuple[Interface, ...]
    rigid: RigidProperties
    omega2: np.ndarray
    L_P: np.ndarray
    D_P0: np.ndarray
    shapes: np.ndarray
    Phi_C: np.ndarray
    tau_C: np.ndarray
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def D_P(self) -> np.ndarray:
        return self.rigid.D_P

    @property
    def frequencies_hz(self) -> np.ndarray:
        return np.sqrt(np.maximum(self.omega2, 0.0)) / (2 * np.pi)

    @property
    def effective_mass(self) -> np.ndarray:
        """(N, 6) L_P^2: kg (x, y, z), kg m^2 (rx, ry, rz about P)."""
        return self.L_P ** 2

    @property
    def effective_mass_cumulative_fraction(self) -> np.ndarray:
        """(N, 6) cumulative effective mass / diag(D_P) (dimensionless, rises with i)."""
        return np.cumsum(self.effective_mass, axis=0) / np.diag(self.D_P)


def check_residual_mass(D_P0: np.ndarray, name: str, rtol: float = 1e-9) -> np.ndarray:
    """Return the symmetrised D_P0, or raise SolverError unless it is symmetric positive
    definite: on the matrix scaled to a unit diagonal (dimensionless), the asymmetry must
    stay below 1e-8 and the smallest eigenvalue above ``rtol`` times the largest."""
    D = np.asarray(D_P0, dtype=float)
    diag = np.diag(D)
    if not np.all(np.isfinite(D)) or np.any(diag <= 0):
        raise SolverError(f"connection '{name}': residual mass D_P0 = D_P - L_P^T L_P has a "
                          f"non-positive diagonal {np.array2string(diag, precision=4)}; expected "
                          "a symmetric positive definite matrix (are the clamped modes "
                          "M-orthonormal and computed on the unsupported body?)")
    s = 1.0 / np.sqrt(diag)
    Dn = D * s[:, None] * s[None, :]
    asym = float(np.abs(Dn - Dn.T).max())
    eig = np.linalg.eigvalsh(0.5 * (Dn + Dn.T))
    if asym > 1e-8 or eig[0] <= rtol * eig[-1]:
        raise SolverError(
            f"connection '{name}': residual mass D_P0 = D_P - L_P^T L_P is not symmetric "
            f"positive definite (smallest eigenvalue of the diagonally scaled matrix "
            f"{eig[0]:.3e}, asymmetry {asym:.3e}); the model is refused: the clamped modes "
            "are not M-orthonormal, or not clamped at this connection, or the mass matrix "
            "is not that of the unsupported body")
    return 0.5 * (D + D.T)


def clamped_modes(K: sp.spmatrix, M: sp.spmatrix, n_modes: int | None, backend: str = "auto",
                  tolerance: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(omega2 (N,), shapes (n, N) M-orthonormal, residuals (N,)) of a supported problem.

    ``backend="dense"``: scipy.linalg.eigh on dense copies (small problems; ``n_modes``
    None gives every mode). Otherwise :func:`pipeline.solve.eigen.solve_modes` (shift-invert
    eigsh with ``backend`` auto | pardiso | superlu).
    """
    if backend == "dense":
        Kd, Md = K.toarray(), M.toarray()
        Kd, Md = 0.5 * (Kd + Kd.T), 0.5 * (Md + Md.T)
        n = Kd.shape[0]
        subset = None if n_modes is None else [0, min(n_modes, n) - 1]
        w, V = sla.eigh(Kd, Md, subset_by_index=subset)
        res = np.linalg.norm(Kd @ V - (Md @ V) * w, axis=0) / np.maximum(
            np.linalg.norm(Kd @ V, axis=0), 1e-300)
        return w, V, res
    if n_modes is None:
        raise SolverError("n_modes=None (every mode) needs backend='dense'")
    modes = eigen.solve_modes(K, M, n_modes, supported=True, backend=backend, tolerance=tolerance)
    return modes.omega2, modes.shapes, modes.residuals


def connection_model(space, K_full: sp.spmatrix, M_full: sp.spmatrix,
                     interfaces: Sequence[Interface], n_modes: int | None,
                     backend: str = "auto", tolerance: float = 0.0) -> ConnectionModel:
    """The hybrid-cantilever model at ``interfaces[0]`` (the parent point P), with
    ``interfaces[1:]`` as child points.

    ``K_full``, ``M_full``: (n_dofs x n_dofs) assembled matrices of the UNSUPPORTED body
    (before :func:`pipeline.fe.assemble.restrict`: the connection replaces the supports).
    ``n_modes``: number of clamped modes N. ``backend``/``tolerance``: as for
    :func:`pipeline.solve.eigen.solve_modes`, or ``backend="dense"`` for a dense solve of a
    small model (then ``n_modes=None`` keeps every mode).
    """
    interfaces = tuple(interfaces)
    if not interfaces:
        raise RegionError("connections: expected at least one connection (the parent point)")
    check_interfaces(interfaces)
    parent, children = interfaces[0], interfaces[1:]
    node_points = space.node_points if hasattr(space, "node_points") else np.asarray(space)
    n_dofs = 3 * node_points.shape[0]
    # q_P last, so the clamped coordinates are the leading columns [z; q_C]
    tr = interface_transformation(n_dofs, node_points, children + (parent,))
    n_c = tr.n_z + 6 * len(children)
    Tc = tr.T[:, :n_c].tocsc()
    Kc = project(K_full, Tc)
    Mc = project(M_full, Tc)
    omega2, Phi_x, residuals = clamped_modes(Kc, Mc, n_modes, backend, tolerance)
    shapes = np.asarray(Tc @ Phi_x)
    rigid = rigid_properties_at(M_full, node_points, parent.point)
    R_P = rigid_body_modes(node_points, parent.point)
    L_P = shapes.T @ (M_full @ R_P)
    return model_from_clamped(parent, children, rigid, omega2, L_P, shapes,
                              Phi_x[tr.n_z:n_c], residuals)


def model_from_clamped(parent: Interface, children: tuple[Interface, ...],
                       rigid: RigidProperties, omega2: np.ndarray, L_P: np.ndarray, shapes,
                       Phi_C: np.ndarray, residuals: np.ndarray) -> ConnectionModel:
    """The :class:`ConnectionModel` from its clamped solve's results (the fields' units
    and shapes are the record's): the residual mass checked, the child transports
    tau_C made."""
    D_P0 = check_residual_mass(rigid.D_P - L_P.T @ L_P, parent.name)
    tau_C = (np.vstack([twist_transform(parent.point, c.point) for c in children])
             if children else np.zeros((0, 6)))
    f = np.sqrt(np.maximum(omega2, 0.0)) / (2 * np.pi)
    log.info("connection '%s': %d clamped modes, %.4g .. %.4g Hz, %d child point(s)",
             parent.name, omega2.size, f[0], f[-1], len(children))
    return ConnectionModel(parent, children, rigid, omega2, L_P, D_P0, shapes, Phi_C,
                           tau_C, residuals)


def connection_model_from_modes(parent: Interface, node_points: np.ndarray, M_full,
                                 shapes: np.ndarray, omega2: np.ndarray) -> ConnectionModel:
    """The model of a single rigid connection from clamped modes already solved elsewhere
    (e.g. the pipeline's own modes of a body supported on exactly the parent region):
    ``shapes`` (n_dofs, N) M-orthonormal, zero on the region's DOFs."""
    rigid = rigid_properties_at(M_full, node_points, parent.point)
    R_P = rigid_body_modes(node_points, parent.point)
    L_P = shapes.T @ (M_full @ R_P)
    D_P0 = check_residual_mass(rigid.D_P - L_P.T @ L_P, parent.name)
    return ConnectionModel(parent, (), rigid, np.asarray(omega2, float), L_P, D_P0,
                           np.asarray(shapes), np.zeros((0, len(omega2))), np.zeros((0, 6)))


# --------------------------------------------------------------------------- state space
ACC_UNITS = ("m/s^2",) * 3 + ("rad/s^2",) * 3
WRENCH_UNITS = ("N",) * 3 + ("N m",) * 3
ACC_NAMES = ("ax", "ay", "az", "alpha_x", "alpha_y", "alpha_z")
WRENCH_NAMES = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")


def _xi(damping_ratio, n: int) -> np.ndarray:
    xi = np.broadcast_to(np.asarray(damping_ratio, dtype=float), (n,)).copy()
    if np.any(xi < 0) or np.any(xi >= 1):
        raise SolverError(f"connection damping ratios must lie in [0, 1), got {xi}")
    return xi


def connection_statespace(model: ConnectionModel, damping_ratio=0.0) -> StateSpace:
    """The 6(1 + n_c)-input, 6(1 + n_c)-output model of the module docstring, a
    :class:`StateSpace` labelled ``"connection"``: u = [a_P; W_1; ...], y = [W_P; a_1; ...],
    x = [eta; eta'] (eta in m kg^1/2), units per name in ``input_units`` /
    ``output_units``; ``attrs["damping_ratio"]`` holds the (n,) modal damping ratios.

    ``damping_ratio``: one ratio for every clamped mode, or one per mode.
    """
    omega2 = np.asarray(model.omega2, dtype=float)
    n = omega2.size
    xi = _xi(damping_ratio, n)
    w = np.sqrt(np.maximum(omega2, 0.0))
    O2, G2 = np.diag(omega2), np.diag(2.0 * xi * w)
    L, Pc, tau = model.L_P, model.Phi_C, model.tau_C
    nc = Pc.shape[0]
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-O2, -G2]])
    B = np.block([[np.zeros((n, 6)), np.zeros((n, nc))], [-L, Pc.T]])
    C = np.block([[-L.T @ O2, -L.T @ G2], [-Pc @ O2, -Pc @ G2]])
    D = np.block([[model.D_P0, L.T @ Pc.T - tau.T], [tau - Pc @ L, Pc @ Pc.T]])
    p = model.parent.name
    in_names = [f"{p}.{a}" for a in ACC_NAMES]
    out_names = [f"{p}.{f}" for f in WRENCH_NAMES]
    in_units, out_units = list(ACC_UNITS), list(WRENCH_UNITS)
    for c in model.children:
        in_names += [f"{c.name}.{f}" for f in WRENCH_NAMES]
        out_names += [f"{c.name}.{a}" for a in ACC_NAMES]
        in_units += WRENCH_UNITS
        out_units += ACC_UNITS
    states = [f"eta_{i + 1}" for i in range(n)] + [f"eta_{i + 1}_dot" for i in range(n)]
    return StateSpace(A, B, C, D, input_names=tuple(in_names), output_names=tuple(out_names),
                      state_names=tuple(states), input_units=tuple(in_units),
                      output_units=tuple(out_units), label="connection",
                      attrs={"damping_ratio": xi})


# --------------------------------------------------------------------------- tables
def effective_mass_table(model: ConnectionModel, count: int | None = None,
                         labels: Sequence[str] | None = None) -> list[str]:
    """Text table: frequency, effective masses and cumulative fractions per direction."""
    n = model.omega2.size if count is None else min(count, model.omega2.size)
    me, cf = model.effective_mass, model.effective_mass_cumulative_fraction
    head = (f"{'mode':>4} {'f [Hz]':>10} " + " ".join(f"{'m_' + d:>10}" for d in DIRECTIONS)
            + "  " + " ".join(f"{'cum_' + d:>7}" for d in DIRECTIONS)
            + ("  label" if labels is not None else ""))
    lines = [head, "-" * len(head)]
    for i in range(n):
        lines.append(f"{i + 1:4d} {model.frequencies_hz[i]:10.3f} "
                     + " ".join(f"{v:10.3e}" for v in me[i]) + "  "
                     + " ".join(f"{100 * v:6.2f}%" for v in cf[i])
                     + (f"  {labels[i]}" if labels is not None else ""))
    lines.append(f"{'D_P':>4} {'diag':>10} " + " ".join(f"{v:10.3e}" for v in np.diag(model.D_P)))
    lines.append(f"{'D_P0':>4} {'diag':>10} " + " ".join(f"{v:10.3e}" for v in np.diag(model.D_P0)))
    return lines


# --------------------------------------------------------------------------- one call
def _ratios(damping, omega2: np.ndarray) -> np.ndarray:
    """Damping ratios at ``omega2``: a number, a per-mode sequence, or an object with
    ``ratios_for(omega)`` (:class:`pipeline.reduce.modal.DampingSpec`)."""
    if hasattr(damping, "ratios_for"):
        return np.asarray(damping.ratios_for(np.sqrt(np.maximum(omega2, 0.0))), dtype=float)
    return _xi(damping, omega2.size)


def build_connection_model(space, regions: Mapping[str, np.ndarray], K_full: sp.spmatrix,
                           M_full: sp.spmatrix, connections: Sequence[Any], n_modes: int,
                           damping=0.0, backend: str = "auto"
                           ) -> tuple[ConnectionModel, StateSpace]:
    """Everything for ``/connections/<parent>``, in one call.

    ``connections``: the config's records (name, region, point, coupling); the first is
    the parent point P, the others child points. ``K_full``, ``M_full``: assembled
    matrices of the unsupported body. ``damping``: a ratio, one per mode, or a
    :class:`pipeline.reduce.modal.DampingSpec`. Returns (model, state space); the datasets
    are :func:`pipeline.store.schema.connection_datasets`.
    """
    interfaces = make_interfaces(space, regions, connections)
    model = connection_model(space, K_full, M_full, interfaces, n_modes, backend=backend)
    ss = connection_statespace(model, _ratios(damping, model.omega2))
    return model, ss
