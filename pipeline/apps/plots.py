"""Pictures of an HDF5 result: ``python -m pipeline plot FILE.h5 [-o DIR]``.

Reads only the HDF5 file (verified: schema, version, checksum) and writes, into
``DIR`` (default: ``<FILE stem>_plots`` next to the file):

- ``mode_NN.png``: mode NN, the deformed body (boundary surface coloured by the
  displacement magnitude, lit) over the undeformed outline (feature edges), with its
  frequency and label in the title; quadratic elements are drawn with their
  edge-midpoint nodes, so bending looks curved, not faceted;
- ``modes.png``: all modes (up to 12) side by side, small;
- ``frequencies.png`` and ``frequencies.csv``: the frequency table (mode, Hz, label,
  and for the modes kept in the reduced model their damping ratio);
- where the file holds a reduced model (``/statespace``): ``bode.png``, the magnitude
  and phase of every input -> position output of the plant (and of the filtered model,
  dashed), and ``step.png``, the response of every position output to a unit step of
  every input (:mod:`pipeline.apps.response_plots`);
- with ``--animate``: ``mode_NN.gif`` (and ``.mp4`` where ffmpeg is installed), the mode
  shapes moving (:mod:`pipeline.apps.animate`);
- where the file holds stress modes: ``static_von_mises_<input>.png``, the static von
  Mises stress per unit input on the body (:mod:`pipeline.apps.stress_plots`);
- where the file holds ``/rotation``: ``campbell.png``, the prestressed frequencies
  against the spin speed with the 1x and 2x engine orders (:mod:`pipeline.apps.campbell`).

Axes are labelled ``quantity [unit]`` (the package's one convention: ``f [Hz]``,
``x [m]``); the colour of a mode picture is |u| / max |u| (a mode shape has no absolute
scale) with its colour bar.

Only matplotlib's object API is used (no pyplot, no global backend switch), so this
module is safe to call from a library or a test.
"""

from __future__ import annotations

import argparse
import csv
import logging
from pathlib import Path

import numpy as np

from pipeline._util.atomic import atomic_path
from pipeline.apps.mode_drawing import (DEFORMATION_FRACTION, DPI, Surface, boundary_surface,
                                        colour_bar, draw_mode, draw_mode_2d, is_slender,
                                        mode_title)
from pipeline.apps.response_plots import plot_bode, plot_step, save_figure
from pipeline.store.read import StoredMesh, load_model, read_rotation, read_stored_mesh

log = logging.getLogger(__name__)

__all__ = ["boundary_surface", "plot_mode", "plot_modes_overview",
           "plot_frequency_table", "plot_bode", "plot_step", "plot_file", "add_plot_parser"]


# --------------------------------------------------------------------------- mode pictures
def _savefig(fig, out: Path) -> None:
    """Save ``fig`` to ``out`` through the atomic writer (the format from the suffix)."""
    save_figure(fig, out)


def plot_mode(data: StoredMesh, mode: int, out: str | Path, surface: Surface | None = None) -> Path:
    """One mode (0-based index) as a PNG."""
    from matplotlib.figure import Figure

    surface = surface or boundary_surface(data.points, data.cells)
    slender = is_slender(data.points)
    fig = Figure(figsize=(9.0, 4.8) if slender else (8.0, 6.0), dpi=DPI, facecolor="white")
    if slender:
        ax = fig.add_subplot()
        fig.subplots_adjust(left=0.1, right=0.98, top=0.86, bottom=0.2)
        end_on = draw_mode_2d(ax, data, surface, mode, colorbar_fig=fig)
        if end_on:
            fig.set_size_inches(6.4, 5.6)
            fig.subplots_adjust(left=0.16, right=0.95, top=0.88, bottom=0.16)
        view = ("end-on view along the long axis (a twist)" if end_on
                else "side view, not to scale across")
    else:
        ax = fig.add_subplot(projection="3d", computed_zorder=False)
        draw_mode(ax, data, surface, mode, colorbar_fig=fig)
        view = "3D view from where the motion shows"
    fig.suptitle(mode_title(data, mode), fontsize=14, fontweight="bold", y=0.96)
    extent = np.ptp(data.points, axis=0)
    fig.text(0.5, 0.015, f"{data.name}: body {' x '.join(f'{e * 1e3:.4g}' for e in extent)} mm, "
             f"{view};\ndeformation exaggerated to {DEFORMATION_FRACTION:.0%} of the largest "
             "dimension in view; grey: undeformed outline", ha="center", fontsize=8, color="0.3")
    out = Path(out)
    _savefig(fig, out)
    return out


