"""Von Mises stress drawn on the body: ``static_von_mises_<input>.png`` (``plot``) and the
per-point peak of a simulation (``simulate``).

The static field per unit input is :func:`pipeline.apps.stress_fields.static_von_mises`.
The boundary surface is coloured by the mean of its nodes' values, undeformed, with the hot
spot marked.
Only matplotlib's object API is used (no pyplot).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from pipeline._util.atomic import atomic_path
from pipeline.apps.mode_drawing import boundary_surface
from pipeline.apps.stress_fields import static_von_mises
from pipeline.store.read import StoredMesh, read_stored_mesh

log = logging.getLogger(__name__)

__all__ = ["plot_von_mises", "plot_static_von_mises"]


def plot_von_mises(mesh: StoredMesh, values: np.ndarray, title: str, out: str | Path,
                   unit_note: str = "Pa") -> Path:
    """The boundary surface of ``mesh`` coloured by ``values`` (n_points,), hot spot marked."""
    import matplotlib
    from matplotlib import cm, colors
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    surface = boundary_surface(mesh.points, mesh.cells)
    p = mesh.points
    norm = colors.Normalize(0.0, float(values.max()) / 1e6 or 1.0)
    cmap = matplotlib.colormaps["inferno"]
    rgba = cmap(norm(values[surface.drawn].mean(axis=1) / 1e6))
    fig = Figure(figsize=(9.0, 6.0), dpi=110, facecolor="white")
    ax = fig.add_subplot(projection="3d", computed_zorder=False)
    ax.add_collection3d(Poly3DCollection(p[surface.drawn], facecolors=rgba, edgecolors="none"))
    hot = int(np.argmax(values))
    ax.scatter(*p[hot], s=60, c="cyan", edgecolors="black", depthshade=False, zorder=10)
    lo, hi = p.min(axis=0), p.max(axis=0)
    span = np.maximum(hi - lo, 1e-3 * (hi - lo).max())
    for set_lim, c, s in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), 0.5 * (lo + hi), span):
        set_lim(c - s / 2, c + s / 2)
    ax.set_box_aspect(tuple(np.maximum(span / span.max(), 0.05)), zoom=1.1)
    ax.view_init(elev=24, azim=-58)
    ax.set_axis_off()
    bar = fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, shrink=0.6, pad=0.02)
    bar.set_label(f"von Mises [MPa{unit_note[2:]}]")
    fig.suptitle(title, fontsize=12, fontweight="bold")
    fig.text(0.5, 0.03, f"hot spot (cyan) at ({p[hot, 0]:.4g}, {p[hot, 1]:.4g}, "
             f"{p[hot, 2]:.4g}) m: {values[hot] / 1e6:.4g} MPa{unit_note[2:]}; undeformed body",
             ha="center", fontsize=9, color="0.25")
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png")
    return out


def plot_static_von_mises(path: str | Path, out_dir: str | Path) -> list[Path]:
    """``static_von_mises_<input>.png`` per input of a file with stress modes."""
    fields = static_von_mises(path)
    if not fields:
        return []
    mesh = read_stored_mesh(path)
    written = []
    for name, vm in fields.items():
        written.append(plot_von_mises(mesh, vm, f"{mesh.name}: static von Mises stress, "
                                      f"1 unit of {name}", Path(out_dir) /
                                      f"static_von_mises_{name}.png", "Pa per unit input"))
        log.info("wrote %s", written[-1])
    return written
