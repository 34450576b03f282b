"""Connection points of a flexible body: rigid-body properties at a point, interface
couplings (RBE2 / RBE3) and the hybrid-cantilever (6x6) model of METHODS section 5.

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
  weights of the nodes (:func:`pipeline.fe.space.surface_region`). The region keeps
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

Hybrid-cantilever model (one parent point P, optional child points C_k)
-----------------------------------------------------------------------
With the parent interface clamped (q_P = 0) and the child interfaces free, the modes of
(K_c, M_c) are the clamped modes Phi_c (M-orthonormal, N of them). The body's motion is
s = R_P q_P + Phi_c eta, exactly (K R_P = 0 for an unsupported body), so

    [D_P  L_P^T] [a_P ]   [0          ]   [W_P + sum_k tau_k^T W_k]
    [L_P  I    ] [eta''] + [Omega2 eta ] = [Phi_k^T W_k            ]

with L_P = Phi_c^T M R_P (N x 6), tau_k = [[I, skew(P - C_k)], [0, I]] (twist at P to
twist at C_k), Phi_k the rows of the clamped modes at the child coordinates q_k (6 x N)
and W_k the wrench applied to the body at C_k. Eliminating eta'' gives the state-space
model of :func:`connection_statespace` (inputs [a_P; W_1; ...], outputs [W_P; a_1; ...],
states [eta; eta']):

    A = [[0, I], [-Omega2, -2 Xi Omega]]
    B = [[0, 0], [-L_P, Phi_C^T]]
    C = [[-L_P^T Omega2, -L_P^T 2 Xi Omega], [-Phi_C Omega2, -Phi_C 2 Xi Omega]]
    D = [[D_P0, L_P^T Phi_C^T - tau^T], [tau - Phi_C L_P, Phi_C Phi_C^T]]

D_P0 = D_P - L_P^T L_P is the residual (interface) mass. W_P is the wrench the parent
exerts on the body at P (the body exerts -W_P on the parent); at zero frequency
W_P = D_P a_P: the body moves as a rigid body. Without child points this is exactly
METHODS section 5.

Effective modal masses: m_eff[i, d] = L_P[i, d]^2 (kg for d = x, y, z translations,
kg m^2 for rotations about P). Summed over all modes they reach D_P - D_P0, where D_P0
is the mass the interface carries itself (for a lumped mass matrix and rigid coupling,
exactly the rigid mass of the region nodes). The cumulative fraction per direction is
sum_{j <= i} m_eff[j, d] / D_P[d, d], the "90% of the mass" criterion.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from pipeline.fe.body import rigid_body_modes, skew
from pipeline.errors import RegionError, SolverError
from pipeline.reduce.statespace import StateSpace

log = logging.getLogger(__name__)

__all__ = [
    "COUPLINGS",
    "DIRECTIONS",
    "RigidProperties",
    "rigid_properties_at",
    "twist_transform",
    "Interface",
    "make_interface",
    "make_interfaces",
    "check_interface",
    "check_interfaces",
    "clamped_modes",
    "connection_model_from_modes",
    "check_residual_mass",
    "InterfaceTransformation",
    "interface_transformation",
    "ConnectionModel",
    "connection_model",
    "connection_statespace",
    "effective_mass_table",
    "build_connection_model",
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

    ``twist_transform(P, G)`` is METHODS' tau_GP. Its transpose moves a wrench from B to A.
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
    D = R.T @ (M_full @ R)
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

    ``regions``: the name -> boundary triangles mapping of
    :func:`pipeline.fe.regions.resolve_regions`. ``key`` names the config entry in messages
    (default ``connections.<name>``). Raises RegionError naming the region.
    """
    from pipeline.fe.space import region_nodes, surface_region
    from pipeline.fe.regions import get_region

    key = key or f"connections.{name}"
    if coupling not in COUPLINGS:
        raise RegionError(f"{key}.coupling: got {coupling!r}, expected one of "
                          f"{', '.join(COUPLINGS)}")
    tris = get_region(regions, region, f"{key}.region")
    sr = surface_region(space, region, tris)  # P2: edge nodes only (corners weigh 0)
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
    interfaces: in the order of the q blocks. ``q_slice(k)`` gives the columns of q_k.
    """

    T: sp.csc_matrix
    n_z: int
    interfaces: tuple[Interface, ...]

    def q_slice(self, k: int) -> slice:
        return slice(self.n_z + 6 * k, self.n_z + 6 * (k + 1))

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


# --------------------------------------------------------------------------- 6x6 model
@dataclass(frozen=True)
class ConnectionModel:
    """Hybrid-cantilever model of the body at its parent point (see module docstring).

    parent: the parent interface; children: child interfaces (may be empty).
    rigid: RigidProperties at the parent point (D_P = rigid.D_P).
    omega2 (N,) rad^2/s^2 clamped modes; L_P (N, 6) (kg^1/2 | kg^1/2 m); D_P0 (6, 6).
    shapes: (n_dofs, N) clamped mode shapes on every DOF, kg^-1/2.
    Phi_C: (6 n_c, N) clamped modes at the child coordinates (m kg^-1/2 | rad kg^-1/2).
    tau_C: (6 n_c, 6) rigid transport of a twist from P to each child point.
    residuals: (N,) eigen-residuals of the clamped solve.
    """

    parent: Interface
    children: tuple[Interface, ...]
    rigid: RigidProperties
    omega2: np.ndarray
    L_P: np.ndarray
    D_P0: np.ndarray
    shapes: np.ndarray
    Phi_C: np.ndarray
    tau_C: np.ndarray
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def D_P(self) -> np.ndarray:
        return self.rigid.D_P

    @property
    def frequencies_hz(self) -> np.ndarray:
        return np.sqrt(np.maximum(self.omega2, 0.0)) / (2 * np.pi)

    @property
    def effective_mass(self) -> np.ndarray:
        """(N, 6) L_P^2: kg (x, y, z), kg m^2 (rx, ry, rz about P)."""
        return self.L_P ** 2

    @property
    def effective_mass_cumulative_fraction(self) -> np.ndarray:
        """(N, 6) cumulative effective mass / diag(D_P) (dimensionless, rises with i)."""
        return np.cumsum(self.effective_mass, axis=0) / np.diag(self.D_P)


def check_residual_mass(D_P0: np.ndarray, name: str, rtol: float = 1e-9) -> np.ndarray:
    """Return the symmetrised D_P0, or raise SolverError unless it is symmetric positive
    definite: on the matrix scaled to a unit diagonal (dimensionless), the asymmetry must
    stay below 1e-8 and the smallest eigenvalue above ``rtol`` times the largest."""
    D = np.asarray(D_P0, dtype=float)
    diag = np.diag(D)
    if not np.all(np.isfinite(D)) or np.any(diag <= 0):
        raise SolverError(f"connection '{name}': residual mass D_P0 = D_P - L_P^T L_P has a "
                          f"non-positive diagonal {np.array2string(diag, precision=4)}; expected "
                          "a symmetric positive definite matrix (are the clamped modes "
                          "M-orthonormal and computed on the unsupported body?)")
    s = 1.0 / np.sqrt(diag)
    Dn = D * s[:, None] * s[None, :]
    asym = float(np.abs(Dn - Dn.T).max())
    eig = np.linalg.eigvalsh(0.5 * (Dn + Dn.T))
    if asym > 1e-8 or eig[0] <= rtol * eig[-1]:
        raise SolverError(
            f"connection '{name}': residual mass D_P0 = D_P - L_P^T L_P is not symmetric "
            f"positive definite (smallest eigenvalue of the diagonally scaled matrix "
            f"{eig[0]:.3e}, asymmetry {asym:.3e}); the model is refused: the clamped modes "
            "are not M-orthonormal, or not clamped at this connection, or the mass matrix "
            "is not that of the unsupported body")
    return 0.5 * (D + D.T)


def clamped_modes(K: sp.spmatrix, M: sp.spmatrix, n_modes: int | None, backend: str = "auto",
                  tolerance: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(omega2 (N,), shapes (n, N) M-orthonormal, residuals (N,)) of a supported problem.

    ``backend="dense"``: scipy.linalg.eigh on dense copies (small problems; ``n_modes``
    None gives every mode). Otherwise :func:`pipeline.solve.eigen.solve_modes` (shift-invert
    eigsh with ``backend`` auto | pardiso | superlu).
    """
    if backend == "dense":
        Kd, Md = K.toarray(), M.toarray()
        Kd, Md = 0.5 * (Kd + Kd.T), 0.5 * (Md + Md.T)
        n = Kd.shape[0]
        subset = None if n_modes is None else [0, min(n_modes, n) - 1]
        w, V = sla.eigh(Kd, Md, subset_by_index=subset)
        res = np.linalg.norm(Kd @ V - (Md @ V) * w, axis=0) / np.maximum(
            np.linalg.norm(Kd @ V, axis=0), 1e-300)
        return w, V, res
    from pipeline.solve.eigen import solve_modes

    if n_modes is None:
        raise SolverError("n_modes=None (every mode) needs backend='dense'")
    modes = solve_modes(K, M, n_modes, supported=True, backend=backend, tolerance=tolerance)
    return modes.omega2, modes.shapes, modes.residuals


