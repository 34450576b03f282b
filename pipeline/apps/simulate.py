"""Reference stepper: replay the classic flexible-cantilever experiments from the HDF5 file.

``python -m pipeline simulate MODEL.h5 SCENARIO.yaml [...] [-o RESULT.h5]`` and
:func:`simulate`. The model is read from the file only (:func:`pipeline.store.read.load_model`
and h5py), never from the mesh or the FE code, coupled with rigid bodies where a scenario
asks, and integrated in time with :func:`scipy.integrate.solve_ivp`. Everything is linear
(small motions), so every scenario is one LTI system

    z' = Abar z + Bbar w(t),     signals = S z + Sw w(t),

with ``w`` piecewise constant (loads switched on and off). ``Abar`` is assembled from the
file's A, B, C, D and the rigid-body equations; the algebraic loop of a rigid mass on a
force-in/motion-out model is broken either by the file's filtered model (``loop:
filtered``: its D = 0, the mass force is an explicit function of the state) or solved
exactly (``loop: exact``: a small linear solve built into Abar; with a residual-flexibility
feedthrough in the position output, the force becomes a state, see docs/simulate.md).

Scenarios (docs/simulate.md lists every key):

- ``step_load``: a force on an input port switched on at ``t_on`` and off at ``t_off``;
- ``body_load``: a rigid mass welded to an output port, under gravity or released from a
  preload;
- ``mass_sweep``: the body load for several masses, T^2 fitted against the mass;
- ``spring_mount``: the body's root on a revolute joint about z with a torsional spring,
  the tip mass on; planar rotation coupled to the elastic model (the elastic input is the
  tip reaction force in the rotating body frame).

Each runs on the FE model and, when the file has one and its tip matches the ports, on the
lumped chain too. Measured (from the response: zero crossings, FFT peak refined by
Gaussian interpolation, steady state by Aitken extrapolation of the half-cycle extremes)
and predicted values (DC gain, eigenvalues of Abar) are reported side by side.
"""

from __future__ import annotations

import csv
import logging
import math
import re
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from pipeline._util.atomic import atomic_path
from pipeline.reduce.statespace import StateSpace
from pipeline.store.read import ModelFile, read_model_file
from pipeline.errors import ConfigError, FileFormatError

log = logging.getLogger(__name__)

__all__ = [
    "KINDS",
    "METHODS",
    "LOOPS",
    "Integrator",
    "Scenario",
    "Run",
    "Row",
    "ScenarioResult",
    "SimulationResults",
    "load_scenarios",
    "parse_scenarios",
    "simulate",
    "zero_crossing_frequency",
    "fft_peak_frequency",
    "steady_state",
    "decay_damping_ratio",
    "add_simulate_parser",
]

KINDS = ("step_load", "body_load", "mass_sweep", "spring_mount")
METHODS = ("LSODA", "Radau", "BDF", "RK45", "DOP853")
LOOPS = ("filtered", "exact")
#: ``gravity: true`` means this vector (m/s^2): the reference cantilever hangs along -y.
DEFAULT_GRAVITY = (0.0, -9.81, 0.0)
#: Most samples one run may produce (memory guard).
MAX_SAMPLES = 2_000_000
#: A mode counts as an oscillation (candidate for "the measured frequency") below this
#: damping ratio; the filter poles of a filtered model are far more damped.
OSCILLATION_MAX_DAMPING = 0.3
#: Relative tolerance of the checks that a file's outputs are consistent (velocity and
#: acceleration rows equal to the derivatives of the position row through A and B).
CONSISTENCY_TOL = 1e-8

_COMMON = ("name", "kind", "duration", "output_rate", "input", "output", "damping",
           "integrator", "lumped")
_LOOP_KEYS = ("gravity", "preload", "loop", "cutoff_hz")
_KEYS = {
    "step_load": _COMMON + ("force", "t_on", "t_off"),
    "body_load": _COMMON + ("mass",) + _LOOP_KEYS,
    "mass_sweep": _COMMON + ("masses", "cycles") + _LOOP_KEYS,
    "spring_mount": _COMMON + ("mass", "stiffness", "joint_damping", "joint",
                               "initial_angle") + _LOOP_KEYS,
}
_REQUIRED = {"step_load": ("force",), "body_load": ("mass",), "mass_sweep": ("masses",),
             "spring_mount": ("mass", "stiffness")}
