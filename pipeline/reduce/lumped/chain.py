"""The linearised rigid-element chain and its modal state space (theory.md §7, §8):
spring constants (simple | refined), bodies, joints, M q'' + C q' + K q = F u, y = T q,
and the :class:`~pipeline.reduce.statespace.StateSpace` of the tip response. Conventions
(joint DOFs, units, damping rule): :mod:`pipeline.reduce.lumped`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from pipeline._util import validate
from pipeline.reduce.lumped.section import (SectionProperties, check_beam, poisson_ratio,
                                            positive, raw_field, unit_direction)
from pipeline.reduce.statespace import StateSpace

log = logging.getLogger(__name__)

__all__ = ["JOINT_DOFS", "DOF_KIND", "DOF_AXIS", "SpringConstants", "spring_constants",
           "LumpedModel", "lumped_model", "tip_load", "static_response", "body_motion"]

JOINT_DOFS: tuple[str, ...] = ("axial", "torsion", "bend_y", "bend_z")
"""The joint DOFs of the refined chain, in the order they appear at every joint."""

DOF_KIND = {"axial": "prismatic", "torsion": "revolute", "bend_y": "revolute", "bend_z": "revolute"}
DOF_AXIS = {"axial": (1.0, 0.0, 0.0), "torsion": (1.0, 0.0, 0.0),
             "bend_y": (0.0, 1.0, 0.0), "bend_z": (0.0, 0.0, 1.0)}
_DOF_LABEL = {"axial": "axial", "torsion": "torsion", "bend_y": "bending_y", "bend_z": "bending_z"}
_KINDS = ("simple", "refined")


# --------------------------------------------------------------------------- constants
@dataclass(frozen=True, eq=False)
class SpringConstants:
    """Joint positions and spring constants of an n-element chain.

    kind: ``simple`` | ``refined``. n: number of elements. element_length: l = L / n (m).
    x: (n,) m, joint positions along the beam axis. K_axial: (n,) N/m. K_torsion: (n,)
    N m/rad. K_bend_y, K_bend_z: (n,) N m/rad, about y and z. ``inf`` marks a DOF the
    chain does not have (the simple chain is rigid in extension and torsion).
    dofs: the joint DOFs present at every joint, a subset of :data:`JOINT_DOFS`.
    """

    kind: str
    n: int
    element_length: float
    x: np.ndarray
    K_axial: np.ndarray
    K_torsion: np.ndarray
    K_bend_y: np.ndarray
    K_bend_z: np.ndarray
    dofs: tuple[str, ...]

    def stiffness(self, dof: str) -> np.ndarray:
        """(n,) constants of one joint DOF (N/m or N m/rad)."""
        return {"axial": self.K_axial, "torsion": self.K_torsion,
                "bend_y": self.K_bend_y, "bend_z": self.K_bend_z}[dof]


def spring_constants(section: SectionProperties, E: float, nu: float, length: float, n: int,
                     kind: str = "refined") -> SpringConstants:
    """Spring constants of theory.md §7 for ``n`` elements (E in Pa, length in m).

    simple: joints at x = (i - 1/2) l, K_bend = E I / l, axial and torsion rigid (inf).
    refined: joints at x = (i - 1) l; K_axial = E A / l; K_torsion = G J / l with 2 G J / l
    at the clamp joint; K_bend = E I / l with (E I / l) 6n / (3n - 1) at the clamp joint.
    ``n < 1``, an unknown kind, a bad material or a section that is not a beam raise
    :class:`~pipeline.errors.ConfigError`.
    """
    n = validate.integer(raw_field("lumped.elements", n), "lumped.elements", "", lo=1)
    kind = validate.choice(raw_field("lumped.constants", kind), "lumped.constants", "", _KINDS)
    E = positive(E, "material.E")
    nu = poisson_ratio(nu)
    L = check_beam(section, length)
    l = L / n
    G = E / (2.0 * (1.0 + nu))
    i = np.arange(n, dtype=float)
    ones = np.ones(n)
    if kind == "simple":
        return SpringConstants(kind=kind, n=n, element_length=l, x=(i + 0.5) * l,
                               K_axial=np.full(n, np.inf), K_torsion=np.full(n, np.inf),
                               K_bend_y=E * section.I_y / l * ones,
                               K_bend_z=E * section.I_z / l * ones, dofs=("bend_y", "bend_z"))
    end = ones.copy()
    end[0] = 6.0 * n / (3.0 * n - 1.0)
    twist = ones.copy()
    twist[0] = 2.0
    return SpringConstants(kind=kind, n=n, element_length=l, x=i * l,
                           K_axial=E * section.area / l * ones, K_torsion=G * section.J / l * twist,
                           K_bend_y=E * section.I_y / l * end, K_bend_z=E * section.I_z / l * end,
                           dofs=JOINT_DOFS)


# --------------------------------------------------------------------------- chain model
@dataclass(frozen=True, eq=False)
class LumpedModel:
    """The linearised chain and its modal state-space model.

    Coordinates ``q`` (n_q = n * len(constants.dofs)): the joint DOFs, joint-major.
    Bodies: the n moving rigid bodies, body b between joint b and joint b + 1 (the last
    one to the tip).

    constants: :class:`SpringConstants`. section: :class:`SectionProperties`.
    E, nu, rho: Pa, 1, kg/m^3. length: m.
    dof_joint: (n_q,) joint index (0-based) of each coordinate. dof_names: (n_q,) the
    joint DOF name of each coordinate (``axial`` ...).
    element_extent: (n, 2) m, x at both ends of each body. element_mass: (n,) kg.
    element_com: (n, 3) m. element_inertia: (n, 3, 3) kg m^2 about the body's centre of
    mass, x y z axes. body_jacobian: (n, 6, n_q), twist [v_com; omega] of each body per
    unit q. tip_jacobian: (6, n_q), twist [v; omega] of the tip point (x = L, on axis).
    M, K, damping_matrix: (n_q, n_q); units per entry follow q (kg, kg m, kg m^2; N/m,
    N m/rad; N s/m, N m s/rad). K and damping_matrix are diagonal: one spring and one
    damper per joint DOF. joint_damping: (n_q,) their diagonal.
    damping_ratio: the ratio asked for; damping_beta: s, C = beta K; damping_reference_hz.
    frequencies_hz: (n_q,) sorted. mode_labels: (n_q,) ``bending_z`` ... mode_shapes:
    (n_q, n_q), column i = mode i, M-normalised (Phi^T M Phi = I). modal_damping_ratios:
    (n_q,). input_direction, output_direction: (3,) unit vectors. F: (n_q, 1) generalised
    force of a unit tip force along input_direction. T: (1, n_q) tip displacement along
    output_direction per unit q. tip_compliance: m/N, tip displacement along the force per
    newton. tip_force: N. tip_deflection: (3,) m, the tip displacement under ``tip_force``
    N along input_direction. statespace: a :class:`StateSpace` (also read as A, B, C, D and
    the names), A (2n_q, 2n_q), B (2n_q, 1), C (3, 2n_q), D (3, 1): theory.md
    §3 with all modes; state [eta; eta'], output [position; velocity; acceleration]
    of the tip along output_direction.
    """

    constants: SpringConstants
    section: SectionProperties
    E: float
    nu: float
    rho: float
    length: float
    dof_joint: np.ndarray
    dof_names: tuple[str, ...]
    element_extent: np.ndarray
    element_mass: np.ndarray
    element_com: np.ndarray
    element_inertia: np.ndarray
    body_jacobian: np.ndarray
    tip_jacobian: np.ndarray
    M: np.ndarray
    K: np.ndarray
    damping_matrix: np.ndarray
    joint_damping: np.ndarray
    damping_ratio: float
    damping_beta: float
    damping_reference_hz: float
    frequencies_hz: np.ndarray
    mode_labels: tuple[str, ...]
    mode_shapes: np.ndarray
    modal_damping_ratios: np.ndarray
    input_direction: np.ndarray
    output_direction: np.ndarray
    F: np.ndarray
    T: np.ndarray
    tip_compliance: float
    tip_force: float
    tip_deflection: np.ndarray
    statespace: StateSpace

    # the chain's state space, also as the flat attributes its users read
    @property
    def A(self) -> np.ndarray:
        return self.statespace.A

    @property
    def B(self) -> np.ndarray:
        return self.statespace.B

    @property
    def C(self) -> np.ndarray:
        return self.statespace.C

    @property
    def D(self) -> np.ndarray:
        return self.statespace.D

    @property
    def input_names(self) -> tuple[str, ...]:
        return self.statespace.input_names

    @property
    def output_names(self) -> tuple[str, ...]:
        return self.statespace.output_names

    @property
    def state_names(self) -> tuple[str, ...]:
        return self.statespace.state_names

    @property
    def kind(self) -> str:
        return self.constants.kind

    @property
    def n(self) -> int:
        return self.constants.n

    @property
    def joint_positions(self) -> np.ndarray:
        """(n, 3) m: joint positions, on the beam axis through the section centroid."""
        c = self.section.centroid
        x = self.constants.x
        return np.column_stack([x, np.full_like(x, c[0]), np.full_like(x, c[1])])

    def frequencies_of(self, label: str) -> np.ndarray:
        """Sorted frequencies (Hz) of the modes labelled ``label`` (e.g. ``bending_z``)."""
        return self.frequencies_hz[[i for i, s in enumerate(self.mode_labels) if s == label]]


def _point_jacobian(x_point: float, joint_x: np.ndarray, upstream: int,
                    dofs: tuple[str, ...]) -> np.ndarray:
    """(6, n_q) twist [v; omega] of an axis point at ``x_point`` per unit joint coordinate,
    for a point downstream of joints 0 .. upstream - 1 (linearised, straight chain)."""
    nd = len(dofs)
    Jp = np.zeros((6, nd * joint_x.size))
    for j in range(upstream):
        arm = x_point - joint_x[j]
        for k, dof in enumerate(dofs):
            col = nd * j + k
            if dof == "axial":
                Jp[0, col] = 1.0
            elif dof == "torsion":
                Jp[3, col] = 1.0
            elif dof == "bend_y":  # omega e_y x arm e_x = -arm e_z
                Jp[4, col] = 1.0
                Jp[2, col] = -arm
            else:  # bend_z: omega e_z x arm e_x = +arm e_y
                Jp[5, col] = 1.0
                Jp[1, col] = arm
    return Jp


def lumped_model(section: SectionProperties, E: float, nu: float, rho: float, length: float,
                 n: int, kind: str = "refined", damping_ratio: float = 0.0, *,
                 input_direction: Sequence[float] = (0.0, -1.0, 0.0),
                 output_direction: Sequence[float] = (0.0, 1.0, 0.0),
                 tip_force: float = 1.0,
                 damping_reference_hz: float | None = None,
                 point_masses: Sequence[tuple[float, float, Sequence[float]]] = ()
                 ) -> LumpedModel:
    """The clamped chain of ``n`` rigid elements, linearised about the straight beam.

    Bodies: body b spans joint b to joint b + 1 (the last to the tip), mass rho A l_b,
    inertia about its centre of mass diag(rho l_b I_p, m l_b^2/12 + rho l_b I_y,
    m l_b^2/12 + rho l_b I_z). ``M = sum_b J_b^T M_b J_b`` with J_b the map from joint
    coordinates to the body's twist at its centre of mass; ``K = diag(spring constants)``;
    ``C = beta K`` (module docstring). Modes are solved per joint-DOF family (the families
    are uncoupled for a section with principal axes along y, z), labelled, sorted,
    M-normalised and signed so that their largest coordinate is positive.

    damping_ratio: xi >= 0 at ``damping_reference_hz`` (default: the lowest mode).
    input_direction: unit tip force direction (default -y). output_direction: measured
    tip displacement direction (default +y). tip_force: N, for ``tip_deflection``.
    point_masses: rigid masses on the beam axis, each (x m, mass kg, (Jxx, Jyy, Jzz) kg m^2
    about the point), carried by the body whose span holds x (the last body beyond the
    tip): M += J_p^T diag(m I, J) J_p with J_p the twist of the axis point x (on the axis
    with principal inertia along x, y, z they keep the joint-DOF families uncoupled).
    """
    import scipy.linalg as sla

    constants = spring_constants(section, E, nu, length, n, kind)
    rho = positive(rho, "material.rho")
    xi = validate.number(raw_field("damping.ratio", damping_ratio), "damping.ratio", "", lo=0.0)
    d_in = unit_direction(input_direction, "lumped input_direction")
    d_out = unit_direction(output_direction, "lumped output_direction")
    P = validate.number(raw_field("tip_force", tip_force), "tip_force", "")
    E, nu, L = float(E), float(nu), float(length)
    n = constants.n
    dofs = constants.dofs
    nd = len(dofs)
    nq = nd * n
    xj = constants.x

    ends = np.append(xj[1:], L)
    extent = np.column_stack([xj, ends])
    lb = ends - xj
    mass = rho * section.area * lb
    com_x = 0.5 * (xj + ends)
    inertia = np.zeros((n, 3, 3))
    inertia[:, 0, 0] = rho * lb * section.I_p
    inertia[:, 1, 1] = mass * lb**2 / 12.0 + rho * lb * section.I_y
    inertia[:, 2, 2] = mass * lb**2 / 12.0 + rho * lb * section.I_z
    body_J = np.stack([_point_jacobian(com_x[b], xj, b + 1, dofs) for b in range(n)])
    M = np.zeros((nq, nq))
    for b in range(n):
        Mb = np.zeros((6, 6))
        Mb[:3, :3] = mass[b] * np.eye(3)
        Mb[3:, 3:] = inertia[b]
        M += body_J[b].T @ Mb @ body_J[b]
    for x_p, m_p, J_p in point_masses:
        Jp = _point_jacobian(float(x_p), xj, int(np.count_nonzero(xj <= x_p)), dofs)
        M += Jp.T @ np.diag([m_p, m_p, m_p, *J_p]) @ Jp
    M = 0.5 * (M + M.T)
    kdiag = np.concatenate([[constants.stiffness(d)[j] for d in dofs] for j in range(n)])
    K = np.diag(kdiag)
    dof_joint = np.repeat(np.arange(n), nd)
    dof_names = tuple(dofs) * n

    # modes, one uncoupled family at a time
    freqs, labels, shapes = [], [], []
    for k, dof in enumerate(dofs):
        idx = np.arange(k, nq, nd)
        w2, V = sla.eigh(K[np.ix_(idx, idx)], M[np.ix_(idx, idx)])
        for i in range(w2.size):
            v = np.zeros(nq)
            v[idx] = V[:, i]
            v *= 1.0 / math.sqrt(v @ M @ v)
            if v[np.argmax(np.abs(v))] < 0:
                v = -v
            freqs.append(math.sqrt(max(w2[i], 0.0)) / (2.0 * math.pi))
            labels.append(_DOF_LABEL[dof])
            shapes.append(v)
    order = np.argsort(np.asarray(freqs), kind="stable")
    f_hz = np.asarray(freqs)[order]
    labels_sorted = tuple(labels[i] for i in order)
    Phi = np.column_stack([shapes[i] for i in order])
    omega = 2.0 * np.pi * f_hz

    # stiffness-proportional joint damping
    f_ref = f_hz[0] if damping_reference_hz is None else positive(
        damping_reference_hz, "damping_reference_hz")
    beta = 2.0 * xi / (2.0 * np.pi * f_ref)
    Cq = beta * K
    zeta = 0.5 * beta * omega
    if np.any(zeta >= 1.0):
        log.info("lumped chain: stiffness-proportional damping (xi = %g at %.4g Hz) overdamps "
                 "%d of %d modes", xi, f_ref, int(np.sum(zeta >= 1.0)), nq)

    tipJ = _point_jacobian(L, xj, n, dofs)
    F = (tipJ[:3].T @ d_in).reshape(nq, 1)
    T = (d_out @ tipJ[:3]).reshape(1, nq)
    q_unit = np.linalg.solve(K, F[:, 0])
    u_unit = tipJ[:3] @ q_unit
    compliance = float(d_in @ u_unit)

    Omega2 = np.diag(omega**2)
    Gamma = np.diag(zeta * omega)
    Sigma = Phi.T @ F
    Theta = T @ Phi
    Z = np.zeros((nq, nq))
    A = np.block([[Z, np.eye(nq)], [-Omega2, -2.0 * Gamma]])
    B = np.vstack([np.zeros((nq, 1)), Sigma])
    C = np.vstack([np.hstack([Theta, np.zeros_like(Theta)]),
                   np.hstack([np.zeros_like(Theta), Theta]),
                   np.hstack([-Theta @ Omega2, -2.0 * Theta @ Gamma])])
    D = np.vstack([np.zeros((2, 1)), Theta @ Sigma])
    log.info("lumped %s chain, n = %d: %d DOFs, f1 = %.5g Hz (%s), tip compliance %.6g m/N",
             constants.kind, n, nq, f_hz[0], labels_sorted[0], compliance)
    return LumpedModel(
        constants=constants, section=section, E=E, nu=nu, rho=rho, length=L,
        dof_joint=dof_joint, dof_names=dof_names, element_extent=extent, element_mass=mass,
        element_com=np.column_stack([com_x, np.full(n, section.centroid[0]),
                                     np.full(n, section.centroid[1])]),
        element_inertia=inertia, body_jacobian=body_J, tip_jacobian=tipJ, M=M, K=K,
        damping_matrix=Cq, joint_damping=np.diag(Cq).copy(), damping_ratio=xi,
        damping_beta=beta, damping_reference_hz=float(f_ref), frequencies_hz=f_hz,
        mode_labels=labels_sorted, mode_shapes=Phi, modal_damping_ratios=zeta,
        input_direction=d_in, output_direction=d_out, F=F, T=T, tip_compliance=compliance,
        tip_force=P, tip_deflection=P * u_unit,
        statespace=StateSpace(
            A, B, C, D, input_names=("tip_force",),
            output_names=("tip_position", "tip_velocity", "tip_acceleration"),
            state_names=tuple(f"eta_{i + 1}" for i in range(nq))
            + tuple(f"eta_dot_{i + 1}" for i in range(nq)),
            label="lumped"),
    )


def tip_load(model: LumpedModel, force: Sequence[float] = (0.0, 0.0, 0.0),
             moment: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(n_q,) generalised joint forces of a tip force (N, 3) and tip moment (N m, 3)."""
    w = np.concatenate([np.asarray(force, dtype=float), np.asarray(moment, dtype=float)])
    return model.tip_jacobian.T @ w


def static_response(model: LumpedModel, force: Sequence[float] = (0.0, 0.0, 0.0),
                    moment: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(n_q,) joint coordinates (m, rad) under a static tip force (N) and moment (N m)."""
    return np.linalg.solve(model.K, tip_load(model, force, moment))


def body_motion(model: LumpedModel, q: np.ndarray) -> np.ndarray:
    """(n, 6) small motion [u_com (m); rotation (rad)] of every body for coordinates q."""
    return np.einsum("bij,j->bi", model.body_jacobian, np.asarray(q, dtype=float))
