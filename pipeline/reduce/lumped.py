"""Lumped-parameter beam model: rigid elements joined by springs (METHODS sections 7, 8).

A straight beam of length ``L`` along x, clamped at x = 0, is cut into ``n`` rigid
elements of length ``l = L / n`` joined by joints with springs and dampers. The chain
is linearised about its straight, unloaded configuration, so its model is linear:
``M q'' + C q' + K q = F u``, ``y = T q``, with ``q`` the joint coordinates.

Conventions (SI units throughout: m, kg, s, N, Pa, rad):

- Section axes: ``y`` along the section ``height``, ``z`` along its ``depth``. ``I_y`` is
  the second moment about y (``int z^2 dA``, bending in the x-z plane) and ``I_z`` the one
  about z (``int y^2 dA``, bending in the x-y plane, the plane of a tip force along -y).
- Joint degrees of freedom, in this order at every joint (:data:`JOINT_DOFS`):
  ``axial`` (prismatic, stretch along x, m), ``torsion`` (revolute about x, rad),
  ``bend_y`` (revolute about y, rad), ``bend_z`` (revolute about z, rad).
  ``q`` is joint-major: ``[joint 1 dofs, joint 2 dofs, ...]``.
- Mode labels: ``axial``, ``torsion``, ``bending_y`` (rotation about y: deflection along
  z) and ``bending_z`` (rotation about z: deflection along y, the x-y plane).
- Constants (METHODS section 7):
  ``refined``: joints at x = (i - 1) l, joint 1 at the clamp; extension E A / l,
  torsion 2 G J / l at joint 1 and G J / l after, bending (E I / l) 6n / (3n - 1) at
  joint 1 and E I / l after. All four joint DOFs exist.
  ``simple``: the generalised pure-bending element, two rigid halves of length l / 2
  with a revolute joint between them, welded end to end: joints at x = (i - 1/2) l,
  bending only, k = E I / l about each transverse axis. The chain is rigid in extension
  and torsion (those joint DOFs do not exist; their constants are reported as ``inf``).
  Its moving bodies are the welded halves between two joints (length l, mass m / n) and
  the last half at the tip (length l / 2); the half at the clamp is part of the ground.
- Joint damping: stiffness-proportional, ``C = beta K`` with ``beta = 2 xi / omega_ref``,
  ``omega_ref`` the chain's lowest natural frequency (or a given reference). Because ``K``
  is diagonal in joint coordinates, this is one damper per joint DOF,
  ``c_j = beta k_j`` (what a rigid-body code can model), and it is classical damping,
  so the modal state-space form of METHODS section 3 is exact: mode i gets the ratio
  ``xi_i = xi omega_i / omega_ref`` (the reference mode gets ``xi``, higher modes more;
  modes with ``xi_i >= 1`` are overdamped, which the state-space form still represents).

The section is assumed doubly symmetric in the sense the chain needs: principal axes
along y and z, shear centre at the centroid. Sections whose product of area ``I_yz`` is
not negligible are refused; for a section that is not symmetric the shear centre may sit
off the centroid (bending-torsion coupling), which the chain ignores.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from pipeline._util import validate
from pipeline.errors import ConfigError
from pipeline.reduce.statespace import StateSpace

log = logging.getLogger(__name__)

__all__ = [
    "JOINT_DOFS",
    "SectionProperties",
    "SpringConstants",
    "LumpedModel",
    "ComparisonRow",
    "box_section",
    "rectangle_torsion_constant",
    "section_from_mesh",
    "check_beam",
    "spring_constants",
    "lumped_model",
    "tip_load",
    "static_response",
    "body_motion",
    "beam_theory_frequencies_hz",
    "beam_theory_tip_deflection",
    "cantilever_beta_l",
    "comparison_table",
    "format_comparison",
]

JOINT_DOFS: tuple[str, ...] = ("axial", "torsion", "bend_y", "bend_z")
"""The joint DOFs of the refined chain, in the order they appear at every joint."""

DOF_KIND = {"axial": "prismatic", "torsion": "revolute", "bend_y": "revolute", "bend_z": "revolute"}
DOF_AXIS = {"axial": (1.0, 0.0, 0.0), "torsion": (1.0, 0.0, 0.0),
             "bend_y": (0.0, 1.0, 0.0), "bend_z": (0.0, 0.0, 1.0)}
_DOF_LABEL = {"axial": "axial", "torsion": "torsion", "bend_y": "bending_y", "bend_z": "bending_z"}
_KINDS = ("simple", "refined")
_AXES = ("bending_z", "bending_y", "axial", "torsion")

# Refused below this slenderness: L >= SLENDER_MIN * max(section height, depth).
SLENDER_MIN = 2.0
# Warned below this one: shear deformation and rotary inertia are no longer small.
SLENDER_WARN = 10.0


# --------------------------------------------------------------------------- checks
# Raw values from library callers go through the one field checker
# (pipeline._util.validate); values from a Config have passed it already.
def _field(key: str, value: Any) -> dict:
    """The one-entry mapping the field checker reads; numpy scalars as Python numbers."""
    return {key: value.item() if isinstance(value, np.generic) else value}


def _positive(value: Any, name: str) -> float:
    return validate.number(_field(name, value), name, "", lo=0.0, lo_open=True)


def _poisson(value: Any, name: str = "material.nu") -> float:
    return validate.number(_field(name, value), name, "", lo=-1.0, hi=0.5, lo_open=True,
                           hi_open=True)


def _direction(value: Any, name: str) -> np.ndarray:
    raw = value.tolist() if isinstance(value, np.ndarray) else value
    d = np.asarray(validate.vector(_field(name, raw), name, "", nonzero=True), dtype=float)
    return d / np.linalg.norm(d)


# --------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class SectionProperties:
    """Properties of a beam cross-section (the y-z plane), about its centroid.

    area: m^2. I_y: m^4, ``int z^2 dA`` (about y, bending in x-z). I_z: m^4,
    ``int y^2 dA`` (about z, bending in x-y). J: m^4, Saint-Venant torsion constant.
    I_p: m^4, polar moment ``I_y + I_z``. source: ``"analytic box"`` or
    ``"FE cross-section"``. height, depth: m, extent of the section along y and z (used
    by the slenderness check). centroid: (y, z) m, where the beam axis runs. I_yz: m^4,
    product of area ``int y z dA`` (0 when y and z are principal axes).
    """

    area: float
    I_y: float
    I_z: float
    J: float
    I_p: float
    source: str
    height: float
    depth: float
    centroid: tuple[float, float] = (0.0, 0.0)
    I_yz: float = 0.0

    def second_moment(self, axis: str) -> float:
        """``I_y`` for ``bending_y`` / ``bend_y``, ``I_z`` for ``bending_z`` / ``bend_z`` (m^4)."""
        if axis in ("bending_y", "bend_y"):
            return self.I_y
        if axis in ("bending_z", "bend_z"):
            return self.I_z
        raise ValueError(f"no bending axis {axis!r}")


def rectangle_torsion_constant(height: float, depth: float) -> float:
    """Saint-Venant torsion constant of a solid ``height`` x ``depth`` rectangle (m^4).

    With ``a >= b`` the long and short sides, the exact series solution (Timoshenko &
    Goodier, torsion of a rectangular bar) is
    ``J = a b^3 / 3 [1 - (192 / pi^5) (b / a) sum_{k odd} tanh(k pi a / (2 b)) / k^5]``.
    The series is summed to k = 4001 (tail below 1e-15 relative), not truncated to the
    usual one-term approximation.
    """
    a, b = max(height, depth), min(height, depth)
    k = np.arange(1, 4002, 2, dtype=float)
    series = np.sum(np.tanh(k * np.pi * a / (2.0 * b)) / k**5)
    return float(a * b**3 / 3.0 * (1.0 - 192.0 / np.pi**5 * (b / a) * series))


def box_section(height: float, depth: float, centroid: tuple[float, float] = (0.0, 0.0)
                ) -> SectionProperties:
    """Solid rectangular section: ``height`` along y, ``depth`` along z (m).

    Returns area = h d, I_z = d h^3 / 12, I_y = h d^3 / 12, J from
    :func:`rectangle_torsion_constant`, source ``"analytic box"``. ``centroid`` (y, z)
    places the beam axis (e.g. (h/2, d/2) for a box spanning y in [0, h], z in [0, d]).
    """
    h = _positive(height, "geometry.height")
    d = _positive(depth, "geometry.depth")
    c = (float(centroid[0]), float(centroid[1]))
    I_y = h * d**3 / 12.0
    I_z = d * h**3 / 12.0
    return SectionProperties(area=h * d, I_y=I_y, I_z=I_z, J=float(rectangle_torsion_constant(h, d)),
                             I_p=I_y + I_z, source="analytic box", height=h, depth=d, centroid=c)


def section_from_mesh(points2d: Any, triangles: Any, source: str = "FE cross-section"
                      ) -> SectionProperties:
    """Section properties of an arbitrary cross-section from its 2D triangle mesh.

    points2d: (n_p, 2) m, the (y, z) coordinates of the vertices. triangles: (n_t, 3)
    vertex indices (any orientation; straight-sided). The section may have holes but must
    be one connected piece.

    Area, centroid and second moments are integrated exactly (polynomials on straight
    triangles, quadrature of degree 4). The torsion constant comes from the warping
    function ``w`` (u_x = theta' w), solved with scikit-fem P2 triangles:
    ``int grad w . grad v dA = int (z dv/dy - y dv/dz) dA`` for all v (traction-free
    boundary, natural; holes need nothing special), w fixed at one node, and
    ``J = I_p - int |grad w|^2 dA`` (coordinates about the centroid). The discrete J
    converges from above as the mesh is refined.
    """
    from scipy.sparse.csgraph import connected_components
    import scipy.sparse as sp
    from skfem import Basis, BilinearForm, ElementTriP2, Functional, LinearForm, MeshTri, condense, solve

    p = np.asarray(points2d, dtype=float)
    t = np.asarray(triangles)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 3 or not np.all(np.isfinite(p)):
        raise ConfigError(f"section mesh points: got an array of shape {p.shape}, expected "
                          "(n_points >= 3, 2) finite (y, z) coordinates in m")
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] < 1 or not np.issubdtype(t.dtype, np.integer):
        raise ConfigError(f"section mesh triangles: got an array of shape {t.shape} "
                          f"({t.dtype}), expected (n_triangles >= 1, 3) integer vertex indices")
    if t.min() < 0 or t.max() >= p.shape[0]:
        raise ConfigError(f"section mesh triangles: vertex indices span [{t.min()}, {t.max()}], "
                          f"expected indices in [0, {p.shape[0] - 1}]")
    used, t = np.unique(t, return_inverse=True)
    t = t.reshape(-1, 3)
    p = p[used]
    e1 = p[t[:, 1]] - p[t[:, 0]]
    e2 = p[t[:, 2]] - p[t[:, 0]]
    signed = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    scale = max(np.ptp(p[:, 0]), np.ptp(p[:, 1])) ** 2
    flat = np.flatnonzero(np.abs(signed) <= 1e-14 * scale)
    if flat.size:
        raise ConfigError(f"section mesh: {flat.size} degenerate (zero-area) triangles, e.g. "
                          f"triangle {int(flat[0])}; expected a valid triangulation")
    t[signed < 0] = t[signed < 0][:, [0, 2, 1]]
    rows = np.repeat(t, 3, axis=1).ravel()
    cols = np.tile(t, 3).ravel()
    graph = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(p.shape[0],) * 2)
    n_parts, _ = connected_components(graph, directed=False)
    if n_parts != 1:
        raise ConfigError(f"section mesh: got {n_parts} disconnected pieces, expected one "
                          "connected cross-section")

    mesh = MeshTri(p.T.copy(), t.T.copy())
    basis = Basis(mesh, ElementTriP2(), intorder=4)
    area = Functional(lambda w: 1.0 + 0.0 * w.x[0]).assemble(basis)
    yc = Functional(lambda w: w.x[0]).assemble(basis) / area
    zc = Functional(lambda w: w.x[1]).assemble(basis) / area
    I_z = Functional(lambda w: (w.x[0] - yc) ** 2).assemble(basis)
    I_y = Functional(lambda w: (w.x[1] - zc) ** 2).assemble(basis)
    I_yz = Functional(lambda w: (w.x[0] - yc) * (w.x[1] - zc)).assemble(basis)

    @BilinearForm
    def laplace(u, v, w):
        return u.grad[0] * v.grad[0] + u.grad[1] * v.grad[1]

    @LinearForm
    def load(v, w):
        y, z = w.x[0] - yc, w.x[1] - zc
        return z * v.grad[0] - y * v.grad[1]

    K = laplace.assemble(basis)
    f = load.assemble(basis)
    warp = solve(*condense(K, f, D=np.array([0])))
    J = I_y + I_z - float(warp @ (K @ warp))
    log.info("section from %d triangles (%d P2 DOFs): A = %.6g m^2, I_y = %.6g, I_z = %.6g, "
             "J = %.6g m^4", t.shape[0], basis.N, area, I_y, I_z, J)
    return SectionProperties(area=float(area), I_y=float(I_y), I_z=float(I_z), J=float(J),
                             I_p=float(I_y + I_z), source=source, height=float(np.ptp(p[:, 0])),
                             depth=float(np.ptp(p[:, 1])), centroid=(float(yc), float(zc)),
                             I_yz=float(I_yz))


def check_beam(section: SectionProperties, length: float) -> float:
    """Refuse a body that is not a beam; return the length (m).

    Rules: section area, I_y, I_z, J > 0; principal axes along y and z
    (``|I_yz| <= 1e-6 sqrt(I_y I_z)``); slenderness ``L >= 2 max(height, depth)``
    (:data:`SLENDER_MIN`). Below ``L = 10 max(height, depth)`` a warning is logged: shear
    deformation, which neither the chain nor Euler-Bernoulli theory has, is then no
    longer small.
    """
    L = _positive(length, "geometry.length")
    for name in ("area", "I_y", "I_z", "J"):
        _positive(getattr(section, name), f"section.{name}")
    if abs(section.I_yz) > 1e-6 * math.sqrt(section.I_y * section.I_z):
        angle = 0.5 * math.degrees(math.atan2(-2.0 * section.I_yz, section.I_z - section.I_y))
        raise ConfigError(
            f"section.I_yz: got {section.I_yz:g} m^4, expected 0 (principal axes along y and z); "
            f"the principal axes are rotated by about {angle:.3g} deg, rotate the section",
            key="section.I_yz", value=section.I_yz, expected="0 (principal axes along y and z)")
    size = max(section.height, section.depth)
    if L < SLENDER_MIN * size:
        raise ConfigError(
            f"geometry.length: got {L:g} m, expected a beam: length >= {SLENDER_MIN:g} x the "
            f"largest section dimension {size:g} m (rule L >= {SLENDER_MIN:g} max(height, depth)); "
            "this body is not slender enough for a lumped beam model",
            key="geometry.length", value=L,
            expected=f"length >= {SLENDER_MIN:g} max(height, depth) = {SLENDER_MIN * size:g} m")
    if L < SLENDER_WARN * size:
        log.warning("lumped model of a stocky beam: L / max(height, depth) = %.3g < %g; shear "
                    "deformation is not small and the chain (Euler-Bernoulli) will be too stiff",
                    L / size, SLENDER_WARN)
    return L


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
    """Spring constants of METHODS section 7 for ``n`` elements (E in Pa, length in m).

    simple: joints at x = (i - 1/2) l, K_bend = E I / l, axial and torsion rigid (inf).
    refined: joints at x = (i - 1) l; K_axial = E A / l; K_torsion = G J / l with 2 G J / l
    at the clamp joint; K_bend = E I / l with (E I / l) 6n / (3n - 1) at the clamp joint.
    ``n < 1``, an unknown kind, a bad material or a section that is not a beam raise
    :class:`~pipeline.errors.ConfigError`.
    """
    n = validate.integer(_field("lumped.elements", n), "lumped.elements", "", lo=1)
    kind = validate.choice(_field("lumped.constants", kind), "lumped.constants", "", _KINDS)
    E = _positive(E, "material.E")
    nu = _poisson(nu)
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
    the names), A (2n_q, 2n_q), B (2n_q, 1), C (3, 2n_q), D (3, 1): METHODS
    section 3 with all modes; state [eta; eta'], output [position; velocity; acceleration]
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
                 damping_reference_hz: float | None = None) -> LumpedModel:
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
    """
    import scipy.linalg as sla

    constants = spring_constants(section, E, nu, length, n, kind)
    rho = _positive(rho, "material.rho")
    xi = validate.number(_field("damping.ratio", damping_ratio), "damping.ratio", "", lo=0.0)
    d_in = _direction(input_direction, "lumped input_direction")
    d_out = _direction(output_direction, "lumped output_direction")
    P = validate.number(_field("tip_force", tip_force), "tip_force", "")
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
    f_ref = f_hz[0] if damping_reference_hz is None else _positive(
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


# --------------------------------------------------------------------------- beam theory
def cantilever_beta_l(count: int) -> np.ndarray:
    """(count,) roots beta_k L of 1 + cos(x) cosh(x) = 0 (clamped-free Euler-Bernoulli beam):
    1.875104, 4.694091, 7.854757, ... solved to machine precision."""
    from scipy.optimize import brentq

    def g(x: float) -> float:  # 1 + cos cosh, scaled so it stays O(1)
        return math.cos(x) + 1.0 / math.cosh(x)

    roots = []
    for k in range(1, count + 1):
        guess = (2 * k - 1) * math.pi / 2.0
        roots.append(brentq(g, guess - 1.0, guess + 1.0, xtol=1e-15) if k <= 3 else
                     brentq(g, guess - 0.1, guess + 0.1, xtol=1e-15))
    return np.asarray(roots)


def beam_theory_frequencies_hz(section: SectionProperties, E: float, rho: float, length: float,
                               count: int = 3, axis: str = "bending_z", nu: float | None = None
                               ) -> np.ndarray:
    """(count,) Hz: the lowest cantilever frequencies of METHODS section 8.

    bending_z (x-y plane, I_z) / bending_y (x-z plane, I_y): Euler-Bernoulli,
    omega_k = (beta_k L)^2 sqrt(E I / (rho A L^4)). axial: (2k - 1)/(4L) sqrt(E / rho).
    torsion (needs nu): (2k - 1)/(4L) sqrt(G J / (rho I_p)).
    """
    count = validate.integer(_field("count", count), "count", "", lo=1)
    axis = validate.choice(_field("axis", axis), "axis", "", _AXES)
    E = _positive(E, "material.E")
    rho = _positive(rho, "material.rho")
    L = _positive(length, "geometry.length")
    k = np.arange(1, count + 1)
    if axis == "axial":
        return (2 * k - 1) / (4.0 * L) * math.sqrt(E / rho)
    if axis == "torsion":
        if nu is None:
            raise ConfigError("torsion frequencies need Poisson's ratio nu: got None")
        G = E / (2.0 * (1.0 + _poisson(nu)))
        return (2 * k - 1) / (4.0 * L) * math.sqrt(G * section.J / (rho * section.I_p))
    EI = E * section.second_moment(axis)
    omega = cantilever_beta_l(count) ** 2 * math.sqrt(EI / (rho * section.area * L**4))
    return omega / (2.0 * math.pi)


def beam_theory_tip_deflection(section: SectionProperties, E: float, length: float,
                               load: float = 1.0, axis: str = "bending_z",
                               nu: float | None = None) -> float:
    """Static tip response of a cantilever under a tip load (METHODS section 8).

    bending_z / bending_y: P L^3 / (3 E I) (m, P the tip force in N, I = I_z / I_y).
    axial: P L / (E A) (m). torsion (needs nu): T L / (G J) (rad, T the tip torque N m).
    """
    axis = validate.choice(_field("axis", axis), "axis", "", _AXES)
    E = _positive(E, "material.E")
    L = _positive(length, "geometry.length")
    P = validate.number(_field("load", load), "load", "")
    if axis == "axial":
        return P * L / (E * section.area)
    if axis == "torsion":
        if nu is None:
            raise ConfigError("torsion deflection needs Poisson's ratio nu: got None")
        G = E / (2.0 * (1.0 + _poisson(nu)))
        return P * L / (G * section.J)
    return P * L**3 / (3.0 * E * section.second_moment(axis))


# --------------------------------------------------------------------------- comparison
@dataclass(frozen=True)
class ComparisonRow:
    """One row of the chain / FE / beam-theory comparison.

    model: ``beam theory`` | ``FE`` | ``simple`` | ``refined``. n: elements (None for the
    references). frequencies_hz: (count,) Hz, the lowest modes of the compared bending
    plane (NaN where the model has fewer). tip_deflection: m, static tip displacement
    along the force under ``load`` N. frequency_error, deflection_error: relative to beam
    theory ((model - beam) / beam). fe_frequency_error, fe_deflection_error: relative to FE
    (NaN without FE data).
    """

    model: str
    n: int | None
    frequencies_hz: tuple[float, ...]
    tip_deflection: float
    frequency_error: tuple[float, ...]
    deflection_error: float
    fe_frequency_error: tuple[float, ...]
    fe_deflection_error: float


def _padded(values: Sequence[float], count: int) -> np.ndarray:
    out = np.full(count, np.nan)
    v = np.asarray(values, dtype=float).reshape(-1)[:count]
    out[:v.size] = v
    return out


def comparison_table(section: SectionProperties, E: float, nu: float, rho: float, length: float,
                     ns: Sequence[int] = (1, 2, 3, 5, 10, 20),
                     kinds: Sequence[str] = ("simple", "refined"), *, axis: str = "bending_z",
                     count: int = 3, load: float = 1.0,
                     fe_frequencies_hz: Sequence[float] | None = None,
                     fe_tip_deflection: float | None = None) -> list[ComparisonRow]:
    """Rows: beam theory, FE (when given), then each kind for each n.

    axis: the bending plane compared, ``bending_z`` (x-y plane, tip force along y, the
    default) or ``bending_y``. count: how many frequencies per row (3: f1, f2, f3).
    load: tip force magnitude (N). fe_frequencies_hz: the FE model's lowest frequencies of
    the same bending family (Hz), fe_tip_deflection: its static tip deflection (m, along
    the force) under ``load``; the caller fills these from the FE run.
    """
    axis = validate.choice(_field("axis", axis), "axis", "", ("bending_z", "bending_y"))
    force_dir = (0.0, -1.0, 0.0) if axis == "bending_z" else (0.0, 0.0, -1.0)
    f_beam = beam_theory_frequencies_hz(section, E, rho, length, count, axis)
    d_beam = beam_theory_tip_deflection(section, E, length, load, axis)
    f_fe = None if fe_frequencies_hz is None else _padded(fe_frequencies_hz, count)
    d_fe = None if fe_tip_deflection is None else float(fe_tip_deflection)

    def row(model: str, n: int | None, f: np.ndarray, d: float) -> ComparisonRow:
        nan = (math.nan,) * count
        return ComparisonRow(
            model=model, n=n, frequencies_hz=tuple(map(float, f)), tip_deflection=float(d),
            frequency_error=tuple(map(float, f / f_beam - 1.0)),
            deflection_error=float(d / d_beam - 1.0),
            fe_frequency_error=nan if f_fe is None else tuple(map(float, f / f_fe - 1.0)),
            fe_deflection_error=math.nan if not d_fe else float(d / d_fe - 1.0))

    rows = [row("beam theory", None, f_beam, d_beam)]
    if f_fe is not None or d_fe is not None:
        rows.append(row("FE", None, f_fe if f_fe is not None else np.full(count, np.nan),
                        d_fe if d_fe is not None else math.nan))
    for kind in kinds:
        for n in ns:
            m = lumped_model(section, E, nu, rho, length, n, kind, 0.0,
                             input_direction=force_dir, output_direction=force_dir, tip_force=load)
            rows.append(row(kind, int(n), _padded(m.frequencies_of(axis), count),
                            m.tip_compliance * load))
    return rows


def format_comparison(rows: Sequence[ComparisonRow]) -> str:
    """A plain-text table of :func:`comparison_table` rows (Hz, mm; errors vs beam theory)."""
    count = len(rows[0].frequencies_hz) if rows else 0
    head = f"{'model':<12}{'n':>4}" + "".join(f"{f'f{i + 1} [Hz]':>12}{'err':>8}" for i in range(count)) \
        + f"{'tip [mm]':>12}{'err':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        cells = "".join(f"{f:>12.4f}{e:>+8.2%}" if math.isfinite(f) else f"{'-':>12}{'':>8}"
                        for f, e in zip(r.frequencies_hz, r.frequency_error))
        tip = f"{r.tip_deflection * 1e3:>12.6f}{r.deflection_error:>+9.3%}" \
            if math.isfinite(r.tip_deflection) else f"{'-':>12}{'':>9}"
        lines.append(f"{r.model:<12}{'' if r.n is None else r.n:>4}{cells}{tip}")
    return "\n".join(lines)