def plot_modes_overview(data: StoredMesh, out: str | Path, surface: Surface | None = None,
                        max_modes: int = 12) -> Path:
    """Small multiples of the first ``max_modes`` modes."""
    from matplotlib.figure import Figure

    n = min(data.frequencies_hz.size, max_modes)
    surface = surface or boundary_surface(data.points, data.cells, subdivide_below=0)
    slender = is_slender(data.points)
    cols = min(n, 2 if slender else 4)
    rows = int(np.ceil(n / cols))
    size = (5.0 * cols, 2.4 * rows + 0.7) if slender else (3.4 * cols, 3.0 * rows + 0.6)
    fig = Figure(figsize=size, dpi=DPI, facecolor="white")
    for k in range(n):
        if slender:
            ax = fig.add_subplot(rows, cols, k + 1)
            draw_mode_2d(ax, data, surface, k, small=True)
        else:
            ax = fig.add_subplot(rows, cols, k + 1, projection="3d", computed_zorder=False)
            draw_mode(ax, data, surface, k, outline=True, light=True, triad=k == 0)
        ax.set_title(mode_title(data, k), fontsize=9)
    fig.suptitle(f"{data.name}: {n} modes", fontsize=13, fontweight="bold")
    right = 1 - 0.9 / fig.get_size_inches()[0]  # room for the colour bar
    if slender:
        fig.tight_layout(rect=(0, 0, right, 0.95))
    else:
        fig.subplots_adjust(left=0, right=right, bottom=0, top=0.92, wspace=0, hspace=0.08)
    colour_bar(fig, cax=fig.add_axes((right + 0.15 / fig.get_size_inches()[0], 0.15,
                                       0.18 / fig.get_size_inches()[0], 0.65)))
    out = Path(out)
    _savefig(fig, out)
    return out


# --------------------------------------------------------------------------- table
def frequency_rows(data: StoredMesh) -> list[dict]:
    rows = []
    for i, f in enumerate(data.frequencies_hz):
        damping = data.retained_damping[i] if i < data.retained_damping.size else None
        rows.append({"mode": i + 1, "frequency_hz": float(f),
                     "label": data.labels[i] if i < len(data.labels) else "",
                     "in_reduced_model": damping is not None,
                     "damping_ratio": None if damping is None else float(damping)})
    return rows


def write_frequency_csv(data: StoredMesh, out: str | Path) -> Path:
    out = Path(out)
    with atomic_path(out) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(["mode", "frequency_hz", "label", "in_reduced_model", "damping_ratio"])
        for r in frequency_rows(data):
            writer.writerow([r["mode"], f"{r['frequency_hz']:.9g}", r["label"],
                             int(r["in_reduced_model"]),
                             "" if r["damping_ratio"] is None else f"{r['damping_ratio']:.6g}"])
    return out


def plot_frequency_table(data: StoredMesh, out: str | Path) -> Path:
    """The frequencies as a chart (left) and a table (right)."""
    from matplotlib.figure import Figure

    rows = frequency_rows(data)
    n = len(rows)
    fig = Figure(figsize=(11.0, max(3.2, 0.8 + 0.32 * n)), dpi=DPI, facecolor="white")
    ax = fig.add_axes((0.07, 0.14, 0.38, 0.72))
    families = sorted({r["label"].rstrip("_0123456789") or "mode" for r in rows})
    palette = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf",
               "#7f7f7f"]
    colour = {fam: palette[i % len(palette)] for i, fam in enumerate(families)}
    freqs = np.array([r["frequency_hz"] for r in rows])
    modes = np.arange(1, n + 1)
    fam_of = [r["label"].rstrip("_0123456789") or "mode" for r in rows]
    for fam in families:
        sel = [i for i, f in enumerate(fam_of) if f == fam]
        ax.bar(modes[sel], freqs[sel], color=colour[fam], label=fam, width=0.7)
    positive = freqs[freqs > 0]
    if positive.size and positive.max() / positive.min() > 30:
        ax.set_yscale("log")
    ax.set_xlabel("mode")
    ax.set_ylabel("f [Hz]")
    ax.set_xticks(modes)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, frameon=False)
    ax.set_title(f"{data.name}: natural frequencies", fontsize=12, fontweight="bold")
    tab = fig.add_axes((0.5, 0.04, 0.48, 0.86))
    tab.set_axis_off()
    cells = [[str(r["mode"]), f"{r['frequency_hz']:.6g}", r["label"],
              "" if r["damping_ratio"] is None else f"{r['damping_ratio']:.3g}"] for r in rows]
    table = tab.table(cellText=cells, colLabels=["mode", "f [Hz]", "label", "damping ratio [1]*"],
                      colWidths=[0.12, 0.26, 0.36, 0.26], loc="upper center", cellLoc="center")
    tab.text(0.5, 0.0, "* of the modes kept in the reduced model", ha="center", va="bottom",
             fontsize=8, color="0.35", transform=tab.transAxes)
    table.auto_set_font_size(False)
    table.set_fontsize(9)
    table.scale(1.0, 1.25)
    for (row, col), cell in table.get_celld().items():
        cell.set_edgecolor("0.8")
        if row == 0:
            cell.set_facecolor("0.9")
            cell.set_text_props(fontweight="bold")
        elif row % 2 == 0:
            cell.set_facecolor("#f6f6f6")
    out = Path(out)
    _savefig(fig, out)
    return out


