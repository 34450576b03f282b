"""Interfaces of a flexible body: rigid-body properties at a point, the RBE2 / RBE3
couplings of a boundary region to a point, and the change of coordinates that clamps
interface points (theory.md §5). Used by the connection-point model
(:mod:`pipeline.reduce.connection`) and Craig-Bampton (:mod:`pipeline.reduce.craig_bampton`).

Notation (SI; twist order [v; omega], wrench order [F; T]):

- ``R_P`` (n_dofs x 6): nodal displacements of the whole body for a unit twist at P,
  node j at x_j gets [I_3, -skew(x_j - P)] (:func:`pipeline.fe.body.rigid_body_modes`).
- ``D_P = R_P^T M R_P`` (6 x 6): rigid-body mass matrix at P, equal to
  ``tau_GP^T diag(m I_3, I_G) tau_GP`` with ``tau_GP = [[I_3, skew(P - G)], [0, I_3]]``
  (moves a twist from P to G).

Interfaces
----------
An interface ties the nodes of a named boundary region to a point with six DOFs q
(a twist-like displacement [u_P; theta_P]):

- ``rigid`` (RBE2): every region node follows the point rigidly, u_r = R_r q. The
  region becomes a rigid patch (it stiffens the body locally).
- ``distributing`` (RBE3): the point moves with the weighted least-squares rigid fit of
  the region, q = G u_r with G = (R_r^T W R_r)^-1 R_r^T W, W the consistent area
  weights of the nodes (:func:`pipeline.fe.space.weighted_region`). The region keeps
  deforming freely; only these six averages are tied. A wrench at P reaches the nodes
  as f_r = G^T [F; T] (the classic RBE3 load distribution). G R_r = I_6.

Both are written as one change of coordinates s = T [z; q_1; ...; q_k] of the body's
DOFs s (:func:`interface_transformation`): N (columns for z) spans the motions with
every interface point fixed, and E_k = R_k on the rows of region k (zero elsewhere) is
a particular motion for a unit q_k. For RBE2, N keeps the DOFs outside the regions
(the region DOFs are eliminated); for RBE3, N also keeps the region DOFs but for six
per region, which are eliminated by the six constraints G_k u_r = 0 (chosen by a
column-pivoted QR of G_k, so they are well conditioned). The clamped problem at the
points is then K_c = N^T K N, M_c = N^T M N.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from pipeline.errors import RegionError, SolverError
from pipeline.fe.body import rigid_body_modes, skew
from pipeline.fe.regions import get_region
from pipeline.fe.space import region_nodes, weighted_region

__all__ = [
    "COUPLINGS",
    "DIRECTIONS",
    "TWIST_UNITS_BLOCKS",
    "RigidProperties",
    "rigid_properties_at",
    "rigid_properties_from_mass",
    "twist_transform",
    "Interface",
    "make_interface",
    "make_interfaces",
    "check_interface",
    "check_interfaces",
    "InterfaceTransformation",
    "interface_transformation",
    "rbe3_matrix",
    "project",
]

COUPLINGS = ("rigid", "distributing")
#: names of the six components of a twist / wrench at a point
DIRECTIONS = ("x", "y", "z", "rx", "ry", "rz")
TWIST_UNITS_BLOCKS = "kg | kg m ; kg m | kg m^2"

#: relative tolerance on the smallest eigenvalue of the (dimensionless) rigid-fit matrix of a
#: region below which the region cannot carry six DOFs (its nodes lie on a line or a point).
RANK_TOL = 1e-8


# --------------------------------------------------------------------------- rigid body
@dataclass(frozen=True)
class RigidProperties:
    """Rigid-body properties of the body about a point P.

    mass (kg); center_of_mass G (3,) m; inertia_G (3, 3) kg m^2 about G; point P (3,) m;
    inertia_P (3, 3) kg m^2 about P; D_P (6, 6) = R_P^T M R_P (blocks kg | kg m; kg m |
    kg m^2), twist order [v; omega].
    """

    mass: float
    center_of_mass: np.ndarray
    inertia_G: np.ndarray
    point: np.ndarray
    inertia_P: np.ndarray
    D_P: np.ndarray


def twist_transform(from_point, to_point) -> np.ndarray:
    """tau (6, 6) moving a twist [v; omega] from ``from_point`` A to ``to_point`` B:
    v_B = v_A + omega x (B - A), i.e. tau = [[I, skew(A - B)], [0, I]].

    ``twist_transform(P, G)`` is tau_GP of theory.md §5. Its transpose moves a wrench from B to A.
    """
    a = np.asarray(from_point, dtype=float)
    b = np.asarray(to_point, dtype=float)
    tau = np.eye(6)
    tau[0:3, 3:6] = skew(a - b)
    return tau


def rigid_properties_at(M_full: sp.spmatrix, node_points: np.ndarray, point) -> RigidProperties:
    """Mass, centre of mass, inertia at G and at ``point`` from the full (unsupported) mass
    matrix ``M_full`` (n_dofs x n_dofs, kg) and the node coordinates (n_nodes, 3) m.

    D_P = R_P^T M R_P directly; m, G and I_G are read off it (the translational-rotational
    block of D_P is -m skew(G - P)).
    """
    P = np.asarray(point, dtype=float).reshape(3)
    R = rigid_body_modes(node_points, P)
    return rigid_properties_from_mass(R.T @ (M_full @ R), P)


def rigid_properties_from_mass(D_P: np.ndarray, point) -> RigidProperties:
    """Mass, centre of mass, inertia at G and at ``point`` P (3,) m from the rigid-body
    mass matrix D_P = R_P^T M R_P (6, 6) at P (symmetrised here)."""
    P = np.asarray(point, dtype=float).reshape(3)
    D = np.asarray(D_P, dtype=float)
    D = 0.5 * (D + D.T)
    m = float(D[0, 0])
    if not m > 0:
        raise SolverError(f"rigid_properties_at: mass from R^T M R is {m:.6g} kg, expected > 0")
    S = -D[0:3, 3:6] / m  # skew(G - P)
    g = P + np.array([S[2, 1], S[0, 2], S[1, 0]])
    I_P = D[3:6, 3:6]
    d = g - P
    I_G = I_P - m * (d @ d * np.eye(3) - np.outer(d, d))
    return RigidProperties(m, g, 0.5 * (I_G + I_G.T), P, I_P.copy(), D)


# --------------------------------------------------------------------------- interfaces
@dataclass(frozen=True)
class Interface:
    """A region tied to a point with six DOFs.

    name: the connection / interface name; region: the region name; point (3,) m;
    coupling: ``rigid`` (RBE2) or ``distributing`` (RBE3); nodes (n_r,) node indices of
    the region; weights (n_r,) m^2 consistent area weights (RBE3 weighting; zero for P2
    corner nodes of flat faces).
    """

    name: str
    region: str
    point: np.ndarray
    coupling: str
    nodes: np.ndarray
    weights: np.ndarray

    @property
    def coordinate_names(self) -> tuple[str, ...]:
        return tuple(f"{self.name}.{d}" for d in DIRECTIONS)

    def fit_weights(self) -> np.ndarray:
        """Node weights of the rigid fit: 1 per node (RBE2), area weights (RBE3)."""
        return np.ones(self.nodes.size) if self.coupling == "rigid" else self.weights


def check_interface(iface: Interface, node_points: np.ndarray, key: str) -> None:
    """Refuse a region whose (weighted) nodes cannot carry 3 translations and 3 rotations."""
    w = iface.fit_weights()
    used = w > 0
    n_used = int(used.sum())
    x = node_points[iface.nodes[used]]
    if n_used >= 3:
        c = (w[used, None] * x).sum(0) / w[used].sum()
        r = x - c
        scale = np.sqrt((w[used] * (r * r).sum(1)).sum() / w[used].sum())
        if scale > 0:
            R = rigid_body_modes(r / scale)  # dimensionless rigid fit about the centroid
            A = R.T @ (np.repeat(w[used] / w[used].sum(), 3)[:, None] * R)
            eig = np.linalg.eigvalsh(0.5 * (A + A.T))
            if eig[0] > RANK_TOL * eig[-1]:
                return
    raise RegionError(
        f"{key}: region '{iface.region}' cannot carry the six DOFs of interface "
        f"'{iface.name}' ({iface.coupling} coupling): its {n_used} "
        f"{'weighted ' if iface.coupling == 'distributing' else ''}node(s) lie on a point "
        "or a line; expected a surface region with at least three non-collinear nodes")


def make_interface(space, regions: Mapping[str, np.ndarray], name: str, region: str,
                   point, coupling: str = "rigid", key: str | None = None) -> Interface:
    """Resolve one interface on a region of ``space`` and check it carries six DOFs.

    ``regions``: the name -> vertex cells (face, line or point) mapping of
    :func:`pipeline.fe.regions.resolve_regions`. ``key`` names the config entry in messages
    (default ``connections.<name>``). Raises RegionError naming the region.
    """

    key = key or f"connections.{name}"
    if coupling not in COUPLINGS:
        raise RegionError(f"{key}.coupling: got {coupling!r}, expected one of "
                          f"{', '.join(COUPLINGS)}")
    tris = get_region(regions, region, f"{key}.region")
    sr = weighted_region(space, region, tris)  # P2 face: edge nodes only (corners weigh 0)
    nodes = np.unique(region_nodes(space, tris)).astype(np.int64)
    weights = np.zeros(nodes.size)
    weights[np.searchsorted(nodes, sr.nodes)] = sr.weights
    iface = Interface(name, region, np.asarray(point, dtype=float).reshape(3), coupling,
                      nodes, weights)
    check_interface(iface, space.node_points, key)
    return iface


def check_interfaces(interfaces: Sequence[Interface], key: str = "connections") -> None:
    """Refuse overlapping interfaces (a node tied to two points) and duplicate names,
    before any solve. Raises RegionError naming both regions."""
    seen: dict[str, int] = {}
    for i, a in enumerate(interfaces):
        if a.name in seen:
            raise RegionError(f"{key}[{i}].name: interface name '{a.name}' is used twice")
        seen[a.name] = i
        for j in range(i):
            b = interfaces[j]
            common = np.intersect1d(a.nodes, b.nodes)
            if common.size:
                what = ("is the same region as" if a.region == b.region else "overlaps")
                raise RegionError(
                    f"{key}[{i}].region: region '{a.region}' (interface '{a.name}') {what} "
                    f"region '{b.region}' (interface '{b.name}'): {common.size} node(s) in "
                    "common; expected disjoint interface regions (a node can be tied to one "
                    "point only)")


def make_interfaces(space, regions: Mapping[str, np.ndarray], connections: Sequence[Any],
                    key: str = "connections") -> list[Interface]:
    """Interfaces for config records with ``name``, ``region``, ``point``, ``coupling``
    (:class:`pipeline.config.Connection`), checked one by one and for overlaps."""
    out = [make_interface(space, regions, c.name, c.region, c.point,
                          getattr(c, "coupling", "rigid"), key=f"{key}[{i}]")
           for i, c in enumerate(connections)]
    check_interfaces(out, key)
    return out


# --------------------------------------------------------------------------- transformation
@dataclass(frozen=True)
class InterfaceTransformation:
    """s = T [z; q_1; ...; q_k] (see the module docstring).

    T: (n_dofs x (n_z + 6 k)) sparse CSC; n_z: number of interior coordinates z;
    interfaces: in the order of the q blocks; q_k is columns n_z + 6k .. n_z + 6k + 5.
    """

    T: sp.csc_matrix
    n_z: int
    interfaces: tuple[Interface, ...]

    @property
    def N(self) -> sp.csc_matrix:
        return self.T[:, : self.n_z]

    @property
    def E(self) -> sp.csc_matrix:
        return self.T[:, self.n_z:]


def rbe3_matrix(iface: Interface, node_points: np.ndarray) -> np.ndarray:
    """G (6 x 3 n_r): q = G u_r, the weighted least-squares rigid fit of the region at the
    interface point (G R_r = I_6)."""
    R = rigid_body_modes(node_points[iface.nodes], iface.point)
    w = np.repeat(iface.weights, 3)
    A = R.T @ (w[:, None] * R)
    return np.linalg.solve(A, R.T * w)


def interface_transformation(n_dofs: int, node_points: np.ndarray,
                             interfaces: Sequence[Interface]) -> InterfaceTransformation:
    """The coordinates [z; q_1..q_k] of the body with ``interfaces`` (checked disjoint)."""
    interfaces = tuple(interfaces)
    region_dof_mask = np.zeros(n_dofs, dtype=bool)
    rows_e, cols_e, vals_e = [], [], []
    dependent = []  # (dofs (6,), X (6 x n_o), independent dofs (n_o,)) per RBE3 region
    for k, iface in enumerate(interfaces):
        dofs = (3 * iface.nodes[:, None] + np.arange(3)).ravel()
        region_dof_mask[dofs] = True
        R = rigid_body_modes(node_points[iface.nodes], iface.point)
        r, c = np.nonzero(R)
        rows_e.append(dofs[r])
        cols_e.append(6 * k + c)
        vals_e.append(R[r, c])
        if iface.coupling == "distributing":
            G = rbe3_matrix(iface, node_points)
            _, _, piv = sla.qr(G, mode="economic", pivoting=True)
            d_local, o_local = piv[:6], np.sort(piv[6:])
            X = -np.linalg.solve(G[:, d_local], G[:, o_local])  # u_d = X u_o
            dependent.append((dofs[d_local], X, dofs[o_local]))
    keep = np.flatnonzero(~region_dof_mask)
    for _, _, o_dofs in dependent:
        keep = np.concatenate([keep, o_dofs])
    keep = np.sort(keep)
    n_z = keep.size
    col_of = np.full(n_dofs, -1, dtype=np.int64)
    col_of[keep] = np.arange(n_z)
    rows = [keep]
    cols = [np.arange(n_z)]
    vals = [np.ones(n_z)]
    for d_dofs, X, o_dofs in dependent:
        rr, cc = np.nonzero(X)
        rows.append(d_dofs[rr])
        cols.append(col_of[o_dofs[cc]])
        vals.append(X[rr, cc])
    for r, c, v in zip(rows_e, cols_e, vals_e):
        rows.append(r)
        cols.append(n_z + c)
        vals.append(v)
    T = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n_dofs, n_z + 6 * len(interfaces)))
    return InterfaceTransformation(T, n_z, interfaces)


def project(A: sp.spmatrix, T: sp.spmatrix) -> sp.csr_matrix:
    """T^T A T, symmetrised (sparse)."""
    B = (T.T @ (A @ T)).tocsr()
    return ((B + B.T) * 0.5).tocsr()
