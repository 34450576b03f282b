"""Rigid-body properties of the discretised body, and the nodal volume weights.

Everything here is computed from the FE mass matrix and the node positions, so it is
an independent check of the mesh and the assembly against the analytic body. (Mode
labels live in :mod:`pipeline.solve.labels`.)
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
    """Mass, centre of mass and inertia from the full (unconstrained) mass matrix M.

    M: (3 n, 3 n) kg, or the (n, n) node-level matrix N of a mass M = N (x) I_3 (the
    consistent mass of a vector Lagrange space): then R^T M R = sum_c R_c^T N R_c over
    the rows R_c of component c of the rigid-body modes.
    """
    R = rigid_body_modes(node_points)
    n = np.asarray(node_points).shape[0]
    if M.shape == (n, n) and n:
        D = sum(R[c::3].T @ (M @ R[c::3]) for c in range(3))
    else:
        D = R.T @ (M @ R)
    return properties_from_rigid_mass(D)


def properties_from_rigid_mass(D: np.ndarray) -> BodyProperties:
    """Mass, centre of mass and inertia about it from the (6, 6) rigid mass matrix D at
    the origin (R_O^T M R_O; a sum of such matrices for a body with added masses)."""
    D = 0.5 * (D + D.T)
    m = D[0, 0]
    # translational-rotational block: R_t^T M R_r = -m skew(G)
    S = -D[0:3, 3:6] / m
    com = np.array([S[2, 1], S[0, 2], S[1, 0]])
    I_O = D[3:6, 3:6]
    I_G = I_O - m * (com @ com * np.eye(3) - np.outer(com, com))
    return BodyProperties(float(m), com, 0.5 * (I_G + I_G.T), D)


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
