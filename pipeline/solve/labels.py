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
"""

from __future__ import annotations

import logging

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


def _no_sum(a: np.ndarray) -> np.ndarray:
    return a


def effective_mass_shares(node_points: np.ndarray, shapes: np.ndarray,
                          weights: np.ndarray | None = None, nodes: np.ndarray | None = None,
                          reduce_sum=_no_sum) -> tuple[np.ndarray, list[str]]:
    """Effective mass share (6, n_m) of every mode in the three translations and the
    three rotations along / about the principal axes (see the module docstring), and the
    axis names (3,). shapes: (n_nodes, 3, n_m); weights: node masses or volumes (n,).

    ``nodes`` (p,): ``shapes`` (p, 3, n_m) holds only these nodes (a share of the body's
    DOFs, zero in the others), and ``reduce_sum`` adds such partial sums over the shares
    (the distributed path's MPI_Allreduce); every sum over nodes is one of them."""
    x = np.asarray(node_points, dtype=float)
    w = np.ones(x.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    c, axes, names = principal_frame(x, w)
    sel = slice(None) if nodes is None else nodes
    rigid = [np.broadcast_to(axes[:, k], x.shape) for k in range(3)]
    rigid += [np.cross(axes[:, k], x - c) for k in range(3)]
    phi2 = reduce_sum(np.einsum("i,ijm,ijm->m", w[sel], shapes, shapes))
    shares = np.empty((6, shapes.shape[2]))
    for d, r in enumerate(rigid):
        gamma = reduce_sum(np.einsum("i,ij,ijm->m", w[sel], r[sel], shapes))
        r2 = float(np.einsum("i,ij,ij->", w, r, r))
        shares[d] = gamma ** 2 / np.where(r2 * phi2 > 0, r2 * phi2, 1.0)
    return shares, names


def describe_modes(node_points, shapes, n_rigid: int = 0, weights=None, nodes=None,
                   reduce_sum=_no_sum) -> list[str]:
    """Labels of a body that is not a beam (see the module docstring; ``nodes``,
    ``reduce_sum``: as :func:`effective_mass_shares`)."""
    shares, names = effective_mass_shares(node_points, shapes, weights, nodes, reduce_sum)
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
                slender_ratio: float = 3.0, nodes: np.ndarray | None = None,
                reduce_sum=_no_sum) -> list[str]:
    """A label per mode from its dominant motion: ``bending_<axis>_<k>`` (bending about
    that axis), ``torsion_<k>``, ``axial_<k>``, or ``rigid_<k>`` for the first n_rigid.
    A body whose longest dimension is less than ``slender_ratio`` times the next one is
    not beam-like: its modes are named by :func:`describe_modes`.

    The body is cut into slices along its longest dimension (the beam axis a); in each
    slice the weighted mean displacement and the mean rotation about a are taken; the
    family with the largest kinetic-energy-like sum wins. shapes: (n_nodes, 3, n_m).
    ``nodes`` (p,), ``reduce_sum``: shapes (p, 3, n_m) of these nodes only, one share of
    the body's DOFs, as :func:`effective_mass_shares`.
    """
    x = np.asarray(node_points, dtype=float)
    w = np.ones(x.shape[0]) if node_weights is None else np.asarray(node_weights, dtype=float)
    extent = x.max(axis=0) - x.min(axis=0)
    a = int(np.argmax(extent))
    if extent[a] < slender_ratio * np.sort(extent)[1]:
        # not beam-like: bending/torsion/axial would be guesses; the rigid motion instead
        return describe_modes(x, shapes, n_rigid, w, nodes, reduce_sum)
    others = [c for c in range(3) if c != a]
    edges = np.linspace(x[:, a].min(), x[:, a].max(), n_slices + 1)
    slice_of = np.clip(np.searchsorted(edges, x[:, a], side="right") - 1, 0, n_slices - 1)
    # per-slice weighted sums for all modes at once: P (n_slices x n_nodes) holds w
    P = sp.csr_matrix((w, (slice_of, np.arange(x.shape[0]))), shape=(n_slices, x.shape[0]))
    ms = np.asarray(P.sum(axis=1)).ravel()
    filled = ms > 0
    c = (P @ x)[filled] / ms[filled, None]  # slice centroids
    P = P[filled]
    ms = ms[filled]
    row = np.cumsum(filled) - 1  # slice index -> its row among the filled slices
    r = x - c[row[slice_of]]  # position relative to the centroid of the node's slice
    r1, r2 = r[:, others[0]], r[:, others[1]]
    polar = P @ (r1**2 + r2**2)
    if nodes is not None:  # the shapes of these nodes only
        P, r1, r2 = P[:, nodes], r1[nodes], r2[nodes]
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
