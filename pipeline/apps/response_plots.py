"""Pictures of a reduced model (``/statespace`` of an HDF5 result): Bode diagram and step
response, written by ``python -m pipeline plot`` (see :mod:`pipeline.apps.plots`).

- :func:`plot_bode`: for every input -> position output of the plant, the magnitude
  |G(j 2 pi f)| (log-log, in output unit / input unit, e.g. [m/N]) above the phase
  arg G [deg] in (-180, 180], plant solid and filtered model dashed, with the
  retained natural frequencies dotted;
- :func:`plot_step`: the response of every position output to a unit step of every input.

G is evaluated as C (s I - A)^-1 B + D for all frequencies at once. Axis labels follow the
one convention of the package: ``quantity [unit]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline._util.atomic import atomic_path
from pipeline.store.read import StoredModels, load_model

DPI = 130
PLANT = "#1f4e9c"
FILTERED = "#d62728"


def save_figure(fig, out: Path) -> Path:
    """Save ``fig`` to ``out`` through the atomic writer (the format from the suffix)."""
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=DPI, facecolor="white", format=out.suffix.lstrip(".") or None)
    return out


def position_outputs(names: tuple[str, ...]) -> list[int]:
    pos = [i for i, n in enumerate(names) if n.endswith("/position")]
    return pos or list(range(len(names)))


def port_units(model: StoredModels) -> tuple[list[str], list[str]]:
    """(input units, output port units) of the file's plant."""
    return list(model.input_units), list(model.port_units)


def ratio_unit(units: tuple[list[str], list[str]], r: int, c: int) -> str:
    """Unit of position output port ``r`` per unit of input ``c`` ('1' when unknown)."""
    ins, outs = units
    if c < len(ins) and r < len(outs):
        return f"{outs[r]}/{ins[c]}"
    return "1"


def _margins(fig, rows: int, cols: int) -> None:
    """Fixed margins (tight_layout on log axes costs seconds)."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=0.95 / w, right=1 - 0.25 / w, bottom=0.6 / h, top=1 - 0.9 / h,
                        wspace=0.8 / (w / cols), hspace=0.55 / (h / rows))


def frequency_response(sys, f: np.ndarray) -> np.ndarray:
    """G(j 2 pi f) (p, m, n_f) complex, of a python-control StateSpace, all f at once.

    The same as ``sys.frequency_response(2 pi f)``, which evaluates one frequency at a
    time (seconds for a few thousand points); here one batched solve.
    """
    A, B, C, D = (np.asarray(M, dtype=float) for M in (sys.A, sys.B, sys.C, sys.D))
    s = 2j * np.pi * f
    eye = np.eye(A.shape[0])
    X = np.linalg.solve(s[:, None, None] * eye - A, np.broadcast_to(B, (f.size, *B.shape)))
    G = C @ X + D                                   # (n_f, p, m)
    return np.moveaxis(G, 0, -1)


def phase_deg(G: np.ndarray) -> np.ndarray:
    """Phase [deg] in (-180, 180]. Not unwrapped: an off-diagonal transfer function
    whose numerator changes sign (a zero on the imaginary axis) would drift by 360 deg
    per crossing, a picture that reads like extra delay; the line is broken at the wraps
    instead (:func:`broken_at_wraps`)."""
    return np.degrees(np.angle(G))


def broken_at_wraps(f: np.ndarray, ph: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(f, ph) with NaN inserted where the phase wraps (jumps by more than 180 deg), so
    that no vertical line is drawn across the plot."""
    jumps = np.flatnonzero(np.abs(np.diff(ph)) > 180.0) + 1
    return np.insert(f, jumps, np.nan), np.insert(ph, jumps, np.nan)


def bode_frequencies(model) -> np.ndarray:
    """Log-spaced frequencies [Hz] over the retained modes (and the filter), refined
    within a few half-power bandwidths of every resonance."""
    retained = np.asarray(model.frequencies_hz[:model.damping_ratios.size])
    retained = retained[retained > 0]
    f_lo = max(retained.min() / 20.0, 1e-6) if retained.size else 0.1
    f_hi = retained.max() * 10.0 if retained.size else 1e4
    if model.cutoff_hz:
        f_hi = max(f_hi, 3.0 * model.cutoff_hz)
    zeta = model.damping_ratios if model.damping_ratios.size else np.full(retained.size, 0.02)
    near = [fr * (1.0 + np.linspace(-5, 5, 61) * max(z, 1e-3)) for fr, z in zip(retained, zeta)]
    f = np.unique(np.concatenate([np.logspace(np.log10(f_lo), np.log10(f_hi), 800), *near]))
    return f[(f >= f_lo) & (f <= f_hi)]


