"""The models an FMU can hold, with their tunable parameters (any model ``inspect`` lists).

:func:`fmu_model` picks one model of a result file by name and returns an
:class:`FmuModel`: the state space as stored (what the FMU reproduces at its start values),
units, and the parameters the C code rebuilds the matrices from:

- damping ratios zeta_k (``damping_ratio_<k>``) of a modal model (states ``eta_k``,
  ``eta_dot_k`` or ``eta_k_dot`` with A[eta_k, eta_dot_k] = 1, A[eta_dot_k, eta_k] = -omega_k^2,
  A[eta_dot_k, eta_dot_k] = -2 zeta_k omega_k): A and C are affine in zeta,

      A(zeta) = A_base + sum_k zeta_k GA[:, k] e_{v_k}^T,
      C(zeta) = C_base + sum_k zeta_k GC[:, k] e_{v_k}^T     (v_k: the column of eta_dot_k)

  An output row r depends on zeta_k where C[r, eta_dot_k] = C[r, eta_k] 2 zeta_k / omega_k
  (C[r, eta_k] != 0): the acceleration rows C_acc = C_vel A of the plant and the lumped
  chain (C_acc[eta_k] = -omega_k^2 c, C_acc[eta_dot_k] = -2 zeta_k omega_k c) and every row
  of the connection-point model (C = -[L^T Omega2, L^T 2 Xi Omega]); any other entry is
  independent of zeta. A mode stored with zeta_k = 0 (or omega_k = 0) keeps its damping:
  the two cases cannot be told apart from the matrices.
- the Craig-Bampton body M q'' + C_d q' + K q = S f: x = [q; q'], inputs the forces and
  moments f on the interface coordinates (S selects them), outputs their position,
  velocity and acceleration; C_d = blockdiag(0, diag(2 zeta_k omega_k)) damps the
  fixed-interface modes (M_ee = I, K_ee = diag(omega_k^2)), zeta_k from the stored config's
  uniform damping ratio (0 without one), so A = [[0, I], [-M^-1 K, -M^-1 C_d]] is affine in
  zeta with GA[:, k] = -2 omega_k M^-1 e_{eta_k} in the velocity rows.
- the filter cut-off f_c (``filter_cutoff``, Hz) of the filtered model: the output filter
  in series with the plant (pipeline.reduce.filters), A = [[A_p, 0], [K B_f1 C_p, K A_f1]],
  B = [[B_p], [K B_f1 D_p]], C = [0, C_f1 K^pow], D = 0 with K = 2 pi f_c, where (A_f1,
  B_f1, C_f1) is the filter at K = 1 and pow the power of K of each output row (0 for
  positions, 1 velocities, 2 accelerations of the third-order filter; 0 for the first).

Every structure is checked against the stored matrices at export (relative 1e-9); a model
that does not have it gets no such parameter (it is then exported as stored).
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError, FileFormatError
from pipeline.reduce.statespace import StateSpace
from pipeline.store import layout as L
from pipeline.store.read import StoredModels, load_model

log = logging.getLogger(__name__)

__all__ = ["FmuModel", "Damping", "OutputFilter", "fmu_model", "check_model_name",
           "modal_damping", "output_filter", "craig_bampton_model", "ALIASES"]

#: the names ``inspect`` prints (its groups) for the models of :attr:`StoredModels.models`
ALIASES = {L.STATESPACE.path.strip("/"): "plant", L.STATESPACE_FILTERED.path.strip("/"): "filtered",
           L.LUMPED.path.strip("/"): "lumped"}
QUANTITY_SUFFIX = {"position": "", "velocity": "/s", "acceleration": "/s2"}
#: force (moment) input of each Craig-Bampton interface coordinate
CB_INPUT = {"x": ("Fx", "N"), "y": ("Fy", "N"), "z": ("Fz", "N"),
            "rx": ("Tx", "N m"), "ry": ("Ty", "N m"), "rz": ("Tz", "N m")}
#: relative tolerance of the structure checks behind the parameters
STRUCTURE_RTOL = 1e-9


@dataclass(frozen=True)
class Damping:
    """Damping ratios as parameters: A(zeta), C(zeta) affine (module docstring).
    vcol (n_z,): state column of eta_dot_k; omega (n_z,) rad/s; zeta (n_z,) start values;
    mode (n_z,): 1-based mode number; A_base, GA (n_x, n_z); C_base, GC (n_y, n_z)."""

    vcol: tuple[int, ...]
    omega: np.ndarray
    zeta: np.ndarray
    mode: tuple[int, ...]
    A_base: np.ndarray
    GA: np.ndarray
    C_base: np.ndarray
    GC: np.ndarray


@dataclass(frozen=True)
class OutputFilter:
    """The filtered model's output filter at K = 1: A_f1 (n_f, n_f), B_f1 (n_f, n_in),
    C_f1 (n_y, n_f), pow (n_y,), rows (n_in,): plant output feeding each filter input;
    kind; cutoff_hz (start value)."""

    A_f1: np.ndarray
    B_f1: np.ndarray
    C_f1: np.ndarray
    pow: tuple[int, ...]
    rows: tuple[int, ...]
    kind: str
    cutoff_hz: float


@dataclass(frozen=True)
class FmuModel:
    """What goes into the FMU. name: the file's stem; model: the model's name in the file;
    ss: the model as stored (names from the file); plant: the part the damping acts on
    (``ss`` itself without a filter); input_units, output_units: one SI unit per input /
    output ('' unknown); damping, filter: the parameters, or None; nominals (n_x,)."""

    name: str
    model: str
    ss: StateSpace
    plant: StateSpace
    input_units: tuple[str, ...]
    output_units: tuple[str, ...]
    damping: Damping | None
    filter: OutputFilter | None
    nominals: np.ndarray

    @property
    def n_parameters(self) -> int:
        return (0 if self.damping is None else len(self.damping.vcol)) + (self.filter is not None)


# --------------------------------------------------------------------------- damping
def _close(a: np.ndarray, b: np.ndarray) -> bool:
    scale = max(float(np.abs(b).max(initial=0.0)), 1e-300)
    return bool(np.all(np.abs(a - b) <= STRUCTURE_RTOL * scale))


def _affine(ss: StateSpace, A_base, GA, C_base, GC, vcol, zeta) -> bool:
    """A(zeta0), C(zeta0) of the affine form equal the stored A and C."""
    A, C = A_base.copy(), C_base.copy()
    for k, v in enumerate(vcol):
        A[:, v] += zeta[k] * GA[:, k]
        C[:, v] += zeta[k] * GC[:, k]
    return _close(A, ss.A) and _close(C, ss.C)


def modal_damping(ss: StateSpace) -> Damping | None:
    """The damping parameters of a modal model (module docstring), or None."""
    # the connection-point model names its velocity states eta_<k>_dot
    names = tuple(re.sub(r"^eta_(\d+)_dot$", r"eta_dot_\1", n) for n in ss.state_names)
    idx = ss.with_(state_names=names).modal_indices()
    if idx is None:
        return None
    e, d = idx
    A, C = np.array(ss.A), np.array(ss.C)
    w2 = -A[d, e]
    w = np.sqrt(np.clip(w2, 0.0, None))
    zeta = np.where(w > 0, -A[d, d] / (2 * np.where(w > 0, w, 1.0)), 0.0)
    keep = [k for k in range(e.size) if w2[k] > 0 and zeta[k] > 0]
    if not keep:
        return None
    A_base, C_base = A.copy(), C.copy()
    GA, GC = np.zeros((A.shape[0], len(keep))), np.zeros((C.shape[0], len(keep)))
    for j, k in enumerate(keep):
        A_base[d[k], d[k]] = 0.0
        GA[d[k], j] = -2.0 * w[k]
        c_pos, c_vel = C[:, e[k]], C[:, d[k]]
        ratio = 2.0 * zeta[k] / w[k]
        rows = (c_pos != 0) & (np.abs(c_vel - ratio * c_pos) <= STRUCTURE_RTOL * np.abs(c_vel))
        GC[rows, j] = 2.0 * c_pos[rows] / w[k]
        C_base[rows, d[k]] = 0.0
    vcol = tuple(int(d[k]) for k in keep)
    if not _affine(ss, A_base, GA, C_base, GC, vcol, zeta[keep]):
        return None
    return Damping(vcol, w[keep], zeta[keep], tuple(k + 1 for k in keep), A_base, GA, C_base, GC)


# --------------------------------------------------------------------------- filter
def output_filter(plant: StateSpace, filtered: StateSpace) -> OutputFilter | None:
    """The output filter of ``filtered`` at K = 1 when filtered = filter(K0) * plant
    (pipeline.reduce.filters), else None."""
    from pipeline.reduce.filters import first_order_filter, third_order_position_filter

    kind, f_c = filtered.filter_kind, filtered.cutoff_hz
    if kind not in ("first_order", "third_order") or not f_c or not f_c > 0:
        return None
    n_out = len(plant.output_names)
    if kind == "first_order":
        f1, rows, pw = first_order_filter(n_out, 1.0), tuple(range(n_out)), (0,) * n_out
    else:
        ports = plant.ports
        f1 = third_order_position_filter(len(ports), 1.0)
        rows = tuple(plant.rows(p)[0] for p in ports)
        pw = (0,) * len(ports) + (1,) * len(ports) + (2,) * len(ports)
    K = 2.0 * math.pi * f_c
    nf = f1.A.shape[0]
    if filtered.A.shape[0] != plant.A.shape[0] + nf or filtered.C.shape[0] != f1.C.shape[0]:
        return None
    Cp, Dp = plant.C[list(rows)], plant.D[list(rows)]
    A = np.block([[plant.A, np.zeros((plant.A.shape[0], nf))], [K * f1.B @ Cp, K * f1.A]])
    B = np.vstack([plant.B, K * f1.B @ Dp])
    C = np.hstack([np.zeros((f1.C.shape[0], plant.A.shape[0])),
                   f1.C * K ** np.array(pw, float)[:, None]])
    if not (_close(A, filtered.A) and _close(B, filtered.B) and _close(C, filtered.C)
            and not np.any(filtered.D)):
        return None
    return OutputFilter(np.array(f1.A), np.array(f1.B), np.array(f1.C), pw, rows, kind, float(f_c))


# --------------------------------------------------------------------------- Craig-Bampton
def _uniform_ratio(config_yaml: str) -> float:
    """The stored config's uniform damping ratio (0 without one)."""
    import yaml

    try:
        cfg = yaml.safe_load(config_yaml) if config_yaml else None
    except yaml.YAMLError:
        cfg = None
    damping = cfg.get("damping") if isinstance(cfg, dict) else None
    if isinstance(damping, dict) and damping.get("kind", "uniform") == "uniform":
        ratio = damping.get("ratio")
        if isinstance(ratio, (int, float)) and math.isfinite(ratio) and ratio >= 0:
            return float(ratio)
    return 0.0


