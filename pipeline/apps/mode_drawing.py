"""How a mode shape is drawn, shared by the pictures (:mod:`pipeline.apps.plots`), the
animations (:mod:`pipeline.apps.animate`) and the stress pictures
(:mod:`pipeline.apps.stress_plots`): the body's boundary surface and outline, the
deformed shape on 3D axes or, for a slender body, a side / end-on view, its colour bar
and its title.

Only matplotlib's object API is used (imported inside the drawing functions), so the
geometry (:func:`boundary_surface`, :func:`is_slender`) needs numpy alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.apps.views import is_twist, view_for_mode
from pipeline.store.read import StoredMesh

__all__ = ["DEFORMATION_FRACTION", "FEATURE_ANGLE_DEG", "SUBDIVIDE_BELOW", "CMAP", "DPI",
           "SLENDER_RATIO", "Surface", "boundary_surface", "is_slender", "draw_mode",
           "draw_mode_2d", "colour_bar", "mode_title"]

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


def colour_bar(fig, mappable_norm=None, ax=None, cax=None, shrink=0.7) -> None:
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


def draw_mode_2d(ax, data: StoredMesh, surface: Surface, mode: int, *, colorbar_fig=None,
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
        colour_bar(colorbar_fig, ax=ax, shrink=0.8)
    return end_on


def draw_mode(ax, data: StoredMesh, surface: Surface, mode: int, *, light=True, outline=True,
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
        colour_bar(colorbar_fig, norm, ax=ax, shrink=0.6)


def _fmt_hz(f: float) -> str:
    return f"{f:.1f}" if abs(f) >= 100 else f"{f:.4g}"


def mode_title(data: StoredMesh, mode: int) -> str:
    label = data.labels[mode] if mode < len(data.labels) else ""
    return f"mode {mode + 1}: {_fmt_hz(data.frequencies_hz[mode])} Hz" + (
        f"  ({label})" if label else "")
