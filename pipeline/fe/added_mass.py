"""Added masses (config ``masses``): their mass matrix on the body's DOFs and their share
of the rigid-body properties.

- point mass (``kind: point``), distributing coupling (RBE3): a rigid body of mass m and
  inertia J (about its point P) whose six motions q = [u_P; theta_P] follow the region's
  nodes by the weighted least-squares rigid fit q = G u_r, G = (R^T W R)^-1 R^T W (R: the
  region nodes' rigid modes at P, 3 n_r x 6; W: their consistent area weights; built at
  the weights' centroid c and carried to P, u_P = u_c + theta x (P - c): the same G, its
  conditioning independent of the distance to P). Its
  kinetic energy 1/2 q'^T M6 q' gives M_add = G^T M6 G, M6 = diag(m I_3, J): mass, no
  stiffness. G R = I_6, so in a rigid motion of the body the point moves rigidly with it
  and the body's rigid mass matrix gains exactly the point's own.
- point mass, rigid coupling (RBE2, ``coupling: rigid``): the same M_add (the region
  moves rigidly, u_r = R q, so G u_r = q and M_add acts as M6 on the point's motions),
  and the region's nodes follow the point exactly: the constraint u = T q of
  :func:`rigid_couplings` and :mod:`pipeline.fe.constraints`.
- mass per area (``kind: area``): density mu (kg/m^2) on the boundary region's
  triangles, as the consistent surface mass int mu N_a N_b dA for linear elements
  (mu A/12 (1 + delta_ab) per triangle) and, for quadratic elements, mu A/3 at each edge
  midpoint (the midpoint rule, exact for quadratics). Both integrate every product of two
  linear functions exactly, so mass, centre of mass and inertia come out exact.
- mass per volume (``kind: volume``) is added to the elements' rho in the assembly
  (:func:`pipeline.fe.materials.assign_materials`), not here.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import scipy.sparse as sp

from pipeline.config.materials import AddedMass
from pipeline.errors import RegionError
from pipeline.fe.body import rigid_body_modes, skew
from pipeline.fe.regions import get_region
from pipeline.fe.space import FESpace, region_nodes, weighted_region


def point_rigid_mass(mass: float, inertia: Sequence[float]) -> np.ndarray:
    """(6, 6) M6 = diag(m I_3, J) at the point; inertia (Ixx, Iyy, Izz, Ixy, Ixz, Iyz)."""
    Ixx, Iyy, Izz, Ixy, Ixz, Iyz = inertia
    M6 = np.zeros((6, 6))
    M6[:3, :3] = mass * np.eye(3)
    M6[3:, 3:] = [[Ixx, Ixy, Ixz], [Ixy, Iyy, Iyz], [Ixz, Iyz, Izz]]
    return M6


def _distributing_map(space: FESpace, name: str, tris: np.ndarray, point, key: str):
    """(nodes (n_r,), G (6, 3 n_r)): the RBE3 fit of the region at ``point``."""
    sr = weighted_region(space, name, tris)
    x = space.node_points[sr.nodes]
    c = sr.weights @ x / sr.weights.sum()
    # the fit at the weights' centroid c (its conditioning does not depend on how far the
    # point lies), then carried to the point: u_P = u_c + theta x (P - c)
    R = rigid_body_modes(x, c)
    w = np.repeat(sr.weights, 3)
    A = R.T @ (w[:, None] * R)
    if np.linalg.cond(A) > 1e12:
        raise RegionError(f"config key '{key}': region '{name}' cannot carry a distributing "
                          "mass (its weighted nodes lie on a line); expected a surface region")
    T = np.eye(6)
    T[:3, 3:] = -skew(np.asarray(point, dtype=float) - c)  # theta x d = -d x theta
    return sr.nodes, T @ np.linalg.solve(A, R.T * w)


def rigid_couplings(space: FESpace, regions: Mapping[str, np.ndarray],
                    masses: Sequence[AddedMass], free: np.ndarray, held: np.ndarray | None
                    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(slave nodes (n_s,), their points (n_s, 3) m, the mass's point (3,) m) of every
    point mass with ``coupling: rigid``, for :func:`pipeline.fe.constraints.build_constraint`.

    Refuses (RegionError, one line naming the config key) a region with a DOF that is not
    in ``free`` (held by the supports), with a node in ``held`` (DOFs of components held
    in a local frame, or None) or shared with another rigid coupling."""
    out = []
    taken = np.zeros(space.n_dofs, dtype=bool)
    if held is not None:
        taken[held] = True
    is_free = np.zeros(space.n_dofs, dtype=bool)
    is_free[free] = True
    for i, m in enumerate(masses):
        if m.kind != "point" or m.coupling != "rigid":
            continue
        key = f"masses[{i}].region"
        nodes = region_nodes(space, get_region(regions, m.region, key))
        dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        why = ("is held by the supports" if not is_free[dofs].all() else
               "shares nodes with a local-frame support or another rigid coupling"
               if taken[dofs].any() else None)
        if why:
            raise RegionError(f"config key '{key}': region '{m.region}' {why}; expected a "
                              "region whose nodes are free for a rigid coupling (or "
                              "coupling: distributing)")
        taken[dofs] = True
        out.append((nodes, space.node_points[nodes], np.asarray(m.point, dtype=float)))
    return out


