"""The ``spin_up`` scenario: a flexible body on a hub driven through a prescribed speed.

The hub turns about the file's spin axis a (``/rotation``: unit axis, point p) with the
smooth ramp of Kane, Ryan and Banerjee (1987), final speed Omega_s (rad/s), ramp time T:

    Omega(t) = Omega_s / T (t - T / (2 pi) sin(2 pi t / T))   for t < T,   Omega_s after;
    alpha(t) = Omega' = Omega_s / T (1 - cos(2 pi t / T))       (0 after T);
    theta(t) = Omega_s / T (t^2 / 2 + (T / (2 pi))^2 (cos(2 pi t / T) - 1))   (hub angle).

In the frame of the hub (omega = Omega a, alpha = Omega' a) the deflection u = Phi q
(the file's n_m modes at rest, M-orthonormal) obeys the body-frame modal equations

    q'' + (D + 2 Omega C_a) q' + (K_r + Omega^2 (G_a - S_a) + Omega' C_a) q
        = Omega^2 f_a - Omega' e_a,

with, from :class:`~pipeline.reduce.spin.RotationModel` restricted to the modes:
K_r = diag(w_k^2); G_a = sum_ij a_i a_j G_ij, the geometric stiffness of the centrifugal
stress per unit Omega^2 (the stiffening); S_a = sum_ij a_i a_j S_ij, the spin softening
(the centrifugal force of the deflection, kinematics every floating-frame code has);
C_a = sum_k a_k C_k (skew: Coriolis 2 Omega C_a q', and the Euler force of the
deflection Omega' C_a q); f_a = sum_ij a_i a_j f_ij the centrifugal load and e_a =
sum_k a_k E_k the Euler (tangential) load of the undeformed body; D = diag(2 zeta_k w_k)
the file's modal damping (``damping: false``: none). Two modal models are stepped:

- ``stiffened``: the equations above;
- ``linear``: the same without G_a, the classical linear floating-frame model whose
  stiffness K_r - Omega^2 S_a loses definiteness once Omega passes the first in-plane
  frequency: its deflection runs away (the spin-up failure Kane, Ryan and Banerjee
  showed). The run stops when the deflection exceeds the body's largest extent.

Recorded: the deflection of the output port (the region's mean displacement along the
port's direction, in the hub frame, m), the hub speed (rad/s) and angle (rad). Predicted
beside it: the quasi-static deflection K(Omega)^-1 (Omega^2 f_a - Omega' e_a) at the peak
and at the end, and the speed where the linear model's stiffness loses definiteness.
The lumped chain is stepped with its rigid-body kinematics by :mod:`.spinchain`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from scipy.integrate import solve_ivp

from pipeline.config.rotation import tensor_weights
from pipeline.errors import FileFormatError, SolverError
from pipeline.reduce.spin import RotationModel
from pipeline.store.read import ModelFile, read_fe_model, read_rotation

from pipeline.apps.simulate.integrate import time_grid
from pipeline.apps.simulate.results import Row, Run, ScenarioResult
from pipeline.apps.simulate.scenarios import Scenario, check_step_budget
from pipeline.apps.simulate.spinchain import planar_chain, step_chain

__all__ = ["hub_profile", "SpinSystem", "spin_system", "step_spin", "run_spin_up",
           "port_row", "check_spin_file", "check_spin_budget", "plot_spin_up"]

#: labels of the two modal models a spin_up scenario steps
MODELS = {"stiffened": "modal, geometric stiffening", "linear": "modal, no stiffening",
          "lumped": "lumped chain, rigid-body kinematics"}


def hub_profile(t, final_speed: float, ramp_time: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Omega (rad/s), alpha (rad/s^2), theta (rad)) of the Kane-Ryan-Banerjee ramp at the
    times ``t`` (s), each shaped like ``t``."""
    t = np.asarray(t, dtype=float)
    T, W = float(ramp_time), float(final_speed)
    c = 2 * math.pi / T
    ramp = t < T
    tr = np.where(ramp, t, T)
    speed = np.where(ramp, W / T * (tr - np.sin(c * tr) / c), W)
    alpha = np.where(ramp, W / T * (1 - np.cos(c * tr)), 0.0)
    angle = W / T * (tr ** 2 / 2 + (np.cos(c * tr) - 1) / c ** 2) + W * (t - tr)
    return speed, alpha, angle


