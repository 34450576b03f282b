"""Measurements on a sampled response, and the eigen-analysis they are compared with.

Signals y (n_t,) on sample times t (n_t,), s. For one damped mode about a level y_ss,
y = y_ss + a exp(-zeta omega t) cos(omega_d t + phi), omega_d = omega sqrt(1 - zeta^2):

- :func:`steady_state`: Aitken's extrapolation of consecutive half-cycle extremes (their
  deviations from y_ss form a geometric series);
- :func:`zero_crossing_frequency`: crossings of y_ss are pi / omega_d apart (Hz);
- :func:`fft_peak_frequency`: largest spectral peak, Hann window, Gaussian interpolation;
- :func:`decay_damping_ratio`: log decrement d per half cycle, zeta = d / sqrt(pi^2 + d^2);
- :func:`modes_in`: which eigenvalues of a system a transient excites;
- :func:`fit_sweep`: T^2 = a + b m through a mass sweep's periods.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from pipeline.apps.simulate.systems import SteppedSystem

__all__ = ["OSCILLATION_MAX_DAMPING", "crossings", "extremes", "steady_state",
           "decay_damping_ratio", "zero_crossing_frequency", "fft_peak_frequency", "modes_in",
           "fit_sweep"]

#: A mode counts as an oscillation (candidate for "the measured frequency") below this
#: damping ratio; the filter poles of a filtered model are far more damped.
OSCILLATION_MAX_DAMPING = 0.3


def crossings(t: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Times (s) where s changes sign, linearly interpolated; crossings closer than a
    quarter of the median gap to the previous one (ripple of a higher mode) dropped."""
    sgn = np.sign(s)
    idx = np.flatnonzero(sgn[:-1] * sgn[1:] < 0)
    tc = t[idx] - s[idx] * (t[idx + 1] - t[idx]) / (s[idx + 1] - s[idx])
    if tc.size > 2:  # drop ripple crossings (a higher mode near a slow zero crossing)
        gap = np.median(np.diff(tc))
        keep = [0]
        for i in range(1, tc.size):
            if tc[i] - tc[keep[-1]] > 0.25 * gap:
                keep.append(i)
        tc = tc[keep]
    return tc


def extremes(t: np.ndarray, y: np.ndarray, level: float) -> np.ndarray:
    """Half-cycle extremes of y about ``level`` (one per interval between crossings),
    refined by a parabola through the three samples around each."""
    s = y - level
    sgn = np.sign(s)
    idx = np.flatnonzero(sgn[:-1] * sgn[1:] < 0) + 1
    out = []
    for a, b in zip(idx[:-1], idx[1:]):
        if b - a < 3:
            continue
        i = a + int(np.argmax(np.abs(s[a:b])))
        if 0 < i < y.size - 1:
            y0, y1, y2 = y[i - 1], y[i], y[i + 1]
            den = y0 - 2 * y1 + y2
            out.append(y1 - 0.125 * (y2 - y0) ** 2 / den if den != 0 else y1)
        else:
            out.append(y[i])
    return np.asarray(out)


