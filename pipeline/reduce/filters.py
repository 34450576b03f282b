"""Output filters that break the algebraic loop of a force-in, motion-out model.

theory.md §4. The plant's acceleration output depends on its force input at the
same instant (D != 0); coupling it to a joint whose reaction force is fed back forms an
algebraic loop. A low-pass filter with cutoff K (rad/s) in series removes the direct
feedthrough:

- ``first_order``: every output through H(s) = K / (s + K);
- ``third_order``: only the positions, through K^3 / (s + K)^3, which yields consistent
  position, velocity and acceleration p = K^3/(s+K)^3 y, v = s p, a = s^2 p.

The series connection filter * plant is built here with numpy block matrices (no
python-control at run time):

    x' = [[A_p, 0], [B_f C_p, A_f]] x + [[B_p], [B_f D_p]] u
    y  = [D_f C_p, C_f] x + D_f D_p u          (D_f = 0, so D = 0)

Realisation of the third-order filter (one per port). theory.md §4 writes it as
w''' = -3K w'' - 3K^2 w' - K^3 w + y, (p, v, a) = K^3 (w, w', w''). Here the states are
that realisation scaled by diag(K^3, K^2, K): z = (K^3 w, K^2 w', K w'') = (p, v/K, a/K^2),
all in the unit of the position output, so

    z' = K [[0, 1, 0], [0, 0, 1], [-1, -3, -3]] z + K [0, 0, 1]^T y,
    (p, v, a) = (z1, K z2, K^2 z3).

Same transfer functions; the state magnitudes stay comparable (K^3 w would be ~1e-12 of
the signal for K ~ 1e4 rad/s, which breaks the absolute tolerances of a variable-step
integrator downstream).
"""

from __future__ import annotations

import logging
import math
import numpy as np

from pipeline._util import validate
from pipeline.reduce.modal import ReducedModel, StateSpaceModel
from pipeline.reduce.statespace import StateSpace

log = logging.getLogger(__name__)

__all__ = [
    "FILTER_KINDS",
    "CUTOFF_MARGIN",
    "first_order_filter",
    "third_order_position_filter",
    "filtered_model",
]

FILTER_KINDS = ("none", "first_order", "third_order")

#: The cutoff should be at least this many times the highest retained mode frequency.
CUTOFF_MARGIN = 5.0


def _check_cutoff_rad_s(cutoff_rad_s: float) -> float:
    return validate.number({"cutoff_rad_s": cutoff_rad_s}, "cutoff_rad_s", "", lo=0.0,
                           lo_open=True)


def first_order_filter(n_channels: int, cutoff_rad_s: float) -> StateSpace:
    """n_channels independent filters K / (s + K), K in rad/s.

    A = -K I, B = K I, C = I, D = 0 (all n_channels x n_channels); state i is the
    filtered channel i (same unit as the channel). Unit DC gain.
    """
    K = _check_cutoff_rad_s(cutoff_rad_s)
    I = np.eye(n_channels)
    return StateSpace(-K * I, K * I, I.copy(), np.zeros((n_channels, n_channels)),
                      label="first_order filter")


def third_order_position_filter(n_ports: int, cutoff_rad_s: float) -> StateSpace:
    """Third-order filter K^3/(s+K)^3 on n_ports position signals, giving p, v, a.

    Inputs: the n_ports position signals y. Outputs (3 n_ports): all filtered
    positions p, then velocities v = p', then accelerations a = p'' (same order as the
    plant's outputs). States: per port (z1, z2, z3) = (K^3 w, K^2 w', K w'') of theory.md §4's
    w''' = -3K w'' - 3K^2 w' - K^3 w + y (see the module docstring). Shapes: A (3n x 3n),
    B (3n x n), C (3n x 3n), D = 0 (3n x n). DC gain: 1 on positions, 0 on v and a.
    """
    K = _check_cutoff_rad_s(cutoff_rad_s)
    n = int(n_ports)
    a1 = K * np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -3.0, -3.0]])
    A = np.kron(np.eye(n), a1)
    B = np.zeros((3 * n, n))
    C = np.zeros((3 * n, 3 * n))
    for i in range(n):
        B[3 * i + 2, i] = K
        C[i, 3 * i] = 1.0               # p = z1
        C[n + i, 3 * i + 1] = K         # v = K z2
        C[2 * n + i, 3 * i + 2] = K * K  # a = K^2 z3
    return StateSpace(A, B, C, np.zeros((3 * n, n)), label="third_order filter")


