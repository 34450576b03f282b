"""Mode labels: the dominant motion of every mode.

A beam-like body (longest side >= ``slender_ratio`` x the next) gets beam names
(``bending_z_1``, ``torsion_1``, ``axial_1``). Any other body (a bracket) gets the rigid
motion each mode resembles most: ``translation_<a>_<k>`` or ``rotation_<a>_<k>`` about
the body's principal axis ``a`` through its centre of mass (``x``, ``y``, ``z`` when that
principal axis is within 15 degrees of a global axis, else ``p1``..``p3`` in the order of
increasing principal moment), ``internal_<k>`` when no rigid motion holds even
:data:`INTERNAL_SHARE` of the mode. "Resembles" is measured by the effective mass share
(:func:`effective_mass_shares`): with the node masses m_i (proportional to the node
weights), a rigid motion r (n_nodes, 3) and the mode phi (n_nodes, 3),

    share = (sum_i m_i phi_i . r_i)^2 / ((sum_i m_i r_i . r_i) (sum_i m_i phi_i . phi_i)),

the fraction of the body's mass (translation) or inertia (rotation) the mode carries in
that direction, in [0, 1]; summed over all modes of the body it is 1.

Pure array code (no finite-element objects): the caller passes the node coordinates
(n_nodes, 3) m, the mode shapes on every node (n_nodes, 3, n_m) and optional positive
node weights (n_nodes,), e.g. the nodal volume shares of
:func:`pipeline.fe.body.node_volume_weights`.

Two kinds of sums make a label: sums over the body's points of its geometry alone
(extent, centre of mass, principal axes, the slices' masses, centroids and polar
moments, sum_i m_i r_i . r_i), gathered in a :class:`LabelFrame` made once from every
point (:func:`label_frame`), and sums over the points of the mode shapes (the slices'
mean displacements and rotations, sum_i m_i phi_i . r_i, sum_i m_i phi_i . phi_i). The
second kind may be split over shares of the points: the distributed path passes each
rank's own points, the frame rank 0 made from the whole mesh, and ``reduce_sum`` (its
MPI_Allreduce) adds the shares' sums, so that no other rank holds every point. One
process is the case of one share holding every point (``reduce_sum`` the identity):
the same operations in the same order as a frame-less evaluation.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

log = logging.getLogger(__name__)

AXES = "xyz"
#: below this effective mass share in every rigid direction a mode is ``internal``
INTERNAL_SHARE = 0.01
#: a principal axis within this angle of a global axis takes its name (degrees)
AXIS_NAME_DEG = 15.0
#: the six rigid directions of :func:`effective_mass_shares`, in its column order
DIRECTIONS = ("translation", "translation", "translation", "rotation", "rotation", "rotation")


def principal_frame(node_points: np.ndarray, weights: np.ndarray):
    """(centre of mass (3,), principal axes (3, 3) as columns by increasing moment, axis
    names (3,)) of the point masses ``weights`` at ``node_points`` (n, 3)."""
    x = np.asarray(node_points, dtype=float)
    w = np.asarray(weights, dtype=float)
    c = w @ x / w.sum()
    r = x - c
    inertia = np.eye(3) * (w @ (r * r).sum(axis=1)) - (r * w[:, None]).T @ r
    _, axes = np.linalg.eigh(inertia)
    names = []
    for k in range(3):
        g = int(np.argmax(np.abs(axes[:, k])))
        aligned = abs(axes[g, k]) >= np.cos(np.radians(AXIS_NAME_DEG))
        names.append(AXES[g] if aligned and AXES[g] not in names else f"p{k + 1}")
    return c, axes, names


@dataclass(frozen=True)
class LabelFrame:
    """The geometric sums of the labels (module docstring), made from every point of the
    body by :func:`label_frame`; a few numbers per slice, whatever the mesh size.

    beam: the body is beam-like (sliced along ``axis``) or not (principal frame).
    Principal frame (every body): ``center`` (3,) m, ``axes`` (3, 3) columns, ``names``
    (3,), ``rigid_norms`` (6,) sum_i m_i r_i . r_i of the six rigid motions of
    :func:`effective_mass_shares`. Slices (a beam): ``axis`` the beam axis, ``edges``
    (n_slices + 1,) m along it, ``slice_row`` (n_slices,) the row of each slice among
    the non-empty ones, ``slice_mass`` (n_filled,) and ``centroids`` (n_filled, 3) m,
    ``polar`` (n_filled,) sum m_i (r1^2 + r2^2) about each slice's centroid."""

    beam: bool
    center: np.ndarray | None = None
    axes: np.ndarray | None = None
    names: tuple[str, ...] = ()
    rigid_norms: np.ndarray | None = None
    axis: int = 0
    edges: np.ndarray | None = None
    slice_row: np.ndarray | None = None
    filled: np.ndarray | None = None
    slice_mass: np.ndarray | None = None
    centroids: np.ndarray | None = None
    polar: np.ndarray | None = None

    @property
    def others(self) -> list[int]:
        """The two axes across the beam axis."""
        return [c for c in range(3) if c != self.axis]

    def rigid_fields(self, x: np.ndarray) -> list[np.ndarray]:
        """The six rigid motions (n, 3) at the points ``x`` (n, 3): translations along
        and rotations about the principal axes through the centre of mass."""
        fields = [np.broadcast_to(self.axes[:, k], x.shape) for k in range(3)]
        return fields + [np.cross(self.axes[:, k], x - self.center) for k in range(3)]

    def slices(self, x: np.ndarray, w: np.ndarray):
        """(P (n_filled, n) CSR holding the weights ``w`` of the points ``x`` (n, 3) in
        their slices, r1, r2 (n,): their offsets across the beam axis from their slice's
        centroid)."""
        n_slices = self.edges.size - 1
        slice_of = np.clip(np.searchsorted(self.edges, x[:, self.axis], side="right") - 1,
                           0, n_slices - 1)
        P = sp.csr_matrix((w, (slice_of, np.arange(x.shape[0]))),
                          shape=(n_slices, x.shape[0]))[self.filled]
        r = x - self.centroids[self.slice_row[slice_of]]
        return P, r[:, self.others[0]], r[:, self.others[1]]


