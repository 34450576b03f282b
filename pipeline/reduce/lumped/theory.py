"""Euler-Bernoulli beam theory of the clamped beam (natural frequencies, tip deflection)
and the comparison table lumped chain vs beam theory vs FE (theory.md §8).

Frequencies in Hz, deflections in m per the given load (N); ``axis`` is a mode family
(``bending_z``: deflection along y, ``bending_y``, ``axial``, ``torsion``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from pipeline._util import validate
from pipeline.errors import ConfigError
from pipeline.reduce.lumped.chain import lumped_model
from pipeline.reduce.lumped.section import SectionProperties, poisson_ratio, positive, raw_field

__all__ = ["cantilever_beta_l", "beam_theory_frequencies_hz", "beam_theory_tip_deflection",
           "tip_mass_frequencies_hz",
           "ComparisonRow", "comparison_table", "format_comparison"]

_AXES = ("bending_z", "bending_y", "axial", "torsion")


# --------------------------------------------------------------------------- beam theory
def cantilever_beta_l(count: int) -> np.ndarray:
    """(count,) roots beta_k L of 1 + cos(x) cosh(x) = 0 (clamped-free Euler-Bernoulli beam):
    1.875104, 4.694091, 7.854757, ... solved to machine precision.

    Each root lies within a bracket around (2k - 1) pi / 2 where g = cos x + 1 / cosh x
    (1 + cos cosh scaled to stay O(1)) changes sign once; Newton steps that leave the
    bracket are replaced by bisection (``scipy.optimize.brentq`` would do the same job,
    but importing scipy.optimize would add about 0.1 s to every run for three numbers).

    >>> np.round(cantilever_beta_l(3), 6)
    array([1.875104, 4.694091, 7.854757])
    """
    def g(x: float) -> float:
        return math.cos(x) + 1.0 / math.cosh(x)

    def dg(x: float) -> float:
        return -math.sin(x) - math.tanh(x) / math.cosh(x)

    roots = []
    for k in range(1, count + 1):
        guess = (2 * k - 1) * math.pi / 2.0
        half = 1.0 if k <= 3 else 0.1
        lo, hi = guess - half, guess + half
        g_lo = g(lo)
        x = guess
        for _ in range(200):
            gx = g(x)
            if gx == 0.0:
                break
            if (gx < 0.0) == (g_lo < 0.0):
                lo, g_lo = x, gx
            else:
                hi = x
            step = gx / dg(x)
            x_new = x - step
            if not lo < x_new < hi:  # Newton left the bracket: bisect
                x_new = 0.5 * (lo + hi)
            if abs(x_new - x) <= 4.0 * np.finfo(float).eps * abs(x_new):
                x = x_new
                break
            x = x_new
        roots.append(x)
    return np.asarray(roots)


def beam_theory_frequencies_hz(section: SectionProperties, E: float, rho: float, length: float,
                               count: int = 3, axis: str = "bending_z", nu: float | None = None
                               ) -> np.ndarray:
    """(count,) Hz: the lowest cantilever frequencies of theory.md §8.

    bending_z (x-y plane, I_z) / bending_y (x-z plane, I_y): Euler-Bernoulli,
    omega_k = (beta_k L)^2 sqrt(E I / (rho A L^4)). axial: (2k - 1)/(4L) sqrt(E / rho).
    torsion (needs nu): (2k - 1)/(4L) sqrt(G J / (rho I_p)).
    """
    count = validate.integer(raw_field("count", count), "count", "", lo=1)
    axis = validate.choice(raw_field("axis", axis), "axis", "", _AXES)
    E = positive(E, "material.E")
    rho = positive(rho, "material.rho")
    L = positive(length, "geometry.length")
    k = np.arange(1, count + 1)
    if axis == "axial":
        return (2 * k - 1) / (4.0 * L) * math.sqrt(E / rho)
    if axis == "torsion":
        if nu is None:
            raise ConfigError("torsion frequencies need Poisson's ratio nu: got None")
        G = E / (2.0 * (1.0 + poisson_ratio(nu)))
        return (2 * k - 1) / (4.0 * L) * math.sqrt(G * section.J / (rho * section.I_p))
    EI = E * section.second_moment(axis)
    omega = cantilever_beta_l(count) ** 2 * math.sqrt(EI / (rho * section.area * L**4))
    return omega / (2.0 * math.pi)


def tip_mass_frequencies_hz(section: SectionProperties, E: float, rho: float, length: float,
                            mass: float, inertia: float, count: int = 3,
                            axis: str = "bending_z") -> np.ndarray:
    """(count,) Hz: Euler-Bernoulli cantilever with a tip mass ``mass`` (kg) and rotary
    inertia ``inertia`` (kg m^2, about the bending axis) [Blevins 1979, table 8-1]: the
    roots b_k of, with r = mass / (rho A L) and j = inertia / (rho A L^3),

        1 + cos b cosh b + r b (cos b sinh b - sin b cosh b)
          - j b^3 (cosh b sin b + sinh b cos b) + r j b^4 (1 - cos b cosh b) = 0,

    omega_k = b_k^2 sqrt(E I / (rho A L^4))."""
    from scipy.optimize import brentq

    L = positive(length, "geometry.length")
    m_beam = rho * section.area * L
    r, j = mass / m_beam, inertia / (m_beam * L**2)

    def f(b):
        c, s, ch, sh = np.cos(b), np.sin(b), np.cosh(b), np.sinh(b)
        # divided by cosh b (the terms grow like e^b; the roots are the same)
        return ((1 + c * ch + r * b * (c * sh - s * ch) - j * b**3 * (ch * s + sh * c)
                 + r * j * b**4 * (1 - c * ch)) / ch)

    grid = np.linspace(1e-3, (count + 1) * math.pi, 400 * (count + 1))
    values = f(grid)
    cross = np.flatnonzero(np.sign(values[:-1]) != np.sign(values[1:]))[:count]
    b = np.array([brentq(f, grid[k], grid[k + 1]) for k in cross])
    EI = E * section.second_moment(axis)
    return b**2 * math.sqrt(EI / (rho * section.area * L**4)) / (2.0 * math.pi)


def beam_theory_tip_deflection(section: SectionProperties, E: float, length: float,
                               load: float = 1.0, axis: str = "bending_z",
                               nu: float | None = None) -> float:
    """Static tip response of a cantilever under a tip load (theory.md §8).

    bending_z / bending_y: P L^3 / (3 E I) (m, P the tip force in N, I = I_z / I_y).
    axial: P L / (E A) (m). torsion (needs nu): T L / (G J) (rad, T the tip torque N m).
    """
    axis = validate.choice(raw_field("axis", axis), "axis", "", _AXES)
    E = positive(E, "material.E")
    L = positive(length, "geometry.length")
    P = validate.number(raw_field("load", load), "load", "")
    if axis == "axial":
        return P * L / (E * section.area)
    if axis == "torsion":
        if nu is None:
            raise ConfigError("torsion deflection needs Poisson's ratio nu: got None")
        G = E / (2.0 * (1.0 + poisson_ratio(nu)))
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
                     fe_tip_deflection: float | None = None,
                     point_masses: Sequence[tuple[float, float, Sequence[float]]] = ()
                     ) -> list[ComparisonRow]:
    """Rows: beam theory, FE (when given), then each kind for each n.

    axis: the bending plane compared, ``bending_z`` (x-y plane, tip force along y, the
    default) or ``bending_y``. count: how many frequencies per row (3: f1, f2, f3).
    load: tip force magnitude (N). fe_frequencies_hz: the FE model's lowest frequencies of
    the same bending family (Hz), fe_tip_deflection: its static tip deflection (m, along
    the force) under ``load``; the caller fills these from the FE run. point_masses: on
    the axis, (x, mass, (Jxx, Jyy, Jzz)) as :func:`lumped_model` takes them; beam theory is
    then the tip-mass frequency equation (:func:`tip_mass_frequencies_hz`) when they all
    sit at the tip, else not given (NaN).
    """
    axis = validate.choice(raw_field("axis", axis), "axis", "", ("bending_z", "bending_y"))
    force_dir = (0.0, -1.0, 0.0) if axis == "bending_z" else (0.0, 0.0, -1.0)
    f_beam = beam_theory_frequencies_hz(section, E, rho, length, count, axis)
    if point_masses:
        at_tip = all(abs(x - length) <= 1e-9 * length for x, _, _ in point_masses)
        J = sum(float(j[2 if axis == "bending_z" else 1]) for _, _, j in point_masses)
        m = sum(m for _, m, _ in point_masses)
        f_beam = (tip_mass_frequencies_hz(section, E, rho, length, m, J, count, axis)
                  if at_tip else np.full(count, math.nan))
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
                             input_direction=force_dir, output_direction=force_dir, tip_force=load,
                             point_masses=point_masses)
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