def _area_mass(space: FESpace, tris: np.ndarray, density: float):
    """(rows, cols, values) of the scalar surface mass of ``tris`` on node indices."""
    v = space.body.vertices
    a, b, c = (v[tris[:, i]] for i in range(3))
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if space.order == 1:
        local = (np.ones((3, 3)) + np.eye(3)) / 12.0
        rows = np.repeat(tris, 3, axis=1).ravel()
        cols = np.tile(tris, (1, 3)).ravel()
        vals = (density * areas[:, None] * local.ravel()[None, :]).ravel()
        return rows, cols, vals
    sr = weighted_region(space, "area", tris)  # P2: area/3 per edge midpoint, 0 per corner
    return sr.nodes, sr.nodes, density * sr.weights


def added_mass_matrix(space: FESpace, regions: Mapping[str, np.ndarray],
                      masses: Sequence[AddedMass]) -> sp.csr_matrix | None:
    """(n_dofs, n_dofs) CSR kg of the point and area masses, DOF 3 p + c; None if none."""
    parts = []
    n = space.n_dofs
    for i, m in enumerate(masses):
        key = f"masses[{i}]"
        if m.kind == "volume":
            continue
        tris = get_region(regions, m.region, f"{key}.region")
        if tris.ndim != 2 or tris.shape[1] != 3:  # a line or point region
            raise RegionError(f"config key '{key}.region': region '{m.region}' is not a face "
                              "(a line or a point); expected a surface region for a "
                              f"{'distributing' if m.kind == 'point' else 'per-area'} mass")
        if m.kind == "point":
            nodes, G = _distributing_map(space, m.region, tris, m.point, f"{key}.region")
            dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
            block = G.T @ point_rigid_mass(m.mass, m.inertia) @ G
            rows, cols = np.meshgrid(dofs, dofs, indexing="ij")
            parts.append(sp.csr_matrix((block.ravel(), (rows.ravel(), cols.ravel())),
                                       shape=(n, n)))
        else:
            r, c, val = _area_mass(space, tris, m.density)
            N = sp.csr_matrix((val, (r, c)), shape=(space.n_nodes, space.n_nodes))
            parts.append(sp.kron(N, sp.identity(3), format="csr"))
    if not parts:
        return None
    total = parts[0]
    for p in parts[1:]:
        total = total + p
    return total.tocsr()


def area_node_mass(space: FESpace, regions: Mapping[str, np.ndarray],
                   masses: Sequence[AddedMass]) -> sp.csr_matrix | None:
    """(n_nodes, n_nodes) CSR kg: the scalar consistent mass of the area masses (their
    share of M is this (x) I_3, as a body's own), None if none. The rotating body's
    centrifugal load, spin softening and inertia loads take it with the body's."""
    total = None
    for i, m in enumerate(masses):
        if m.kind != "area":
            continue
        tris = get_region(regions, m.region, f"masses[{i}].region")
        r, c, val = _area_mass(space, tris, m.density)
        N = sp.csr_matrix((val, (r, c)), shape=(space.n_nodes, space.n_nodes))
        total = N if total is None else total + N
    return total


def distributing_point_masses(space: FESpace, regions: Mapping[str, np.ndarray],
                              masses: Sequence[AddedMass]) -> list[tuple]:
    """(dofs (3 n_r,), G (6, 3 n_r), M6 (6, 6), point (3,) m) of every point mass with a
    distributing coupling: its six motions q = G u[dofs] and its rigid mass (the same
    fit as :func:`added_mass_matrix`'s, M_add = G^T M6 G)."""
    out = []
    for i, m in enumerate(masses):
        if m.kind != "point" or m.coupling != "distributing":
            continue
        tris = get_region(regions, m.region, f"masses[{i}].region")
        nodes, G = _distributing_map(space, m.region, tris, m.point, f"masses[{i}].region")
        out.append(((3 * nodes[:, None] + np.arange(3)).ravel(), G,
                    point_rigid_mass(m.mass, m.inertia), np.asarray(m.point, dtype=float)))
    return out


def refuse_rigid_couplings(raw_masses, path) -> None:
    """Refuse (ConfigError, one line) an Exudyn export of the file ``path`` whose stored
    config (``raw_masses``: its ``masses`` list as read) has a point mass with a rigid
    coupling: the export's matrices are the unconstrained body's, which cannot carry the
    constraint u = T q that makes the region rigid."""
    from pipeline._util import validate

    for i, item in enumerate(raw_masses or []):
        if isinstance(item, dict) and item.get("coupling") == "rigid":
            raise validate.fail(
                f"masses[{i}].coupling", "rigid",
                "distributing couplings only, for an Exudyn export (its matrices are the "
                f"unconstrained body's; the config stored in {path} has a rigid coupling)")