@dataclass(frozen=True)
class SpinSystem:
    """The modal equations of the module docstring, all (n_m, n_m) or (n_m,):
    stiffness K_r (rad^2/s^2), stiffening G_a and softening S_a (per rad^2/s^2),
    coriolis C_a, damping D (1/s), centrifugal f_a and euler e_a loads, and ``row``: the
    output port's displacement per unit q (m kg^1/2)."""

    stiffness: np.ndarray
    stiffening: np.ndarray
    softening: np.ndarray
    coriolis: np.ndarray
    damping: np.ndarray
    centrifugal: np.ndarray
    euler: np.ndarray
    row: np.ndarray

    def stiffness_at(self, speed: float, alpha: float = 0.0, stiffened: bool = True
                     ) -> np.ndarray:
        G = self.stiffening if stiffened else 0.0
        return self.stiffness + speed ** 2 * (G - self.softening) + alpha * self.coriolis

    def quasi_static(self, speed: float, alpha: float) -> float:
        """The output's deflection (m) with q'' = q' = 0 at this speed and acceleration."""
        load = speed ** 2 * self.centrifugal - alpha * self.euler
        return float(self.row @ np.linalg.solve(self.stiffness_at(speed, alpha), load))

    def onset_speed(self) -> float:
        """Lowest speed (rad/s) where K_r - Omega^2 S_a has a zero eigenvalue: the linear
        model's instability (inf when S_a has no positive eigenvalue)."""
        mu = sla.eigh(self.softening, self.stiffness, eigvals_only=True)
        top = float(mu.max(initial=0.0))
        return 1.0 / math.sqrt(top) if top > 0 else math.inf