def connection_model(space, K_full: sp.spmatrix, M_full: sp.spmatrix,
                     interfaces: Sequence[Interface], n_modes: int | None,
                     backend: str = "auto", tolerance: float = 0.0) -> ConnectionModel:
    """The hybrid-cantilever model at ``interfaces[0]`` (the parent point P), with
    ``interfaces[1:]`` as child points.

    ``K_full``, ``M_full``: (n_dofs x n_dofs) assembled matrices of the UNSUPPORTED body
    (before :func:`pipeline.fe.assemble.restrict`: the connection replaces the supports).
    ``n_modes``: number of clamped modes N. ``backend``/``tolerance``: as for
    :func:`pipeline.solve.eigen.solve_modes`, or ``backend="dense"`` for a dense solve of a
    small model (then ``n_modes=None`` keeps every mode).
    """
    interfaces = tuple(interfaces)
    if not interfaces:
        raise RegionError("connections: expected at least one connection (the parent point)")
    check_interfaces(interfaces)
    parent, children = interfaces[0], interfaces[1:]
    node_points = space.node_points if hasattr(space, "node_points") else np.asarray(space)
    n_dofs = 3 * node_points.shape[0]
    # q_P last, so the clamped coordinates are the leading columns [z; q_C]
    tr = interface_transformation(n_dofs, node_points, children + (parent,))
    n_c = tr.n_z + 6 * len(children)
    Tc = tr.T[:, :n_c].tocsc()
    Kc = project(K_full, Tc)
    Mc = project(M_full, Tc)
    omega2, Phi_x, residuals = clamped_modes(Kc, Mc, n_modes, backend, tolerance)
    shapes = np.asarray(Tc @ Phi_x)
    rigid = rigid_properties_at(M_full, node_points, parent.point)
    R_P = rigid_body_modes(node_points, parent.point)
    L_P = shapes.T @ (M_full @ R_P)
    D_P0 = check_residual_mass(rigid.D_P - L_P.T @ L_P, parent.name)
    Phi_C = Phi_x[tr.n_z:n_c]
    tau_C = (np.vstack([twist_transform(parent.point, c.point) for c in children])
             if children else np.zeros((0, 6)))
    f = np.sqrt(np.maximum(omega2, 0.0)) / (2 * np.pi)
    log.info("connection '%s': %d clamped modes, %.4g .. %.4g Hz, %d child point(s)",
             parent.name, omega2.size, f[0], f[-1], len(children))
    return ConnectionModel(parent, children, rigid, omega2, L_P, D_P0, shapes, Phi_C,
                           tau_C, residuals)


