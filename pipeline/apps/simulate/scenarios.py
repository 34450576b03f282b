"""Scenario records and their validation: what a scenario file may say, checked once.

A scenario file holds one scenario (a mapping with a ``kind``) or a list of them; every
key is checked by the one field checker :mod:`pipeline._util.validate`, so a bad value
is one :class:`~pipeline.errors.ConfigError` line whose ``key`` is the dotted path of
the value (``scenario.force`` for a single scenario, ``scenarios[2].mass`` in a list,
``scenarios[0].integrator.rtol``), ``value`` what was given and ``expected`` what would
be accepted. Units are SI (N, kg, s, Hz, rad, N m/rad); docs/simulate.md lists every key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from pipeline._util import validate as v
from pipeline._util.yamlio import parse_yaml, read_text_bounded
from pipeline.config.numerics import MIN_RELATIVE_TOLERANCE
from pipeline.errors import ConfigError, SolverError

__all__ = ["KINDS", "METHODS", "LOOPS", "DEFAULT_GRAVITY", "MAX_SAMPLES", "SCENARIO_KEYS",
           "Integrator", "Scenario", "parse_scenario", "parse_scenarios", "load_scenarios",
           "as_scenarios"]

KINDS = ("step_load", "body_load", "mass_sweep", "spring_mount", "spin_up")
METHODS = ("LSODA", "Radau", "BDF", "RK45", "DOP853")
LOOPS = ("filtered", "exact")
#: ``gravity: true`` means this vector (m/s^2): the reference cantilever hangs along -y.
DEFAULT_GRAVITY = (0.0, -9.81, 0.0)
#: Most samples one run may produce (memory guard).
MAX_SAMPLES = 2_000_000
#: Fewest samples a run needs to measure anything.
MIN_SAMPLES = 16
#: Most right-hand-side evaluations (in LSODA-call equivalents) one segment may need,
#: estimated before integrating (:func:`check_step_budget`); one takes ~20 us on these
#: small systems, so this is about a minute. The shipped scenarios need ~4e4.
MAX_STEPS = 3_000_000
#: Cost model of each method: (right-hand-side calls per period of the fastest
#: oscillation at rtol = 1e-8, p, cost of one call relative to LSODA's), calls growing as
#: (rtol / 1e-8)^(-1/p). Measured on the cantilever's step_load (195 periods of its 976 Hz
#: fastest mode, rtol 1e-6 to 1e-14): LSODA 8.1e3 to 5.4e4 calls, RK45 1.1e4 to 3.5e5,
#: DOP853 9.6e3 to 5.8e4, Radau 2.2e4 to 1.8e6 (140 s at 1e-14), BDF 7.8e3 to 1.5e5 (its
#: calls carry Jacobian factorisations: 190 us each, Radau 75 us, the others ~20 us).
INTEGRATOR_COST = {"LSODA": (70.0, 10.0, 1.0), "RK45": (130.0, 5.0, 1.0),
                   "DOP853": (70.0, 10.0, 0.6), "Radau": (330.0, 4.0, 4.0),
                   "BDF": (85.0, 6.0, 10.0)}
#: Right-hand-side calls an explicit method spends per unit of duration x max|lambda|
#: (stability: its stages over its stability radius, 6 / 3.3 for RK45, 12 / 6 for DOP853)
EXPLICIT_CALLS_PER_RATE = 2.0
#: Largest |load| (N: force, preload), |gravity| (m/s^2) and mass (kg) a scenario takes:
#: far beyond any engineering case (a rocket engine ~1e7 N, a gun shock ~1e6 m/s^2, a ship
#: 1e8 kg) and far below where the responses' squares (energies) overflow double precision.
MAX_LOAD_N = 1e12
MAX_GRAVITY = 1e7
MAX_MASS_KG = 1e12
#: Lightest non-zero mass (kg), a microgram: lighter ones change nothing a run can show
#: and their gravity loads reach the subnormal range where the integrator stalls.
MIN_MASS_KG = 1e-9
#: Shortest duration (s): a microsecond holds no period of any structure's mode, and far
#: shorter runs put the integrator's steps below the clock's resolution (it hangs).
MIN_DURATION_S = 1e-6
#: Highest cutoff_hz: beyond it the filter's K^3 gains overflow double precision long
#: before the run, and already far beyond it the step budget refuses the run.
MAX_CUTOFF_HZ = 1e9
#: Largest duration x max|lambda| (time scales spanned by one run): beyond ~1/(4500 eps)
#: the fast states swamp the slow ones in A y at double precision and even an implicit
#: integrator stalls (a 1e30 kg body load gives 1e36 1/s next to 2e-6 1/s). The shipped
#: scenarios span ~1e7.
MAX_TIME_SCALE_SPAN = 1e12

_COMMON = ("name", "kind", "duration", "output_rate", "input", "output", "damping",
           "integrator", "lumped")
_LOOP_KEYS = ("gravity", "preload", "loop", "cutoff_hz")
#: The keys each kind of scenario accepts.
SCENARIO_KEYS = {
    "step_load": _COMMON + ("force", "t_on", "t_off", "stress_instants"),
    "body_load": _COMMON + ("mass",) + _LOOP_KEYS,
    "mass_sweep": _COMMON + ("masses", "cycles") + _LOOP_KEYS,
    "spring_mount": _COMMON + ("mass", "stiffness", "joint_damping", "joint",
                               "initial_angle") + _LOOP_KEYS,
    "spin_up": _COMMON + ("final_speed", "ramp_time"),
}
_REQUIRED = {"step_load": ("force",), "body_load": ("mass",), "mass_sweep": ("masses",),
             "spring_mount": ("mass", "stiffness"), "spin_up": ("final_speed", "ramp_time")}
_INTEGRATOR_KEYS = ("method", "rtol", "atol")
#: Largest joint coordinate (m): the arm's inertia m r^2 overflows far beyond it, and a
#: joint a thousand km from the body is no mount.
MAX_JOINT_M = 1e6
#: Largest |initial_angle| (rad): the mount is linearised about theta = 0.
MAX_INITIAL_ANGLE = 0.1
#: Largest |final_speed| of a spin_up (rad/s), the rotation section's MAX_SPEED: a body at
#: 1e6 rad/s has left linear elasticity.
MAX_SPIN_SPEED = 1e6


# =========================================================================== scenarios
@dataclass(frozen=True)
class Integrator:
    """solve_ivp settings. ``atol`` is relative to the peak magnitude of each state (the
    peaks come from an exact matrix-exponential pass, so the tolerance means the same for
    states in m kg^1/2, m kg^1/2/s, rad or N)."""

    method: str = "LSODA"
    rtol: float = 1e-8
    atol: float = 1e-8


@dataclass(frozen=True)
class Scenario:
    """One validated scenario (units SI; see docs/simulate.md for the meaning of each key).

    kind: step_load | body_load | mass_sweep | spring_mount. duration: s. output_rate: Hz
    (samples per second of the recorded time series). input / output: port names (None:
    the model's only input / output port). damping: False removes the modal damping of the
    model (the coupled system is then undamped, apart from the filter's own small effect).
    lumped: also run the lumped chain when the file has one.
    step_load: force (N along the input port's direction), t_on, t_off (s; None: stays on),
    stress_instants (s: instants at which the whole stress field is recovered, docs/stress.md).
    body_load / mass_sweep / spring_mount: mass (kg) or masses, gravity ((3,) m/s^2 or
    None), preload (N on the input port, held for t < 0 and released at t = 0), loop
    (filtered | exact), cutoff_hz (re-filter the plant at this cutoff instead of using the
    file's filtered model). spring_mount: stiffness (N m/rad), joint_damping (N m s/rad),
    joint ((3,) m, the revolute joint's point; None: centroid of the support region),
    initial_angle (rad, the joint's angle at t = 0).
    spin_up: final_speed (rad/s, the hub's speed after the ramp; the sign is the sense of
    rotation about the file's spin axis), ramp_time (s, the Kane-Ryan-Banerjee ramp's
    length T).
    """

    name: str
    kind: str
    duration: float
    output_rate: float = 5000.0
    input: str | None = None
    output: str | None = None
    damping: bool = True
    integrator: Integrator = Integrator()
    lumped: bool = True
    force: float = 0.0
    t_on: float = 0.0
    t_off: float | None = None
    mass: float = 0.0
    masses: tuple[float, ...] = ()
    gravity: tuple[float, float, float] | None = None
    preload: float = 0.0
    loop: str = "filtered"
    cutoff_hz: float | None = None
    stiffness: float = 0.0
    joint_damping: float = 0.0
    joint: tuple[float, float, float] | None = None
    initial_angle: float = 0.0
    cycles: float | None = None
    stress_instants: tuple[float, ...] = ()
    final_speed: float = 0.0
    ramp_time: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        """The keys a scenario file would hold for this scenario (round-trips)."""
        out: dict[str, Any] = {"name": self.name, "kind": self.kind, "duration": self.duration,
                               "output_rate": self.output_rate, "input": self.input,
                               "output": self.output, "damping": self.damping,
                               "lumped": self.lumped,
                               "integrator": {"method": self.integrator.method,
                                              "rtol": self.integrator.rtol,
                                              "atol": self.integrator.atol}}
        allowed = SCENARIO_KEYS[self.kind]
        for key in allowed:
            if key in out:
                continue
            value = getattr(self, key)
            out[key] = list(value) if isinstance(value, tuple) else value
        return out



def _optional_number(raw: Mapping, key: str, path: str, **bounds) -> float | None:
    """``raw[key]`` checked by :func:`validate.number`, or None when absent or null."""
    return None if raw.get(key) is None else v.number(raw, key, path, **bounds)


def _port_name(raw: Mapping, key: str, path: str) -> str | None:
    """A port name (the rule of config port names), or None: the model's only port."""
    return None if raw.get(key) is None else v.name(raw, key, path)


def _integrator(raw: Mapping, path: str) -> Integrator:
    where = f"{path}.integrator"
    integ_raw = raw.get("integrator")
    if integ_raw is None:
        return Integrator()
    v.mapping(integ_raw, where, _INTEGRATOR_KEYS)
    return Integrator(v.choice(integ_raw, "method", where, METHODS, Integrator.method),
                      v.number(integ_raw, "rtol", where, Integrator.rtol,
                               lo=MIN_RELATIVE_TOLERANCE, hi=1e-3),
                      v.number(integ_raw, "atol", where, Integrator.atol,
                               lo=MIN_RELATIVE_TOLERANCE, hi=1e-2))


def _masses(raw: Mapping, path: str) -> tuple[float, ...]:
    masses = raw.get("masses")
    if not isinstance(masses, list) or len(masses) < 3:
        raise v.fail(f"{path}.masses", masses, "a list of at least three masses (kg)")
    items = {f"masses[{i}]": m for i, m in enumerate(masses)}
    values = tuple(_mass(items, key, path) for key in items)
    if len(set(values)) < 3:
        raise v.fail(f"{path}.masses", masses, "at least three different masses (a line "
                     "through two points has no residual)")
    return values


def _mass(raw: Mapping, key: str, path: str) -> float:
    """A mass >= 0 (kg), at most MAX_MASS_KG."""
    mass = v.number(raw, key, path, lo=0.0)
    if mass > MAX_MASS_KG or 0.0 < mass < MIN_MASS_KG:
        raise v.fail(f"{path}.{key}", mass, f"0 or a mass of {MIN_MASS_KG:g} to "
                     f"{MAX_MASS_KG:g} kg")
    return mass


def parse_scenario(raw: Any, path: str) -> Scenario:
    """Validate one scenario mapping; ``path`` is its dotted path (``scenarios[0]``)."""
    if not isinstance(raw, Mapping):
        raise v.fail(path, raw, "a mapping of scenario keys (with a 'kind')")
    kind = v.choice(raw, "kind", path, KINDS)
    name = v.name(raw, "name", path, kind)
    v.mapping(raw, path, SCENARIO_KEYS[kind], _REQUIRED[kind] + ("duration",))
    duration = v.number(raw, "duration", path, lo=MIN_DURATION_S)
    rate = v.number(raw, "output_rate", path, 5000.0, lo=0.0, lo_open=True)
    samples = duration * rate
    if not MIN_SAMPLES <= samples <= MAX_SAMPLES:
        raise v.fail(f"{path}.duration", duration,
                     f"a duration giving {MIN_SAMPLES} to {MAX_SAMPLES:g} samples at "
                     f"output_rate {rate:g} Hz (duration x output_rate = {samples:.3g})")
    common = dict(name=name, kind=kind, duration=duration, output_rate=rate,
                  input=_port_name(raw, "input", path), output=_port_name(raw, "output", path),
                  damping=v.boolean(raw, "damping", path, kind != "mass_sweep"),
                  integrator=_integrator(raw, path),
                  lumped=v.boolean(raw, "lumped", path, True))
    if kind == "step_load":
        t_on = v.number(raw, "t_on", path, 0.0, lo=0.0)
        t_off = _optional_number(raw, "t_off", path, lo=0.0)
        if t_on >= duration:
            raise v.fail(f"{path}.t_on", t_on,
                         f"a time before the end of the run (duration {duration:g} s)")
        if t_off is not None and not t_on < t_off:
            raise v.fail(f"{path}.t_off", t_off,
                         f"a time after t_on = {t_on:g} s (or null: stays on)")
        if t_off is not None and t_off >= duration:
            t_off = None  # switched off at or after the end: never within the run
        force = v.number(raw, "force", path, lo=-MAX_LOAD_N, hi=MAX_LOAD_N)
        if force == 0.0:
            raise v.fail(f"{path}.force", force, "a non-zero force (N)")
        raw_instants = raw.get("stress_instants") or []
        if not isinstance(raw_instants, list):
            raise v.fail(f"{path}.stress_instants", raw_instants, "a list of times (s)")
        items = {f"stress_instants[{i}]": x for i, x in enumerate(raw_instants)}
        instants = tuple(v.number(items, k, path, lo=0.0, hi=duration) for k in items)
        return Scenario(**common, force=force, t_on=t_on, t_off=t_off, stress_instants=instants)
    if kind == "spin_up":
        speed = v.number(raw, "final_speed", path, lo=-MAX_SPIN_SPEED, hi=MAX_SPIN_SPEED)
        if speed == 0.0:
            raise v.fail(f"{path}.final_speed", speed, "a non-zero hub speed (rad/s)")
        ramp = v.number(raw, "ramp_time", path, lo=MIN_DURATION_S)
        return Scenario(**common, final_speed=speed, ramp_time=ramp)

    loop = v.choice(raw, "loop", path, LOOPS, "filtered")
    gravity_raw = raw.get("gravity", False)
    if gravity_raw is True:
        gravity = DEFAULT_GRAVITY
    elif gravity_raw is False or gravity_raw is None:
        gravity = None
    else:
        gravity = v.vector(raw, "gravity", path)
        if math.hypot(*gravity) > MAX_GRAVITY:
            raise v.fail(f"{path}.gravity", list(gravity), f"an acceleration of at most "
                         f"{MAX_GRAVITY:g} m/s^2 (|g| = {math.hypot(*gravity):.3g})")
        if not any(gravity):
            gravity = None
    extra: dict[str, Any] = dict(
        gravity=gravity, preload=v.number(raw, "preload", path, 0.0, lo=-MAX_LOAD_N,
                                          hi=MAX_LOAD_N), loop=loop,
        cutoff_hz=_optional_number(raw, "cutoff_hz", path, lo=0.0, lo_open=True,
                                   hi=MAX_CUTOFF_HZ))
    if extra["cutoff_hz"] is not None and loop != "filtered":
        raise v.fail(f"{path}.cutoff_hz", extra["cutoff_hz"], "no cutoff with loop: exact "
                     "(a cutoff re-filters the plant for loop: filtered)")
    if kind == "mass_sweep":
        extra["masses"] = _masses(raw, path)
        extra["cycles"] = _optional_number(raw, "cycles", path, lo=2.0)
        lightest = min(extra["masses"])
    else:
        extra["mass"] = _mass(raw, "mass", path)
        lightest = extra["mass"]
    if kind == "spring_mount":
        extra["stiffness"] = v.number(raw, "stiffness", path, lo=0.0, lo_open=True)
        extra["joint_damping"] = v.number(raw, "joint_damping", path, 0.0, lo=0.0)
        extra["joint"] = v.vector(raw, "joint", path, None)
        if extra["joint"] is not None and max(map(abs, extra["joint"])) > MAX_JOINT_M:
            raise v.fail(f"{path}.joint", list(extra["joint"]), f"a point within "
                         f"{MAX_JOINT_M:g} m of the origin (m; null: the support's centroid)")
        extra["initial_angle"] = v.number(raw, "initial_angle", path, 0.0)
        if abs(extra["initial_angle"]) > MAX_INITIAL_ANGLE:
            raise v.fail(f"{path}.initial_angle", extra["initial_angle"],
                         f"a small angle, |angle| <= {MAX_INITIAL_ANGLE:g} rad (the model is "
                         "linearised)")
    excited = extra["preload"] != 0.0 or (gravity is not None and lightest > 0.0) \
        or (kind == "spring_mount" and (extra["initial_angle"] != 0.0 or gravity is not None))
    if not excited:
        why = ("with mass 0 in the sweep, gravity does not load the body; " if
               gravity is not None else "")
        load = "preload (N) or gravity" + (" or initial_angle" if kind == "spring_mount" else "")
        raise ConfigError(f"config key '{path}': nothing excites the system: {why}set {load}",
                          key=path, expected=f"a load: {load}")
    return Scenario(**common, **extra)


def _unique_names(scenarios: list[Scenario], path: str) -> list[Scenario]:
    names = [s.name for s in scenarios]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"config key '{path}': scenario name(s) {', '.join(dup)} used more "
                          "than once; give each scenario its own 'name'", key=path,
                          value=dup, expected="a different name for each scenario")
    return scenarios


def parse_scenarios(raw: Any, source: str | None = None) -> list[Scenario]:
    """Validate a parsed scenario document: one mapping (one scenario) or a list of them.

    Keys in errors are ``scenario.<key>`` for a mapping and ``scenarios[i].<key>`` for a
    list, under ``source`` when given."""
    if isinstance(raw, Mapping):
        return [parse_scenario(raw, source or "scenario")]
    root = source or "scenarios"
    if not (isinstance(raw, list) and raw):
        raise v.fail(root, raw, "a scenario (a mapping with a 'kind') or a non-empty list "
                     "of scenarios")
    return _unique_names([parse_scenario(item, f"{root}[{i}]") for i, item in enumerate(raw)],
                         root)


def load_scenarios(path: str | Path) -> list[Scenario]:
    """Read and validate a scenario YAML file (one scenario or a list). An error names the
    file in its message; its ``key`` stays the path inside the document."""
    path = Path(path)
    try:
        text = read_text_bounded(path, "scenario file")  # regular file, bounded size
    except FileNotFoundError:
        raise ConfigError(f"scenario file '{path}': not found", key=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"scenario file '{path}': cannot be read ({exc})",
                          key=str(path)) from None
    raw = parse_yaml(text, f"scenario file '{path}'")
    if raw is None:
        raise ConfigError(f"scenario file '{path}': is empty, expected a scenario or a list",
                          key=str(path), expected="a scenario or a list of scenarios")
    try:
        return parse_scenarios(raw)
    except ConfigError as exc:
        raise ConfigError(f"scenario file '{path}': {exc}", key=exc.key, value=exc.value,
                          expected=exc.expected) from None


def as_scenarios(scenario: Any) -> list[Scenario]:
    """Scenarios from what :func:`simulate` accepts: a Scenario, a file path, a parsed
    mapping or list, or a list of Scenarios or of file paths (names unique across files)."""
    if isinstance(scenario, Scenario):
        return [scenario]
    if isinstance(scenario, (str, Path)):
        return load_scenarios(scenario)
    if isinstance(scenario, (list, tuple)) and scenario and all(
            isinstance(s, Scenario) for s in scenario):
        return list(scenario)
    if isinstance(scenario, (list, tuple)) and scenario and all(
            isinstance(s, (str, Path)) for s in scenario):
        out: list[Scenario] = []
        for s in scenario:
            out.extend(load_scenarios(s))
        names = [s.name for s in out]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(f"scenario name(s) {', '.join(dup)} used in more than one file",
                              key="name", value=dup,
                              expected="a different name for each scenario")
        return out
    return parse_scenarios(list(scenario) if isinstance(scenario, tuple) else scenario)


def check_step_budget(A: np.ndarray, duration: float, method: str, name: str = "",
                      rtol: float = Integrator.rtol) -> float:
    """Refuse (SolverError, one line) a coupled system the integrator cannot step through
    within :data:`MAX_STEPS` right-hand-side calls (about a minute): extreme but valid
    scenario numbers (a 1e30 kg mass, a 1e30 N m/rad spring) make its eigenvalues lambda
    huge, and a tight ``rtol`` multiplies the steps per period. The estimate, in LSODA-call
    equivalents: duration x f_max (periods of the fastest oscillation, f_max =
    max|Im lambda| / 2 pi) x calls per period at ``rtol`` (:data:`INTEGRATOR_COST`), for an
    explicit method at least :data:`EXPLICIT_CALLS_PER_RATE` x duration x max|lambda|
    (stability), times the method's cost per call. Non-finite A is refused too. Returns
    the estimate."""
    if not np.all(np.isfinite(A)):
        raise SolverError(f"{_which(name)}: the coupled system has non-finite entries "
                          "(a mass, stiffness or load beyond double precision); use values "
                          "within engineering ranges")
    lam = np.linalg.eigvals(A) if A.size else np.zeros(0)
    rate = float(np.abs(lam).max(initial=0.0))
    f_max = float(np.abs(lam.imag).max(initial=0.0)) / (2 * math.pi)
    per_period, order, weight = INTEGRATOR_COST.get(method, INTEGRATOR_COST["LSODA"])
    tightening = (rtol / Integrator.rtol) ** (-1.0 / order)
    calls = duration * f_max * per_period * tightening
    if method not in ("LSODA", "BDF", "Radau"):
        calls = max(calls, EXPLICIT_CALLS_PER_RATE * duration * rate)
    steps = calls * weight
    span = duration * rate
    if not math.isfinite(span) or span > MAX_TIME_SCALE_SPAN:
        raise SolverError(
            f"{_which(name)}: the coupled system's fastest rate |lambda| = "
            f"{rate:.3g} 1/s over {duration:g} s spans "
            f"{span:.2g} time scales (more than {MAX_TIME_SCALE_SPAN:.0e}, beyond double "
            "precision); a mass, stiffness or cutoff far outside the model's range does "
            "this: use values of the order of the body's own")
    if not math.isfinite(steps) or steps > MAX_STEPS:
        looser = ""
        if math.isfinite(steps) and steps / tightening <= MAX_STEPS:
            need = Integrator.rtol * (steps / tightening / MAX_STEPS) ** order
            looser = (f"; with {method}, integrator.rtol = {rtol:g} alone does this: use "
                      f"rtol >= {need:.2g}" + ("" if method in ("LSODA", "DOP853") else
                                               " or method LSODA"))
        raise SolverError(
            f"{_which(name)}: the coupled system oscillates up to {f_max:.3g} Hz "
            f"(fastest |lambda| {rate:.3g} 1/s), so integrating {duration:g} s with "
            f"{method} at rtol {rtol:g} would take ~{steps:.2g} right-hand-side calls (more "
            f"than {MAX_STEPS:.0e}, about a minute){looser}; otherwise a mass, stiffness or "
            "cutoff far outside the model's range does this: use values of the order of the "
            "body's own, or a shorter duration")
    return steps


def _which(name: str) -> str:
    return f"scenario '{name}'" if name else "scenario"