def craig_bampton_model(cb, zeta0: float) -> tuple[StateSpace, Damping | None]:
    """The Craig-Bampton body as a state space (module docstring) and its damping
    parameters (one per fixed-interface mode; None when zeta0 = 0)."""
    names, units = list(cb.coordinate_names), list(cb.coordinate_units)
    n = len(names)
    iface = [i for i, c in enumerate(names) if not c.startswith("mode_")]
    modes = [i for i, c in enumerate(names) if c.startswith("mode_")]
    omega = np.sqrt(np.clip(np.diag(cb.K)[modes], 0.0, None))
    Minv = np.linalg.inv(cb.M)
    nb = len(iface)
    S = np.zeros((n, nb))
    S[iface, range(nb)] = 1.0
    GA = np.zeros((2 * n, len(modes)))
    for j, i in enumerate(modes):
        GA[n:, j] = -2.0 * omega[j] * Minv[:, i]
    A_base = np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ cb.K, np.zeros((n, n))]])
    B = np.vstack([np.zeros((n, nb)), Minv @ S])
    C_base = np.vstack([np.hstack([S.T, np.zeros((nb, n))]), np.hstack([np.zeros((nb, n)), S.T]),
                        S.T @ A_base[n:]])
    D = np.vstack([np.zeros((2 * nb, nb)), S.T @ Minv @ S])
    GC = np.vstack([np.zeros((2 * nb, len(modes))), S.T @ GA[n:]])
    vcol = tuple(n + i for i in modes)
    zeta = np.full(len(modes), zeta0)
    A, C = A_base.copy(), C_base.copy()
    A[:, list(vcol)] += GA * zeta
    C[:, list(vcol)] += GC * zeta
    coord = [names[i] for i in iface]
    inputs = [c.rsplit(".", 1)[0] + "." + CB_INPUT.get(c.rsplit(".", 1)[-1], ("F", ""))[0]
              for c in coord]
    in_units = [CB_INPUT.get(c.rsplit(".", 1)[-1], ("", ""))[1] for c in coord]
    outputs = [f"{c}/{q}" for q in QUANTITY_SUFFIX for c in coord]
    out_units = [units[i] + s if units[i] in ("m", "rad") else ""
                 for s in QUANTITY_SUFFIX.values() for i in iface]
    ss = StateSpace(A, B, C, D, input_names=inputs, output_names=outputs,
                    state_names=names + [f"{c}_dot" for c in names], input_units=in_units,
                    output_units=out_units, label="craig_bampton")
    damping = (Damping(vcol, omega, zeta, tuple(range(1, len(modes) + 1)), A_base, GA, C_base, GC)
               if zeta0 > 0 and np.all(omega > 0) else None)
    return ss, damping


