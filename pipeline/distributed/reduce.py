"""The modes' last step and the reduce stage on distributed mode shapes.

Every tall quantity stays a :class:`~pipeline.distributed.blocks.RowBlock` (each rank
its own rows); only small matrices are made collectively and are the same on every
rank (n: free DOFs, m: modes, n_u inputs, n_y outputs):

- Rayleigh-Ritz (:func:`rayleigh_ritz_rows`): K_r = Phi^T (K Phi), M_r = Phi^T (M Phi)
  (m, m) by local products and MPI_Allreduce, K_r Q = M_r Q diag(omega^2), Phi <- Phi Q,
  each column's largest-magnitude entry made positive (the serial convention);
- the basis check (:func:`check_basis_rows`): |Phi^T M Phi - I| and
  |Phi^T K Phi - Omega^2| / max omega^2, as :func:`pipeline.reduce.modal.check_modal_basis`;
- the static shapes X = K^-1 F (n, n_u) by the kept MUMPS factor, each rank its rows of
  F and X, refined until the normwise backward error |F - K X| / (|K| |X| + |F|) (inf
  norms) is below :data:`pipeline.solve.refine.BACKWARD_ERROR_TOL`;
- a partly held body's inertia-relief shapes (:func:`relief_rows`, the serial
  :func:`pipeline.reduce.statics.relief_shapes`): K X = F - M R R^T F, R^T M X = 0 (R:
  its M-orthonormal rigid modes, the first of the basis), by the same fixed point with
  MUMPS' factor of K - sigma M at the serial path's sigma = -1e-3 omega_{r+1}^2 (the
  eigen solve's factor is at -1e-7 of the stiffness scale, which may lie near omega_{r+1}^2:
  the fixed point's steps then shrink the error by only ~1/2 each);
- the plant: Sigma = Phi^T F (m, n_u), Theta = T Phi (n_y, m) and the static compliance
  G = T X (n_y, n_u), summed over the ranks' rows; with ``residual`` the residual
  flexibility G - Theta Omega^-2 Sigma and the correction shapes X - Phi Omega^-2 Sigma
  (rows stay; rigid modes carry no static deflection; a partly held body floats: its
  G is the inertia-relief compliance, not stored); with ``augment`` the Ritz basis of
  [Phi, X] (:mod:`pipeline.reduce.augment`, its Gram-Schmidt and projected pencil from
  the same local products and sums);
- stress modes (:func:`stress_blocks`): the recovery to the mesh points is linear in the
  displacements, so each rank recovers its own rows' share over the elements that
  touch them and the shares are summed point block by point block as rank 0 writes.
"""

from __future__ import annotations

import logging

import numpy as np

from pipeline.config import Config
from pipeline.distributed.blocks import PointBlocks, RowBlock, dof_rows
from pipeline.distributed.constraints import Unconstrained
from pipeline.distributed.eigen import shifted_cholesky
from pipeline.distributed.mpi import allreduce_sum, petsc
from pipeline.distributed.operators import KspSolve, of_diagonals
from pipeline.errors import ConfigError, SolverError
from pipeline.distributed.submesh import RankMesh
from pipeline.fe.strain import nodal_strains_at, stresses_from_strains
from pipeline.reduce.augment import augment
from pipeline.reduce.build import _damping_spec, check_ports_act
from pipeline.reduce.modal import (DampingSpec, ReducedModel, _keep_clusters_whole, _omega,
                                   _ro, modal_statespace)
from pipeline.reduce.statics import relief_fixed_point
from pipeline.solve.refine import BACKWARD_ERROR_TOL
from pipeline.solve.thresholds import stiffness_scale

log = logging.getLogger(__name__)

#: refinement steps of the distributed static solve before it is refused
MAX_REFINEMENTS = 4


def rayleigh_ritz_rows(K, M, v: RowBlock, sigma: float):
    """(omega2 (m,) ascending, Ritz vectors (RowBlock), residuals (m,)): the distributed
    twin of :func:`pipeline.solve.eigen.rayleigh_ritz` (same convention and measure)."""
    from scipy.linalg import eigh

    Kv, Mv = K.apply(v), M.apply(v)
    Kr, Mr = v.gram(Kv), v.gram(Mv)
    Kr, Mr = 0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T)
    w, Q = eigh(Kr, Mr)
    order = np.argsort(w)
    w, Q = w[order], Q[:, order]
    v = v.times(Q)
    signs = v.signs_of_largest()
    Q = Q * signs
    v = v.like(v.local * signs)
    Kv, Mv = Kv.times(Q), Mv.times(Q)
    scale = np.maximum(Kv.column_norms(), abs(sigma) * Mv.column_norms())
    residuals = Kv.like(Kv.local - Mv.local * w).column_norms() / np.where(scale > 0, scale,
                                                                            1.0)
    return w, v, residuals


