"""Reduction stage: modal damping, static correction and the modal state-space model.

Pure functions on plain arrays (theory.md §2 and §3). Inputs come from the FE
stages, already restricted to the free degrees of freedom:

- ``K``, ``M``: scipy.sparse (n_s x n_s), symmetric; K in N/m, M in kg.
- ``Phi``: (n_s x n_m) mode shapes, M-orthonormal (Phi^T M Phi = I, units kg^-1/2);
  ``omega2``: (n_m,) ascending squared circular frequencies in rad^2/s^2.
- ``F``: (n_s x n_u) load distribution, column j = nodal forces (N) of a unit input j.
- ``T``: (n_y x n_s) sensor matrix, row i = output i as a linear combination of DOFs.

With s = Phi eta the equations of motion become n_m independent damped oscillators

    eta'' + 2 Gamma eta' + Omega2 eta = Sigma u,   Sigma = Phi^T F,  Theta = T Phi,

and the model stacks position, velocity and acceleration of every output:

    A = [[0, I], [-Omega2, -2 Gamma]]                        (2 n_m x 2 n_m)
    B = [[0], [Sigma]]                                        (2 n_m x n_u)
    C = [[Theta, 0], [0, Theta], [-Theta Omega2, -2 Theta Gamma]]   (3 n_y x 2 n_m)
    D = [[R], [0], [Theta Sigma]]                             (3 n_y x n_u)

R = 0, or the residual flexibility T K^-1 F - Theta Omega2^-1 Sigma with
``static_correction="residual"``. ``"augment"`` instead adds the static shapes K^-1 F to
the basis and re-solves the small eigenproblem (a Ritz basis), so the DC gain is exact
without any feedthrough on the position output.

Nothing here imports python-control; the loader builds ``control.ss`` from the arrays.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from pipeline._util import validate
from pipeline.errors import SolverError
from pipeline.reduce.augment import AUGMENT_DROP_TOL, Columns, augment  # noqa: F401
from pipeline.reduce.statespace import StateSpace
from pipeline.solve.blas import sparse_times_dense
from pipeline.reduce.statics import relief_shapes, Solve, dense_array, static_shapes
from pipeline.solve.thresholds import rigid_omega2_threshold, stiffness_scale

log = logging.getLogger(__name__)

__all__ = [
    "DAMPING_KINDS",
    "STATIC_CORRECTIONS",
    "DampingSpec",
    "StateSpaceModel",
    "ReducedModel",
    "damping_ratios",
    "check_modal_basis",
    "modal_statespace",
    "reduce_model",
    "cluster_end",
]

DAMPING_KINDS = ("uniform", "per_mode", "rayleigh")
STATIC_CORRECTIONS = ("none", "residual", "augment")

#: Two modes whose frequencies differ by less than this fraction are one cluster of
#: (nearly) repeated frequencies (a square section bends alike about both axes): their
#: shapes are fixed only up to a rotation within the cluster, by mesh noise (an
#: unstructured mesh splits such a pair by ~1e-5 with P2, ~1e-4 with P1 elements; a
#: physically distinct pair is normally percent apart). A reduction keeps them together.
CLUSTER_REL_GAP = 1e-3


# --------------------------------------------------------------------------- damping
# Raw values from library callers go through the one field checker
# (pipeline._util.validate); values from a Config have passed it already.
def _number(key: str, value, **bounds) -> float:
    raw = {key: value.item() if isinstance(value, np.generic) else value}
    return validate.number(raw, key, "", **bounds)


def _ratio(key: str, value) -> float:
    """A damping ratio in [0, 1) (underdamped modes)."""
    return _number(key, value, lo=0.0, hi=1.0, hi_open=True)


def damping_ratios(omega, kind: str, ratio=None, ratios=None, alpha=None, beta=None
                   ) -> np.ndarray:
    """Modal damping ratio xi_i (dimensionless) of every mode.

    Parameters
    ----------
    omega : (n_m,) circular frequencies in rad/s (not squared), >= 0.
    kind : ``"uniform"`` (one ``ratio`` for every mode), ``"per_mode"`` (``ratios``,
        a list with exactly one entry per mode of ``omega``) or ``"rayleigh"``
        (C = alpha M + beta K with ``alpha`` in 1/s and ``beta`` in s, giving
        xi_i = alpha / (2 omega_i) + beta omega_i / 2).

    Returns (n_m,) float array. Every ratio must lie in [0, 1): the model is built for
    underdamped modes (its poles are -xi w +/- i w sqrt(1 - xi^2)). Anything else is
    refused with :class:`ConfigError` naming the key (``damping.kind``,
    ``damping.ratio``, ``damping.ratios``, ``damping.alpha``, ``damping.beta``) and the
    value received.
    """
    omega = np.asarray(omega, dtype=float).reshape(-1)
    n = omega.size
    if kind == "uniform":
        if ratio is None:
            raise validate.fail("damping.ratio", ratio, "a damping ratio in [0, 1) for kind uniform")
        return np.full(n, _ratio("damping.ratio", ratio))
    if kind == "per_mode":
        if ratios is None or isinstance(ratios, (str, bytes)) or not hasattr(ratios, "__len__"):
            raise validate.fail("damping.ratios", ratios, f"a list of {n} damping ratios (one per mode)")
        if len(ratios) != n:
            raise validate.fail("damping.ratios", list(ratios),
                       f"a list of {n} damping ratios (one per retained mode), "
                       f"not {len(ratios)}")
        return np.array([_ratio(f"damping.ratios[{i}]", r) for i, r in enumerate(ratios)],
                        dtype=float)
    if kind == "rayleigh":
        a = _number("damping.alpha", 0.0 if alpha is None else alpha)
        b = _number("damping.beta", 0.0 if beta is None else beta)
        if alpha is None and beta is None:
            raise validate.fail("damping.alpha", alpha, "alpha (1/s) and/or beta (s) for kind rayleigh")
        if a < 0:
            raise validate.fail("damping.alpha", alpha, "alpha >= 0 (1/s)")
        if b < 0:
            raise validate.fail("damping.beta", beta, "beta >= 0 (s)")
        xi = np.empty(n)
        for i, w in enumerate(omega):
            if w <= 0.0:
                if a > 0.0:
                    raise validate.fail("damping.alpha", alpha,
                               f"alpha = 0: mode {i + 1} has zero frequency (rigid-body "
                               "mode) and mass-proportional damping would be infinite")
                xi[i] = 0.0
            else:
                xi[i] = a / (2.0 * w) + b * w / 2.0
        over = np.flatnonzero(xi >= 1.0)
        if over.size:
            i = int(over[0])
            key = "damping.alpha" if a / (2.0 * omega[i]) >= b * omega[i] / 2.0 else "damping.beta"
            raise validate.fail(key, alpha if key == "damping.alpha" else beta,
                       f"Rayleigh damping below critical: mode {i + 1} "
                       f"(omega = {omega[i]:.6g} rad/s) gets xi = {xi[i]:.6g} >= 1")
        return xi
    raise validate.fail("damping.kind", kind, "one of " + ", ".join(DAMPING_KINDS))


@dataclass(frozen=True)
class DampingSpec:
    """A damping rule, to be evaluated at whatever frequencies the basis ends up with.

    ``kind`` uniform | per_mode | rayleigh; ``ratio`` (uniform), ``ratios`` (per_mode,
    one per retained mode), ``alpha`` (1/s) and ``beta`` (s) (rayleigh).

    With ``static_correction="augment"`` the model has more modes than were retained:
    the first n_modes Ritz modes are the retained modes (same frequencies), the extra
    high-frequency ones get ``ratio`` (uniform), the Rayleigh formula at their own
    frequency (rayleigh) or the last listed ratio (per_mode).
    """

    kind: str
    ratio: float | None = None
    ratios: tuple[float, ...] | None = None
    alpha: float | None = None
    beta: float | None = None

    def ratios_for(self, omega, n_listed: int | None = None) -> np.ndarray:
        """xi (n,) at ``omega`` (rad/s). ``n_listed``: how many of ``omega`` the
        per_mode list covers (the rest get its last entry); default all."""
        omega = np.asarray(omega, dtype=float).reshape(-1)
        if self.kind == "per_mode" and n_listed is not None and n_listed < omega.size:
            head = damping_ratios(omega[:n_listed], "per_mode", ratios=self.ratios)
            return np.concatenate([head, np.full(omega.size - n_listed, head[-1])])
        return damping_ratios(omega, self.kind, ratio=self.ratio, ratios=self.ratios,
                              alpha=self.alpha, beta=self.beta)


# --------------------------------------------------------------------------- checks
def _omega(omega2: np.ndarray) -> np.ndarray:
    """Circular frequencies (rad/s) from omega^2, with round-off negatives set to 0."""
    return np.sqrt(np.maximum(np.asarray(omega2, dtype=float), 0.0))


def check_modal_basis(K, M, Phi, omega2, tol: float = 1e-6,
                      mesh_scale: float | None = None) -> tuple[float, float]:
    """Verify that ``Phi`` is an M-orthonormal eigenbasis with eigenvalues ``omega2``.

    Checks  max |Phi^T M Phi - I|                       <= tol   (dimensionless), and
            max |Phi^T K Phi - diag(omega2)| / max|omega2| <= tol   (relative to the
            largest eigenvalue, i.e. to the norm of the projected stiffness).

    ``omega2`` must be the squared circular frequencies (rad^2/s^2); passing omega (or a
    basis scaled so that Phi^T K Phi = diag(omega)) fails the check. Raises
    :class:`SolverError` naming the worst entry (row, column, value, expected value).
    Returns the two measured errors (M, K) on success. ``mesh_scale``: the mesh's
    :func:`~pipeline.solve.thresholds.stiffness_scale` where the caller has it.
    """
    Phi = np.asarray(Phi, dtype=float)
    omega2 = np.asarray(omega2, dtype=float).reshape(-1)
    if Phi.ndim != 2 or Phi.shape[1] != omega2.size or Phi.shape[0] != K.shape[0]:
        raise SolverError(f"modal basis has shape {Phi.shape}, expected ({K.shape[0]}, "
                          f"{omega2.size}) to match K and omega2")
    n = omega2.size
    # sparse_times_dense: threaded MKL product, 2x scipy's at 1M DOFs
    Mr = Phi.T @ sparse_times_dense(M, Phi)
    Kr = Phi.T @ sparse_times_dense(K, Phi)
    eM = np.abs(Mr - np.eye(n))
    # stiffness scale: the largest retained omega^2, but never below 1e-6 of the mesh's
    # own eigenvalue scale (diag K / diag M), so rigid-body modes (omega^2 = 0) are judged
    # against round-off of K, not against 1 rad^2/s^2
    if mesh_scale is None:
        mesh_scale = stiffness_scale(K, M) if K.shape[0] else 0.0
    floor = 1e-6 * mesh_scale
    scale = max(float(np.max(np.abs(omega2))) if n else 0.0, floor)
    scale = scale if scale > 0 else 1.0
    eK = np.abs(Kr - np.diag(omega2)) / scale
    errM, errK = float(eM.max(initial=0.0)), float(eK.max(initial=0.0))
    if errM > tol:
        i, j = np.unravel_index(int(np.argmax(eM)), eM.shape)
        raise SolverError(
            f"mode shapes are not M-orthonormal: (Phi^T M Phi)[{i + 1},{j + 1}] = "
            f"{Mr[i, j]:.9g}, expected {float(i == j):g} (max error {errM:.3g} > tol {tol:g})")
    if errK > tol:
        i, j = np.unravel_index(int(np.argmax(eK)), eK.shape)
        expected = omega2[i] if i == j else 0.0
        raise SolverError(
            f"Phi^T K Phi is not diag(omega^2): entry [{i + 1},{j + 1}] = {Kr[i, j]:.9g} "
            f"rad^2/s^2, expected {expected:.9g} (error {errK:.3g} of max omega^2 "
            f"{scale:.6g} > tol {tol:g}); omega^2, not omega, belongs on the diagonal")
    log.debug("modal basis check: |Phi^T M Phi - I| = %.3g, |Phi^T K Phi - Omega2|/max = %.3g",
              errM, errK)
    return errM, errK


# --------------------------------------------------------------------------- models
def _ro(a) -> np.ndarray:
    a = np.array(a, dtype=float)  # copy
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class StateSpaceModel(StateSpace):
    """The modal model: a :class:`~pipeline.reduce.statespace.StateSpace` (same
    constructor and checks) that also records its structural modes.

    For the modal model n_x = 2 n_m (state [eta; eta'], ``eta_i`` in m kg^1/2) and
    n_out = 3 n_y, rows ordered: every port's position, then every port's velocity, then
    every port's acceleration, named ``"<port>/position"``, ``"<port>/velocity"``,
    ``"<port>/acceleration"``. ``omega2`` (rad^2/s^2) and ``damping_ratios`` (n_m,) are
    those of the structural modes in the model; ``n_retained`` of them are modes the user
    asked for (the rest are the high Ritz modes of an augmented basis). ``filter_kind``
    and ``cutoff_hz`` (inherited) describe an output filter in series (``"none"`` for the
    plant). Build it with keywords.
    """

    omega2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    damping_ratios: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_retained: int | None = None

    def __post_init__(self):
        super().__post_init__()
        for name in ("omega2", "damping_ratios"):
            object.__setattr__(self, name, _ro(np.asarray(getattr(self, name)).reshape(-1)))
        if self.omega2.shape != self.damping_ratios.shape:
            raise ValueError("omega2 and damping_ratios differ in length")
        if self.n_retained is None:
            object.__setattr__(self, "n_retained", int(self.omega2.size))

    @property
    def port_names(self) -> tuple[str, ...]:
        """Output port names (the output names up to ``/position``)."""
        n = len(self.output_names) // 3
        return tuple(s.rsplit("/", 1)[0] for s in self.output_names[:n])

    @property
    def frequencies_hz(self) -> np.ndarray:
        """Undamped natural frequencies of the structural modes, Hz."""
        return _omega(self.omega2) / (2.0 * math.pi)

    def output_rows(self, quantity: str) -> slice:
        """Row slice of ``"position"``, ``"velocity"`` or ``"acceleration"`` outputs."""
        n = len(self.output_names) // 3
        k = ("position", "velocity", "acceleration").index(quantity)
        return slice(k * n, (k + 1) * n)


def output_names_for(ports: Sequence[str]) -> tuple[str, ...]:
    """``"<port>/position"`` for every port, then velocities, then accelerations."""
    return tuple(f"{p}/{q}" for q in ("position", "velocity", "acceleration") for p in ports)


def modal_statespace(omega2, xi, Sigma, Theta, residual=None, input_names=None,
                     output_names=None, n_retained: int | None = None) -> StateSpaceModel:
    """The modal state-space model of theory.md §3.

    omega2 (n_m,) rad^2/s^2; xi (n_m,) damping ratios; Sigma = Phi^T F (n_m x n_u);
    Theta = T Phi (n_y x n_m); ``residual`` (n_y x n_u), if given, is added to the
    position rows of D (residual flexibility, m per unit input). ``input_names``
    (n_u) and ``output_names`` (n_y port names) default to ``u1..`` and ``y1..``.
    State names: ``eta_1..eta_n`` then ``eta_dot_1..eta_dot_n``.
    """
    omega2 = np.asarray(omega2, dtype=float).reshape(-1)
    xi = np.asarray(xi, dtype=float).reshape(-1)
    Sigma = np.atleast_2d(np.asarray(Sigma, dtype=float))
    Theta = np.atleast_2d(np.asarray(Theta, dtype=float))
    n = omega2.size
    if xi.size != n or Sigma.shape[0] != n or Theta.shape[1] != n:
        raise ValueError(f"inconsistent sizes: omega2 {n}, xi {xi.size}, Sigma {Sigma.shape}, "
                         f"Theta {Theta.shape}")
    n_u, n_y = Sigma.shape[1], Theta.shape[0]
    gamma2 = 2.0 * xi * _omega(omega2)  # 2 Gamma, 1/s
    Z, I = np.zeros((n, n)), np.eye(n)
    A = np.block([[Z, I], [-np.diag(omega2), -np.diag(gamma2)]])
    B = np.vstack([np.zeros((n, n_u)), Sigma])
    C = np.block([[Theta, np.zeros((n_y, n))],
                  [np.zeros((n_y, n)), Theta],
                  [-Theta * omega2, -Theta * gamma2]])
    D = np.vstack([np.zeros((n_y, n_u)), np.zeros((n_y, n_u)), Theta @ Sigma])
    if residual is not None:
        residual = np.asarray(residual, dtype=float)
        if residual.shape != (n_y, n_u):
            raise ValueError(f"residual has shape {residual.shape}, expected {(n_y, n_u)}")
        D[:n_y] += residual
    inputs = (tuple(input_names) if input_names is not None
              else tuple(f"u{j + 1}" for j in range(n_u)))
    ports = (tuple(output_names) if output_names is not None
             else tuple(f"y{i + 1}" for i in range(n_y)))
    if len(inputs) != n_u or len(ports) != n_y:
        raise ValueError(f"{len(inputs)} input names for {n_u} inputs or {len(ports)} output "
                         f"names for {n_y} outputs")
    states = tuple(f"eta_{i + 1}" for i in range(n)) + tuple(f"eta_dot_{i + 1}" for i in range(n))
    return StateSpaceModel(A, B, C, D, input_names=inputs, output_names=output_names_for(ports),
                           state_names=states, label="plant", omega2=omega2, damping_ratios=xi,
                           n_retained=n if n_retained is None else n_retained)


@dataclass(frozen=True, eq=False)
class ReducedModel:
    """The reduced model and what it was built from.

    statespace: the :class:`StateSpaceModel` (plant, unfiltered).
    static_compliance: (n_y x n_u) exact FE T K^-1 F (m/N for force -> displacement),
        or None for a free body (no statics).
    omega2: (n_b,) squared frequencies of the basis used (rad^2/s^2): the retained modes,
        plus the high Ritz modes for ``augment``.
    n_basis: n_b, the number of basis vectors (n_modes, or n_modes + kept static shapes).
    n_modes: the number of retained eigenmodes asked for.
    static_correction: none | residual | augment.
    residual: (n_y x n_u) residual flexibility added to D (``residual``), else None.
    basis: (n_s x n_b) the M-orthonormal basis actually used (Phi, or the Ritz vectors).
    correction_shapes: (n_s x n_u) residual-flexibility shapes K^-1 F - basis Omega2^-1
        Sigma (m per unit input) with ``residual`` (the static part the D rows carry;
        stress recovery needs them), else None.
    """

    statespace: StateSpaceModel
    static_compliance: np.ndarray | None
    omega2: np.ndarray
    n_basis: int
    n_modes: int
    static_correction: str
    residual: np.ndarray | None
    basis: np.ndarray
    correction_shapes: np.ndarray | None = None

    @property
    def dc_gain_position(self) -> np.ndarray:
        """Static gain of the position outputs, -C_pos A^-1 B + D_pos (n_y x n_u)."""
        ss = self.statespace
        return ss.dc_gain()[ss.output_rows("position")]


def _augment_basis(K, M, Phi, X, input_names, omega2_retained
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Ritz basis of span[Phi, X]: (omega2 (n_b,), Psi (n_s x n_b) M-orthonormal)
    (:func:`pipeline.reduce.augment.augment` on whole arrays)."""
    w2, Psi = augment(lambda B: B.like(sparse_times_dense(K, B.local)),
                      lambda B: B.like(sparse_times_dense(M, B.local)),
                      Columns(Phi), Columns(X), input_names, omega2_retained)
    return w2, Psi.local


def cluster_end(omega2: np.ndarray, n: int, rel_gap: float = CLUSTER_REL_GAP) -> int:
    """The smallest n' >= n such that modes n' and n'+1 (1-based) are not in one cluster:
    |omega_{n'+1} - omega_{n'}| > rel_gap omega_{n'} (omega in rad/s). Returns len(omega2)
    when the cluster reaches the last mode given (then where it ends is unknown)."""
    w = _omega(omega2)
    while n < w.size and abs(w[n] - w[n - 1]) <= rel_gap * max(w[n - 1], 0.0) \
            and w[n - 1] > 0:
        n += 1
    return n


def _keep_clusters_whole(omega2: np.ndarray, n_modes: int, xi) -> int:
    """n_modes, raised to the end of a frequency cluster that reduction.modes would cut
    (warning), or a refusal when the cluster runs past the computed modes or a per-mode
    damping list is too short for the whole cluster."""
    n_end = cluster_end(omega2, n_modes)
    if n_end == n_modes:
        return n_modes
    f = _omega(omega2) / (2 * math.pi)
    if n_end >= omega2.size:
        raise validate.fail(
            "reduction.modes", n_modes,
            f"a count that does not cut the cluster of nearly repeated frequencies "
            f"{f[n_modes - 1]:.6g}, {f[n_modes]:.6g} Hz (within {CLUSTER_REL_GAP:g}, e.g. "
            "the two bending directions of a square section): its shapes are fixed only by "
            "mesh noise; the cluster continues to the last computed mode, so raise "
            "modes.count to see where it ends")
    if isinstance(xi, DampingSpec) and xi.kind == "per_mode" and len(xi.ratios) < n_end:
        raise validate.fail(
            "damping.ratios", list(xi.ratios),
            f"{n_end} ratios: reduction.modes = {n_modes} cuts a cluster of nearly repeated "
            f"frequencies (modes {cluster_start(omega2, n_modes)}-{n_end}, {f[n_modes - 1]:.6g} "
            f"Hz) that is "
            f"kept whole")
    if not isinstance(xi, DampingSpec) and np.size(xi) < n_end:
        raise validate.fail(
            "reduction.modes", n_modes,
            f"{n_end} (the end of the cluster of nearly repeated frequencies at "
            f"{f[n_modes - 1]:.6g} Hz), with one damping ratio per mode")
    start = cluster_start(omega2, n_modes)
    log.warning("reduction.modes = %d cuts a cluster of nearly repeated frequencies (modes "
                "%d-%d at %.6g Hz, within %g, e.g. the two bending directions of a square "
                "section): which of them comes first is mesh noise, so the cluster is kept "
                "whole and the model has %d modes; set reduction.modes: %d%s to silence this",
                n_modes, start, n_end, f[n_modes - 1], CLUSTER_REL_GAP, n_end, n_end,
                f" (or {start - 1})" if start > 1 else "")
    return n_end


def cluster_start(omega2: np.ndarray, n: int, rel_gap: float = CLUSTER_REL_GAP) -> int:
    """The 1-based index of the first mode of the cluster that holds mode n."""
    w = _omega(omega2)
    while n > 1 and abs(w[n - 1] - w[n - 2]) <= rel_gap * w[n - 2] and w[n - 2] > 0:
        n -= 1
    return n


def reduce_model(K, M, Phi, omega2, F, T, n_modes: int, xi, static_correction: str,
                 input_names: Sequence[str], output_names: Sequence[str],
                 solve: Solve | None = None, factorize=None, basis_tol: float = 1e-6,
                 n_rigid: int | None = None, inertia_relief: bool = False,
                 constraint=None) -> ReducedModel:
    """Build the reduced state-space model from the FE matrices and modes.

    Parameters
    ----------
    K, M : sparse (n_s x n_s) stiffness (N/m) and mass (kg) on the free DOFs.
    Phi, omega2 : (n_s x n_c) M-orthonormal modes and (n_c,) ascending omega^2
        (rad^2/s^2), n_c >= n_modes. Checked with :func:`check_modal_basis` (``basis_tol``).
    F : (n_s x n_u) load distribution; T : (n_y x n_s) sensors.
    n_modes : number of lowest modes to keep (config ``reduction.modes``).
    xi : a :class:`DampingSpec` (evaluated at the final frequencies, see there) or an
        array of n_modes ratios (treated as per_mode).
    static_correction : ``"none"``, ``"residual"`` (D_pos += T K^-1 F - Theta
        Omega2^-1 Sigma) or ``"augment"`` (Ritz basis of [Phi, K^-1 F]).
    input_names, output_names : n_u input and n_y output port names.
    solve / factorize : K^-1 solver, see :func:`static_shapes`.
    constraint : (n_s x n_q) T of an exact constraint u = T q
        (:mod:`pipeline.fe.constraints`), or None: the static solves then run on
        T^T K T (``solve`` is its solver) and Phi satisfies it.
    n_rigid : rigid-body modes among the first (the modes stage's count); default: the
        modes below :func:`pipeline.solve.thresholds.rigid_omega2_threshold`.
    inertia_relief : a partly held body (its supports leave the rigid modes): the static
        correction uses the inertia-relief shapes (:func:`relief_shapes`); the model
        floats (no static compliance).

    The static compliance T K^-1 F is always computed, except for a body with rigid-body
    modes (omega^2 below the relative rigid_omega2_threshold) and no correction, where it is None (with a warning);
    residual and augment need a supported body.
    """
    omega2 = np.asarray(omega2, dtype=float).reshape(-1)
    Phi = np.asarray(Phi, dtype=float)
    n_avail = omega2.size
    if isinstance(n_modes, bool) or not isinstance(n_modes, (int, np.integer)) \
            or not 1 <= n_modes <= n_avail:
        raise validate.fail("reduction.modes", n_modes,
                   f"an integer from 1 to {n_avail} (the number of computed modes, modes.count)")
    n_modes = int(n_modes)
    if static_correction not in STATIC_CORRECTIONS:
        raise validate.fail("reduction.static_correction", static_correction,
                   "one of " + ", ".join(STATIC_CORRECTIONS))
    input_names, output_names = list(input_names), list(output_names)
    Fd = dense_array(F)
    if Fd.ndim == 1:
        Fd = Fd[:, None]
    if Fd.shape != (K.shape[0], len(input_names)):
        raise ValueError(f"F has shape {Fd.shape}, expected ({K.shape[0]}, {len(input_names)})")
    if T.shape != (len(output_names), K.shape[0]):
        raise ValueError(f"T has shape {T.shape}, expected ({len(output_names)}, {K.shape[0]})")
    if Phi.shape != (K.shape[0], n_avail):
        raise ValueError(f"Phi has shape {Phi.shape}, expected ({K.shape[0]}, {n_avail})")

    n_modes = _keep_clusters_whole(omega2, n_modes, xi)
    Phi_r, w2_r = Phi[:, :n_modes], omega2[:n_modes]
    scale = stiffness_scale(K, M)
    check_modal_basis(K, M, Phi_r, w2_r, tol=basis_tol, mesh_scale=scale)
    spec = xi if isinstance(xi, DampingSpec) else DampingSpec(
        "per_mode", ratios=tuple(np.asarray(xi, dtype=float).reshape(-1)))

    if n_rigid is None:  # library callers: zero to round-off, relative to the mesh
        n_rigid = int(np.count_nonzero(w2_r < rigid_omega2_threshold(scale)))
    else:  # the modes stage knows (0 for a supported body: its K was factorised)
        n_rigid = min(int(n_rigid), n_modes)
    X = None
    G = None
    G_relief = None  # a partly held body's inertia-relief compliance (no DC gain: floating)
    if n_rigid and inertia_relief and static_correction != "none":
        X = relief_shapes(K, M, Fd, Phi_r[:, :n_rigid], -1e-3 * float(omega2[n_rigid]),
                          factorize, constraint=constraint)
        G_relief = np.asarray(T @ X, dtype=float)
    elif n_rigid:
        if static_correction != "none":
            raise validate.fail("reduction.static_correction", static_correction,
                       f"none: the body has {n_rigid} rigid-body mode(s) among the retained "
                       "ones, so it has no static compliance to correct towards")
        log.warning("floating body (%d rigid-body modes): no static compliance computed", n_rigid)
    else:
        X = static_shapes(K, Fd, solve, factorize, lowest_omega2=float(omega2[0]),
                          stiffness_scale=scale, constraint=constraint)
        G = np.asarray(T @ X, dtype=float)

    residual = None
    if static_correction == "augment":
        w2, basis = _augment_basis(K, M, Phi_r, X, input_names, w2_r)
    else:
        w2, basis = w2_r, Phi_r
    xi_all = spec.ratios_for(_omega(w2), n_listed=n_modes)
    Sigma = basis.T @ Fd
    Theta = np.asarray(T @ basis, dtype=float)
    correction = None
    if static_correction == "residual":
        # rigid modes (omega^2 = 0, inertia relief) carry no static deflection
        flex = Sigma / np.where(np.arange(w2.size) < n_rigid, np.inf, w2)[:, None]
        residual = (G if G_relief is None else G_relief) - Theta @ flex
        correction = X - basis @ flex
    ss = modal_statespace(w2, xi_all, Sigma, Theta, residual=residual,
                          input_names=input_names, output_names=output_names,
                          n_retained=n_modes)
    model = ReducedModel(ss, None if G is None else _ro(G), _ro(w2), int(w2.size), n_modes,
                         static_correction, None if residual is None else _ro(residual),
                         _ro(basis), None if correction is None else _ro(correction))
    if G is not None:
        rel = np.linalg.norm(model.dc_gain_position - G) / max(np.linalg.norm(G), 1e-300)
        log.info("reduced model: %d states, static correction %s, DC gain error %.3g "
                 "(relative to T K^-1 F)", ss.n_states, static_correction, rel)
    return model
