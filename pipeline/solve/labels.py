"""Mode labels: the dominant motion of every mode of a beam-like body.

Pure array code (no finite-element objects): the caller passes the node coordinates
(n_nodes, 3) m, the mode shapes on every node (n_nodes, 3, n_m) and optional positive
node weights (n_nodes,), e.g. the nodal volume shares of
:func:`pipeline.fe.body.node_volume_weights`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

AXES = "xyz"


def label_modes(node_points: np.ndarray, shapes: np.ndarray, n_rigid: int,
                node_weights: np.ndarray | None = None, n_slices: int = 24,
                slender_ratio: float = 3.0) -> list[str]:
    """A label per mode from its dominant motion: ``bending_<axis>_<k>`` (bending about
    that axis), ``torsion_<k>``, ``axial_<k>``, or ``rigid_<k>`` for the first n_rigid.
    A body whose longest dimension is less than ``slender_ratio`` times the next one is
    not beam-like: its elastic modes are labelled ``elastic_<k>``.

    The body is cut into slices along its longest dimension (the beam axis a); in each
    slice the weighted mean displacement and the mean rotation about a are taken; the
    family with the largest kinetic-energy-like sum wins. shapes: (n_nodes, 3, n_m).
    """
    x = np.asarray(node_points, dtype=float)
    w = np.ones(x.shape[0]) if node_weights is None else np.asarray(node_weights, dtype=float)
    extent = x.max(axis=0) - x.min(axis=0)
    a = int(np.argmax(extent))
    if extent[a] < slender_ratio * np.sort(extent)[1]:
        # not beam-like: bending/torsion/axial would be guesses; number the modes instead
        return [f"rigid_{k + 1}" if k < n_rigid else f"elastic_{k + 1 - n_rigid}"
                for k in range(shapes.shape[2])]
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
    ubar = np.stack([P @ shapes[:, j, :] for j in range(3)], axis=1) / ms[:, None, None]
    moment = P @ (r1[:, None] * shapes[:, others[1], :] - r2[:, None] * shapes[:, others[0], :])
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