def port_row(mf: ModelFile, port: str, n_modes: int) -> np.ndarray:
    """(n_modes,) the output port's displacement per unit modal coordinate: the mean of
    the modes over the port's region along its direction, with the port's weights
    (integrals of the shape functions: a third of each triangle's area on its corners
    for linear elements, on its mid-edge nodes for quadratic ones)."""
    info = mf.ports.get(port)
    if info is None or info["direction"] is None or info["region"] is None \
            or info["kind"] != "displacement":
        raise FileFormatError(f"file '{mf.path}': output port '{port}' is not a displacement "
                              "port with a region and a direction (spin_up needs one)")
    fe = read_fe_model(mf.path, basis="modes")
    faces = fe.regions.get(str(info["region"]))
    if faces is None or faces.ndim != 2 or faces.shape[1] != 3:
        raise FileFormatError(f"file '{mf.path}': region '{info['region']}' of port '{port}' "
                              "is not a surface (spin_up reads its triangles)")
    pts = fe.points
    a, b, c = (pts[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    weights = np.zeros(len(pts))
    if fe.cell_type.endswith("10"):  # quadratic: the mid-edge nodes carry the weight
        index = {tuple(np.round(p, 12)): i for i, p in enumerate(pts)}
        for u, v in ((0, 1), (1, 2), (2, 0)):
            mids = 0.5 * (pts[faces[:, u]] + pts[faces[:, v]])
            nodes = [index.get(tuple(np.round(m, 12))) for m in mids]
            if any(n is None for n in nodes):
                raise FileFormatError(f"file '{mf.path}': region '{info['region']}' has "
                                      "no mid-edge node on some edge")
            np.add.at(weights, np.asarray(nodes), area / 3)
    else:
        for k in range(3):
            np.add.at(weights, faces[:, k], area / 3)
    shapes = fe.basis.shapes.reshape(len(pts), 3, -1)[:, :, :n_modes]
    along = np.einsum("pcm,c->pm", shapes, info["direction"])
    return weights @ along / weights.sum()


def _damping(mf: ModelFile, sc: Scenario, omega: np.ndarray, notes: list[str]) -> np.ndarray:
    """diag(2 zeta_k w_k): the plant's modal damping ratios in mode order (modes beyond
    the plant's take its last ratio), or zeros for ``damping: false``."""
    if not sc.damping:
        return np.zeros((omega.size, omega.size))
    idx = mf.plant.modal_indices()
    if idx is None:
        notes.append("the plant is not modal: its damping is not known, none applied")
        return np.zeros((omega.size, omega.size))
    e, d = idx
    w = np.sqrt(np.maximum(-np.diag(mf.plant.A[np.ix_(d, e)]), 0.0))
    zeta = -np.diag(mf.plant.A[np.ix_(d, d)]) / np.maximum(2 * w, 1e-300)
    ratios = np.resize(zeta, omega.size) if zeta.size else np.zeros(omega.size)
    if zeta.size < omega.size:
        ratios[zeta.size:] = zeta[-1]
        notes.append(f"modes {zeta.size + 1}-{omega.size} take the damping ratio of the "
                     f"plant's last mode ({zeta[-1]:.3g})")
    return np.diag(2 * ratios * omega)


def spin_system(mf: ModelFile, rot: RotationModel, sc: Scenario, port: str,
                notes: list[str]) -> SpinSystem:
    """The :class:`SpinSystem` of the file's modes (the head of the rotation basis)."""
    n = rot.n_modes
    a = rot.axis
    wts = tensor_weights(a)
    K = rot.stiffness[:n, :n]
    omega = np.sqrt(np.maximum(np.diag(K), 0.0))
    if rot.stiffness.shape[0] > n:
        notes.append(f"the modal model steps the {n} modes of the file; the other "
                     f"{rot.stiffness.shape[0] - n} shapes of the rotation basis have no "
                     "stored output row")
    return SpinSystem(
        stiffness=K, stiffening=np.tensordot(wts, rot.geometric, axes=1)[:n, :n],
        softening=np.tensordot(wts, rot.softening, axes=1)[:n, :n],
        coriolis=np.tensordot(a, rot.coriolis, axes=1)[:n, :n],
        damping=_damping(mf, sc, omega, notes),
        centrifugal=(wts @ rot.centrifugal_load)[:n], euler=(a @ rot.euler_load)[:n],
        row=port_row(mf, port, n))


def step_spin(system: SpinSystem, sc: Scenario, stiffened: bool, limit: float
              ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Integrate from rest (q = q' = 0 at t = 0) on the scenario's sample grid. Returns
    (t (n_t,) s, deflection (n_t,) m, statistics); the run stops early (t shorter) when
    |deflection| exceeds ``limit`` (m): the model has run away."""
    n = system.stiffness.shape[0]
    t = time_grid(sc)
    W, T = sc.final_speed, sc.ramp_time
    M_dq = system.damping

    def rhs(time, z):
        speed, alpha, _ = hub_profile(time, W, T)
        q, dq = z[:n], z[n:]
        K = system.stiffness_at(float(speed), float(alpha), stiffened)
        ddq = (speed ** 2 * system.centrifugal - alpha * system.euler - K @ q
               - (M_dq + 2 * speed * system.coriolis) @ dq)
        return np.concatenate([dq, ddq])

    def runaway(_time, z):
        return limit - abs(float(system.row @ z[:n]))
    runaway.terminal = True

    # absolute tolerance from the size of the quasi-static response at the ramp's peak
    scale = np.abs(np.linalg.solve(system.stiffness_at(0.0),
                                   W ** 2 * system.centrifugal + 2 * W / T * system.euler))
    scale = np.maximum(scale, 1e-9 * max(float(scale.max()), 1e-300))
    omega = np.sqrt(np.maximum(np.diag(system.stiffness), 1e-300))
    atol = sc.integrator.atol * np.concatenate([scale, scale * omega])
    kw = {"jac": lambda time, z: _jacobian(system, time, W, T, stiffened)} \
        if sc.integrator.method in ("Radau", "BDF", "LSODA") else {}
    start = time.perf_counter()
    sol = solve_ivp(rhs, (0.0, float(t[-1])), np.zeros(2 * n), method=sc.integrator.method,
                    t_eval=t, rtol=sc.integrator.rtol, atol=atol, events=runaway, **kw)
    if sol.status == -1:
        raise SolverError(f"scenario '{sc.name}': solve_ivp ({sc.integrator.method}) "
                          f"failed: {sol.message}")
    stats = {"nfev": int(sol.nfev), "njev": int(sol.njev), "nlu": int(sol.nlu),
             "method": sc.integrator.method, "rtol": sc.integrator.rtol,
             "atol": sc.integrator.atol, "wall_s": time.perf_counter() - start}
    if sol.status == 1 and sol.t_events[0].size:
        stats["runaway_s"] = float(sol.t_events[0][0])
    return sol.t, system.row @ sol.y[:n], stats


def _jacobian(system: SpinSystem, time: float, W: float, T: float, stiffened: bool
              ) -> np.ndarray:
    n = system.stiffness.shape[0]
    speed, alpha, _ = hub_profile(time, W, T)
    J = np.zeros((2 * n, 2 * n))
    J[:n, n:] = np.eye(n)
    J[n:, :n] = -system.stiffness_at(float(speed), float(alpha), stiffened)
    J[n:, n:] = -(system.damping + 2 * float(speed) * system.coriolis)
    return J


def check_spin_budget(mf: ModelFile, sc: Scenario, port: str) -> None:
    """Refuse (SolverError, one line, before any run) a spin-up whose stiffened modal
    model is unstable at the final speed (K_r + Omega_s^2 (G_a - S_a) not positive
    definite: a spin-softening instability or buckling under the centrifugal stress; it
    is then definite at every lower speed of the ramp, K being affine in Omega^2), or
    which the integrator cannot step within the stepper's budget (the estimate of
    :func:`~pipeline.apps.simulate.scenarios.check_step_budget` for the stiffened system
    at the final speed)."""
    system = spin_system(mf, check_spin_file(mf, sc), sc, port, [])
    n = system.stiffness.shape[0]
    K = system.stiffness_at(sc.final_speed)
    if np.linalg.eigvalsh(0.5 * (K + K.T))[0] <= 0.0:
        raise SolverError(
            f"scenario '{sc.name}'.final_speed: at {sc.final_speed:g} rad/s the prestressed "
            "stiffness K_r + Omega^2 (G - S) of the modal model is not positive definite (a "
            "spin-softening instability or buckling under the centrifugal stress); expected "
            "a speed below it", key=f"{sc.name}.final_speed", value=sc.final_speed)
    A = np.block([[np.zeros((n, n)), np.eye(n)],
                  [-system.stiffness_at(sc.final_speed), -system.damping]])
    check_step_budget(A, sc.duration, sc.integrator.method, sc.name, rtol=sc.integrator.rtol)


def check_spin_file(mf: ModelFile, sc: Scenario) -> RotationModel:
    """The file's rotation model, or FileFormatError (one line) for a file without what
    spin_up needs: ``/rotation`` with its inertia loads (files of this version)."""
    rot = read_rotation(mf.path)
    if rot is None:
        raise FileFormatError(f"file '{mf.path}': has no /rotation group, which scenario "
                              f"'{sc.name}' (spin_up) needs; add a rotation section to the "
                              "config and run it again")
    if rot.centrifugal_load is None:
        raise FileFormatError(f"file '{mf.path}': /rotation has no centrifugal_load, "
                              f"euler_load, coriolis (an older file), which scenario "
                              f"'{sc.name}' (spin_up) needs; run the config again")
    return rot


def run_spin_up(mf: ModelFile, sc: Scenario, port: str) -> ScenarioResult:
    """Step the stiffened and the linear modal model through the scenario's ramp."""
    rot = check_spin_file(mf, sc)
    notes: list[str] = []
    system = spin_system(mf, rot, sc, port, notes)
    fe = read_fe_model(mf.path, basis="modes")
    limit = float(np.max(fe.points.max(axis=0) - fe.points.min(axis=0)))
    result = ScenarioResult(sc, [], [], notes)
    t_grid = time_grid(sc)
    speeds, alphas, _ = hub_profile(t_grid, sc.final_speed, sc.ramp_time)
    quasi = np.array([system.quasi_static(float(w), float(al)) for w, al in zip(speeds, alphas)])
    k_peak = int(np.argmax(np.abs(quasi)))
    onset = system.onset_speed()
    for key, stiffened in (("stiffened", True), ("linear", False)):
        t, y, stats = step_spin(system, sc, stiffened, limit)
        speed, _, angle = hub_profile(t, sc.final_speed, sc.ramp_time)
        run = Run(MODELS[key], key, t, {f"{port}/position": y, "hub_speed": speed,
                                        "hub_angle": angle},
                  {f"{port}/position": "m", "hub_speed": "rad/s", "hub_angle": "rad"},
                  {}, {}, dict(stats))
        peak = float(y[np.argmax(np.abs(y))]) if y.size else math.nan
        run.measured["peak_deflection"] = peak
        result.runs.append(run)
        label = run.model
        if stiffened:
            tail = t >= max(sc.ramp_time, t[-1] - 0.1 * sc.duration)
            final = 0.5 * float(y[tail].max() + y[tail].min()) if tail.any() else math.nan
            final_pred = system.quasi_static(sc.final_speed, 0.0)
            run.measured["final_deflection"] = final
            run.predicted.update(peak_deflection=float(quasi[k_peak]),
                                 final_deflection=final_pred)
            result.rows += [
                Row(sc.name, label, "peak deflection", peak, float(quasi[k_peak]), "m",
                    f"quasi-static at t = {t_grid[k_peak]:.4g} s"),
                Row(sc.name, label, "deflection at final speed (mid-range)", final, final_pred,
                    "m", "static under the centrifugal load")]
        else:
            ran = stats.get("runaway_s", math.nan)
            t_onset = float(t_grid[np.argmax(speeds >= onset)]) if np.any(speeds >= onset) \
                else math.nan
            run.measured["runaway_s"] = ran
            run.predicted["instability_onset_s"] = t_onset
            run.predicted["instability_speed_rad_s"] = onset
            result.rows += [
                Row(sc.name, label, "peak deflection", peak, float(quasi[k_peak]), "m",
                    "stiffened quasi-static"),
                Row(sc.name, label, "runaway time (|deflection| > body)", ran, t_onset, "s",
                    f"predicted: K_r - Omega^2 S_a indefinite at {onset:.4g} rad/s")]
            if math.isfinite(ran):
                notes.append(f"the linear model ran away at t = {ran:.4g} s (deflection past "
                             f"{limit:.3g} m, the body's size); the hub passed {onset:.4g} "
                             "rad/s, where its stiffness K_r - Omega^2 S_a loses definiteness")
    chain, why = planar_chain(mf, rot.axis, rot.point, port, sc.damping) if sc.lumped \
        else (None, "lumped: false")
    if chain is None:
        notes.append(f"no lumped run: {why}")
        return result
    t, y, stats = step_chain(chain, sc, lambda x: hub_profile(x, sc.final_speed, sc.ramp_time),
                             limit, float(quasi[k_peak]), math.sqrt(system.stiffness[0, 0]))
    speed, _, angle = hub_profile(t, sc.final_speed, sc.ramp_time)
    run = Run(MODELS["lumped"], "lumped", t, {f"{port}/position": y, "hub_speed": speed,
                                              "hub_angle": angle},
              {f"{port}/position": "m", "hub_speed": "rad/s", "hub_angle": "rad"}, {}, {},
              dict(stats))
    peak = float(y[np.argmax(np.abs(y))]) if y.size else math.nan
    run.measured["peak_deflection"] = peak
    run.predicted["peak_deflection"] = float(quasi[k_peak])
    result.runs.append(run)
    result.rows.append(Row(sc.name, run.model, "peak deflection", peak, float(quasi[k_peak]),
                           "m", "stiffened modal quasi-static"))
    return result


def plot_spin_up(path, s: ScenarioResult, port: str):
    """``<stem>.<scenario>.png``: the output's deflection in the hub frame against time for
    each model (the linear one until it runs away) with the stiffened quasi-static
    deflection dotted, and the hub speed below."""
    # deferred: heavy, only needed when plots are asked for; a Figure of its own (no
    # pyplot), so the host's matplotlib backend and open figures are left alone
    from matplotlib.figure import Figure

    from pipeline._util.atomic import atomic_path

    sc = s.scenario
    style = {"stiffened": dict(color="C0", lw=1.4), "linear": dict(color="C3", lw=1.0, ls="--"),
             "lumped": dict(color="C2", lw=1.0, ls="-.")}
    fig = Figure(figsize=(10, 6.2))
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    for run in s.runs:
        ax1.plot(run.t, 1e3 * run.signals[f"{port}/position"], label=run.model,
                 **style.get(run.key, {}))
        if run.key == "stiffened":
            ax2.plot(run.t, run.signals["hub_speed"], color="k", lw=1.2)
    bounded = [np.abs(r.signals[f"{port}/position"]).max() for r in s.runs
               if "runaway_s" not in r.info and r.t.size]
    if bounded and max(bounded) > 0:  # the runaway leaves the axes: the bounded ones stay legible
        ax1.set_ylim(-3e3 * max(bounded), 3e3 * max(bounded))
    for run in s.runs:
        if "runaway_s" in run.info:
            ax1.axvline(run.info["runaway_s"], color="C3", ls=":", lw=0.8)
            ax1.annotate(f"{run.model}: runs away ({run.info['runaway_s']:.3g} s)",
                         (run.info["runaway_s"], 0), xytext=(4, 4),
                         textcoords="offset points", fontsize=8, color="C3")
    ax1.set_ylabel(f"{port} deflection, hub frame [mm]")
    ax1.legend(fontsize=8, loc="best")
    ax2.set_ylabel("hub speed [rad/s]")
    ax2.set_xlabel("time [s]")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.axvspan(0.0, min(sc.ramp_time, sc.duration), color="0.93", zorder=0)
    fig.suptitle(f"{sc.name} (spin_up to {sc.final_speed:g} rad/s in {sc.ramp_time:g} s)",
                 fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    return path
