"""Rigid-body properties of the discretised body, and mode labels.

Everything here is computed from the FE mass matrix and the node positions, so it is
an independent check of the mesh and the assembly against the analytic body.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


def skew(v: np.ndarray) -> np.ndarray:
    """(3, 3) matrix with skew(v) @ w = v x w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rigid_body_modes(node_points: np.ndarray, point=(0.0, 0.0, 0.0)) -> np.ndarray:
    """R_P (3 n_nodes x 6): nodal displacements for a unit twist [v; omega] at ``point``.

    Node j at x_j moves by v + omega x (x_j - P), i.e. its rows are [I_3, -skew(x_j - P)].
    """
    r = np.asarray(node_points, dtype=float) - np.asarray(point, dtype=float)
    n = r.shape[0]
    R = np.zeros((n, 3, 6))
    R[:, [0, 1, 2], [0, 1, 2]] = 1.0
    # omega x r = [w_y r_z - w_z r_y, w_z r_x - w_x r_z, w_x r_y - w_y r_x]
    R[:, 0, 4], R[:, 0, 5] = r[:, 2], -r[:, 1]
    R[:, 1, 3], R[:, 1, 5] = -r[:, 2], r[:, 0]
    R[:, 2, 3], R[:, 2, 4] = r[:, 1], -r[:, 0]
    return R.reshape(3 * n, 6)


@dataclass(frozen=True)
class BodyProperties:
    """mass (kg), center_of_mass (3,) m, inertia (3, 3) kg m^2 about the centre of mass,
    rigid_mass (6, 6): R_O^T M R_O at the origin (kg, kg m, kg m^2 blocks)."""

    mass: float
    center_of_mass: np.ndarray
    inertia: np.ndarray
    rigid_mass: np.ndarray


def body_properties(M: sp.spmatrix, node_points: np.ndarray) -> BodyProperties:
    """Mass, centre of mass and inertia from the full (unconstrained) mass matrix M."""
    R = rigid_body_modes(node_points)
    D = R.T @ (M @ R)
    D = 0.5 * (D + D.T)
    m = D[0, 0]
    # translational-rotational block: R_t^T M R_r = -m skew(G)
    S = -D[0:3, 3:6] / m
    com = np.array([S[2, 1], S[0, 2], S[1, 0]])
    I_O = D[3:6, 3:6]
    I_G = I_O - m * (com @ com * np.eye(3) - np.outer(com, com))
    return BodyProperties(float(m), com, 0.5 * (I_G + I_G.T), D)


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
    import scipy.sparse as sp

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


def node_volume_weights(space) -> np.ndarray:
    """(n_nodes,) m^3: each element's volume shared equally by its nodes (positive weights)."""
    v = space.body.vertices
    t = space.body.tetrahedra
    a = v[t[:, 0]]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(v[t[:, 1]] - a, v[t[:, 2]] - a),
                           v[t[:, 3]] - a)) / 6.0
    en = space.element_nodes
    return np.bincount(en.ravel(), weights=np.repeat(vol / en.shape[1], en.shape[1]),
                       minlength=space.n_nodes)