def connection_model_from_modes(parent: Interface, node_points: np.ndarray, M_full,
                                 shapes: np.ndarray, omega2: np.ndarray) -> ConnectionModel:
    """The model of a single rigid connection from clamped modes already solved elsewhere
    (e.g. the pipeline's own modes of a body supported on exactly the parent region):
    ``shapes`` (n_dofs, N) M-orthonormal, zero on the region's DOFs."""
    rigid = rigid_properties_at(M_full, node_points, parent.point)
    R_P = rigid_body_modes(node_points, parent.point)
    L_P = shapes.T @ (M_full @ R_P)
    D_P0 = check_residual_mass(rigid.D_P - L_P.T @ L_P, parent.name)
    return ConnectionModel(parent, (), rigid, np.asarray(omega2, float), L_P, D_P0,
                           np.asarray(shapes), np.zeros((0, len(omega2))), np.zeros((0, 6)))


# --------------------------------------------------------------------------- state space
ACC_UNITS = ("m/s^2",) * 3 + ("rad/s^2",) * 3
WRENCH_UNITS = ("N",) * 3 + ("N m",) * 3
ACC_NAMES = ("ax", "ay", "az", "alpha_x", "alpha_y", "alpha_z")
WRENCH_NAMES = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")


def _xi(damping_ratio, n: int) -> np.ndarray:
    xi = np.broadcast_to(np.asarray(damping_ratio, dtype=float), (n,)).copy()
    if np.any(xi < 0) or np.any(xi >= 1):
        raise SolverError(f"connection damping ratios must lie in [0, 1), got {xi}")
    return xi


