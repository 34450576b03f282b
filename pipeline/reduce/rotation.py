"""Rotating and preloaded bodies: prestressed modes of the full FE model and of the
reduced one, and the terms a stepper needs to add geometric stiffening.

With the matrices of :mod:`pipeline.fe.prestress` restricted to the free DOFs (n_s),
per unit entry W_ij = omega_i omega_j of the angular-velocity tensor (i <= j, the
six of :data:`~pipeline.fe.prestress.TENSOR_ENTRIES`):

- K_G,ij: the geometric stiffness of the static stress under the centrifugal load
  f_ij (K u_ij = f_ij), N/m per rad^2/s^2;
- M_ij = m (x) A_ij: the spin-softening mass, kg.

A spin Omega (rad/s) about the unit axis a has W = Omega^2 a a^T, so the linearised
stiffness at speed is

    K(Omega) = K + Omega^2 (K_G1 - M_perp),  K_G1 = sum a_i a_j K_G,ij,
                                              M_perp = sum a_i a_j M_ij = m (x) (I - a a^T),

and the prestressed modes solve K(Omega) phi = w^2 M phi (Coriolis coupling left out).
The full FE sweep solves this at each speed with the pipeline's eigensolver. The
reduced model is the Rayleigh-Ritz projection onto a basis V (n_s x n_b): the first
``n_m`` modes of the body at rest (M-orthonormal), optionally followed by the static
shape under the centrifugal load of the axis, u_c = K^-1 f (M-orthonormalised against
the modes), and optionally the first-order corrections of the first modes,
K^-1 (K_G1 - M_perp) phi_k (the shapes the modes move towards as the speed rises: the
derivative of phi_k with Omega^2 lies in their span with the modes'). Stored terms (all
n_b x n_b):

    K_r = V^T K V  (N/m; diag(w_0^2) for the modes alone),  M_r = V^T M V (= I),
    G_ij = V^T K_G,ij V,  S_ij = V^T M_ij V,
    P_k = V^T K_G(sigma(F_k)) V  per unit value of input port k (N or N m),

and the reduced model at any angular velocity omega and preload values lambda_k is

    (K_r + sum_ij omega_i omega_j (G_ij - S_ij) + sum_k lambda_k P_k) q = w^2 M_r q.

Rayleigh-Ritz gives upper bounds: the reduced w is never below the full FE's.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pipeline.config.rotation import Rotation
from pipeline.errors import SolverError
from pipeline.fe.assemble import restrict
from pipeline.fe.materials import ElementMaterials, config_materials
from pipeline.fe.prestress import (TENSOR_ENTRIES, centrifugal_loads, entry_matrix,
                                   geometric_stiffness, node_mass_matrix, point_mass_prestress,
                                   rigid_mass_of, tensor_mass, tensor_weights)
from pipeline.reduce.spin import RotationModel, reduced_frequencies, unit, unstable
from pipeline.reduce.statics import static_shapes
from pipeline.solve.eigen import solve_modes
from pipeline.solve.factorization import factorize

log = logging.getLogger(__name__)

__all__ = ["PrestressTerms", "prestress_terms", "inertia_loads", "RotationModel", "reduced_basis", "project",
           "reduced_frequencies", "full_frequencies", "build_rotation", "rotation_model"]


@dataclass(frozen=True)
class PrestressTerms:
    """The prestress matrices of a supported body on its free DOFs (n_s).

    centrifugal_shapes: (n_s, 6) static displacements per unit W_ij (m per rad^2/s^2).
    geometric: six (n_s x n_s) CSR K_G,ij (N/m per rad^2/s^2).
    softening: six (n_s x n_s) CSR M_ij (kg).
    preload_shapes: (n_s, n_in) static displacements per unit input (m per N or N m).
    preload_geometric: n_in (n_s x n_s) CSR K_G per unit input (N/m per N or N m).
    centrifugal_loads: (n_s, 6) the consistent centrifugal loads f_ij per unit W_ij.
    node_mass: (n_nodes x n_nodes) CSR the scalar consistent mass m (kg).
    node_offsets: (n_nodes, 3) x - point of every node (m).
    point_masses: (dofs, G, M6, P - point) of each rigid mass tied by a distributing
    coupling (:func:`pipeline.fe.added_mass.distributing_point_masses`).
    """

    centrifugal_shapes: np.ndarray
    geometric: tuple[sp.csr_matrix, ...]
    softening: tuple[sp.csr_matrix, ...]
    preload_shapes: np.ndarray
    preload_geometric: tuple[sp.csr_matrix, ...]
    centrifugal_loads: np.ndarray | None = None
    node_mass: sp.csr_matrix | None = None
    node_offsets: np.ndarray | None = None
    point_masses: tuple = ()

    def spin_matrices(self, axis) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """(K_G1, M_perp) of a spin about the unit ``axis``: K(Omega) = K + Omega^2 (K_G1 -
        M_perp)."""
        weights = tensor_weights(unit(axis))
        return _weighted(self.geometric, weights), _weighted(self.softening, weights)

    def centrifugal_shape(self, axis) -> np.ndarray:
        """(n_s,) the static displacement per unit Omega^2 of a spin about ``axis`` (m s^2)."""
        return self.centrifugal_shapes @ tensor_weights(unit(axis))


def _weighted(matrices, weights) -> sp.csr_matrix:
    out = None
    for w, A in zip(weights, matrices):
        if w != 0.0:
            out = w * A if out is None else out + w * A
    return out if out is not None else sp.csr_matrix(matrices[0].shape)


def prestress_terms(space, material, free: np.ndarray, K: sp.spmatrix, point,
                    F_inputs: np.ndarray | None = None, solve=None,
                    backend: str = "auto", constraint=None,
                    extra_node_mass: sp.spmatrix | None = None,
                    point_masses=()) -> PrestressTerms:
    """The :class:`PrestressTerms` of the body of ``space`` (supported: ``free`` DOFs,
    ``K`` (n_s x n_s) its stiffness) spinning about ``point`` (3,) m, and preloaded by
    the input loads ``F_inputs`` (n_dofs x n_in, per unit input; None: none).
    ``material``: one isotropic Material or each element's
    (:class:`~pipeline.fe.materials.ElementMaterials`: its densities in the mass, its laws
    in the stress); ``extra_node_mass``: a scalar node mass (n_nodes x n_nodes, kg) added
    to the body's (the area masses), or None; ``point_masses``: (dofs, G, M6, P) of the
    rigid masses tied by distributing couplings (their load, softening and own geometric
    stiffness: :func:`pipeline.fe.prestress.point_mass_prestress`).
    ``solve``: b -> K^-1 b when a factor of K is at hand; ``constraint``: T of an exact
    constraint u = T q (n_s x n_q, ``solve`` then that of T^T K T), or None."""
    node_mass = node_mass_matrix(space, _density(material))
    if extra_node_mass is not None:
        node_mass = (node_mass + extra_node_mass).tocsr()
    loads = centrifugal_loads(space, node_mass, point)  # (n_dofs, 6)
    if point_masses:
        pm_loads, pm_soft, pm_geo = point_mass_prestress(point_masses, point, space.n_dofs)
        loads = loads + pm_loads
    n_in = 0 if F_inputs is None else F_inputs.shape[1]
    rhs = loads[free]
    if n_in:
        F = F_inputs.toarray() if sp.issparse(F_inputs) else np.asarray(F_inputs)
        rhs = np.hstack([rhs, F[free]])
    shapes = static_shapes(K, rhs, solve,
                           lambda A: factorize(A, backend, positive_definite=True).solve,
                           constraint=constraint)
    U = np.zeros((space.n_dofs, shapes.shape[1]))
    U[free] = shapes
    geometric = [restrict(G, free) for G in geometric_stiffness(space, material, U)]
    softening = [restrict(tensor_mass(node_mass, entry_matrix(i, j)), free)
                 for i, j in TENSOR_ENTRIES]
    k = len(TENSOR_ENTRIES)
    if point_masses:
        for col in range(k):
            geometric[col] = geometric[col] + restrict(pm_geo[col], free)
            softening[col] = softening[col] + restrict(pm_soft[col], free)
    p = np.asarray(point, dtype=float)
    return PrestressTerms(shapes[:, :k], tuple(geometric[:k]), tuple(softening),
                          shapes[:, k:], tuple(geometric[k:]), loads[free], node_mass,
                          space.node_points - p,
                          tuple((d, G, M6, np.asarray(P, float) - p)
                                for d, G, M6, P in point_masses))


def _density(material):
    """kg/m^3: one density, or each element's (n_e,) where they differ."""
    if isinstance(material, ElementMaterials):
        return material.uniform.rho if material.uniform is not None else material.rho
    return material.rho