def steady_state(t: np.ndarray, y: np.ndarray) -> float:
    """Steady value of a decaying oscillation: Aitken's extrapolation of consecutive
    half-cycle extremes (exact for one damped mode: the deviations of its extremes form a
    geometric series), median over the triples of the second half. Falls back to the last
    sample when the signal does not oscillate (fewer than three extremes)."""
    level = float(np.mean(y))
    for _ in range(2):
        e = extremes(t, y, level)
        if e.size < 3:
            return float(y[-1])
        est = []
        for i in range(e.size - 2):
            e1, e2, e3 = e[i], e[i + 1], e[i + 2]
            den = e1 + e3 - 2 * e2
            if den != 0:
                est.append((e1 * e3 - e2 * e2) / den)
        if not est:
            return float(y[-1])
        est_arr = np.asarray(est)
        level = float(np.median(est_arr[est_arr.size // 2:]))
    return level


def decay_damping_ratio(t: np.ndarray, y: np.ndarray, level: float | None = None) -> float:
    """Damping ratio from the decay of the half-cycle extremes about ``level`` (default:
    the steady state): the slope -d of ln|extreme - level| per half cycle (least squares)
    gives zeta = d / sqrt(pi^2 + d^2). NaN with fewer than 4 extremes."""
    if level is None:
        level = steady_state(t, y)
    e = np.abs(extremes(t, y, level) - level)
    e = e[e > 0]
    if e.size < 4:
        return math.nan
    d = -np.polyfit(np.arange(e.size, dtype=float), np.log(e), 1)[0]
    return float(d / math.sqrt(math.pi ** 2 + d * d))


def zero_crossing_frequency(t: np.ndarray, y: np.ndarray, level: float | None = None) -> float:
    """Frequency (Hz) from the crossings of y through ``level`` (default: its steady
    state): the half period is the slope of a least-squares line through the crossing
    times against their index (less sensitive to the jitter a higher mode adds to single
    crossings than first-to-last). Exact for one damped mode (its crossings are
    pi / omega_d apart). NaN with fewer than 3 crossings."""
    if level is None:
        level = steady_state(t, y)
    tc = crossings(t, y - level)
    if tc.size < 3:
        return math.nan
    k = np.arange(tc.size, dtype=float)
    half_period = np.polyfit(k, tc, 1)[0]   # least squares: averages the crossing jitter
    return 1.0 / (2.0 * half_period)


def fft_peak_frequency(t: np.ndarray, y: np.ndarray, fmin: float | None = None,
                       fmax: float | None = None, level: float | None = None
                       ) -> tuple[float, float]:
    """(frequency Hz, relative peak height) of the largest spectral peak in [fmin, fmax].

    Hann window, zero padding to >= 16x the length, Gaussian interpolation (parabola
    through the log magnitudes of the three bins around the peak). The height is the peak
    magnitude over the largest magnitude above fmin (1 for the main peak)."""
    dt = float(t[1] - t[0])
    s = y - (float(np.mean(y)) if level is None else level)
    n = s.size
    nfft = 1 << int(math.ceil(math.log2(16 * n)))
    X = np.abs(np.fft.rfft(s * np.hanning(n), nfft))
    f = np.fft.rfftfreq(nfft, dt)
    lo = 2.0 / (n * dt) if fmin is None else fmin
    hi = f[-1] if fmax is None else fmax
    band = np.flatnonzero((f >= lo) & (f <= hi))
    if band.size < 3:
        return math.nan, math.nan
    k = int(band[np.argmax(X[band])])
    top = float(X[f >= 2.0 / (n * dt)].max())
    if k <= 0 or k >= X.size - 1 or X[k] <= 0:
        return float(f[k]), (float(X[k] / top) if top > 0 else math.nan)
    a, b, c = np.log(np.maximum(X[k - 1:k + 2], 1e-300))
    den = a - 2 * b + c
    p = 0.5 * (a - c) / den if den != 0 else 0.0
    return float(f[k] + p * (f[1] - f[0])), float(X[k] / top)


def modes_in(sys: SteppedSystem, dz: np.ndarray, signal_rows: Sequence[int]
              ) -> list[tuple[float, float, float, complex]]:
    """Oscillation modes of A in a transient z - z_eq = dz: (damped Hz, damping ratio,
    score, eigenvalue), score = largest share of a signal's modal amplitude."""
    lam, V = np.linalg.eig(sys.A)
    coef = np.linalg.lstsq(V, dz.astype(complex), rcond=None)[0]
    out = []
    amps = []
    for r in signal_rows:
        amps.append(np.abs(sys.S[r] @ V) * np.abs(coef))
    amps_arr = np.asarray(amps)
    norm = amps_arr.max(axis=1, keepdims=True)
    norm[norm == 0] = 1.0
    share = (amps_arr / norm).max(axis=0)
    for i, l in enumerate(lam):
        if l.imag <= 0:
            continue
        zeta = -l.real / abs(l)
        if zeta >= OSCILLATION_MAX_DAMPING:
            continue
        out.append((abs(l.imag) / (2 * math.pi), zeta, float(share[i]), complex(l)))
    return sorted(out, key=lambda m: -m[2])


def fit_sweep(masses: np.ndarray, freqs: np.ndarray) -> dict[str, float]:
    """T^2 = a + b m fitted with relative residuals (weights 1/T^4: a period measurement's
    error is relative). Also the ordinary least-squares intercept, for comparison.

    Every value is NaN when fewer than three masses have a measured frequency (a run too
    short or a filter too slow to show a period) or when their periods do not differ (masses
    too light to change the body's period at double precision): no line fits then."""
    masses, freqs = np.asarray(masses, float), np.asarray(freqs, float)
    ok = np.isfinite(freqs) & (freqs > 0)
    masses, freqs = masses[ok], freqs[ok]
    T2 = 1.0 / freqs**2
    if T2.size < 3 or not np.all(np.isfinite(T2)) or np.ptp(T2) <= 1e-12 * T2.max() \
            or np.ptp(masses) == 0:
        return dict.fromkeys(("a_s2", "b_s2_per_kg", "r2", "r2_weighted", "f0_hz",
                              "effective_mass_kg", "f0_ols_hz", "r2_ols"), math.nan)
    X = np.column_stack([np.ones_like(masses), masses])
    w = 1.0 / T2
    (a, b), *_ = np.linalg.lstsq(X * w[:, None], T2 * w, rcond=None)
    resid = T2 - (a + b * masses)
    r2 = 1.0 - float(resid @ resid) / float(((T2 - T2.mean()) ** 2).sum())
    r2w = 1.0 - float(((resid * w) ** 2).sum()) / float((((T2 - np.average(T2, weights=w**2))
                                                          * w) ** 2).sum())
    (a_ols, b_ols), *_ = np.linalg.lstsq(X, T2, rcond=None)
    return {"a_s2": float(a), "b_s2_per_kg": float(b), "r2": r2, "r2_weighted": r2w,
            "f0_hz": 1.0 / math.sqrt(a) if a > 0 else math.nan,
            "effective_mass_kg": float(a / b) if b != 0 else math.nan,
            "f0_ols_hz": 1.0 / math.sqrt(a_ols) if a_ols > 0 else math.nan,
            "r2_ols": 1.0 - float(((T2 - X @ np.array([a_ols, b_ols])) ** 2).sum())
            / float(((T2 - T2.mean()) ** 2).sum())}