# --------------------------------------------------------------------------- the model
def _units(lm: StoredModels, ss: StateSpace) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(input units, output units): the model's own, else the plant's port units expanded
    to position/velocity/acceleration ('' where unknown)."""
    if ss.input_units or ss.output_units:
        return (ss.input_units or ("",) * ss.n_inputs, ss.output_units or ("",) * ss.n_outputs)
    if ss.label == "lumped":  # the chain's tip force (N) and tip motion along it (m)
        return (("N",) * ss.n_inputs,
                tuple("m" + QUANTITY_SUFFIX.get(n.rsplit("_", 1)[-1], "?")
                      for n in ss.output_names))
    u_units = tuple(lm.input_units)
    if len(u_units) != ss.n_inputs:
        u_units = ("",) * ss.n_inputs
    per_port = (dict(zip(lm.plant.ports, lm.port_units))
                if lm.plant is not None and len(lm.port_units) == len(lm.plant.ports) else {})
    y_units = []
    for name in ss.output_names:
        port, _, quantity = name.rpartition("/")
        base = per_port.get(port, "")
        y_units.append(base + QUANTITY_SUFFIX[quantity] if base and quantity in QUANTITY_SUFFIX
                       else "")
    return u_units, tuple(y_units)


def _nominals(ss: StateSpace) -> np.ndarray:
    """Per state, the smallest over the inputs of its RMS response to that one input as
    unit white noise: sqrt(min_j diag W_j), A W_j + W_j A^T + b_j b_j^T = 0 (the
    controllability Gramian of input j). Importers scale absolute tolerances with it
    (fmpy: rtol * nominal), so the response to any single input is resolved, also where
    the inputs' units differ (a connection model mixes m/s^2 and N). 1.0 where A is not
    Hurwitz or a state responds to no input."""
    import scipy.linalg as sla

    n = ss.A.shape[0]
    if n == 0 or not np.all(np.linalg.eigvals(ss.A).real < 0):
        return np.ones(n)
    best = np.full(n, np.inf)
    for j in range(ss.B.shape[1]):
        b = ss.B[:, j:j + 1]
        if not np.any(b):
            continue
        d = np.sqrt(np.clip(np.diag(sla.solve_continuous_lyapunov(ss.A, -b @ b.T)), 0.0, None))
        best = np.where(np.isfinite(d) & (d > 0), np.minimum(best, d), best)
    return np.where(np.isfinite(best), best, 1.0)


def check_model_name(model: str) -> str:
    """``model`` with the inspect aliases resolved; ConfigError for a name that is no
    model kind at all (one the file lacks is refused by :func:`fmu_model`)."""
    model = ALIASES.get(model, model)
    known = ("plant", "filtered", "lumped", "craig_bampton")
    if model in known or (model.startswith("connection/") and len(model) > len("connection/")):
        return model
    raise ConfigError(f"export --model: got {model!r}, expected one of {', '.join(known)}, "
                      "connection/<name>", key="--model",
                      value=model, expected=" | ".join(known + ("connection/<name>",)))


def fmu_model(h5_path: str | Path, model: str = "plant") -> FmuModel:
    """The model ``model`` of ``h5_path`` (plant, filtered, lumped, connection/<name>,
    craig_bampton; or the group names statespace, statespace_filtered) with units and
    parameters, as the FMU export writes it. FileFormatError when the file lacks it."""
    h5_path = Path(h5_path)
    model = check_model_name(model)
    lm = load_model(h5_path)
    if model not in lm.models:
        hint = {"filtered": " (the config had no 'filter' section)",
                "plant": " (the config had no 'reduction' section)"}.get(model, "")
        raise FileFormatError(f"file '{h5_path}': holds no '{model}' model{hint}; it holds "
                              f"{', '.join(lm.models) or 'none'}", key="--model", value=model,
                              expected="one of " + ", ".join(lm.models))
    filt = None
    if model == "craig_bampton":
        ss, damping = craig_bampton_model(lm.craig_bampton, _uniform_ratio(lm.config_yaml))
        plant = ss
    else:
        ss = lm.model(model)
        plant = ss
        if model == "filtered":
            filt = output_filter(lm.plant, ss)
            if filt is not None:
                plant = lm.plant
            else:
                log.info("fmu: the filtered model is not filter * plant; no cut-off parameter")
        damping = modal_damping(plant)
        if model == "filtered" and filt is None:
            damping = None  # the filter rows of A would not follow the damping
    if damping is None:
        log.info("fmu: %s model: no damping parameters (not modal with damping in A)", model)
    u_units, y_units = _units(lm, ss)
    return FmuModel(str(lm.path.stem), model, ss, plant, u_units, y_units, damping, filt,
                    _nominals(ss))
