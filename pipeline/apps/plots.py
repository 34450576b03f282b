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
  Mises stress per unit input on the body (:mod:`pipeline.apps.stress_plots`).

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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline._util.atomic import atomic_path
from pipeline.apps.response_plots import plot_bode, plot_step, save_figure
from pipeline.apps.views import is_twist, view_for_mode
from pipeline.store.read import StoredMesh, read_stored_mesh

log = logging.getLogger(__name__)

__all__ = ["boundary_surface", "plot_mode", "plot_modes_overview",
           "plot_frequency_table", "plot_bode", "plot_step", "plot_file", "add_plot_parser"]

#: Largest deformation drawn, as a fraction of the body's largest dimension.
DEFORMATION_FRACTION = 0.12
#: Feature edges: boundary edges whose two faces meet at more than this angle (degrees).
FEATURE_ANGLE_DEG = 40.0
#: Subdivide quadratic faces (4 flat triangles each) while the surface has fewer faces.
SUBDIVIDE_BELOW = 6000
CMAP = "turbo"
DPI = 130

# faces of a tetrahedron (local corner indices; the fourth corner is opposite)
_TET_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
_TET_OPPOSITE = np.array([0, 1, 2, 3])
# local node of the midpoint of corner edge (i, j) in meshio's tetra10 order
_TET10_EDGE = {(0, 1): 4, (1, 2): 5, (0, 2): 6, (0, 3): 7, (1, 3): 8, (2, 3): 9}


# --------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class Surface:
    """The boundary of a tetrahedral mesh, for drawing.

    triangles: (n_f, 3) corner node indices, outward oriented.
    drawn: (n_d, 3) node indices of the triangles to draw (the corner triangles, or
        four per corner triangle through the edge midpoints of quadratic cells).
    feature_edges: (n_e, k) node chains of the outline (k = 2, or 3 through the
        midpoint for quadratic cells).
    """

    triangles: np.ndarray
    drawn: np.ndarray
    feature_edges: np.ndarray