def label_frame(node_points: np.ndarray, node_weights: np.ndarray | None = None,
                n_slices: int = 24, slender_ratio: float = 3.0) -> LabelFrame:
    """The :class:`LabelFrame` of a body with every point at ``node_points`` (n, 3) m,
    weights ``node_weights`` (n,) (None: ones); beam-like when its longest extent is at
    least ``slender_ratio`` times the next (then ``n_slices`` slices along it)."""
    x = np.asarray(node_points, dtype=float)
    w = np.ones(x.shape[0]) if node_weights is None else np.asarray(node_weights, dtype=float)
    extent = x.max(axis=0) - x.min(axis=0)
    a = int(np.argmax(extent))
    if extent[a] < slender_ratio * np.sort(extent)[1]:
        return _principal_label_frame(x, w)
    edges = np.linspace(x[:, a].min(), x[:, a].max(), n_slices + 1)
    slice_of = np.clip(np.searchsorted(edges, x[:, a], side="right") - 1, 0, n_slices - 1)
    # per-slice weighted sums: P (n_slices x n_nodes) holds w
    P = sp.csr_matrix((w, (slice_of, np.arange(x.shape[0]))), shape=(n_slices, x.shape[0]))
    ms = np.asarray(P.sum(axis=1)).ravel()
    filled = ms > 0
    c = (P @ x)[filled] / ms[filled, None]  # slice centroids
    row = np.cumsum(filled) - 1  # slice index -> its row among the filled slices
    frame = LabelFrame(True, axis=a, edges=edges, slice_row=row, filled=filled,
                       slice_mass=ms[filled], centroids=c)
    P, r1, r2 = frame.slices(x, w)
    return dataclasses.replace(frame, polar=P @ (r1**2 + r2**2))


def _principal_label_frame(x: np.ndarray, w: np.ndarray) -> LabelFrame:
    """The :class:`LabelFrame` of a body that is not beam-like (points ``x`` (n, 3) m,
    weights ``w`` (n,))."""
    c, axes, names = principal_frame(x, w)
    frame = LabelFrame(False, c, axes, tuple(names))
    norms = [float(np.einsum("i,ij,ij->", w, r, r)) for r in frame.rigid_fields(x)]
    return dataclasses.replace(frame, rigid_norms=np.array(norms))


def _no_sum(a: np.ndarray) -> np.ndarray:
    return a