# --------------------------------------------------------------------------- all of it
def plot_file(path: str | Path, out_dir: str | Path | None = None,
              modes: int | None = None, animate: bool = False) -> list[Path]:
    """Every picture of ``path`` into ``out_dir``; the files written. ``animate``: also
    ``mode_NN.gif`` (and ``.mp4`` with ffmpeg) per mode (:mod:`pipeline.apps.animate`)."""
    path = Path(path)
    out_dir = Path(out_dir) if out_dir else path.with_name(f"{path.stem}_plots")
    data = read_stored_mesh(path)
    if data.has_statespace:
        load_model(path)  # refuse a bad model (FileFormatError) before writing any picture
    out_dir.mkdir(parents=True, exist_ok=True)
    n = data.frequencies_hz.size if modes is None else min(modes, data.frequencies_hz.size)
    surface = boundary_surface(data.points, data.cells)
    written = []
    for k in range(n):
        written.append(plot_mode(data, k, out_dir / f"mode_{k + 1:02d}.png", surface))
        log.info("wrote %s", written[-1])
    if n > 1:
        coarse = boundary_surface(data.points, data.cells, subdivide_below=0)
        written.append(plot_modes_overview(data, out_dir / "modes.png", coarse,
                                           max_modes=min(n, 12)))
    written.append(plot_frequency_table(data, out_dir / "frequencies.png"))
    written.append(write_frequency_csv(data, out_dir / "frequencies.csv"))
    if data.has_statespace:
        written.append(plot_bode(path, out_dir / "bode.png"))
        written.append(plot_step(path, out_dir / "step.png"))
        from pipeline.apps.stress_plots import plot_static_von_mises  # needs stress modes

        written.extend(plot_static_von_mises(path, out_dir))
    rotation = read_rotation(path)
    if rotation is not None:
        from pipeline.apps.campbell import plot_campbell

        written.append(plot_campbell(rotation, out_dir / "campbell.png"))
    if animate:
        from pipeline.apps.animate import animate_mode

        coarse = boundary_surface(data.points, data.cells, subdivide_below=0)
        for k in range(n):
            written += animate_mode(data, k, out_dir / f"mode_{k + 1:02d}.gif", coarse)
    return written


def cmd_plot(args: argparse.Namespace) -> int:
    for p in plot_file(args.file, args.output_dir, args.modes, animate=args.animate):
        print(p)
    return 0


def add_plot_parser(subparsers) -> argparse.ArgumentParser:
    """``plot FILE.h5 [-o DIR] [--modes N]`` on the CLI's subparsers."""
    p = subparsers.add_parser("plot", help="PNG pictures of the modes, frequency table, Bode "
                              "and step response of an HDF5 file",
                              description="Write a PNG per mode, an overview, a frequency table "
                              "(PNG and CSV) and, where the file holds a reduced model, its Bode "
                              "magnitude and phase and step response; with --animate a GIF "
                              "per mode. Reads only the HDF5 file.")
    p.add_argument("file", help="HDF5 result of 'python -m pipeline run'")
    p.add_argument("-o", "--output-dir", help="folder for the pictures (default: "
                   "<FILE stem>_plots next to the file)")
    p.add_argument("--modes", type=int, default=None, metavar="N",
                   help="draw only the first N modes (default: all)")
    p.add_argument("--animate", action="store_true",
                   help="also write mode_NN.gif per mode, the shape moving (and mode_NN.mp4 "
                   "where ffmpeg is installed)")
    p.set_defaults(func=cmd_plot)
    return p