def check_basis_rows(K, M, Phi: RowBlock, omega2: np.ndarray, tol: float = 1e-6) -> None:
    """Refuse (SolverError) a basis that is not M-orthonormal with Phi^T K Phi =
    diag(omega2), measured as :func:`pipeline.reduce.modal.check_modal_basis` does."""
    n = omega2.size
    errM = float(np.abs(Phi.gram(M.apply(Phi)) - np.eye(n)).max(initial=0.0))
    floor = 1e-6 * of_diagonals(stiffness_scale, K, M)
    scale = max(float(np.abs(omega2).max(initial=0.0)), floor) or 1.0
    errK = float(np.abs(Phi.gram(K.apply(Phi)) - np.diag(omega2)).max(initial=0.0)) / scale
    if errM > tol or errK > tol:
        raise SolverError(f"distributed mode shapes fail the basis check: |Phi^T M Phi - I| "
                          f"= {errM:.3g}, |Phi^T K Phi - Omega^2| / max omega^2 = {errK:.3g} "
                          f"(tol {tol:g})")


def static_rows(K, factor, F: RowBlock) -> RowBlock:
    """X = K^-1 F (rows stay), refined to the backward-error tolerance (module)."""
    X = F.like(factor.solve_rows(F.local))
    norm_K = K.scaled_inf_norm()
    for step in range(MAX_REFINEMENTS + 1):
        R = F.like(F.local - K.apply(X).local)
        inf = allreduce_sum(F.comm, np.array([np.abs(B.local).max(initial=0.0)
                                              for B in (R, X, F)]), "MAX")
        eta = inf[0] / max(norm_K * inf[1] + inf[2], 1e-300)
        if eta <= BACKWARD_ERROR_TOL:
            log.info("distributed static solve: backward error %.2g after %d refinement(s)",
                     eta, step)
            return X
        X = X.like(X.local + factor.solve_rows(R.local))
    raise SolverError(f"static correction: the distributed solve K X = F reached a backward "
                      f"error of {eta:.2g} after {MAX_REFINEMENTS} refinements; expected "
                      f"<= {BACKWARD_ERROR_TOL:g} (is the body held?)")


def relief_rows(K, M, F: RowBlock, R: RowBlock, shift: float) -> RowBlock:
    """Inertia-relief static shapes X (n_free, n_u; rows stay) of a body that keeps the
    M-orthonormal rigid modes ``R`` (n_free, r): :func:`relief_fixed_point` with a
    factor of K - shift M (``shift`` < 0 rad^2/s^2, made and freed here) and the
    distributed K and M (module; their PETSc matrices attached)."""
    Fe = F.like(F.local - M.apply(R.times(R.gram(F))).local)  # F - M R R^T F

    def mass(X: np.ndarray) -> np.ndarray:
        return M.apply(F.like(X)).local

    def project(X: np.ndarray) -> np.ndarray:
        return X - R.local @ R.gram(M.apply(F.like(X)))

    def norm(X: np.ndarray) -> float:
        return float(np.sqrt(allreduce_sum(F.comm, np.array([np.sum(X * X)]))[0]))

    ksp, A = shifted_cholesky(petsc()[0], K.petsc, M.petsc, shift)
    factor = KspSolve(ksp, K, keep=[ksp, A], shift=shift)
    try:
        return F.like(relief_fixed_point(Fe.local, factor.solve_rows, mass, project, norm,
                                         shift))
    finally:
        factor.release()