def _series(plant: StateSpace, filt: StateSpace, rows: slice) -> tuple[np.ndarray, ...]:
    """filter * plant, the filter fed by the plant outputs ``rows``."""
    Ap, Bp, Cp, Dp = plant.A, plant.B, plant.C[rows], plant.D[rows]
    Af, Bf, Cf, Df = filt.A, filt.B, filt.C, filt.D
    nf = Af.shape[0]
    A = np.block([[Ap, np.zeros((Ap.shape[0], nf))], [Bf @ Cp, Af]])
    B = np.vstack([Bp, Bf @ Dp])
    C = np.hstack([Df @ Cp, Cf])
    D = Df @ Dp
    return A, B, C, D


def check_filter(kind: str, cutoff_hz) -> float | None:
    """The filter kind and its cutoff in Hz (None for ``"none"``), through the one field
    checker (pipeline._util.validate)."""
    kind = validate.choice({"filter.kind": kind}, "filter.kind", "", FILTER_KINDS)
    if kind == "none":
        return None
    if isinstance(cutoff_hz, np.generic):
        cutoff_hz = cutoff_hz.item()
    return validate.number({"filter.cutoff_hz": cutoff_hz}, "filter.cutoff_hz", "", lo=0.0,
                           lo_open=True)


def filtered_model(model: StateSpaceModel | ReducedModel, kind: str, cutoff_hz: float | None
                   ) -> StateSpaceModel:
    """The series connection filter * plant as a new :class:`StateSpaceModel`.

    ``kind``: ``"none"`` (returns the plant unchanged), ``"first_order"`` (every output
    through K/(s+K)) or ``"third_order"`` (the position outputs through K^3/(s+K)^3; its
    p, v, a replace all plant outputs, so velocity and acceleration are the exact time
    derivatives of the position). K = 2 pi ``cutoff_hz`` (Hz). D = 0 for both filters;
    output names are unchanged; states are the plant's followed by
    ``filter/<output>`` (first order) or ``filter/<port>/w``, ``.../w_dot``,
    ``.../w_ddot`` (third order, scaled as in the module docstring).

    Logs a warning when the cutoff is below CUTOFF_MARGIN x the highest retained mode
    frequency (the filter then distorts the dynamics). ``cutoff_hz`` <= 0 ->
    :class:`ConfigError` naming ``filter.cutoff_hz``.
    """
    plant = model.statespace if isinstance(model, ReducedModel) else model
    f_c = check_filter(kind, cutoff_hz)
    if f_c is None:
        return plant
    if plant.filter_kind != "none":
        raise ValueError(f"model is already filtered ({plant.filter_kind})")
    K = 2.0 * math.pi * f_c
    f_ret = plant.frequencies_hz[: plant.n_retained]
    f_max = float(f_ret.max()) if f_ret.size else 0.0
    if f_c < CUTOFF_MARGIN * f_max:
        log.warning("filter.cutoff_hz = %g Hz is below %g x the highest retained mode "
                    "(%.6g Hz): the %s filter will distort the dynamics; raise the cutoff to "
                    "at least %.6g Hz", f_c, CUTOFF_MARGIN, f_max, kind.replace("_", "-"),
                    CUTOFF_MARGIN * f_max)
    n_out = len(plant.output_names)
    if kind == "first_order":
        filt = first_order_filter(n_out, K)
        A, B, C, D = _series(plant, filt, slice(0, n_out))
        extra = tuple(f"filter/{name}" for name in plant.output_names)
    else:
        ports = plant.port_names
        filt = third_order_position_filter(len(ports), K)
        A, B, C, D = _series(plant, filt, plant.output_rows("position"))
        extra = tuple(f"filter/{p}/{s}" for p in ports for s in ("w", "w_dot", "w_ddot"))
    return StateSpaceModel(A, B, C, D, input_names=plant.input_names,
                           output_names=plant.output_names,
                           state_names=plant.state_names + extra, label="filtered",
                           filter_kind=kind, cutoff_hz=f_c, omega2=plant.omega2,
                           damping_ratios=plant.damping_ratios, n_retained=plant.n_retained)