def effective_mass_shares(node_points: np.ndarray, shapes: np.ndarray,
                          weights: np.ndarray | None = None, frame: LabelFrame | None = None,
                          reduce_sum=_no_sum) -> tuple[np.ndarray, list[str]]:
    """Effective mass share (6, n_m) of every mode in the three translations and the
    three rotations along / about the principal axes (see the module docstring), and the
    axis names (3,). shapes: (n_nodes, 3, n_m); weights: node masses or volumes (n,).

    ``frame``: the body's :class:`LabelFrame` (None: made from these points, all of the
    body); then ``node_points``, ``weights`` and ``shapes`` may be one share of the
    body's points (zero in the DOFs others hold), and ``reduce_sum`` adds the shares'
    sums (the distributed path's MPI_Allreduce)."""
    x = np.asarray(node_points, dtype=float)
    w = np.ones(x.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    if frame is None:
        frame = _principal_label_frame(x, w)
    phi2 = reduce_sum(np.einsum("i,ijm,ijm->m", w, shapes, shapes))
    shares = np.empty((6, shapes.shape[2]))
    for d, r in enumerate(frame.rigid_fields(x)):
        gamma = reduce_sum(np.einsum("i,ij,ijm->m", w, r, shapes))
        r2 = frame.rigid_norms[d]
        shares[d] = gamma ** 2 / np.where(r2 * phi2 > 0, r2 * phi2, 1.0)
    return shares, list(frame.names)


def describe_modes(node_points, shapes, n_rigid: int = 0, weights=None,
                   frame: LabelFrame | None = None, reduce_sum=_no_sum) -> list[str]:
    """Labels of a body that is not a beam (see the module docstring; ``frame``,
    ``reduce_sum``: as :func:`effective_mass_shares`)."""
    shares, names = effective_mass_shares(node_points, shapes, weights, frame, reduce_sum)
    labels, counts = [], {}
    for k in range(shapes.shape[2]):
        if k < n_rigid:
            labels.append(f"rigid_{k + 1}")
            continue
        d = int(np.argmax(shares[:, k]))
        name = (f"{DIRECTIONS[d]}_{names[d % 3]}" if shares[d, k] >= INTERNAL_SHARE
                else "internal")
        counts[name] = counts.get(name, 0) + 1
        labels.append(f"{name}_{counts[name]}")
        log.info("mode %d %s: effective mass share %.0f %% (%s)", k + 1, labels[-1],
                 100 * shares[d, k], ", ".join(
                     f"{DIRECTIONS[e][0].upper()}{names[e % 3]} {100 * shares[e, k]:.0f} %"
                     for e in range(6)))
    return labels


def label_modes(node_points: np.ndarray, shapes: np.ndarray, n_rigid: int,
                node_weights: np.ndarray | None = None, n_slices: int = 24,
                slender_ratio: float = 3.0, frame: LabelFrame | None = None,
                reduce_sum=_no_sum) -> list[str]:
    """A label per mode from its dominant motion: ``bending_<axis>_<k>`` (bending about
    that axis), ``torsion_<k>``, ``axial_<k>``, or ``rigid_<k>`` for the first n_rigid.
    A body whose longest dimension is less than ``slender_ratio`` times the next one is
    not beam-like: its modes are named by :func:`describe_modes`.

    The body is cut into slices along its longest dimension (the beam axis a); in each
    slice the weighted mean displacement and the mean rotation about a are taken; the
    family with the largest kinetic-energy-like sum wins. shapes: (n_nodes, 3, n_m).
    ``frame``: the body's :class:`LabelFrame` (None: :func:`label_frame` of these points,
    all of the body, with ``n_slices`` and ``slender_ratio``); with a frame the points,
    weights and shapes may be one share of the body's points and ``reduce_sum`` adds the
    shares' sums, as :func:`effective_mass_shares`.
    """
    x = np.asarray(node_points, dtype=float)
    w = np.ones(x.shape[0]) if node_weights is None else np.asarray(node_weights, dtype=float)
    if frame is None:
        frame = label_frame(x, w, n_slices, slender_ratio)
    if not frame.beam:
        # not beam-like: bending/torsion/axial would be guesses; the rigid motion instead
        return describe_modes(x, shapes, n_rigid, w, frame, reduce_sum)
    a, others = frame.axis, frame.others
    ms, polar = frame.slice_mass, frame.polar
    P, r1, r2 = frame.slices(x, w)
    ubar = reduce_sum(np.stack([P @ shapes[:, j, :] for j in range(3)], axis=1)) \
        / ms[:, None, None]
    moment = reduce_sum(P @ (r1[:, None] * shapes[:, others[1], :]
                             - r2[:, None] * shapes[:, others[0], :]))
    theta = np.divide(moment, polar[:, None], out=np.zeros_like(moment),
                      where=polar[:, None] > 0)
    energies = np.stack([(ms[:, None] * ubar[:, a] ** 2).sum(0),
                         (ms[:, None] * ubar[:, others[0]] ** 2).sum(0),
                         (ms[:, None] * ubar[:, others[1]] ** 2).sum(0),
                         (polar[:, None] * theta**2).sum(0)])  # (4, n_m)
    labels, counts = [], {}
    for k in range(shapes.shape[2]):
        if k < n_rigid:
            labels.append(f"rigid_{k + 1}")
            continue
        energy = energies[:, k]  # axial, transverse others[0], transverse others[1], torsion
        family = int(np.argmax(energy))
        if family == 0:
            name = "axial"
        elif family == 3:
            name = "torsion"
        else:  # displacement along others[0] bends about others[1], and vice versa
            about = others[1] if family == 1 else others[0]
            name = f"bending_{AXES[about]}"
        counts[name] = counts.get(name, 0) + 1
        labels.append(f"{name}_{counts[name]}")
    return labels