_INTEGRATOR_KEYS = ("method", "rtol", "atol")


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
    step_load: force (N along the input port's direction), t_on, t_off (s; None: stays on).
    body_load / mass_sweep / spring_mount: mass (kg) or masses, gravity ((3,) m/s^2 or
    None), preload (N on the input port, held for t < 0 and released at t = 0), loop
    (filtered | exact), cutoff_hz (re-filter the plant at this cutoff instead of using the
    file's filtered model). spring_mount: stiffness (N m/rad), joint_damping (N m s/rad),
    joint ((3,) m, the revolute joint's point; None: centroid of the support region),
    initial_angle (rad, the joint's angle at t = 0).
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

    def as_dict(self) -> dict[str, Any]:
        """The keys a scenario file would hold for this scenario (round-trips)."""
        out: dict[str, Any] = {"name": self.name, "kind": self.kind, "duration": self.duration,
                               "output_rate": self.output_rate, "input": self.input,
                               "output": self.output, "damping": self.damping,
                               "lumped": self.lumped,
                               "integrator": {"method": self.integrator.method,
                                              "rtol": self.integrator.rtol,
                                              "atol": self.integrator.atol}}
        allowed = _KEYS[self.kind]
        for key in allowed:
            if key in out:
                continue
            value = getattr(self, key)
            out[key] = list(value) if isinstance(value, tuple) else value
        return out


def _describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


class _Keys:
    """Reads keys of one scenario mapping, naming ``where.key`` in every error."""

    def __init__(self, raw: Mapping, where: str):
        self.raw, self.where = raw, where

    def fail(self, key: str, value: Any, expected: str) -> ConfigError:
        return ConfigError(f"{self.where}.{key}: got {_describe(value)}, expected {expected}")

    def number(self, key: str, default: Any = None, *, lo: float | None = None,
               lo_open: bool = False, hi: float | None = None, unit: str = "") -> float:
        value = self.raw.get(key, default)
        if value is None:
            raise ConfigError(f"{self.where}.{key} is missing; it is required")
        what = f"a number{f' ({unit})' if unit else ''}"
        if lo is not None:
            what = f"a number {'>' if lo_open else '>='} {lo:g}{f' ({unit})' if unit else ''}"
        if hi is not None:
            what += f" and <= {hi:g}"
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(float(value)):
            raise self.fail(key, value, what)
        x = float(value)
        if lo is not None and (x < lo or (lo_open and x == lo)):
            raise self.fail(key, value, what)
        if hi is not None and x > hi:
            raise self.fail(key, value, what)
        return x

    def optional_number(self, key: str, **kw) -> float | None:
        if self.raw.get(key) is None:
            return None
        return self.number(key, **kw)

    def name(self, key: str) -> str | None:
        value = self.raw.get(key)
        if value is None:
            return None
        if not isinstance(value, str) or not value:
            raise self.fail(key, value, "a port name (string)")
        return value

    def boolean(self, key: str, default: bool) -> bool:
        value = self.raw.get(key, default)
        if isinstance(value, str) and value.lower() in ("on", "off"):
            return value.lower() == "on"
        if not isinstance(value, bool):
            raise self.fail(key, value, "true or false (on | off)")
        return value

    def vector(self, key: str, value: Any) -> tuple[float, float, float]:
        ok = (isinstance(value, (list, tuple)) and len(value) == 3
              and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                      and math.isfinite(float(v)) for v in value))
        if not ok:
            raise self.fail(key, value, "a list of three finite numbers [x, y, z]")
        return tuple(float(v) for v in value)  # type: ignore[return-value]


def _scenario(raw: Any, where: str, index: int) -> Scenario:
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{where}: got {_describe(raw)}, expected a mapping of scenario keys")
    kind = raw.get("kind")
    if kind not in KINDS:
        raise ConfigError(f"{where}.kind: got {_describe(kind)}, expected one of "
                          + " | ".join(KINDS))
    name = raw.get("name", kind)
    if not isinstance(name, str) or not re.match(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$", name):
        raise ConfigError(f"{where}.name: got {_describe(name)}, expected a name of 1-64 "
                          "letters, digits, '_', '-' or '.'")
    where = f"{where} ('{name}')"
    allowed = _KEYS[kind]
    for key in raw:
        if key not in allowed:
            raise ConfigError(f"{where}: key '{key}' is not known for kind {kind}; expected "
                              f"one of: {', '.join(allowed)}")
    for key in _REQUIRED[kind] + ("duration",):
        if raw.get(key) is None:
            raise ConfigError(f"{where}.{key} is missing; it is required for kind {kind}")
    k = _Keys(raw, where)
    duration = k.number("duration", lo=0.0, lo_open=True, unit="s")
    rate = k.number("output_rate", 5000.0, lo=0.0, lo_open=True, unit="Hz")
    if duration * rate > MAX_SAMPLES:
        raise ConfigError(f"{where}: duration x output_rate = {duration * rate:.3g} samples, "
                          f"expected at most {MAX_SAMPLES:g}")
    if duration * rate < 16:
        raise ConfigError(f"{where}: duration x output_rate = {duration * rate:.3g} samples, "
                          "expected at least 16")
    integ_raw = raw.get("integrator") or {}
    if not isinstance(integ_raw, Mapping):
        raise k.fail("integrator", integ_raw, "a mapping {method, rtol, atol}")
    for key in integ_raw:
        if key not in _INTEGRATOR_KEYS:
            raise ConfigError(f"{where}.integrator: key '{key}' is not known; expected one "
                              f"of: {', '.join(_INTEGRATOR_KEYS)}")
    ki = _Keys(integ_raw, f"{where}.integrator")
    method = integ_raw.get("method", Integrator.method)
    if method not in METHODS:
        raise ki.fail("method", method, "one of " + " | ".join(METHODS))
    integ = Integrator(method, ki.number("rtol", Integrator.rtol, lo=1e-14, hi=1e-3),
                       ki.number("atol", Integrator.atol, lo=1e-16, hi=1e-2))
    common = dict(name=name, kind=kind, duration=duration, output_rate=rate,
                  input=k.name("input"), output=k.name("output"),
                  damping=k.boolean("damping", kind != "mass_sweep"), integrator=integ,
                  lumped=k.boolean("lumped", True))
    if kind == "step_load":
        t_on = k.number("t_on", 0.0, lo=0.0, unit="s")
        t_off = k.optional_number("t_off", lo=0.0, unit="s")
        if t_on >= duration:
            raise k.fail("t_on", t_on, f"a time before the end of the run (duration {duration:g} s)")
        if t_off is not None and not t_on < t_off:
            raise k.fail("t_off", t_off, f"a time after t_on = {t_on:g} s (or null: stays on)")
        if t_off is not None and t_off >= duration:
            t_off = None  # switched off at or after the end: never within the run
        force = k.number("force", unit="N")
        if force == 0.0:
            raise k.fail("force", force, "a non-zero force (N)")
        return Scenario(**common, force=force, t_on=t_on, t_off=t_off)

    loop = raw.get("loop", "filtered")
    if loop not in LOOPS:
        raise k.fail("loop", loop, "one of " + " | ".join(LOOPS))
    gravity_raw = raw.get("gravity", False)
    if gravity_raw is True:
        gravity = DEFAULT_GRAVITY
    elif gravity_raw is False or gravity_raw is None:
        gravity = None
    else:
        gravity = k.vector("gravity", gravity_raw)
        if not any(gravity):
            gravity = None
    extra: dict[str, Any] = dict(
        gravity=gravity, preload=k.number("preload", 0.0, unit="N"), loop=loop,
        cutoff_hz=k.optional_number("cutoff_hz", lo=0.0, lo_open=True, unit="Hz"))
    if extra["cutoff_hz"] is not None and loop != "filtered":
        raise k.fail("cutoff_hz", extra["cutoff_hz"], "no cutoff with loop: exact (a cutoff "
                     "re-filters the plant for loop: filtered)")
    if kind == "mass_sweep":
        masses = raw.get("masses")
        if not isinstance(masses, list) or len(masses) < 3:
            raise k.fail("masses", masses, "a list of at least three masses (kg)")
        values = []
        for i, m in enumerate(masses):
            if isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m) \
                    or m < 0:
                raise ConfigError(f"{where}.masses[{i}]: got {_describe(m)}, expected a mass "
                                  ">= 0 (kg)")
            values.append(float(m))
        if len(set(values)) < 3:
            raise k.fail("masses", masses, "at least three different masses (a line through "
                         "two points has no residual)")
        extra["masses"] = tuple(values)
        extra["cycles"] = k.optional_number("cycles", lo=2.0, unit="periods")
        lightest = min(values)
    else:
        extra["mass"] = k.number("mass", lo=0.0, unit="kg")
        lightest = extra["mass"]
    if kind == "spring_mount":
        extra["stiffness"] = k.number("stiffness", lo=0.0, lo_open=True, unit="N m/rad")
        extra["joint_damping"] = k.number("joint_damping", 0.0, lo=0.0, unit="N m s/rad")
        extra["joint"] = None if raw.get("joint") is None else k.vector("joint", raw["joint"])
        extra["initial_angle"] = k.number("initial_angle", 0.0, unit="rad")
        if abs(extra["initial_angle"]) > 0.1:
            raise k.fail("initial_angle", extra["initial_angle"],
                         "a small angle, |angle| <= 0.1 rad (the model is linearised)")
    excited = extra["preload"] != 0.0 or (gravity is not None and lightest > 0.0) \
        or (kind == "spring_mount" and (extra["initial_angle"] != 0.0 or gravity is not None))
    if not excited:
        why = ("with mass 0 in the sweep, gravity does not load the body; " if
               gravity is not None else "")
        raise ConfigError(f"{where}: nothing excites the system: {why}set preload (N) "
                          "or gravity" + (" or initial_angle" if kind == "spring_mount" else ""))
    return Scenario(**common, **extra)


def parse_scenarios(raw: Any, source: str = "scenario") -> list[Scenario]:
    """Validate a parsed scenario document: one mapping (one scenario) or a list of them."""
    if isinstance(raw, Mapping):
        items = [raw]
        wheres = [source]
    elif isinstance(raw, list) and raw:
        items = raw
        wheres = [f"{source}[{i}]" for i in range(len(raw))]
    else:
        raise ConfigError(f"{source}: got {_describe(raw)}, expected a scenario (a mapping "
                          "with a 'kind') or a non-empty list of scenarios")
    out = [_scenario(item, where, i) for i, (item, where) in enumerate(zip(items, wheres))]
    names = [s.name for s in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"{source}: scenario name(s) {', '.join(dup)} used more than once; "
                          "give each scenario its own 'name'")
    return out


def load_scenarios(path: str | Path) -> list[Scenario]:
    """Read and validate a scenario YAML file (one scenario or a list)."""
    from pipeline._util.yamlio import parse_yaml as _parse_yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"scenario file '{path}': not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"scenario file '{path}': cannot be read ({exc})") from None
    raw = _parse_yaml(text, f"scenario file '{path}'")
    if raw is None:
        raise ConfigError(f"scenario file '{path}': is empty, expected a scenario or a list")
    return parse_scenarios(raw, f"scenario file '{path}'")


def _as_scenarios(scenario: Any) -> list[Scenario]:
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
            raise ConfigError(f"scenario name(s) {', '.join(dup)} used in more than one file")
        return out
    return parse_scenarios(list(scenario) if isinstance(scenario, tuple) else scenario)


# =========================================================================== the model file
def ElasticModel(label, A, B, C, D, input_names, output_names, state_names,
                 filter_kind="none", cutoff_hz=None) -> StateSpace:
    """A force-in, motion-out model: the one :class:`StateSpace` type, labelled."""
    return StateSpace(A, B, C, D, input_names, output_names, state_names, label=label,
                      filter_kind=filter_kind, cutoff_hz=cutoff_hz)


# =========================================================================== model algebra
def _rel_close(a: np.ndarray, b: np.ndarray, tol: float = CONSISTENCY_TOL) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = max(float(np.abs(a).max(initial=0.0)), float(np.abs(b).max(initial=0.0)), 1e-300)
    return float(np.abs(a - b).max(initial=0.0)) <= tol * scale


def _derived_rows(em: ElasticModel, port: str, j: int, check: bool) -> dict[str, Any]:
    """Position row of ``port`` and its derivatives through A and B.

    Y = cp x + dp u;  Y' = cp A x + cp b u (+ dp u');  Y'' = cp A^2 x + cp A b u + dp u''
    when cp b = 0 (true for every model of METHODS section 3). With ``check``, the file's
    velocity/acceleration rows must equal these (the exact coupling relies on it).
    """
    ip, iv, ia = em.rows(port)
    A, b = em.A, em.B[:, j]
    cp, dp = em.C[ip], float(em.D[ip, j])
    cv, ca = cp @ A, cp @ A @ A
    dv, da = float(cp @ b), float(cp @ A @ b)
    scale = max(float(np.abs(cv).max()), 1e-300) * max(float(np.abs(b).max()), 1e-300)
    if abs(dv) > CONSISTENCY_TOL * scale:
        raise FileFormatError(f"{em.label} model: the position of port '{port}' responds "
                              f"directly to input rate (C_pos B = {dv:.3g} != 0), so the "
                              "exact mass coupling is not defined; use loop: filtered")
    if check:
        file_ok = (_rel_close(em.C[iv], cv) and _rel_close(em.C[ia], ca)
                   and abs(em.D[iv, j]) <= CONSISTENCY_TOL * max(abs(da), 1e-300)
                   and _rel_close(np.array([em.D[ia, j]]), np.array([da])))
        if not file_ok:
            raise FileFormatError(f"{em.label} model: the velocity/acceleration outputs of port "
                                  f"'{port}' are not the derivatives of its position output "
                                  "through A and B; the file is inconsistent")
    return dict(cp=cp, cv=cv, ca=ca, dp=dp, dv=0.0, da=da)


def undamped(em: ElasticModel, max_hz: float | None = None) -> ElasticModel:
    """The modal model with its damping removed: A[eta_dot_k, eta_dot_k] = 0 for every mode
    with omega_k <= 2 pi ``max_hz`` (all modes when None), and the velocity and
    acceleration rows re-derived from the position rows through the new A (the file's rows
    are first checked to be those derivatives). ConfigError if the model is not modal."""
    idx = em.modal_indices()
    if idx is None:
        raise ConfigError(f"damping: false needs a modal model (states eta_k, eta_dot_k with "
                          f"diagonal blocks); the {em.label} model is not one")
    e, d = idx
    A = em.A.copy()
    omega = np.sqrt(np.maximum(-np.diag(em.A[np.ix_(d, e)]), 0.0))
    keep = d if max_hz is None else d[omega <= 2 * math.pi * max_hz * (1 + 1e-9)]
    A[keep, keep] = 0.0
    C, D = em.C.copy(), em.D.copy()
    for port in em.ports:
        ip, iv, ia = em.rows(port)
        for j in range(len(em.input_names)):
            _derived_rows(em, port, j, check=True)
        C[iv] = em.C[ip] @ A
        C[ia] = em.C[ip] @ A @ A
        D[iv] = em.C[ip] @ em.B
        D[ia] = em.C[ip] @ A @ em.B
    return replace(em, A=A, C=C, D=D)


def _fe_band_hz(mf: "ModelFile") -> float:
    """Highest mode frequency of the FE plant (Hz): the band the FE and lumped models share."""
    idx = mf.plant.modal_indices()
    if idx is None:
        return float(np.max(np.abs(np.linalg.eigvals(mf.plant.A)))) / (2 * math.pi)
    e, d = idx
    return float(np.sqrt(np.max(-np.diag(mf.plant.A[np.ix_(d, e)])))) / (2 * math.pi)


def refilter(plant: ElasticModel, kind: str, cutoff_hz: float) -> ElasticModel:
    """filter * plant with pipeline.reduce.filters' realisation (METHODS section 4), D = 0."""
    from pipeline.reduce.filters import first_order_filter, third_order_position_filter

    K = 2.0 * math.pi * float(cutoff_hz)
    ports = plant.ports
    if kind == "third_order":
        rows = [plant.rows(p)[0] for p in ports]
        Af, Bf, Cf, Df = third_order_position_filter(len(ports), K)
        order = [plant.output_names.index(f"{p}/{q}") for q in
                 ("position", "velocity", "acceleration") for p in ports]
        extra = tuple(f"filter/{p}/{s}" for p in ports for s in ("w", "w_dot", "w_ddot"))
    elif kind == "first_order":
        rows = list(range(len(plant.output_names)))
        Af, Bf, Cf, Df = first_order_filter(len(rows), K)
        order = rows
        extra = tuple(f"filter/{n}" for n in plant.output_names)
    else:
        raise FileFormatError(f"filtered model of kind {kind!r} is not known to the stepper")
    Cp, Dp = plant.C[rows], plant.D[rows]
    n, nf = plant.A.shape[0], Af.shape[0]
    A = np.block([[plant.A, np.zeros((n, nf))], [Bf @ Cp, Af]])
    B = np.vstack([plant.B, Bf @ Dp])
    Cfull = np.hstack([Df @ Cp, Cf])
    C = np.zeros_like(Cfull)
    C[order] = Cfull  # filter outputs are ordered like the plant's
    D = np.zeros((C.shape[0], plant.B.shape[1]))
    return ElasticModel(f"FE filtered ({kind.replace('_', '-')} {cutoff_hz:g} Hz)", A, B, C, D,
                        plant.input_names, plant.output_names, plant.state_names + extra,
                        kind, float(cutoff_hz))


def _filtered_for(mf: ModelFile, sc: Scenario, notes: list[str]) -> ElasticModel:
    """The filtered model a ``loop: filtered`` scenario steps (file's, or re-filtered)."""
    from pipeline.reduce.filters import CUTOFF_MARGIN

    if mf.filtered is None:
        raise FileFormatError(
            f"file '{mf.path}': has no filtered model (/statespace_filtered; the config's "
            f"filter.kind was none), which scenario '{sc.name}' needs for loop: filtered; set "
            "loop: exact in the scenario, or rebuild the file with a filter")
    fk, fc = mf.filtered.filter_kind, mf.filtered.cutoff_hz
    if fc is None or not math.isfinite(fc):
        raise FileFormatError(f"file '{mf.path}': the filtered model has no cutoff_hz")
    rebuilt = refilter(mf.plant, fk, fc)
    same = all(_rel_close(getattr(rebuilt, k), getattr(mf.filtered, k), 1e-9) for k in "ABCD")
    if not same:
        raise FileFormatError(f"file '{mf.path}': /statespace_filtered is not the plant in "
                              f"series with a {fk} filter at {fc:g} Hz as its attributes say")
    cutoff = fc if sc.cutoff_hz is None else sc.cutoff_hz
    plant = mf.plant if sc.damping else undamped(mf.plant)
    model = mf.filtered if (sc.damping and sc.cutoff_hz is None) else refilter(plant, fk, cutoff)
    model = replace(model, label=f"FE filtered ({fk.replace('_', '-')} {cutoff:g} Hz)")
    f_max = float(mf.plant.A.shape[0] and np.max(np.abs(np.linalg.eigvals(mf.plant.A)))) / (
        2 * math.pi)
    if cutoff < CUTOFF_MARGIN * f_max:
        notes.append(f"cutoff {cutoff:g} Hz is below {CUTOFF_MARGIN:g} x the highest mode "
                     f"({f_max:.4g} Hz): the filter distorts the dynamics")
    return model


def _lumped_for(mf: ModelFile, sc: Scenario, inp: str, port: str) -> tuple[ElasticModel | None,
                                                                               str]:
    """The lumped chain with its ports renamed to the FE ports, or (None, why not)."""
    lp = mf.lumped
    if lp is None:
        return None, "the file has no lumped model"
    if not sc.lumped:
        return None, "lumped: false"
    pin, pout = mf.ports.get(inp), mf.ports.get(port)
    if pin is None or pout is None or pin["direction"] is None or pout["direction"] is None:
        return None, "the file does not record the port directions"
    if pin["region"] != "tip" or pout["region"] != "tip":
        return None, (f"the ports are on regions '{pin['region']}'/'{pout['region']}', the "
                      "lumped chain only has the tip")
    if not (np.allclose(pin["direction"], lp["input_direction"], atol=1e-9)
            and np.allclose(pout["direction"], lp["output_direction"], atol=1e-9)):
        return None, "the lumped chain's tip force/displacement directions differ from the ports"
    if len(lp["input_names"]) != 1 or len(lp["output_names"]) != 3:
        return None, "the lumped model is not a single tip force -> tip motion model"
    em = ElasticModel("lumped", lp["A"], lp["B"], lp["C"], lp["D"], (inp,),
                      tuple(f"{port}/{q}" for q in ("position", "velocity", "acceleration")),
                      lp["state_names"])
    if not sc.damping:
        band = _fe_band_hz(mf)
        em = undamped(em, band)
        idx = em.modal_indices()
        if idx is not None:
            e, d = idx
            w = np.sqrt(np.maximum(-np.diag(lp["A"][np.ix_(d, e)]), 0.0)) / (2 * math.pi)
            excited = (np.abs(lp["B"][d, 0]) > 0) & (w > band * (1 + 1e-9))
            if excited.any():
                return em, (f"lumped chain: damping removed from its modes up to {band:.4g} Hz "
                            f"(the FE model's band); its {int(excited.sum())} higher excited "
                            "modes keep their damping (as an integrator's numerical "
                            "dissipation would)")
    return em, ""


# =========================================================================== LTI systems
@dataclass(frozen=True, eq=False)
class LinearSystem:
    """z' = A z + B w, signals = S z + Sw w (w piecewise constant)."""

    A: np.ndarray
    B: np.ndarray
    S: np.ndarray
    Sw: np.ndarray
    signals: tuple[str, ...]
    units: tuple[str, ...]
    inputs: tuple[str, ...]
    modal: tuple[np.ndarray, np.ndarray] | None = None   # (eta, eta_dot) for the energy

    def equilibrium(self, w: np.ndarray) -> np.ndarray:
        return -np.linalg.solve(self.A, self.B @ w)

    def signal(self, name: str) -> int:
        return self.signals.index(name)


def _step_system(em: ElasticModel, inp: str, port: str) -> LinearSystem:
    j = em.col(inp)
    ip, iv, ia = em.rows(port)
    rows = [ip, iv, ia]
    S = np.vstack([em.C[rows], np.zeros((1, em.A.shape[0]))])
    Sw = np.vstack([em.D[rows, j:j + 1], [[1.0]]])
    return LinearSystem(em.A, em.B[:, j:j + 1], S, Sw,
                        (f"{port}/position", f"{port}/velocity", f"{port}/acceleration", inp),
                        ("m", "m/s", "m/s^2", "N"), ("force",), em.modal_indices())


@dataclass(frozen=True)
class Mount:
    """Revolute joint about z: stiffness k (N m/rad), damping c (N m s/rad), the body's
    inertia J about the joint axis (kg m^2), c_theta = (e_z x r_port)·d_out (m, the port's
    displacement along d_out per radian), M_g: gravity moment on the body (N m) per unit
    gravity vector, handled through w."""

    k: float
    c: float
    J: float
    c_theta: float
    arm: np.ndarray
    joint: np.ndarray


def _coupled_system(em: ElasticModel, inp: str, port: str, mass: float, s_io: float,
                    exact: bool, mount: Mount | None) -> tuple[LinearSystem, str]:
    """The elastic model with a rigid mass on ``port`` (and the revolute mount).

    External constant inputs w = [g_out (m/s^2, gravity along d_out), M_g (N m, gravity
    moment on the body about the joint), P (N, preload on the input port)].

    Equations (f: force the mass exerts on the body along d_out; u: the input, along d_in
    = s_io d_out; Y: the port's displacement in the body frame; theta: joint angle):

        u - s_io f = P
        f + m (c_theta theta'' + Y'') = m g_out,   Y'' = ca x + da u + dp u''
        J theta'' + c theta' + k theta = c_theta s_io u + M_g
        x' = A x + b u

    ``exact`` with a position feedthrough dp != 0 (residual flexibility): u becomes a state
    (the residual spring between the modal body and the mass); otherwise u, f and theta''
    are solved from the first three equations (the algebraic loop, solved exactly), or for
    a filtered model (D = 0) they are explicit.
    """
    j = em.col(inp)
    nx = em.A.shape[0]
    A, b = em.A, em.B[:, j]
    if exact:
        r = _derived_rows(em, port, j, check=True)
        cp, cv, ca, dp, dv, da = (r[k] for k in ("cp", "cv", "ca", "dp", "dv", "da"))
    else:
        ip, iv, ia = em.rows(port)
        cp, cv, ca = em.C[ip], em.C[iv], em.C[ia]
        dp, dv, da = float(em.D[ip, j]), float(em.D[iv, j]), float(em.D[ia, j])
        if max(abs(dp), abs(dv), abs(da)) > 0.0:
            raise FileFormatError(f"{em.label}: the filtered model has D != 0 for port "
                                  f"'{port}', so it does not break the loop")
    m = float(mass)
    residual = exact and m > 0.0 and dp != 0.0
    how = ("exact loop, residual flexibility as a spring state" if residual else
           "exact loop (algebraic, solved in closed form)" if exact else
           "filtered model (no algebraic loop)")
    if residual and s_io * dp <= 0.0:
        raise FileFormatError(f"{em.label}: the residual flexibility {dp:.3g} has the sign of "
                              "a negative compliance for these collocated ports")
    names = list(em.state_names)
    it = ithd = iu = iud = -1
    nz = nx
    if mount is not None:
        it, ithd = nz, nz + 1
        nz += 2
        names += ["theta", "theta_dot"]
    if residual:
        iu, iud = nz, nz + 1
        nz += 2
        names += ["u", "u_dot"]
    nq = 3 if mount is not None else 2          # q = [u or u'', f, theta'']
    Eq, Ez, Ew = np.zeros((nq, nq)), np.zeros((nq, nz)), np.zeros((nq, 3))
    # E1: u - s f = P
    Eq[0, 1] = -s_io
    Ew[0, 2] = 1.0
    if residual:
        Ez[0, iu] = -1.0
    else:
        Eq[0, 0] = 1.0
    # E2: f + m (c_theta theta'' + ca x + da u + dp u'') = m g_out
    Eq[1, 1] = 1.0
    Ez[1, :nx] = -m * ca
    Ew[1, 0] = m
    if residual:
        Eq[1, 0] = m * dp
        Ez[1, iu] += -m * da
    else:
        Eq[1, 0] = m * da
    if mount is not None:
        Eq[1, 2] = m * mount.c_theta
        # E3: J theta'' - c_theta s u = -k theta - c theta_dot + M_g
        Eq[2, 2] = mount.J
        Ez[2, it], Ez[2, ithd] = -mount.k, -mount.c
        Ew[2, 1] = 1.0
        if residual:
            Ez[2, iu] += mount.c_theta * s_io
        else:
            Eq[2, 0] = -mount.c_theta * s_io
    if not exact or not residual:
        loop = 1.0 + s_io * m * da
        if loop <= 1e-12:
            raise ConfigError(f"the mass loop on ports '{inp}'/'{port}' is ill-posed "
                              f"(1 + s m D_acc = {loop:.3g} <= 0): the input and output ports "
                              "must be collocated (same point, parallel directions)")
    Qz, Qw = np.linalg.solve(Eq, Ez), np.linalg.solve(Eq, Ew)
    Dz, Dq = np.zeros((nz, nz)), np.zeros((nz, nq))
    Dz[:nx, :nx] = A
    if residual:
        Dz[:nx, iu] = b
        Dz[iu, iud] = 1.0
        Dq[iud, 0] = 1.0
    else:
        Dq[:nx, 0] = b
    if mount is not None:
        Dz[it, ithd] = 1.0
        Dq[ithd, 2] = 1.0
    Abar = Dz + Dq @ Qz
    Bbar = Dq @ Qw

    def row(x=None, z=None, q=None, w=None):
        """(S row, Sw row) of a signal given by its coefficients on the elastic states x,
        other states z, unknowns q and external inputs w."""
        sz, sq, sw = np.zeros(nz), np.zeros(nq), np.zeros(3)
        if x is not None:
            sz[:nx] += x
        for arr, spec in ((sz, z), (sq, q), (sw, w)):
            for k, v in (spec or {}).items():
                arr[k] += v
        return sz + sq @ Qz, sq @ Qw + sw

    u_row = row(z={iu: 1.0}) if residual else row(q={0: 1.0})
    if residual:
        pos = row(x=cp, z={iu: dp})
        vel = row(x=cv, z={iu: dv, iud: dp})
        acc = row(x=ca, z={iu: da}, q={0: dp})
    else:
        pos = row(x=cp, q={0: dp})
        vel = row(x=cv, q={0: dv})
        acc = row(x=ca, q={0: da})
    f_row = row(q={1: 1.0})
    sigs = [(f"{port}/position", "m", pos), (f"{port}/velocity", "m/s", vel),
            (f"{port}/acceleration", "m/s^2", acc), (inp, "N", u_row),
            ("mass_force", "N", f_row)]
    if mount is not None:
        th, thd = row(z={it: 1.0}), row(z={ithd: 1.0})
        tip = (th[0] * mount.c_theta + pos[0], th[1] * mount.c_theta + pos[1])
        sigs += [("theta", "rad", th), ("theta_dot", "rad/s", thd),
                 ("mass_displacement", "m", tip)]
    else:
        sigs += [("mass_displacement", "m", pos)]
    S = np.vstack([s[2][0] for s in sigs])
    Sw = np.vstack([s[2][1] for s in sigs])
    modal = em.modal_indices() if em.filter_kind == "none" else None
    return LinearSystem(Abar, Bbar, S, Sw, tuple(s[0] for s in sigs), tuple(s[1] for s in sigs),
                        ("g_out", "M_g", "preload"), modal), how


# =========================================================================== integration
@dataclass(frozen=True)
class _Segment:
    t0: float
    t1: float
    w: np.ndarray


def _propagate_exact(sys: LinearSystem, z0: np.ndarray, segments: Sequence[_Segment],
                     t: np.ndarray) -> np.ndarray:
    """States at the grid ``t`` by the matrix exponential (exact for piecewise-constant w)."""
    import scipy.linalg as sla

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


def _integrate(sys: LinearSystem, z0: np.ndarray, segments: Sequence[_Segment],
               t: np.ndarray, integ: Integrator) -> tuple[np.ndarray, dict[str, Any]]:
    """solve_ivp over each constant-w segment (restarted at every switch).

    atol_i = integ.atol x peak|z_i| (peaks from the exact pass, floored at 1e-12 of the
    largest); the constant Jacobian A is passed to the implicit methods. Returns the
    states at ``t`` and statistics, including the largest deviation of every signal from
    the exact matrix-exponential solution (relative to the signal's peak)."""
    from scipy.integrate import solve_ivp

    Zx = _propagate_exact(sys, z0, segments, t)
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
        if np.all(te == seg.t0) and te.size <= 1 and seg.t1 == seg.t0:
            sol_y = z[:, None]
        else:
            sol = solve_ivp(lambda _t, y: A @ y + bw, (seg.t0, seg.t1), z,
                            method=integ.method, t_eval=evals, rtol=integ.rtol, atol=atol,
                            **kw)
            if not sol.success:
                from pipeline.errors import SolverError

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


# =========================================================================== measurement
def _crossings(t: np.ndarray, s: np.ndarray) -> np.ndarray:
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


def _extremes(t: np.ndarray, y: np.ndarray, level: float) -> np.ndarray:
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
        e = _extremes(t, y, level)
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
    e = np.abs(_extremes(t, y, level) - level)
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
    tc = _crossings(t, y - level)
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
        return float(f[k]), float(X[k] / top)
    a, b, c = np.log(np.maximum(X[k - 1:k + 2], 1e-300))
    den = a - 2 * b + c
    p = 0.5 * (a - c) / den if den != 0 else 0.0
    return float(f[k] + p * (f[1] - f[0])), float(X[k] / top)


def _modes_in(sys: LinearSystem, dz: np.ndarray, signal_rows: Sequence[int]
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


# =========================================================================== results
@dataclass
class Run:
    """One time integration: a model (FE or lumped) in one scenario (one mass)."""

    model: str
    key: str
    t: np.ndarray
    signals: dict[str, np.ndarray]
    units: dict[str, str]
    measured: dict[str, float]
    predicted: dict[str, float]
    info: dict[str, Any] = field(default_factory=dict)
    mass: float | None = None


@dataclass(frozen=True)
class Row:
    """One line of the summary: a measured value beside its analytic prediction."""

    scenario: str
    model: str
    quantity: str
    measured: float
    predicted: float
    units: str
    note: str = ""

    @property
    def rel_error(self) -> float:
        if not (math.isfinite(self.measured) and math.isfinite(self.predicted)) \
                or self.predicted == 0:
            return math.nan
        return self.measured / self.predicted - 1.0


@dataclass
class ScenarioResult:
    scenario: Scenario
    runs: list[Run]
    rows: list[Row]
    notes: list[str] = field(default_factory=list)
    fits: dict[str, dict[str, Any]] = field(default_factory=dict)

    def run(self, key: str = "fe", mass: float | None = None) -> Run:
        for r in self.runs:
            if r.key == key and (mass is None or (r.mass is not None
                                                  and math.isclose(r.mass, mass))):
                return r
        raise KeyError(f"no run {key!r}" + ("" if mass is None else f" with mass {mass:g}"))

    def row(self, quantity: str, model_key: str = "fe") -> Row:
        prefix = "lumped" if model_key == "lumped" else "FE"
        for r in self.rows:
            if r.quantity == quantity and r.model.startswith(prefix):
                return r
        raise KeyError(f"no row {quantity!r} for {model_key}")


@dataclass
class SimulationResults:
    model_path: Path
    scenarios: list[ScenarioResult]
    output: Path | None = None
    files: list[Path] = field(default_factory=list)
    wall_s: float = 0.0

    def __getitem__(self, name: str) -> ScenarioResult:
        for s in self.scenarios:
            if s.scenario.name == name:
                return s
        raise KeyError(name)

    @property
    def rows(self) -> list[Row]:
        return [r for s in self.scenarios for r in s.rows]

    def table(self) -> str:
        """The printed summary: measured beside predicted, one line per quantity."""
        head = (f"{'scenario':<14}{'model':<36}{'quantity':<38}{'measured':>14}"
                f"{'predicted':>14}{'error':>10}  units")
        lines = [head, "-" * len(head)]
        for r in self.rows:
            err = f"{r.rel_error:+.2e}" if math.isfinite(r.rel_error) else "-"
            fmt = lambda v: f"{v:.6g}" if math.isfinite(v) else "-"  # noqa: E731
            lines.append(f"{r.scenario:<14.14}{r.model:<36.36}{r.quantity:<38.38}"
                         f"{fmt(r.measured):>14}{fmt(r.predicted):>14}{err:>10}  {r.units}"
                         + (f"  ({r.note})" if r.note else ""))
        for s in self.scenarios:
            for n in s.notes:
                lines.append(f"note [{s.scenario.name}]: {n}")
        return "\n".join(lines)


# =========================================================================== scenarios -> runs
def _ports(mf: ModelFile, sc: Scenario) -> tuple[str, str]:
    def pick(name: str | None, names: Sequence[str], what: str, key: str) -> str:
        if name is None:
            if len(names) == 1:
                return names[0]
            raise ConfigError(f"scenario '{sc.name}'.{key} is missing: the model has "
                              f"{len(names)} {what} ports ({', '.join(names)}); name one")
        if name not in names:
            raise ConfigError(f"scenario '{sc.name}'.{key}: {what} port '{name}' is not in "
                              f"'{mf.path}'; it has: {', '.join(names)}")
        return name

    return (pick(sc.input, list(mf.plant.input_names), "input", "input"),
            pick(sc.output, list(mf.plant.ports), "output", "output"))


def _directions(mf: ModelFile, sc: Scenario, inp: str, port: str) -> tuple[np.ndarray,
                                                                          np.ndarray, float]:
    pin, pout = mf.ports.get(inp), mf.ports.get(port)
    if pin is None or pout is None or pin["direction"] is None or pout["direction"] is None:
        raise FileFormatError(f"file '{mf.path}': does not record the directions of ports "
                              f"'{inp}'/'{port}' (root attribute config_yaml), which scenario "
                              f"'{sc.name}' needs to couple a mass")
    if pin.get("kind") not in (None, "force") or pout.get("kind") not in (None, "displacement"):
        raise ConfigError(f"scenario '{sc.name}': a mass needs a force input and a "
                          f"displacement output; '{inp}' is a {pin.get('kind')} port and "
                          f"'{port}' a {pout.get('kind')} port")
    d_in, d_out = pin["direction"], pout["direction"]
    s_io = float(d_in @ d_out)
    if abs(abs(s_io) - 1.0) > 1e-9:
        raise ConfigError(f"scenario '{sc.name}': input '{inp}' (direction {d_in.tolist()}) is "
                          f"not parallel to output '{port}' ({d_out.tolist()}); a welded mass "
                          "needs the force along the measured displacement")
    if pin["region"] != pout["region"]:
        raise ConfigError(f"scenario '{sc.name}': input '{inp}' acts on region "
                          f"'{pin['region']}' but output '{port}' is on '{pout['region']}'; "
                          "the mass needs collocated ports")
    return d_in, d_out, math.copysign(1.0, s_io)


def _grid(sc: Scenario, duration: float | None = None) -> np.ndarray:
    duration = sc.duration if duration is None else duration
    n = int(math.floor(duration * sc.output_rate + 1e-9)) + 1
    return np.arange(n) / sc.output_rate


def _make_run(model: str, key: str, sys: LinearSystem, Z: np.ndarray, t: np.ndarray,
              w_of_t: np.ndarray, stats: dict, mass: float | None = None) -> Run:
    Y = sys.S @ Z + sys.Sw @ w_of_t
    signals = {n: Y[i] for i, n in enumerate(sys.signals)}
    units = dict(zip(sys.signals, sys.units))
    if sys.modal is not None:
        e, d = sys.modal
        om2 = -np.diag(sys.A[np.ix_(d, e)])
        signals["elastic_energy"] = 0.5 * (Z[d] ** 2).sum(axis=0) + 0.5 * (
            om2[:, None] * Z[e] ** 2).sum(axis=0)
        units["elastic_energy"] = "J"
    return Run(model, key, t, signals, units, {}, {}, dict(stats), mass)


def _w_series(segments: Sequence[_Segment], t: np.ndarray) -> np.ndarray:
    W = np.zeros((segments[0].w.size, t.size))
    for seg in segments:
        last = seg is segments[-1]
        mask = (t >= seg.t0) & ((t < seg.t1) | (last & (t <= seg.t1 + 1e-12)))
        W[:, mask] = seg.w[:, None]
    return W


def _run_step(mf: ModelFile, sc: Scenario, em: ElasticModel, key: str, inp: str, port: str
              ) -> tuple[Run, list[Row]]:
    sys = _step_system(em, inp, port)
    t = _grid(sc)
    F = np.array([sc.force])
    t_off = sc.duration if sc.t_off is None else sc.t_off
    segs = [s for s in (_Segment(0.0, sc.t_on, np.zeros(1)), _Segment(sc.t_on, t_off, F),
                        _Segment(t_off, sc.duration, np.zeros(1))) if s.t1 > s.t0]
    if segs[-1].t1 < sc.duration:
        segs.append(_Segment(segs[-1].t1, sc.duration, np.zeros(1)))
    Z, stats = _integrate(sys, np.zeros(sys.A.shape[0]), segs, t, sc.integrator)
    run = _make_run(em.label, key, sys, Z, t, _w_series(segs, t), stats)
    y = run.signals[f"{port}/position"]
    j = em.col(inp)
    ip = em.rows(port)[0]
    dc = float(em.D[ip, j] - em.C[ip] @ np.linalg.solve(em.A, em.B[:, j]))
    z_eq = sys.equilibrium(F)
    modes = _modes_in(sys, z_eq, [0])
    f_pred, zeta = (modes[0][0], modes[0][1]) if modes else (math.nan, math.nan)
    on = (t >= sc.t_on) & (t < t_off)
    free = t >= t_off
    period = 1.0 / f_pred if math.isfinite(f_pred) and f_pred > 0 else math.inf
    use_free = sc.t_off is not None and (sc.duration - t_off) >= 3 * period
    seg_t, seg_y = (t[free], y[free]) if use_free else (t[on], y[on])
    ss = steady_state(t[on], y[on])
    level = steady_state(seg_t, seg_y)
    f_zc = zero_crossing_frequency(seg_t, seg_y, level)
    f_fft, _ = fft_peak_frequency(seg_t, seg_y, level=level)
    zeta_m = decay_damping_ratio(seg_t, seg_y, level)
    run.measured.update(frequency_zc=f_zc, frequency_fft=f_fft, steady_state=ss,
                        damping_ratio=zeta_m)
    run.predicted.update(frequency=f_pred, damping_ratio=zeta, dc_gain=dc,
                         steady_state=dc * sc.force)
    run.info["frequency_window"] = "after t_off (free decay)" if use_free else "load on"
    if "elastic_energy" in run.signals and sc.t_off is not None:
        E = run.signals["elastic_energy"][free]
        if E.size and E[0] > 0:
            run.measured["energy_drift_after_off"] = float(np.abs(E / E[0] - 1.0).max())
    lab = em.label
    win = "free decay" if use_free else "load on"
    rows = [Row(sc.name, lab, f"frequency, zero crossings ({win})", f_zc, f_pred, "Hz",
                "damped mode"),
            Row(sc.name, lab, f"frequency, FFT peak ({win})", f_fft, f_pred, "Hz"),
            Row(sc.name, lab, f"damping ratio, log decrement ({win})", zeta_m, zeta, "1"),
            Row(sc.name, lab, "steady deflection (load on)", ss, dc * sc.force, "m",
                "DC gain x load")]
    return run, rows


def _mount_for(mf: ModelFile, sc: Scenario, key: str, port: str, d_out: np.ndarray,
               gravity: np.ndarray) -> tuple[Mount, float]:
    """The revolute mount (and the gravity moment per unit g along gravity) of a model."""
    if sc.joint is not None:
        P = np.asarray(sc.joint, float)
    else:
        pts = [mf.region_centroids[r] for r in mf.support_regions if r in mf.region_centroids]
        if not pts:
            raise FileFormatError(f"file '{mf.path}': no support region to put the joint on; "
                                  f"give scenario '{sc.name}'.joint [x, y, z]")
        P = np.mean(pts, axis=0)
    ez = np.array([0.0, 0.0, 1.0])
    if key == "lumped":
        lp = mf.lumped or {}
        need = ("element_mass", "element_com", "element_inertia", "element_extent",
                "joint_positions")
        if any(k not in lp for k in need):
            raise FileFormatError(f"file '{mf.path}': the lumped model lacks its element data")
        masses, coms, inertias = lp["element_mass"], lp["element_com"], lp["element_inertia"]
        tip = np.array([lp["element_extent"][-1, 1], *lp["joint_positions"][0, 1:]])
        rel = coms - P
        J = float(inertias[:, 2, 2].sum() + (masses * (rel[:, 0] ** 2 + rel[:, 1] ** 2)).sum())
        Mg = float(sum(np.cross(r, m * gravity)[2] for r, m in zip(rel, masses)))
    else:
        region = mf.ports.get(port, {}).get("region")
        if region not in mf.region_centroids:
            raise FileFormatError(f"file '{mf.path}': the region of port '{port}' is not stored")
        tip = mf.region_centroids[region]
        if not (math.isfinite(mf.body_mass) and np.all(np.isfinite(mf.body_inertia))):
            raise FileFormatError(f"file '{mf.path}': lacks body/mass, body/center_of_mass or "
                                  "body/inertia, which the spring mount needs")
        rel = mf.body_com - P
        J = float(mf.body_inertia[2, 2] + mf.body_mass * (rel[0] ** 2 + rel[1] ** 2))
        Mg = float(np.cross(rel, mf.body_mass * gravity)[2])
    arm = tip - P
    c_theta = float(np.cross(ez, arm) @ d_out)
    if abs(d_out[2]) > 1e-9 or abs(abs(c_theta) - np.linalg.norm(arm[:2])) > 1e-6 * max(
            np.linalg.norm(arm[:2]), 1e-12):
        raise ConfigError(f"scenario '{sc.name}': the spring mount rotates about z, so port "
                          f"'{port}' must measure along the circle about the joint (direction "
                          f"perpendicular to the arm {arm.round(6).tolist()} m in the x-y "
                          f"plane); it measures along {d_out.tolist()}")
    return Mount(sc.stiffness, sc.joint_damping, J, c_theta, arm, P), Mg


def _run_coupled(mf: ModelFile, sc: Scenario, em: ElasticModel, key: str, inp: str,
                 port: str, mass: float, exact: bool, notes: list[str]
                 ) -> tuple[Run, LinearSystem, np.ndarray]:
    d_in, d_out, s_io = _directions(mf, sc, inp, port)
    g = np.zeros(3) if sc.gravity is None else np.asarray(sc.gravity, float)
    mount, Mg = (None, 0.0)
    if sc.kind == "spring_mount":
        mount, Mg = _mount_for(mf, sc, key, port, d_out, g)
    sys, how = _coupled_system(em, inp, port, mass, s_io, exact, mount)
    w_pre = np.array([0.0, 0.0, sc.preload])
    w_run = np.array([float(g @ d_out), Mg, 0.0])
    z0 = sys.equilibrium(w_pre) if sc.preload else np.zeros(sys.A.shape[0])
    if mount is not None and sc.initial_angle:
        z0[_theta_index(sys)] += sc.initial_angle
    z_eq = sys.equilibrium(w_run)
    duration = sc.duration
    if sc.cycles is not None:
        modes = _modes_in(sys, z0 - z_eq, [sys.signal("mass_displacement")])
        if modes and modes[0][0] > 0:
            duration = min(duration, sc.cycles / modes[0][0])
    t = _grid(sc, duration)
    segs = [_Segment(0.0, float(t[-1]), w_run)]
    Z, stats = _integrate(sys, z0, segs, t, sc.integrator)
    stats["coupling"] = how
    run = _make_run(em.label, key, sys, Z, t, _w_series(segs, t), stats, mass)
    run.info["z_eq"] = z_eq
    run.info["z0"] = z0
    run.info["w_run"] = w_run
    return run, sys, z_eq


def _theta_index(sys: LinearSystem) -> int:
    r = sys.S[sys.signal("theta")]
    return int(np.flatnonzero(r)[0])


def _measure_coupled(sc: Scenario, run: Run, sys: LinearSystem, z_eq: np.ndarray,
                     port: str) -> list[Row]:
    t = run.t
    y = run.signals["mass_displacement"]
    rows: list[Row] = []
    lab = run.model + (f", m = {run.mass:g} kg" if sc.kind == "mass_sweep" else "")
    dz = run.info["z0"] - z_eq
    sig_rows = [sys.signal("mass_displacement")]
    if "theta" in sys.signals:
        sig_rows.append(sys.signal("theta"))
    modes = _modes_in(sys, dz, sig_rows)
    # steady state of the signals (the w part of S is the same constant for all t > 0)
    Wc = run.info["w_run"]
    ss_pred = float(sys.S[sys.signal("mass_displacement")] @ z_eq
                    + sys.Sw[sys.signal("mass_displacement")] @ Wc)
    level = steady_state(t, y)
    if sc.kind == "spring_mount":
        two = sorted(modes[:2], key=lambda m: m[0])
        f1p = two[0][0] if two else math.nan
        f2p = two[1][0] if len(two) > 1 else math.nan
        f1_zc = zero_crossing_frequency(t, y, level)
        f1_fft, _ = fft_peak_frequency(t, y, level=level)
        th = run.signals["theta"]
        th_level = steady_state(t, th)
        f2_fft, h2 = (fft_peak_frequency(t, th, 0.75 * f2p, 1.25 * f2p, level=th_level)
                      if math.isfinite(f2p) else (math.nan, math.nan))
        th_pred = float(sys.S[sys.signal("theta")] @ z_eq + sys.Sw[sys.signal("theta")] @ Wc)
        zeta1 = decay_damping_ratio(t, y, level)
        run.measured.update(mode1_zc=f1_zc, mode1_fft=f1_fft, mode2_fft=f2_fft, mode1_damping=zeta1,
                            mode2_peak_height=h2, steady_state=level, theta_steady=th_level)
        run.predicted.update(mode1=f1p, mode2=f2p, steady_state=ss_pred, theta_steady=th_pred,
                             mode1_damping=two[0][1] if two else math.nan,
                             mode2_damping=two[1][1] if len(two) > 1 else math.nan)
        rows += [Row(sc.name, lab, "mode 1 frequency, zero crossings", f1_zc, f1p, "Hz",
                     "coupled eigenvalue"),
                 Row(sc.name, lab, "mode 1 frequency, FFT peak", f1_fft, f1p, "Hz"),
                 Row(sc.name, lab, "mode 1 damping ratio, log decrement", zeta1,
                     two[0][1] if two else math.nan, "1"),
                 Row(sc.name, lab, "mode 2 frequency, FFT of theta", f2_fft, f2p, "Hz",
                     f"peak {h2:.2g} of the largest" if math.isfinite(h2) else ""),
                 Row(sc.name, lab, "steady mass displacement", level, ss_pred, "m",
                     "static equilibrium"),
                 Row(sc.name, lab, "steady joint angle", th_level, th_pred, "rad")]
        return rows
    fp = modes[0][0] if modes else math.nan
    zeta = modes[0][1] if modes else math.nan
    f_zc = zero_crossing_frequency(t, y, level)
    f_fft, _ = fft_peak_frequency(t, y, level=level)
    zeta_m = decay_damping_ratio(t, y, level)
    run.measured.update(frequency_zc=f_zc, frequency_fft=f_fft, steady_state=level,
                        damping_ratio=zeta_m)
    run.predicted.update(frequency=fp, damping_ratio=zeta, steady_state=ss_pred)
    rows += [Row(sc.name, lab, "frequency, zero crossings", f_zc, fp, "Hz", "coupled eigenvalue"),
             Row(sc.name, lab, "frequency, FFT peak", f_fft, fp, "Hz")]
    if sc.kind == "body_load":
        rows += [Row(sc.name, lab, "damping ratio, log decrement", zeta_m, zeta, "1"),
                 Row(sc.name, lab, "steady mass displacement", level, ss_pred, "m",
                     "static equilibrium")]
    return rows


def _exact_reference(mf: ModelFile, sc: Scenario, inp: str, port: str, mass: float
                     ) -> float:
    """Dominant coupled frequency of the plant with the loop solved exactly (the value a
    filtered model tends to as its cutoff grows)."""
    plant = mf.plant if sc.damping else undamped(mf.plant)
    _, d_out, s_io = _directions(mf, sc, inp, port)
    g = np.zeros(3) if sc.gravity is None else np.asarray(sc.gravity, float)
    mount, Mg = (None, 0.0)
    if sc.kind == "spring_mount":
        mount, Mg = _mount_for(mf, sc, "fe", port, d_out, g)
    sys, _ = _coupled_system(plant, inp, port, mass, s_io, True, mount)
    w_run = np.array([float(g @ d_out), Mg, 0.0])
    z0 = sys.equilibrium(np.array([0.0, 0.0, sc.preload])) if sc.preload else np.zeros(
        sys.A.shape[0])
    if mount is not None and sc.initial_angle:
        z0[_theta_index(sys)] += sc.initial_angle
    rows = [sys.signal("mass_displacement")]
    modes = _modes_in(sys, z0 - sys.equilibrium(w_run), rows)
    return (modes[0][0], modes[0][1]) if modes else (math.nan, math.nan)


def _fit_sweep(masses: np.ndarray, freqs: np.ndarray) -> dict[str, float]:
    """T^2 = a + b m fitted with relative residuals (weights 1/T^4: a period measurement's
    error is relative). Also the ordinary least-squares intercept, for comparison."""
    T2 = 1.0 / freqs**2
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


def _check_against_model(mf: ModelFile, sc: Scenario) -> None:
    """Ports, directions, filtered model and mount geometry of ``sc`` against the file
    (the same checks the run makes, done up front)."""
    inp, port = _ports(mf, sc)
    if sc.kind == "step_load":
        return
    _, d_out, _ = _directions(mf, sc, inp, port)
    if sc.loop == "filtered":
        _filtered_for(mf, sc, [])
    if sc.kind == "spring_mount":
        g = np.zeros(3) if sc.gravity is None else np.asarray(sc.gravity, float)
        _mount_for(mf, sc, "fe", port, d_out, g)


def _run_scenario(mf: ModelFile, sc: Scenario) -> ScenarioResult:
    inp, port = _ports(mf, sc)
    notes: list[str] = []
    models: list[tuple[str, ElasticModel, bool]] = []   # key, model, exact loop
    if sc.kind == "step_load":
        plant = mf.plant if sc.damping else undamped(mf.plant)
        models.append(("fe", plant, True))
    else:
        if sc.loop == "filtered":
            models.append(("fe", _filtered_for(mf, sc, notes), False))
        else:
            models.append(("fe", mf.plant if sc.damping else undamped(mf.plant), True))
    lumped, why = _lumped_for(mf, sc, inp, port)
    if lumped is not None:
        models.append(("lumped", lumped, True))
        if why:
            notes.append(why)
        if mf.in_plane:
            notes.append("the FE model is in-plane (u_z = 0, stiffer by about 1/sqrt(1 - nu^2) "
                         "in frequency); the lumped chain is plain beam theory without that "
                         "constraint, so it is expected to be softer")
        if sc.kind != "step_load":
            notes.append("lumped chain: loop solved exactly (the file has no filtered lumped "
                         "model)")
    elif why and sc.lumped:
        notes.append(f"no lumped run: {why}")
    result = ScenarioResult(sc, [], [], notes)
    for key, em, exact in models:
        if sc.kind == "step_load":
            run, rows = _run_step(mf, sc, em, key, inp, port)
            result.runs.append(run)
            result.rows.extend(rows)
            continue
        masses = sc.masses if sc.kind == "mass_sweep" else (sc.mass,)
        f_meas = []
        f_pred = []
        for m in masses:
            run, sys, z_eq = _run_coupled(mf, sc, em, key, inp, port, m, exact, notes)
            rows = _measure_coupled(sc, run, sys, z_eq, port)
            if not exact and key == "fe" and sc.kind != "mass_sweep":
                f_ex, z_ex = _exact_reference(mf, sc, inp, port, m)
                run.predicted["frequency_exact_loop"] = f_ex
                run.predicted["damping_ratio_exact_loop"] = z_ex
                meas = run.measured.get("frequency_zc", run.measured.get("mode1_zc"))
                rows.insert(1, Row(sc.name, rows[0].model, rows[0].quantity.replace(
                    "zero crossings", "z.c. vs exact-loop plant"), meas, f_ex, "Hz",
                    "cutoff-free reference"))
                zm = run.measured.get("damping_ratio", run.measured.get("mode1_damping"))
                rows.append(Row(sc.name, rows[0].model, "damping ratio vs exact-loop plant", zm,
                                z_ex, "1", "the filter lag adds ~1.5 omega/K"))
            result.runs.append(run)
            if sc.kind == "mass_sweep":
                f_meas.append(run.measured["frequency_zc"])
                f_pred.append(run.predicted["frequency"])
                result.rows.append(rows[0])
            else:
                result.rows.extend(rows)
        if sc.kind == "mass_sweep":
            fit = _fit_sweep(np.asarray(masses), np.asarray(f_meas))
            fit_pred = _fit_sweep(np.asarray(masses), np.asarray(f_pred))
            m0 = int(np.argmin(masses))
            f_first = f_pred[m0] if masses[m0] == 0 else math.nan
            fit.update(masses=np.asarray(masses), measured_hz=np.asarray(f_meas),
                       predicted_hz=np.asarray(f_pred), first_mode_hz=f_first,
                       fit_of_predicted=fit_pred)
            result.fits[key] = fit
            lab = em.label
            result.rows += [
                Row(sc.name, lab, "T^2 vs mass: R^2", fit["r2"], 1.0, "1", "linear fit"),
                Row(sc.name, lab, "unloaded frequency from the fit", fit["f0_hz"], f_first,
                    "Hz", "vs first mode (m = 0 eigenvalue)"),
                Row(sc.name, lab, "effective tip mass a/b", fit["effective_mass_kg"],
                    fit_pred["effective_mass_kg"], "kg", "predicted: same fit of eigenvalues")]
            if masses[m0] != 0:
                notes.append("the sweep has no zero mass: the first mode is not simulated, "
                             "compare the recovered frequency with the file's modes")
    return result


# =========================================================================== outputs
def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", name)


def _results_tree(res: SimulationResults, scenarios_yaml: str):
    from pipeline.store.tree import Dataset

    tree: dict[str, Dataset] = {}
    attrs: dict[str, dict[str, Any]] = {}
    for s in res.scenarios:
        sname = _slug(s.scenario.name)
        attrs[sname] = {"kind": s.scenario.kind, "notes": list(s.notes) or ["none"]}
        for i, run in enumerate(s.runs):
            grp = f"{sname}/{run.key}" + ("" if run.mass is None or s.scenario.kind != "mass_sweep"
                                          else f"/run_{i:02d}")
            tree[f"{grp}/time"] = Dataset(run.t, "s", "sample times")
            for name, values in run.signals.items():
                tree[f"{grp}/signals/{name}"] = Dataset(values, run.units[name],
                                                        f"{name} of the {run.model} model")
            a: dict[str, Any] = {"model": run.model}
            if run.mass is not None:
                a["mass_kg"] = float(run.mass)
            for k, v in run.measured.items():
                a[f"measured_{k}"] = float(v)
            for k, v in run.predicted.items():
                a[f"predicted_{k}"] = float(v)
            for k, v in run.info.items():
                if isinstance(v, (int, float, str)):
                    a[f"integrator_{k}" if k in ("nfev", "njev", "nlu", "wall_s", "method",
                                                 "rtol", "atol") else k] = v
                elif k == "deviation_from_exact":
                    for sig, dev in v.items():
                        a[f"deviation_from_exact/{sig}"] = float(dev)
            attrs[grp] = a
        for key, fit in s.fits.items():
            g = f"{sname}/{key}/fit"
            tree[f"{g}/masses"] = Dataset(fit["masses"], "kg", "tip masses of the sweep")
            tree[f"{g}/measured_frequency"] = Dataset(fit["measured_hz"], "Hz",
                                                      "zero-crossing frequency per mass")
            tree[f"{g}/predicted_frequency"] = Dataset(fit["predicted_hz"], "Hz",
                                                       "coupled eigenvalue per mass")
            tree[f"{g}/period_squared"] = Dataset(1.0 / fit["measured_hz"] ** 2, "s^2",
                                                  "measured T^2 per mass")
            attrs[g] = {k: float(v) for k, v in fit.items()
                        if isinstance(v, (int, float)) and not isinstance(v, bool)}
    rows = res.rows
    tree["summary/scenario"] = Dataset([r.scenario for r in rows], "1", "scenario name")
    tree["summary/model"] = Dataset([r.model for r in rows], "1", "model")
    tree["summary/quantity"] = Dataset([r.quantity for r in rows], "1", "what is compared")
    tree["summary/units"] = Dataset([r.units for r in rows], "1", "unit of measured/predicted")
    tree["summary/measured"] = Dataset(np.array([r.measured for r in rows]), "mixed",
                                       "value measured from the response (units: summary/units)")
    tree["summary/predicted"] = Dataset(np.array([r.predicted for r in rows]), "mixed",
                                        "analytic prediction from the matrices")
    return tree, attrs


def _write_csv(path: Path, s: ScenarioResult) -> Path:
    """Time series of every run as columns ``<model>[ m=<kg>]:<signal> [unit]`` (runs of
    a sweep may be shorter than the longest; their cells past the end are empty)."""
    cols: list[tuple[str, np.ndarray]] = []
    t = max((r.t for r in s.runs), key=len)
    for run in s.runs:
        tag = run.key + ("" if run.mass is None or s.scenario.kind != "mass_sweep"
                         else f" m={run.mass:g}kg")
        for name, values in run.signals.items():
            cols.append((f"{tag}:{name} [{run.units[name]}]", values))
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time [s]"] + [c[0] for c in cols])
        for i, ti in enumerate(t):
            w.writerow([f"{ti:.10g}"] + [f"{c[1][i]:.10g}" if i < c[1].size else ""
                                         for c in cols])
    return path


def _plot(path: Path, s: ScenarioResult, port: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sc = s.scenario
    style = {"fe": dict(color="C0", lw=1.4), "lumped": dict(color="C3", lw=1.0, ls="--")}
    if sc.kind == "mass_sweep":
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
        for key, fit in s.fits.items():
            st = style[key]
            m = fit["masses"]
            mm = np.linspace(0, m.max(), 100)
            ax1.plot(m, 1e3 / fit["measured_hz"] ** 2, "o" if key == "fe" else "s",
                     color=st["color"], mfc="none", label=f"{key}: measured")
            ax1.plot(mm, 1e3 * (fit["a_s2"] + fit["b_s2_per_kg"] * mm), color=st["color"],
                     ls=st.get("ls", "-"), lw=1,
                     label=f"{key}: fit, R$^2$={fit['r2']:.6f}, f0={fit['f0_hz']:.2f} Hz")
            ax2.plot(m, fit["measured_hz"], "o" if key == "fe" else "s", color=st["color"],
                     mfc="none", label=f"{key}: measured")
            ax2.plot(m, fit["predicted_hz"], "x", color=st["color"], label=f"{key}: eigenvalue")
        ax1.set_xlabel("tip mass [kg]")
        ax1.set_ylabel("T$^2$ [ms$^2$]")
        ax1.set_title("squared period vs load mass")
        ax2.set_xlabel("tip mass [kg]")
        ax2.set_ylabel("frequency [Hz]")
        ax2.set_yscale("log")
        from matplotlib.ticker import ScalarFormatter

        ax2.yaxis.set_major_formatter(ScalarFormatter())
        ax2.yaxis.set_minor_formatter(ScalarFormatter())
        ax2.set_title("first coupled mode")
        for ax in (ax1, ax2):
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    else:
        n = 3 if sc.kind == "spring_mount" else 2
        fig, axes = plt.subplots(n, 1, figsize=(10, 2.8 * n + 0.6), sharex=sc.kind != "spring_mount")
        sig = f"{port}/position" if sc.kind == "step_load" else "mass_displacement"
        force = sc.input if sc.input else None
        for run in s.runs:
            st = style.get(run.key, {})
            axes[0].plot(run.t, 1e3 * run.signals[sig], label=run.model, **st)
            if sc.kind == "spring_mount":
                axes[1].plot(run.t, 1e3 * run.signals["theta"], label=run.model, **st)
            else:
                name = [k for k in run.signals if run.units[k] == "N" and k != "mass_force"][0]
                force = name
                axes[1].plot(run.t, run.signals[name], label=run.model, **st)
            ss = run.predicted.get("steady_state")
            if ss is not None and math.isfinite(ss):
                axes[0].axhline(1e3 * ss, color=st.get("color", "k"), ls=":", lw=0.8)
        axes[0].set_ylabel(("tip" if sc.kind == "step_load" else "mass") + " displacement [mm]")
        if sc.kind == "step_load":
            axes[0].axvspan(sc.t_on, sc.duration if sc.t_off is None else sc.t_off,
                            color="0.9", zorder=0, label="load on")
        axes[0].legend(fontsize=8, loc="best")
        if sc.kind == "spring_mount":
            axes[1].set_ylabel("joint angle [mrad]")
            axes[1].set_xlabel("time [s]")
            for run in s.runs:
                st = style.get(run.key, {})
                th = run.signals["theta"]
                n_ = th.size
                nfft = 1 << int(math.ceil(math.log2(8 * n_)))
                X = np.abs(np.fft.rfft((th - th.mean()) * np.hanning(n_), nfft))
                f = np.fft.rfftfreq(nfft, run.t[1] - run.t[0])
                axes[2].semilogy(f, X / X.max(), label=f"{run.model}: |FFT(theta)|", **st)
                for k in ("mode1", "mode2"):
                    v = run.predicted.get(k)
                    if v is not None and math.isfinite(v):
                        axes[2].axvline(v, color=st.get("color", "k"), ls=":", lw=0.8)
            f2 = max((r.predicted.get("mode2", 0) for r in s.runs), default=0)
            axes[2].set_xlim(0, 2.0 * f2 if f2 and math.isfinite(f2) else None)
            axes[2].set_ylim(1e-5, 2)
            axes[2].set_xlabel("frequency [Hz] (dotted: coupled eigenvalues)")
            axes[2].set_ylabel("normalised magnitude")
            axes[2].legend(fontsize=8)
        else:
            axes[1].set_ylabel(f"{force} [N]")
            axes[1].set_xlabel("time [s]")
        for ax in axes:
            ax.grid(alpha=0.3)
    lines = []
    for r in s.rows:
        if "frequency" in r.quantity and "FFT" not in r.quantity and "exact" not in r.quantity \
                and sc.kind != "mass_sweep":
            lines.append(f"{r.model.split(' (')[0]}: {r.measured:.4g} Hz "
                         f"(predicted {r.predicted:.4g})")
    fig.suptitle(f"{sc.name} ({sc.kind})" + ("\n" + "; ".join(lines) if lines else ""),
                 fontsize=10)
    fig.tight_layout()
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110)
    finally:
        plt.close(fig)
    return path


# =========================================================================== public API
def simulate(model_path: str | Path, scenario: Any, output: str | Path | None = None,
             plots: bool = True) -> SimulationResults:
    """Run scenario(s) on the model file ``model_path``.

    scenario: a scenario file path, a parsed mapping or list, a :class:`Scenario`, or a list
    of any of these. output: RESULT.h5 to write (atomically, with
    :func:`pipeline.store.h5file.write_file`), with ``<stem>.<scenario>.csv`` and, if ``plots``,
    ``<stem>.<scenario>.png`` beside it; None writes nothing.
    """
    t0 = time.perf_counter()
    scenarios = _as_scenarios(scenario)
    mf = read_model_file(model_path)
    for sc in scenarios:          # refuse a bad scenario before running any
        _check_against_model(mf, sc)
    results = SimulationResults(Path(model_path), [])
    for sc in scenarios:
        ts = time.perf_counter()
        results.scenarios.append(_run_scenario(mf, sc))
        log.info("scenario %s: %.2f s", sc.name, time.perf_counter() - ts)
    results.wall_s = time.perf_counter() - t0
    if output is not None:
        _write_outputs(results, mf, scenarios, Path(output), plots)
    return results


def _write_outputs(results: SimulationResults, mf: ModelFile, scenarios: list[Scenario],
                   output: Path, plots: bool) -> None:
    import yaml

    from pipeline.store.h5file import write_file

    output.parent.mkdir(parents=True, exist_ok=True)
    doc = yaml.safe_dump([s.as_dict() for s in scenarios], sort_keys=False)
    tree, attrs = _results_tree(results, doc)
    write_file(output, tree, attrs, {"content": "simulation results",
                                     "model_file": str(mf.path.resolve()),
                                     "model_content_sha256": mf.sha256,
                                     "scenarios_yaml": doc})
    results.output = output
    results.files.append(output)
    stem = output.with_suffix("")
    for s in results.scenarios:
        port = _ports(mf, s.scenario)[1]
        results.files.append(_write_csv(Path(f"{stem}.{_slug(s.scenario.name)}.csv"), s))
        if plots:
            results.files.append(_plot(Path(f"{stem}.{_slug(s.scenario.name)}.png"), s, port))


# =========================================================================== CLI
def cmd_simulate(args) -> int:
    model = Path(args.model)
    output = Path(args.output) if args.output else Path("outputs") / f"{model.stem}_simulate.h5"
    res = simulate(model, [Path(p) for p in args.scenarios], output, plots=not args.no_plots)
    print(f"{model}: {len(res.scenarios)} scenario(s) in {res.wall_s:.1f} s")
    print(res.table())
    for s in res.scenarios:
        for run in s.runs:
            i = run.info
            dev = max(i.get("deviation_from_exact", {0: 0}).values())
            print(f"  {s.scenario.name:<14.14} {run.model:<36.36}"
                  + (f" m={run.mass:<6g}" if run.mass is not None else " " * 9)
                  + f" {i.get('method')} rtol={i.get('rtol'):g} atol={i.get('atol'):g}: "
                  f"{i.get('nfev')} RHS calls, {i.get('wall_s', 0):.2f} s, max deviation "
                  f"from exact {dev:.1e}" + (f"; {i['coupling']}" if "coupling" in i else ""))
    for f in res.files:
        print(f"wrote {f}")
    return 0


def add_simulate_parser(subparsers):
    """Register ``simulate MODEL.h5 SCENARIO.yaml [...] [-o RESULT.h5]`` on an argparse
    subparsers object (``python -m pipeline simulate``)."""
    p = subparsers.add_parser(
        "simulate", help="step the reduced model of a file through test scenarios",
        description="Step the model of MODEL.h5 (read from the file only) through the "
                    "scenarios of SCENARIO.yaml (one scenario or a list; several files "
                    "allowed) and print measured vs predicted frequencies and deflections.")
    p.add_argument("model", help="HDF5 model file written by 'python -m pipeline run'")
    p.add_argument("scenarios", nargs="+", metavar="SCENARIO.yaml",
                   help="scenario file(s), e.g. configs/scenarios/*.yaml")
    p.add_argument("-o", "--output", help="RESULT.h5 (default outputs/<model>_simulate.h5); "
                   "CSV and PNG files go beside it as <stem>.<scenario>.csv/.png")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.set_defaults(func=cmd_simulate)
    return p