def build_statespace(cfg: Config, space, regions, K, M, free, modes, solve=None):
    """The distributed twin of :func:`pipeline.reduce.build.build_statespace`: (ports,
    reduced, filtered) with the reduced model's ``basis`` and ``correction_shapes`` as
    :class:`RowBlock` (rows on their ranks). Each rank reads the port loads and sensor
    rows of its own rows' DOFs only (``free``: unused, every rank's free DOFs are its
    partition's)."""
    from pipeline.reduce.filters import filtered_model

    Phi: RowBlock = modes.shapes
    ports = space.ports  # rank 0's, from the whole mesh (pipeline.distributed.stage)
    dofs = Phi.dofs()  # this rank's rows: the DOF of each
    F_own = dof_rows(ports.F, dofs)  # (hi - lo, n_u)
    T_own = dof_rows(ports.T.T, dofs).T  # (n_y, hi - lo)
    # each port's largest entry on the free DOFs: the largest over the ranks' own rows
    F_max = allreduce_sum(Phi.comm, _abs_max(F_own, 0), "MAX")
    T_max = allreduce_sum(Phi.comm, _abs_max(T_own, 1), "MAX")
    check_ports_act(cfg, ports, F_max[None, :], T_max[:, None])
    F = Phi.like(F_own.toarray())
    reduced = _reduce_rows(cfg, K, M, Phi, modes, F, ports.T, ports)
    filtered = None
    if cfg.filter.kind != "none":
        filtered = filtered_model(reduced, cfg.filter.kind, cfg.filter.cutoff_hz)
    return ports, reduced, filtered


def _abs_max(A, axis: int) -> np.ndarray:
    """The largest |entry| of each column (``axis`` 0) or row (1) of the sparse ``A``,
    zero for an empty one."""
    if A.shape[axis] == 0:
        return np.zeros(A.shape[1 - axis])
    return abs(A).max(axis=axis).toarray().ravel()


def _reduce_rows(cfg: Config, K, M, Phi: RowBlock, modes, F: RowBlock, T, ports
                 ) -> ReducedModel:
    """:func:`pipeline.reduce.modal.reduce_model` on row blocks (every static correction:
    ``augment``'s Ritz basis by :func:`pipeline.reduce.augment.augment` on the blocks);
    T (n_y, n_dofs): the sensor rows on every DOF."""
    spec: DampingSpec = _damping_spec(cfg)
    correction = cfg.reduction.static_correction
    omega2 = np.asarray(modes.omega2, dtype=float)
    n_modes = int(cfg.reduction.modes)
    if not 1 <= n_modes <= omega2.size:
        raise ConfigError(f"reduction.modes: {n_modes}, expected 1 to {omega2.size} (the "
                          "number of computed modes, modes.count)", key="reduction.modes",
                          value=n_modes, expected=f"1 to {omega2.size}")
    n_modes = _keep_clusters_whole(omega2, n_modes, spec)
    basis, w2 = Phi.columns(slice(0, n_modes)), omega2[:n_modes]
    check_basis_rows(K, M, basis, w2)
    n_rigid = min(int(modes.n_rigid), n_modes)
    # u = T q: the static solves run on the coordinates, X = T X_q (pipeline.fe.constraints)
    on = Unconstrained(K, M) if modes.constraint is None else modes.constraint
    X = G = G_relief = None
    if n_rigid and cfg.supports and correction != "none":
        # a partly held body: inertia relief (pipeline.reduce.modal.reduce_model); floats
        X = on.from_q(relief_rows(on.K, on.M, on.to_q(F),
                                  on.coordinates(basis.columns(slice(0, n_rigid))),
                                  -1e-3 * float(omega2[n_rigid])))
        G_relief = X.dof_sensor_product(T)
    elif n_rigid:
        if correction != "none":
            raise ConfigError(f"reduction.static_correction: {correction}, expected none: the "
                              f"body has {n_rigid} rigid-body mode(s) among the retained ones",
                              key="reduction.static_correction", value=correction,
                              expected="none")
        log.warning("floating body (%d rigid-body modes): no static compliance computed",
                    n_rigid)
    else:
        X = on.from_q(static_rows(on.K, modes.factorization, on.to_q(F)))
        G = X.dof_sensor_product(T)
    if correction == "augment":  # the Ritz basis of [Phi, X], rows on their ranks
        w2, basis = augment(K.apply, M.apply, basis, X, list(ports.input_names), w2)
    xi = spec.ratios_for(_omega(w2), n_listed=n_modes)
    Sigma = basis.gram(F)
    Theta = basis.dof_sensor_product(T)
    residual = shapes = None
    if correction == "residual":
        # rigid modes (omega^2 = 0, inertia relief) carry no static deflection
        flex = Sigma / np.where(np.arange(w2.size) < n_rigid, np.inf, w2)[:, None]
        residual = (G if G_relief is None else G_relief) - Theta @ flex
        shapes = X.like(X.local - basis.times(flex).local)
    ss = modal_statespace(w2, xi, Sigma, Theta, residual=residual,
                          input_names=list(ports.input_names),
                          output_names=list(ports.output_names), n_retained=n_modes)
    model = ReducedModel(ss, None if G is None else _ro(G), _ro(w2), int(w2.size), n_modes,
                         correction, None if residual is None else _ro(residual), basis,
                         shapes)
    if G is not None:
        rel = np.linalg.norm(model.dc_gain_position - G) / max(np.linalg.norm(G), 1e-300)
        log.info("reduced model (distributed): %d states, static correction %s, DC gain "
                 "error %.3g (relative to T K^-1 F)", ss.n_states, correction, rel)
    return model


