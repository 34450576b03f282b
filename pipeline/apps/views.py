"""Where to look from: the viewpoint of a mode picture, chosen per mode so that the
motion is visible (:mod:`pipeline.apps.plots`, :mod:`pipeline.apps.animate`).

Inputs: node coordinates ``points`` (n, 3) m and one mode shape ``u`` (n, 3) (any
scale: only directions matter).
"""

from __future__ import annotations

import numpy as np


def is_twist(points: np.ndarray, u: np.ndarray, label: str = "") -> bool:
    """A mode that turns the cross-sections of a slender body about its long axis
    (torsion): seen from the side it is a fan, so it is drawn end-on. From the label
    when the file has one, else: the rotation about the long axis through the section
    centroid explains more than half of the transverse motion."""
    if label:
        return label.startswith("torsion")
    a = int(np.argmax(np.ptp(points, axis=0)))
    i, j = [c for c in range(3) if c != a]
    r = points - points.mean(axis=0)
    rot = np.stack([-r[:, j], r[:, i]], axis=1)  # transverse motion of a unit twist
    ut = u[:, [i, j]]
    fit = (rot * ut).sum() ** 2 / max((rot * rot).sum() * (ut * ut).sum(), 1e-300)
    return bool(fit > 0.5)


def view_for_mode(u: np.ndarray, base=(24.0, -58.0), blend: float = 0.6) -> tuple[float, float]:
    """(elevation, azimuth) in degrees for a 3D view in which the mode's motion is
    visible: looking along the direction the body moves least (the eigenvector of
    sum_i u_i u_i^T with the smallest eigenvalue: across a translation, along the axis of
    a rotation), tilted towards the default view ``base`` by ``blend`` so that it stays
    a perspective view."""
    el, az = np.radians(base)
    default = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    _, vecs = np.linalg.eigh(u.T @ u)
    least = vecs[:, 0] if np.dot(vecs[:, 0], default) >= 0 else -vecs[:, 0]
    v = least + blend * default
    v /= np.linalg.norm(v)
    return float(np.degrees(np.arcsin(np.clip(v[2], -1, 1)))), \
        float(np.degrees(np.arctan2(v[1], v[0])))
