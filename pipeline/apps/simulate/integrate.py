"""Time integration of a :class:`~pipeline.apps.simulate.systems.SteppedSystem`.

The inputs w are piecewise constant (:class:`Segment`: w on [t0, t1), s), so

    z(t + h) = Phi(h) z(t) + Gamma(h) w,   [Phi Gamma; 0 I] = expm([A B; 0 0] h)

is exact (:func:`propagate_exact`). :func:`integrate` runs scipy's ``solve_ivp`` over each
segment (restarted at every switch), with per-state absolute tolerances scaled by the
peak of each state from the exact pass, and reports how far every signal strays from
the exact solution. States Z are (n_z, n_t) arrays on the sample grid t (n_t,), s.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import scipy.linalg as sla
from scipy.integrate import solve_ivp

from pipeline.errors import SolverError

from pipeline.apps.simulate.scenarios import Integrator, Scenario, check_step_budget
from pipeline.apps.simulate.systems import SteppedSystem

__all__ = ["Segment", "time_grid", "propagate_exact", "integrate", "w_series"]

#: Shortest constant-input segment solve_ivp steps, relative to the time it ends at (or
#: the run's length): below it (~1e4 eps) the integrator's step underflows the clock and
#: the segment is stepped exactly by the matrix exponential instead.
MIN_SEGMENT = 1e-12


@dataclass(frozen=True)
class Segment:
    """Constant external inputs ``w`` (n_w,) on [t0, t1), s."""

    t0: float
    t1: float
    w: np.ndarray


def time_grid(sc: Scenario, duration: float | None = None) -> np.ndarray:
    """Sample times 0, 1/output_rate, ... up to ``duration`` (default the scenario's), s."""
    duration = sc.duration if duration is None else duration
    n = int(math.floor(duration * sc.output_rate + 1e-9)) + 1
    return np.arange(n) / sc.output_rate


def w_series(segments: Sequence[Segment], t: np.ndarray) -> np.ndarray:
    """The inputs at every sample, (n_w, n_t)."""
    W = np.zeros((segments[0].w.size, t.size))
    for seg in segments:
        last = seg is segments[-1]
        mask = (t >= seg.t0) & ((t < seg.t1) | (last & (t <= seg.t1 + 1e-12)))
        W[:, mask] = seg.w[:, None]
    return W


def propagate_exact(sys: SteppedSystem, z0: np.ndarray, segments: Sequence[Segment],
                     t: np.ndarray) -> np.ndarray:
    """States at the grid ``t`` by the matrix exponential (exact for piecewise-constant w)."""
    nz, nw = sys.B.shape
    aug = np.zeros((nz + nw, nz + nw))
    aug[:nz, :nz], aug[:nz, nz:] = sys.A, sys.B
    cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def step(h: float):
        key = round(h, 15)
        if key not in cache:
            E = sla.expm(aug * h)
            cache[key] = (E[:nz, :nz], E[:nz, nz:])
        return cache[key]

    Z = np.empty((nz, t.size))
    z = np.array(z0, dtype=float)
    k = 0
    for seg in segments:
        tc = seg.t0
        last = seg is segments[-1]
        while k < t.size and (t[k] < seg.t1 or (last and t[k] <= seg.t1 + 1e-12)):
            h = t[k] - tc
            if h > 0:
                Phi, Gam = step(h)
                z = Phi @ z + Gam @ seg.w
            Z[:, k] = z
            tc = t[k]
            k += 1
        h = seg.t1 - tc
        if h > 0 and not last:
            Phi, Gam = step(h)
            z = Phi @ z + Gam @ seg.w
    return Z


def integrate(sys: SteppedSystem, z0: np.ndarray, segments: Sequence[Segment],
               t: np.ndarray, integ: Integrator) -> tuple[np.ndarray, dict[str, Any]]:
    """solve_ivp over each constant-w segment (restarted at every switch).

    atol_i = integ.atol x peak|z_i| (peaks from the exact pass, floored at 1e-12 of the
    largest); the constant Jacobian A is passed to the implicit methods. Returns the
    states at ``t`` and statistics, including the largest deviation of every signal from
    the exact matrix-exponential solution (relative to the signal's peak).

    The system is linear, so it is stepped with z0 and w divided by their largest
    magnitude and the states scaled back: a load of 1e-300 N (or 1e300) is integrated
    like one of 1 N, never with subnormal tolerances that stall the integrator."""
    check_step_budget(sys.A, float(t[-1] - t[0]) if t.size else 0.0, integ.method,
                      rtol=integ.rtol)
    scale = max([float(np.abs(z0).max(initial=0.0))]
                + [float(np.abs(seg.w).max(initial=0.0)) for seg in segments])
    if scale > 0 and math.isfinite(scale) and scale != 1.0:
        Z, stats = integrate(sys, np.asarray(z0, float) / scale,
                             [Segment(s.t0, s.t1, s.w / scale) for s in segments], t, integ)
        return Z * scale, stats
    Zx = propagate_exact(sys, z0, segments, t)
    if not np.all(np.isfinite(Zx)):
        raise SolverError("scenario: the response overflows double precision (a load, mass "
                          "or stiffness beyond engineering ranges); use smaller values")
    peak = np.abs(Zx).max(axis=1)
    peak = np.maximum(peak, 1e-12 * max(float(peak.max()), 1e-300))
    atol = integ.atol * peak
    A = sys.A
    Z = np.empty_like(Zx)
    z = np.array(z0, dtype=float)
    stats = {"nfev": 0, "njev": 0, "nlu": 0}
    t_start = time.perf_counter()
    k = 0
    implicit = integ.method in ("LSODA", "Radau", "BDF")
    for seg in segments:
        last = seg is segments[-1]
        mask = (t >= seg.t0 - 1e-15) & ((t < seg.t1) | (last & (t <= seg.t1 + 1e-12)))
        mask[:k] = False
        te = t[mask]
        if seg.t1 - seg.t0 <= 0:
            continue
        bw = sys.B @ seg.w
        evals = np.unique(np.concatenate([te, [seg.t1]]))
        evals = evals[(evals >= seg.t0) & (evals <= seg.t1)]
        kw: dict[str, Any] = {"jac": (lambda _t, _y: A)} if implicit else {}
        if seg.t1 - seg.t0 <= MIN_SEGMENT * max(abs(seg.t1), float(t[-1])):
            # shorter than the integrator can step at this time (a switch 1e-300 s after
            # the start, t_off a rounding error after t_on): the exact step, no sample inside
            h = seg.t1 - seg.t0
            E = sla.expm(np.block([[A, bw[:, None]], [np.zeros((1, A.shape[0] + 1))]]) * h)
            Z[:, k:k + te.size] = z[:, None]
            k += te.size
            z = E[:-1, :-1] @ z + E[:-1, -1]
            continue
        if np.all(te == seg.t0) and te.size <= 1 and seg.t1 == seg.t0:
            sol_y = z[:, None]
        else:
            sol = solve_ivp(lambda _t, y: A @ y + bw, (seg.t0, seg.t1), z,
                            method=integ.method, t_eval=evals, rtol=integ.rtol, atol=atol,
                            **kw)
            if not sol.success:
                raise SolverError(f"solve_ivp ({integ.method}) failed: {sol.message}")
            for key in stats:
                stats[key] += int(getattr(sol, key, 0) or 0)
            sol_y = sol.y
            evals = sol.t
        n = te.size
        pos = np.searchsorted(evals, te)
        Z[:, k:k + n] = sol_y[:, pos]
        k += n
        z = sol_y[:, -1].copy()
    stats["wall_s"] = time.perf_counter() - t_start
    stats["method"] = integ.method
    stats["rtol"] = integ.rtol
    stats["atol"] = integ.atol
    Y, Yx = sys.S @ Z, sys.S @ Zx
    err = {}
    for i, name in enumerate(sys.signals):
        scale = float(np.abs(Yx[i]).max())
        err[name] = float(np.abs(Y[i] - Yx[i]).max() / scale) if scale > 0 else 0.0
    stats["deviation_from_exact"] = err
    return Z, stats