def boundary_surface(points: np.ndarray, cells: np.ndarray,
                     feature_angle_deg: float = FEATURE_ANGLE_DEG,
                     subdivide_below: int = SUBDIVIDE_BELOW) -> Surface:
    """Outward boundary triangles, what to draw, and the feature edges."""
    corners = cells[:, :4]
    faces = corners[:, _TET_FACES].reshape(-1, 3)                      # (4 n_t, 3)
    opposite = corners[:, _TET_OPPOSITE].reshape(-1)
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    outer = first[counts == 1]
    tri = faces[outer].copy()
    # orient outward: the normal points away from the opposite corner
    a, b, c = (points[tri[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    inward = np.einsum("ij,ij->i", normal, points[opposite[outer]] - a) > 0
    tri[inward] = tri[inward][:, [0, 2, 1]]

    quadratic = cells.shape[1] == 10
    mid = None
    if quadratic:
        table = np.zeros((4, 4), dtype=np.int64)
        for (p, q), node in _TET10_EDGE.items():
            table[p, q] = node
        elem = outer // 4
        # midpoint node of each face edge (ab, bc, ca), looked up in the element
        mid = np.empty((tri.shape[0], 3), dtype=np.int64)
        cell_rows = cells[elem]
        for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
            ni, nj = tri[:, i], tri[:, j]
            li = np.argmax(cell_rows[:, :4] == ni[:, None], axis=1)
            lj = np.argmax(cell_rows[:, :4] == nj[:, None], axis=1)
            lo, hi = np.minimum(li, lj), np.maximum(li, lj)
            mid[:, k] = cell_rows[np.arange(len(elem)), table[lo, hi]]
    if quadratic and tri.shape[0] < subdivide_below:
        ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
        drawn = np.concatenate([np.stack([tri[:, 0], ab, ca], 1), np.stack([ab, tri[:, 1], bc], 1),
                                np.stack([ca, bc, tri[:, 2]], 1), np.stack([ab, bc, ca], 1)])
    else:
        drawn = tri

    # feature edges: where the outward normals of the two faces differ by more than the angle
    n = normal * np.where(inward, -1.0, 1.0)[:, None]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    owner = np.tile(np.arange(tri.shape[0]), 3)
    emid = mid.T.reshape(-1) if mid is not None else None
    ekey = np.sort(edges, axis=1)
    order = np.lexsort((ekey[:, 1], ekey[:, 0]))
    ekey, owner, edges = ekey[order], owner[order], edges[order]
    if emid is not None:
        emid = emid[order]
    same = np.all(ekey[1:] == ekey[:-1], axis=1)
    pair = np.flatnonzero(same)                       # edge i and i+1 are one edge
    cos = np.einsum("ij,ij->i", n[owner[pair]], n[owner[pair + 1]])
    sharp = pair[cos < np.cos(np.radians(feature_angle_deg))]
    lonely = np.ones(len(ekey), dtype=bool)
    lonely[pair] = False
    lonely[pair + 1] = False                          # an open edge (should not happen)
    pick = np.concatenate([sharp, np.flatnonzero(lonely)])
    if emid is not None:
        feature = np.stack([ekey[pick, 0], emid[pick], ekey[pick, 1]], axis=1)
    else:
        feature = ekey[pick]
    return Surface(tri, drawn, feature)


def _deformation_scale(points: np.ndarray, u: np.ndarray) -> float:
    extent = float(np.ptp(points, axis=0).max())
    peak = float(np.linalg.norm(u, axis=1).max())
    return DEFORMATION_FRACTION * extent / peak if peak > 0 else 0.0


# --------------------------------------------------------------------------- mode pictures
#: A body whose longest side exceeds this many times the next one is drawn as a side view.
SLENDER_RATIO = 8.0


def is_slender(points: np.ndarray) -> bool:
    """Long and thin: drawn as a 2D side view (a 3D view would show a line)."""
    e = np.sort(np.ptp(points, axis=0))[::-1]
    return bool(e[0] > SLENDER_RATIO * max(e[1], 1e-12))


def _side_axes(points: np.ndarray, u: np.ndarray) -> tuple[int, int, int]:
    """(long axis, the transverse axis the mode moves most along, the other one)."""
    long_axis = int(np.argmax(np.ptp(points, axis=0)))
    others = [i for i in range(3) if i != long_axis]
    motion = [float(np.abs(u[:, i]).max()) for i in others]
    trans = others[int(np.argmax(motion))] if max(motion) > 0 else others[0]
    depth = [i for i in others if i != trans][0]
    return long_axis, trans, depth


def _axis_triad(ax, lo: np.ndarray, span: np.ndarray) -> None:
    """x, y, z arrows (red, green, blue) at the low corner of a 3D view."""
    length = 0.22 * span.max()
    for k, (name, colour) in enumerate(zip("xyz", ("#c0392b", "#27ae60", "#2e5cb8"))):
        tip = np.zeros(3)
        tip[k] = length
        ax.quiver(*lo, *tip, color=colour, lw=1.4, arrow_length_ratio=0.25)
        ax.text(*(lo + 1.25 * tip), name, color=colour, fontsize=9, fontweight="bold")


def _colour_bar(fig, mappable_norm=None, ax=None, cax=None, shrink=0.7) -> None:
    """The colour bar of the mode pictures: |u| / max |u| from 0 to 1."""
    import matplotlib
    from matplotlib import cm, colors

    mappable = cm.ScalarMappable(norm=mappable_norm or colors.Normalize(0.0, 1.0),
                                 cmap=matplotlib.colormaps[CMAP])
    bar = fig.colorbar(mappable, ax=ax, cax=cax, shrink=shrink, pad=0.02)
    bar.set_label("|u| / max |u| [1]")


def _face_colours(mag: np.ndarray, drawn: np.ndarray):
    import matplotlib

    peak = mag.max() if mag.max() > 0 else 1.0
    return matplotlib.colormaps[CMAP](mag[drawn].mean(axis=1) / peak)


def _draw_mode_2d(ax, data: StoredMesh, surface: Surface, mode: int, *, colorbar_fig=None,
                  small=False, amplitude: float = 1.0) -> bool:
    """Side view of a slender body: long axis across, the mode's main transverse axis up;
    a twist (:func:`is_twist`) end-on instead, the cross-section axes across and up,
    drawn to scale, the deformation scaled to the section. Returns True when end-on.
    ``amplitude`` multiplies the drawn deformation (an animation frame)."""
    from matplotlib.collections import LineCollection, PolyCollection

    u = data.shapes[:, :, mode]
    label = data.labels[mode] if mode < len(data.labels) else ""
    end_on = is_twist(data.points, u, label)
    i, j, k = _side_axes(data.points, u)
    if end_on:
        i, j = sorted((j, k))
        k = int(np.argmax(np.ptp(data.points, axis=0)))
        scale = _deformation_scale(data.points[:, [i, j]], u[:, [i, j]])
    else:
        scale = _deformation_scale(data.points, u)
    full = data.points + scale * u
    moved = data.points + amplitude * scale * u
    mag = np.linalg.norm(u, axis=1)
    rgba = _face_colours(mag, surface.drawn)
    order = np.argsort(moved[surface.drawn][:, :, k].mean(axis=1))  # far faces first
    if end_on:  # only the end faces: the long sides, seen edge-on, would be streaks
        a, b, c = (data.points[surface.drawn[order, m]] for m in range(3))
        nrm = np.cross(b - a, c - a)
        along = np.abs(nrm[:, k]) > 0.7 * np.linalg.norm(nrm, axis=1)
        order = order[along]
    polys = moved[surface.drawn[order]][:, :, [i, j]]
    ax.add_collection(PolyCollection(polys, facecolors=rgba[order], edgecolors=rgba[order],
                                     linewidths=0.3))
    if surface.feature_edges.size:
        ax.add_collection(LineCollection(data.points[surface.feature_edges][:, :, [i, j]],
                                         colors="0.55", linewidths=0.8))
        ax.add_collection(LineCollection(moved[surface.feature_edges][:, :, [i, j]],
                                         colors="black", linewidths=0.4, alpha=0.8))
    # limits hold the deformation both ways (the same for every animation frame)
    both = np.vstack([data.points, full, 2 * data.points - full])[:, [i, j]]
    lo, hi = both.min(axis=0), both.max(axis=0)
    pad = 0.05 * (hi - lo) + 1e-12
    ax.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
    ax.set_ylim(lo[1] - (1 if end_on else 3) * pad[1], hi[1] + (1 if end_on else 3) * pad[1])
    if end_on:
        ax.set_aspect("equal")
    names = "xyz"
    ax.set_xlabel(f"{names[i]} [m]", fontsize=8 if small else 10)
    ax.set_ylabel(f"{names[j]} [m]", fontsize=8 if small else 10)
    ax.tick_params(labelsize=7 if small else 9)
    ax.grid(alpha=0.25)
    if colorbar_fig is not None:
        _colour_bar(colorbar_fig, ax=ax, shrink=0.8)
    return end_on


def _draw_mode(ax, data: StoredMesh, surface: Surface, mode: int, *, light=True, outline=True,
               colorbar_fig=None, amplitude: float = 1.0, triad: bool = True) -> None:
    """3D perspective view of mode ``mode`` from :func:`view_for_mode`, with an axis
    triad; ``amplitude`` multiplies the drawn deformation (an animation frame)."""
    import matplotlib
    from matplotlib import colors
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    u = data.shapes[:, :, mode]
    scale = _deformation_scale(data.points, u)
    full = data.points + scale * u
    moved = data.points + amplitude * scale * u
    mag = np.linalg.norm(u, axis=1)
    peak = mag.max() if mag.max() > 0 else 1.0
    norm = colors.Normalize(0.0, 1.0)
    cmap = matplotlib.colormaps[CMAP]
    face_value = mag[surface.drawn].mean(axis=1) / peak
    rgba = cmap(norm(face_value))
    if light:
        a, b, c = (moved[surface.drawn[:, i]] for i in range(3))
        nrm = np.cross(b - a, c - a)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True) + 1e-300
        to_light = np.array([-0.4, -0.5, 0.75])
        to_light /= np.linalg.norm(to_light)
        shade = 0.55 + 0.45 * np.abs(nrm @ to_light)
        rgba[:, :3] *= shade[:, None]
    poly = Poly3DCollection(moved[surface.drawn], facecolors=rgba, edgecolors="none",
                            linewidths=0.0, antialiased=False)
    ax.add_collection3d(poly)
    if outline and surface.feature_edges.size:
        undeformed = Line3DCollection(data.points[surface.feature_edges], colors="0.35",
                                      linewidths=0.7, linestyles="-", alpha=0.75)
        ax.add_collection3d(undeformed)
        deformed = Line3DCollection(moved[surface.feature_edges], colors="black",
                                    linewidths=0.5, alpha=0.9)
        ax.add_collection3d(deformed)
    both = np.vstack([data.points, full, 2 * data.points - full])
    lo, hi = both.min(axis=0), both.max(axis=0)
    span = np.maximum(hi - lo, 1e-3 * (hi - lo).max())
    centre = 0.5 * (lo + hi)
    ax.set_xlim(centre[0] - span[0] / 2, centre[0] + span[0] / 2)
    ax.set_ylim(centre[1] - span[1] / 2, centre[1] + span[1] / 2)
    ax.set_zlim(centre[2] - span[2] / 2, centre[2] + span[2] / 2)
    ax.set_box_aspect(tuple(np.maximum(span / span.max(), 0.02)), zoom=1.1)
    ax.set_proj_type("persp", focal_length=0.5)
    ax.view_init(*view_for_mode(u))
    ax.set_axis_off()
    if triad:
        _axis_triad(ax, centre - span / 2, span)
    if colorbar_fig is not None:
        _colour_bar(colorbar_fig, norm, ax=ax, shrink=0.6)


#: the drawing functions under public names (the animation draws its frames with them)
draw_mode, draw_mode_2d = _draw_mode, _draw_mode_2d


def _savefig(fig, out: Path) -> None:
    """Save ``fig`` to ``out`` through the atomic writer (the format from the suffix)."""
    save_figure(fig, out)


def _fmt_hz(f: float) -> str:
    return f"{f:.1f}" if abs(f) >= 100 else f"{f:.4g}"


def _title(data: StoredMesh, mode: int) -> str:
    label = data.labels[mode] if mode < len(data.labels) else ""
    return f"mode {mode + 1}: {_fmt_hz(data.frequencies_hz[mode])} Hz" + (
        f"  ({label})" if label else "")


mode_title = _title


def plot_mode(data: StoredMesh, mode: int, out: str | Path, surface: Surface | None = None) -> Path:
    """One mode (0-based index) as a PNG."""
    from matplotlib.figure import Figure

    surface = surface or boundary_surface(data.points, data.cells)
    slender = is_slender(data.points)
    fig = Figure(figsize=(9.0, 4.8) if slender else (8.0, 6.0), dpi=DPI, facecolor="white")
    if slender:
        ax = fig.add_subplot()
        fig.subplots_adjust(left=0.1, right=0.98, top=0.86, bottom=0.2)
        end_on = _draw_mode_2d(ax, data, surface, mode, colorbar_fig=fig)
        if end_on:
            fig.set_size_inches(6.4, 5.6)
            fig.subplots_adjust(left=0.16, right=0.95, top=0.88, bottom=0.16)
        view = ("end-on view along the long axis (a twist)" if end_on
                else "side view, not to scale across")
    else:
        ax = fig.add_subplot(projection="3d", computed_zorder=False)
        _draw_mode(ax, data, surface, mode, colorbar_fig=fig)
        view = "3D view from where the motion shows"
    fig.suptitle(_title(data, mode), fontsize=14, fontweight="bold", y=0.96)
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
            _draw_mode_2d(ax, data, surface, k, small=True)
        else:
            ax = fig.add_subplot(rows, cols, k + 1, projection="3d", computed_zorder=False)
            _draw_mode(ax, data, surface, k, outline=True, light=True, triad=k == 0)
        ax.set_title(_title(data, k), fontsize=9)
    fig.suptitle(f"{data.name}: {n} modes", fontsize=13, fontweight="bold")
    right = 1 - 0.9 / fig.get_size_inches()[0]  # room for the colour bar
    if slender:
        fig.tight_layout(rect=(0, 0, right, 0.95))
    else:
        fig.subplots_adjust(left=0, right=right, bottom=0, top=0.92, wspace=0, hspace=0.08)
    _colour_bar(fig, cax=fig.add_axes((right + 0.15 / fig.get_size_inches()[0], 0.15,
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
    out_dir.mkdir(parents=True, exist_ok=True)
    data = read_stored_mesh(path)
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