def connection_statespace(model: ConnectionModel, damping_ratio=0.0) -> StateSpace:
    """The 6(1 + n_c)-input, 6(1 + n_c)-output model of the module docstring, a
    :class:`StateSpace` labelled ``"connection"``: u = [a_P; W_1; ...], y = [W_P; a_1; ...],
    x = [eta; eta'] (eta in m kg^1/2), units per name in ``input_units`` /
    ``output_units``; ``attrs["damping_ratio"]`` holds the (n,) modal damping ratios.

    ``damping_ratio``: one ratio for every clamped mode, or one per mode.
    """
    omega2 = np.asarray(model.omega2, dtype=float)
    n = omega2.size
    xi = _xi(damping_ratio, n)
    w = np.sqrt(np.maximum(omega2, 0.0))
    O2, G2 = np.diag(omega2), np.diag(2.0 * xi * w)
    L, Pc, tau = model.L_P, model.Phi_C, model.tau_C
    nc = Pc.shape[0]
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-O2, -G2]])
    B = np.block([[np.zeros((n, 6)), np.zeros((n, nc))], [-L, Pc.T]])
    C = np.block([[-L.T @ O2, -L.T @ G2], [-Pc @ O2, -Pc @ G2]])
    D = np.block([[model.D_P0, L.T @ Pc.T - tau.T], [tau - Pc @ L, Pc @ Pc.T]])
    p = model.parent.name
    in_names = [f"{p}.{a}" for a in ACC_NAMES]
    out_names = [f"{p}.{f}" for f in WRENCH_NAMES]
    in_units, out_units = list(ACC_UNITS), list(WRENCH_UNITS)
    for c in model.children:
        in_names += [f"{c.name}.{f}" for f in WRENCH_NAMES]
        out_names += [f"{c.name}.{a}" for a in ACC_NAMES]
        in_units += WRENCH_UNITS
        out_units += ACC_UNITS
    states = [f"eta_{i + 1}" for i in range(n)] + [f"eta_{i + 1}_dot" for i in range(n)]
    return StateSpace(A, B, C, D, input_names=tuple(in_names), output_names=tuple(out_names),
                      state_names=tuple(states), input_units=tuple(in_units),
                      output_units=tuple(out_units), label="connection",
                      attrs={"damping_ratio": xi})


# --------------------------------------------------------------------------- tables
def effective_mass_table(model: ConnectionModel, count: int | None = None,
                         labels: Sequence[str] | None = None) -> list[str]:
    """Text table: frequency, effective masses and cumulative fractions per direction."""
    n = model.omega2.size if count is None else min(count, model.omega2.size)
    me, cf = model.effective_mass, model.effective_mass_cumulative_fraction
    head = (f"{'mode':>4} {'f [Hz]':>10} " + " ".join(f"{'m_' + d:>10}" for d in DIRECTIONS)
            + "  " + " ".join(f"{'cum_' + d:>7}" for d in DIRECTIONS)
            + ("  label" if labels is not None else ""))
    lines = [head, "-" * len(head)]
    for i in range(n):
        lines.append(f"{i + 1:4d} {model.frequencies_hz[i]:10.3f} "
                     + " ".join(f"{v:10.3e}" for v in me[i]) + "  "
                     + " ".join(f"{100 * v:6.2f}%" for v in cf[i])
                     + (f"  {labels[i]}" if labels is not None else ""))
    lines.append(f"{'D_P':>4} {'diag':>10} " + " ".join(f"{v:10.3e}" for v in np.diag(model.D_P)))
    lines.append(f"{'D_P0':>4} {'diag':>10} " + " ".join(f"{v:10.3e}" for v in np.diag(model.D_P0)))
    return lines


# --------------------------------------------------------------------------- one call
def _ratios(damping, omega2: np.ndarray) -> np.ndarray:
    """Damping ratios at ``omega2``: a number, a per-mode sequence, or an object with
    ``ratios_for(omega)`` (:class:`pipeline.reduce.modal.DampingSpec`)."""
    if hasattr(damping, "ratios_for"):
        return np.asarray(damping.ratios_for(np.sqrt(np.maximum(omega2, 0.0))), dtype=float)
    return _xi(damping, omega2.size)


def build_connection_model(space, regions: Mapping[str, np.ndarray], K_full: sp.spmatrix,
                           M_full: sp.spmatrix, connections: Sequence[Any], n_modes: int,
                           damping=0.0, backend: str = "auto"
                           ) -> tuple[ConnectionModel, StateSpace]:
    """Everything for ``/connections/<parent>``, in one call.

    ``connections``: the config's records (name, region, point, coupling); the first is
    the parent point P, the others child points. ``K_full``, ``M_full``: assembled
    matrices of the unsupported body. ``damping``: a ratio, one per mode, or a
    :class:`pipeline.reduce.modal.DampingSpec`. Returns (model, state space); the datasets
    are :func:`pipeline.store.schema.connection_datasets`.
    """
    interfaces = make_interfaces(space, regions, connections)
    model = connection_model(space, K_full, M_full, interfaces, n_modes, backend=backend)
    ss = connection_statespace(model, _ratios(damping, model.omega2))
    return model, ss
