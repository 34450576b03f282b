"""The Campbell diagram of a spinning body: ``plot`` draws ``campbell.png``, ``inspect``
prints the table, from the file's ``/rotation`` group
(:func:`pipeline.store.read.read_rotation`).

Every stored mode's frequency (Hz) against the spin speed (rad/s): the full FE
prestressed frequencies (solid lines, dots) and the reduced model's (dashed), with the
engine-order lines f = k |Omega| / (2 pi), k = 1, 2, where a mode crossing one is
excited once or twice per revolution (a resonance speed).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pipeline.reduce.spin import RotationModel

log = logging.getLogger(__name__)

#: the engine orders drawn (excitations k times per revolution)
ENGINE_ORDERS = (1, 2)


def campbell_lines(model: RotationModel) -> list[str]:
    """The Campbell table as text lines: per speed (rad/s), each mode's full FE frequency
    (Hz) and the reduced model's relative difference."""
    n = model.frequencies_hz.shape[1]
    axis = np.round(model.axis, 6).tolist()
    lines = [f"rotation  axis {axis} through {np.round(model.point, 6).tolist()} m; "
             f"reduced basis {model.stiffness.shape[0]} vectors ({model.n_modes} modes)",
             f"  {'speed [rad/s]':>13}  " + "  ".join(f"{'f' + str(k + 1) + ' [Hz]':>11}"
                                                      for k in range(n))]
    for speed, full, reduced in zip(model.speeds_rad_s, model.frequencies_hz,
                                    model.frequencies_reduced_hz):
        lines.append(f"  {speed:13.6g}  " + "  ".join(f"{f:11.4f}" for f in full))
        m = min(n, reduced.size)
        worst = float(np.max(np.abs(reduced[:m] / full[:m] - 1))) if m else 0.0
        lines.append(f"  {'reduced':>13}  " + "  ".join(f"{f:11.4f}" for f in reduced[:m])
                     + f"   (max rel. diff {worst:.1e})")
    return lines


def plot_campbell(model: RotationModel, out: str | Path) -> Path:
    """``campbell.png``: frequency [Hz] against speed [rad/s] for every stored mode, full
    FE and reduced, with the 1x and 2x engine-order lines."""
    from matplotlib.figure import Figure

    from pipeline.apps.response_plots import save_figure

    fig = Figure(figsize=(7.0, 5.0))
    ax = fig.add_subplot(1, 1, 1)
    speeds = model.speeds_rad_s
    n = model.frequencies_hz.shape[1]
    for k in range(n):
        line, = ax.plot(speeds, model.frequencies_hz[:, k], "o-", ms=3,
                        label="full FE" if k == 0 else None)
        if k < model.frequencies_reduced_hz.shape[1]:
            ax.plot(speeds, model.frequencies_reduced_hz[:, k], "--", color=line.get_color(),
                    label="reduced" if k == 0 else None)
    top = float(np.max(model.frequencies_hz)) * 1.05 if model.frequencies_hz.size else 1.0
    grid = np.linspace(float(speeds.min()), float(speeds.max()), 200)
    for order in ENGINE_ORDERS:
        ax.plot(grid, order * np.abs(grid) / (2 * np.pi), ":", color="grey")
        ax.annotate(f"{order}x", (grid[-1], order * abs(grid[-1]) / (2 * np.pi)),
                    color="grey", fontsize=8)
    ax.set_ylim(0.0, top)
    ax.set_xlabel("Omega [rad/s]")
    ax.set_ylabel("f [Hz]")
    ax.set_title("Campbell diagram (prestressed modes; dotted: engine orders)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return save_figure(fig, Path(out))