def label_rows(space, Phi: RowBlock, n_rigid: int) -> list[str]:
    """The serial labels (:func:`pipeline.solve.labels.label_modes`) from each rank's rows:
    rank 0 made the body's :class:`~pipeline.solve.labels.LabelFrame` from every point
    in the FE stage (``space.label_frame``, a few numbers per slice, sent to every
    rank), and each rank sums over the points of its own rows, their positions and
    volume weights from its part of the mesh (``space``:
    a :class:`~pipeline.distributed.submesh.DistributedSpace`; the part holds every
    element around those points, so each weight is the whole mesh's, bit for bit); the
    sums are added over the ranks. No rank but 0 holds every point."""
    from pipeline.fe.body import node_volume_weights
    from pipeline.solve.labels import label_modes

    points, values = Phi.on_points()
    frame = Phi.comm.bcast(space.label_frame if Phi.comm.rank == 0 else None, root=0)
    mesh = space.local
    local = mesh.local_nodes(points)
    weights = node_volume_weights(mesh.space)[local]
    return label_modes(mesh.space.node_points[local], values, n_rigid, weights, frame=frame,
                       reduce_sum=lambda a: allreduce_sum(Phi.comm, a))


def shapes_blocks(n_points: int, Phi: RowBlock) -> PointBlocks:
    """The ``/modes/shapes`` dataset (n_points, 3, m), written from the ranks' rows."""
    return PointBlocks(Phi.comm, n_points, *Phi.on_points())


def stress_blocks(mesh: RankMesh, n_points: int, reduced: ReducedModel
                  ) -> tuple[PointBlocks, PointBlocks]:
    """(stress, strain) datasets (n_points, 6, n_b + n_u) of the basis and the correction
    shapes, each rank recovering its own rows' share (module) on its part of the mesh
    (``mesh``; the whole mesh's element volume around each node as the denominator);
    several laws: each element's own stiffness, as :func:`pipeline.fe.strain.stress_fields`."""
    cols = [reduced.basis] + ([reduced.correction_shapes]
                              if reduced.correction_shapes is not None else [])
    block = cols[0].like(np.hstack([c.local for c in cols]))
    points, values = block.on_points()
    points = mesh.local_nodes(points)
    space = mesh.space
    node_row = np.full(space.n_nodes, points.size)  # others' points: the zero row below
    node_row[points] = np.arange(points.size)
    U = np.concatenate([values, np.zeros((1,) + values.shape[1:])]).reshape(-1,
                                                                            values.shape[2])
    en = space.element_nodes
    mine = np.zeros(space.n_nodes, dtype=bool)
    mine[points] = True
    elements = np.flatnonzero(mine[en].any(axis=1))
    touched = np.unique(en[elements])
    weight = mesh.node_volume[touched]
    strain = nodal_strains_at(space, U, touched, elements, node_row, node_weight=weight)
    materials = mesh.materials
    if materials.uniform is not None:
        stress = stresses_from_strains(strain, materials.uniform)
    else:
        stress = nodal_strains_at(space, U, touched, elements, node_row,
                                  element_D=materials.element_D, node_weight=weight)
    comm = block.comm
    return (PointBlocks(comm, n_points, mesh.points[touched], stress),
            PointBlocks(comm, n_points, mesh.points[touched], strain))