def plot_bode(path: str | Path, out: str | Path) -> Path:
    """Bode magnitude and phase of every input -> position output (plant solid,
    filtered dashed): per output two rows (magnitude above, phase below), one column
    per input."""
    from matplotlib.figure import Figure

    model = load_model(path, require_plant=True)
    units = port_units(model)
    outs = position_outputs(model.output_names)
    n_in = len(model.input_names)
    retained = np.asarray(model.frequencies_hz[:model.damping_ratios.size])
    f = bode_frequencies(model)
    plant = frequency_response(model.ss, f)
    filt = frequency_response(model.ss_filtered, f) if model.ss_filtered is not None else None
    rows = 2 * len(outs)
    fig = Figure(figsize=(max(7.5, 4.6 * n_in + 1.0), 2.2 * rows + 1.2), dpi=DPI,
                 facecolor="white")
    axes = fig.subplots(rows, n_in, squeeze=False, sharex=True,
                        gridspec_kw={"height_ratios": [1.4, 1.0] * len(outs)})
    for r, o in enumerate(outs):
        for c in range(n_in):
            mag, ph = axes[2 * r][c], axes[2 * r + 1][c]
            mag.loglog(f, np.abs(plant[o, c]), color=PLANT, lw=1.6, label="reduced model")
            ph.semilogx(*broken_at_wraps(f, phase_deg(plant[o, c])), color=PLANT, lw=1.4)
            if filt is not None:
                label = f"filtered ({model.filter_kind}, {model.cutoff_hz:g} Hz)"
                mag.loglog(f, np.abs(filt[o, c]), color=FILTERED, lw=1.1, ls="--", label=label)
                ph.semilogx(*broken_at_wraps(f, phase_deg(filt[o, c])), color=FILTERED, lw=1.0,
                            ls="--")
            for ax in (mag, ph):
                for fr in retained:
                    ax.axvline(fr, color="0.6", lw=0.6, ls=":")
                ax.grid(which="both", alpha=0.25)
            ph.yaxis.set_major_locator(_degree_locator())
            ph.set_ylim(-190, 190)
            mag.set_title(f"{model.input_names[c]} -> {model.output_names[o]}", fontsize=9)
            if c == 0:
                mag.set_ylabel(f"|G| [{ratio_unit(units, r, c)}]")
                ph.set_ylabel("phase [deg]")
            if r == len(outs) - 1:
                ph.set_xlabel("f [Hz]")
    axes[0][0].legend(fontsize=8, frameon=False, loc="lower left")
    fig.suptitle(f"{Path(path).stem}: Bode diagram (magnitude and phase)", fontsize=12,
                 fontweight="bold")
    fig.text(0.5, 1 - 0.45 / fig.get_size_inches()[1], "dotted: natural frequencies of the "
             "retained modes", ha="center", fontsize=8, color="0.35")
    _margins(fig, rows, n_in)
    return save_figure(fig, out)


def _degree_locator():
    from matplotlib.ticker import MultipleLocator

    return MultipleLocator(90)


def plot_step(path: str | Path, out: str | Path) -> Path:
    """Response of every position output to a unit step of every input."""
    import control
    from matplotlib.figure import Figure

    model = load_model(path, require_plant=True)
    units = port_units(model)
    outs = position_outputs(model.output_names)
    n_in = len(model.input_names)
    retained = np.asarray(model.frequencies_hz[:model.damping_ratios.size])
    f1 = float(retained[retained > 0].min()) if (retained > 0).any() else 1.0
    zeta = float(np.clip(model.damping_ratios.min(), 0.005, 0.5)) if model.damping_ratios.size \
        else 0.02
    t_end = min(5.0 / (zeta * 2 * np.pi * f1), 60.0 / f1)
    t = np.linspace(0.0, t_end, 3000)
    fig = Figure(figsize=(max(7.5, 4.6 * n_in + 1.0), 2.7 * len(outs) + 1.2), dpi=DPI,
                 facecolor="white")
    axes = fig.subplots(len(outs), n_in, squeeze=False, sharex=True)
    dc = None
    try:
        dc = np.atleast_2d(control.dcgain(model.ss))
    except Exception:  # a free body (rigid modes kept) has no DC gain
        pass
    for c in range(n_in):
        resp = control.step_response(model.ss, t, input=c)
        y = np.asarray(resp.outputs).reshape(len(model.output_names), -1)
        yf = None
        if model.ss_filtered is not None:
            rf = control.step_response(model.ss_filtered, t, input=c)
            yf = np.asarray(rf.outputs).reshape(len(model.ss_filtered.output_labels), -1)
        for r, o in enumerate(outs):
            ax = axes[r][c]
            ax.plot(t, y[o], color=PLANT, lw=1.2, label="reduced model")
            if yf is not None:
                ax.plot(t, yf[o], color=FILTERED, lw=0.9, ls="--", label="filtered")
            if dc is not None and np.isfinite(dc[o, c]):
                ax.axhline(dc[o, c], color="0.4", lw=0.8, ls=":", label="static (DC gain)")
            ax.grid(alpha=0.25)
            unit = units[0][c] if c < len(units[0]) else ""
            ax.set_title(f"step 1 {unit} {model.input_names[c]} -> {model.output_names[o]}",
                         fontsize=9)
            if r == len(outs) - 1:
                ax.set_xlabel("t [s]")
            if c == 0:
                out_unit = units[1][r] if r < len(units[1]) else "1"
                ax.set_ylabel(f"response [{out_unit}]")
    axes[0][0].legend(fontsize=8, frameon=False)
    fig.suptitle(f"{Path(path).stem}: step response", fontsize=11, fontweight="bold")
    _margins(fig, len(outs), n_in)
    return save_figure(fig, out)