def inertia_loads(terms: PrestressTerms, free: np.ndarray, V: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inertia loads of a prescribed rotation on the basis V (n_s x n_b):

    centrifugal (6, n_b): V^T f_ij, the load per unit W_ij of the undeformed body;
    euler (3, n_b): E_k = V^T (m (x) I) (e_k x (x - p)) (kg m), the generalized force of
    an angular acceleration alpha is -sum_k alpha_k E_k;
    coriolis (3, n_b, n_b): C_k = V^T (m (x) [e_k x]) V (kg, skew), the Coriolis force
    is -2 sum_k omega_k C_k q' and the Euler force of the deflection -sum_k alpha_k C_k q.
    A rigid mass tied by a distributing coupling adds the same terms of its six motions
    G u: M6 [e_k x (P - p); e_k] and the rigid-body mass of [e_k x].
    """
    n_nodes = terms.node_mass.shape[0]
    full = np.zeros((3 * n_nodes, V.shape[1]))
    full[free] = V
    nodal = full.reshape(n_nodes, 3, -1)
    euler = np.empty((3, V.shape[1]))
    coriolis = np.empty((3, V.shape[1], V.shape[1]))
    for k, e in enumerate(np.eye(3)):
        arm = np.cross(e, terms.node_offsets)  # (n_nodes, 3)
        euler[k] = full.T @ (terms.node_mass @ arm).reshape(-1)
        turned = np.cross(e[None, :, None], nodal, axis=1)  # e_k x each column's vectors
        mass_turned = (terms.node_mass @ turned.reshape(n_nodes, -1)).reshape(3 * n_nodes, -1)
        coriolis[k] = full.T @ mass_turned
        for dofs, G, M6, offset in terms.point_masses:  # rigid masses: G^T (.) G
            q6 = G @ full[dofs]  # (6, n_b) the masses' six motions
            euler[k] += q6.T @ (M6 @ np.concatenate([np.cross(e, offset), e]))
            coriolis[k] += q6.T @ rigid_mass_of(M6, np.cross(e, np.eye(3)).T) @ q6
    return (V.T @ terms.centrifugal_loads).T, euler, coriolis


def reduced_basis(shapes: np.ndarray, M: sp.spmatrix, extra: np.ndarray | None = None
                  ) -> np.ndarray:
    """V (n_s x n_b): the M-orthonormal ``shapes`` (n_s x n_m), then the columns of
    ``extra`` (n_s x k) M-orthonormalised against them (twice, for round-off) and each
    other; a column already spanned (relative M-norm below 1e-8) is dropped."""
    if extra is None or extra.size == 0:
        return shapes
    V = shapes
    for col in np.atleast_2d(extra.T):
        x = col.copy()
        for _ in range(2):
            x -= V @ (V.T @ (M @ x))
        norm = np.sqrt(x @ (M @ x))
        if norm > 1e-8 * np.sqrt(col @ (M @ col)):
            V = np.column_stack([V, x / norm])
    return V


def project(V: np.ndarray, matrices) -> np.ndarray:
    """(k, n_b, n_b) V^T A V of each sparse A (n_s x n_s) in ``matrices``."""
    return np.array([V.T @ (A @ V) for A in matrices]).reshape(-1, V.shape[1], V.shape[1])


def full_frequencies(K: sp.spmatrix, M: sp.spmatrix, K_G1: sp.spmatrix, M_perp: sp.spmatrix,
                     speeds_rad_s, count: int, backend: str = "auto",
                     rest_hz: np.ndarray | None = None) -> np.ndarray:
    """(n_speeds, count) Hz: the ``count`` lowest prestressed frequencies of the full FE
    model at each speed (rad/s), each solved by shift-invert at 0 (an indefinite
    K(Omega) raises SolverError naming the speed); ``rest_hz`` (count,): the frequencies
    at rest when known (a speed 0 is then not solved again)."""
    out = np.empty((len(speeds_rad_s), count))
    spin = (K_G1 - M_perp).tocsr()
    for n, speed in enumerate(speeds_rad_s):
        if speed == 0 and rest_hz is not None:
            out[n] = rest_hz
            continue
        Ks = (K + speed ** 2 * spin).tocsr() if speed else K
        try:
            modes = solve_modes(Ks, M, count, supported=True, backend=backend)
        except SolverError:
            raise unstable(speed, "the full FE model") from None
        out[n] = modes.frequencies_hz
        log.info("rotation: %g rad/s: f = %s Hz", speed,
                 ", ".join(f"{f:.4g}" for f in modes.frequencies_hz[:4]))
    return out


def rotation_model(cfg, space, regions, free: np.ndarray, K: sp.spmatrix, M: sp.spmatrix,
                   modes) -> RotationModel:
    """:func:`build_rotation` for the config ``cfg`` (its ``rotation`` section, material,
    force and moment input ports as preloads, eigensolver backend) and the modes stage's
    :class:`~pipeline.solve.modes.Modes` (its kept factor of ``K`` is used)."""
    from pipeline.config import Ports
    from pipeline.fe.added_mass import area_node_mass, distributing_point_masses
    from pipeline.fe.ports import port_matrices

    inputs = tuple(p for p in cfg.ports.inputs if p.kind in ("force", "moment"))
    F = port_matrices(space, regions, Ports(inputs=inputs)).F if inputs else None
    material = config_materials(space, cfg) if cfg.materials or cfg.masses else cfg.material
    return build_rotation(cfg.rotation, space, material, free, K, M, modes.shapes,
                          modes.omega2, F, tuple(p.name for p in inputs), modes.solve,
                          cfg.modes.solver, getattr(modes, "constraint", None),
                          area_node_mass(space, regions, cfg.masses),
                          distributing_point_masses(space, regions, cfg.masses))


def build_rotation(rotation: Rotation, space, material, free: np.ndarray, K: sp.spmatrix,
                   M: sp.spmatrix, shapes: np.ndarray, omega2: np.ndarray,
                   F_inputs=None, input_names: tuple[str, ...] = (), solve=None,
                   backend: str = "auto", constraint=None,
                   extra_node_mass: sp.spmatrix | None = None,
                   point_masses=()) -> RotationModel:
    """The :class:`RotationModel` of the config's ``rotation`` section for the supported
    body (``K``, ``M`` (n_s x n_s), its modes ``shapes`` (n_s x n_m, M-orthonormal) and
    ``omega2`` (n_m,) rad^2/s^2); ``F_inputs`` (n_dofs x n_in) the input-port loads;
    ``solve``: b -> K^-1 b when a factor of K is at hand (else one is made and freed);
    ``constraint``: T of an exact constraint u = T q (n_s x n_q; ``solve`` is then that
    of T^T K T and the full sweep runs on the coordinates q), or None; ``material``,
    ``extra_node_mass`` and ``point_masses`` as :func:`prestress_terms` takes them."""
    _check_point(rotation.point, space.node_points)
    axis = unit(rotation.axis)
    _check_stress(rotation, axis, space.node_points, material)
    own = None
    if solve is None:
        own = factorize(K if constraint is None else (constraint.T @ (K @ constraint)).tocsr(),
                        backend, positive_definite=True)
        solve = own.solve
    try:
        terms = prestress_terms(space, material, free, K, rotation.point, F_inputs, solve,
                                backend, constraint, extra_node_mass, point_masses)
        K_G1, M_perp = terms.spin_matrices(axis)
        static = terms.centrifugal_shape(axis)[:, None] if rotation.static_shape else None
        corrections = None
        if rotation.correction_shapes:
            n_c = min(rotation.correction_shapes, shapes.shape[1])
            corrections = static_shapes(K, (K_G1 - M_perp) @ shapes[:, :n_c], solve,
                                        constraint=constraint)
    finally:
        if own is not None:
            own.release()
    with_static = reduced_basis(shapes, M, static)  # a shape the modes span is dropped
    V = reduced_basis(with_static, M, corrections)
    n_m = shapes.shape[1]
    plain = V.shape[1] == n_m
    centrifugal, euler, coriolis = inertia_loads(terms, free, V)
    model = RotationModel(
        axis=axis, point=np.asarray(rotation.point, float),
        speeds_rad_s=np.asarray(rotation.speeds_rad_s, float),
        frequencies_hz=np.zeros((0, n_m)), frequencies_reduced_hz=np.zeros((0, V.shape[1])),
        stiffness=np.diag(omega2).astype(float) if plain else V.T @ (K @ V),
        mass=np.eye(n_m) if plain else V.T @ (M @ V),
        geometric=project(V, terms.geometric), softening=project(V, terms.softening),
        preload=project(V, terms.preload_geometric), input_names=tuple(input_names),
        n_modes=n_m, static_shape=with_static.shape[1] > n_m,
        centrifugal_load=centrifugal, euler_load=euler, coriolis=coriolis)
    reduced = reduced_frequencies(model)  # cheap: an unstable speed is named before the sweep
    on_q = (lambda A: A) if constraint is None else \
        (lambda A: (constraint.T @ (A @ constraint)).tocsr())
    full = full_frequencies(on_q(K), on_q(M), on_q(K_G1), on_q(M_perp), model.speeds_rad_s,
                            n_m, backend,
                            rest_hz=np.sqrt(np.maximum(omega2, 0.0)) / (2 * np.pi))
    return dataclasses.replace(model, frequencies_hz=full, frequencies_reduced_hz=reduced)


def _check_point(point, node_points: np.ndarray) -> None:
    """Log a warning when the spin axis's point lies far outside the body (more than
    ten times its largest extent from its bounding box): it may be intended (a blade
    on a long arm), but a point in mm in a body in m looks the same."""
    lo, hi = node_points.min(axis=0), node_points.max(axis=0)
    size = float(np.max(hi - lo))
    point = np.asarray(point, dtype=float)
    gap = float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - point, point - hi))))
    if gap > 10.0 * size:
        log.warning("rotation.point %s lies %.3g m from the body (largest extent %.3g m): "
                    "the centrifugal load grows with that distance; intended?",
                    point.tolist(), gap, size)


def _check_stress(rotation: Rotation, axis: np.ndarray, node_points: np.ndarray,
                  material) -> None:
    """Log a warning when the centrifugal stress at the top speed, estimated as
    rho Omega^2 R^2 / 2 (R: the largest distance of the body from the axis, Pa), exceeds
    1 % of E: the strain is then beyond the small strains the linear prestress assumes."""
    r = node_points - np.asarray(rotation.point, dtype=float)
    radius = float(np.max(np.linalg.norm(r - np.outer(r @ axis, axis), axis=1)))
    top = float(np.max(np.abs(rotation.speeds_rad_s)))
    if isinstance(material, ElementMaterials):  # the densest law, the softest direction
        rho = float(np.max(material.rho))
        S = np.linalg.inv(material.D[np.unique(material.index)])  # compliances
        E = float(1.0 / np.max(np.diagonal(S, axis1=1, axis2=2)[:, :3]))
    else:
        rho, E = material.rho, material.E
    stress = 0.5 * rho * top ** 2 * radius ** 2
    if stress > 0.01 * E:
        log.warning("rotation.speeds_rad_s: at %g rad/s the centrifugal stress reaches about "
                    "%.3g Pa, %.3g times E: beyond the small strains of the linear prestress "
                    "(its frequencies are not physical there)", top, stress, stress / E)
