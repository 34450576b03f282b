"""The connection-point (hybrid-cantilever) model of :mod:`pipeline.reduce.connection`
on MPI ranks, with optional child points.

Serially the model clamps the parent interface of the UNSUPPORTED body (K_c = T_c^T K
T_c, M_c = T_c^T M T_c, s = T_c [z; q_C]: the interface change of coordinates without
the parent's q_P; K and M before the supports, springs left out, added masses in M)
and solves for its clamped modes Phi_c. Two cases on the ranks:

1. The run's pencil is the clamped one (:func:`clamped_by_supports`): a rigid (RBE2)
   parent, whose q_P = 0 holds every DOF of the parent region and nothing else, and
   supports that hold exactly those DOFs (``supports: [{region: <parent region>, fix:
   all}]``), no spring, no in-plane constraint, no added mass. The clamped problem
   lives on the run's free DOFs, with the run's distributed K and M:

   - no child point: T_c is the identity, Phi_c are the run's modes, already on the
     ranks (a :class:`~pipeline.distributed.blocks.RowBlock` of each rank's rows);
   - child points (RBE2 or RBE3): T_c is an exact constraint u = T_c q of the kind
     :class:`~pipeline.distributed.constraints.DistributedConstraint` handles: rank 0
     builds it with the serial :func:`~pipeline.reduce.interfaces.interface_transformation`
     and sends each rank its own rows (its free DOFs; a column belongs to the rank of
     its first row), PETSc's PtAP makes (K_c, M_c), SLEPc solves it on MUMPS, and
     Phi_C (6 n_c x N) are the clamped modes' rows at the q_C coordinates.

2. Anything else (a distributing parent; supports elsewhere, partial, elastic or none;
   ``constraints.in_plane``; added masses): the unsupported pair of
   :mod:`pipeline.distributed.unsupported` (a second K and M on a partition of every
   DOF, or the run's own for a body with nothing held), T_c's rows on every DOF, the
   same PtAP and MUMPS solve; L_P = Phi_c^T (M R_P) with that M's distributed product
   (the added masses in it), and the floating-frame invariants of the run's elastic
   modes, padded with zero rows on the held DOFs, on that pair.

What remains are products summed over the ranks:

    L_P = Phi_c^T M R_P = sum_r Phi_r^T (M R_P)_r       (N x 6)   RowBlock.gram
    D_P = R_P^T M R_P   = tau^T D_O tau                  (6 x 6)
    D_P0 = D_P - L_P^T L_P

with R_P the rigid-body modes about P (node x_j gets [I, -skew(x_j - P)]). (M R_P)_r
are rank r's rows (its free DOFs) of the unsupported M times R_P (case 1: the free rows of M
couple to the clamped DOFs too, so they are summed from the elements of r's part that
touch its nodes (M = N (x) I_3, N the node-level mass), with every column, held or
free, :func:`~pipeline.distributed.assemble.rigid_mass_rows`; case 2: M's own product).
D_O = R_O^T M R_O is the body's rigid mass about the origin that the FE stage
sums over the ranks (``props.rigid_mass``) and tau = [[I, skew(P)], [0, I]] moves a
twist from P to the origin (R_P = R_O tau). The small dense algebra (the residual-mass
check, the child transports, the state space, the tables) is the serial code's.

Craig-Bampton data (``craig_bampton.modes`` > 0) are
:mod:`pipeline.distributed.craig_bampton`'s (case 1 on the run's pair with the parent
held, case 2 on the unsupported pair), the floating-frame invariants (``/ffrf``) of the
run's modes or of the Craig-Bampton basis :mod:`pipeline.distributed.ffrf`'s.

A rotating body's connection model is its model at rest, as serially (the rotation
stage works from the run's K, M and modes). The unsupported body's FE matrices
(``/fe``) are summed from each rank's elements (and its rows of the added masses) and
written by rank 0 block by block (:mod:`pipeline.distributed.fe_matrices`).
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

import scipy.sparse as sp

from pipeline.config import Config
from pipeline.distributed.assemble import element_share, rigid_mass_rows
from pipeline.distributed.constraints import from_entries
from pipeline.distributed.craig_bampton import (clamped_solve, craig_bampton_on_ranks,
                                                interface_rows)
from pipeline.distributed.fe_matrices import SummedCsr
from pipeline.distributed.ffrf import modes_invariants
from pipeline.distributed.mpi import petsc
from pipeline.distributed.operators import RowMatrix
from pipeline.distributed.partition import RowPartition
from pipeline.distributed.unsupported import assemble_pair, padded
from pipeline.reduce.build import connection_outputs, craig_bampton_line
from pipeline.reduce.connection import model_from_clamped
from pipeline.reduce.ffrf import (craig_bampton_columns, craig_bampton_kind,
                                 modes_basis_labels)
from pipeline.reduce.interfaces import (Interface, interface_transformation, make_interfaces,
                                        rigid_properties_from_mass, twist_transform)
from pipeline.reduce.models import Models

log = logging.getLogger(__name__)

__all__ = ["clamped_by_supports", "connection_interfaces", "clamped_entries", "connection_models"]


def clamped_by_supports(cfg: Config) -> bool:
    """Whether the clamped pencil of the connection model is the run's (module, case 1):
    a rigid parent whose region the supports alone hold (fix: all), nothing else held,
    no spring, no in-plane constraint, no added mass (config only: the same region gives
    the same DOFs)."""
    parent = cfg.connections[0]
    held = [(s.region, tuple(sorted(s.fix)), s.frame, s.spring, s.bushing)
            for s in cfg.supports]
    return (parent.coupling == "rigid" and not cfg.constraints.in_plane and not cfg.masses
            and held == [(parent.region, ("x", "y", "z"), None, None, None)])


def connection_interfaces(cfg: Config, space, regions) -> tuple[Interface, ...] | None:
    """Rank 0, on the whole mesh: the interfaces of ``cfg.connections``, parent first
    (None without), checked (:func:`~pipeline.reduce.interfaces.make_interfaces`)."""
    if not cfg.connections:
        return None
    return tuple(make_interfaces(space, regions, cfg.connections))


def clamped_entries(interfaces: tuple[Interface, ...], node_points: np.ndarray,
                    free: np.ndarray, part: RowPartition) -> tuple[list, int]:
    """Rank 0: (per rank the entries of its rows of T_c, the (n_free, n_c) change of
    coordinates s = T_c [z; q_C] of the body clamped at the parent with free child
    points (the serial :func:`~pipeline.reduce.interfaces.interface_transformation`'s
    columns but q_P, on the free rows: the parent's rows are the held DOFs), in
    :func:`~pipeline.distributed.constraints.rank_entries`' form with each column's
    serial index as its key; n_z, the interior coordinates). A column belongs to the
    rank of its first free row."""
    parent, children = interfaces[0], interfaces[1:]
    free = np.asarray(free)
    tr = interface_transformation(3 * node_points.shape[0], node_points,
                                  children + (parent,))
    T = tr.T[:, :tr.n_z + 6 * len(children)].tocsr()[free]
    Tc = T.tocsc()
    Tc.sort_indices()
    size = part.starts.size - 1
    owner = np.empty(free.size, dtype=np.int64)
    for r in range(size):
        owner[part.owned_free(r)] = r
    column_owner = owner[Tc.indices[Tc.indptr[:-1]]]
    out = []
    for r in range(size):
        own = part.owned_free(r)
        rows = T[own].tocoo()
        out.append((own[rows.row], rows.col.astype(float), rows.data,
                    np.flatnonzero(column_owner == r).astype(float)))
    return out, tr.n_z


def _scatter_entries(comm, interfaces, node_points, part: RowPartition):
    """(this rank's entries of T_c, n_z): rank 0 makes every rank's rows
    (:func:`clamped_entries`, from the whole partition, gathered on rank 0 for it) and
    sends them (collective)."""
    whole = part.whole(comm, root=0)
    sources, n_z = (clamped_entries(interfaces, node_points, whole.free_dofs(), whole)
                    if comm.rank == 0 else (None, None))
    del whole
    return comm.scatter(sources, root=0), comm.bcast(n_z, root=0)


def _clamped_pencil_modes(cfg: Config, entries, n_z: int, n_children: int, K: RowMatrix,
                          M: RowMatrix):
    """(omega2 (N,), shapes (K's rows, N), residuals (N,), Phi_C (6 n_children, N)) of
    (K_c, M_c) = T_c^T (K, M) T_c: PETSc's PtAP on this rank's ``entries`` of T_c, SLEPc
    on MUMPS (collective); the factor and the projected pair are freed here."""
    con = from_entries(K.comm, entries, K.part, "clamped interfaces")
    PETSc, _ = petsc()
    con.project(PETSc, K, M)
    try:
        omega2, coords, residuals, eps = clamped_solve(cfg, con, cfg.modes.count)
        eps.destroy()
        shapes = con.from_q(coords)
    finally:
        con.destroy()
    pick = np.arange(6 * n_children)
    Phi_C = coords.sensor_product(sp.csr_matrix(
        (np.ones(pick.size), (pick, n_z + pick)), shape=(pick.size, con.n_q)))
    return omega2, shapes, residuals, Phi_C


def connection_models(cfg: Config, space, props, K: RowMatrix,
                      M: RowMatrix, modes, models):
    """``models`` (a :class:`~pipeline.reduce.models.Models` record) with the connection
    model at the parent point, its state space and summary lines (module; collective).
    ``space``: the :class:`~pipeline.distributed.submesh.DistributedSpace` with the
    interfaces (rank 0: the whole mesh's points) and, when the clamped pencil is not the
    run's, the unsupported body's part (``space.unsupported``); ``props``: the body's
    properties (``rigid_mass`` about the origin); ``K``, ``M``: the run's distributed matrices with their PETSc matrices; ``modes``:
    the run's."""
    if space.unsupported is not None:
        return _unsupported_models(cfg, space, props, K, M, modes, models)
    interfaces = space.connections
    parent, children = interfaces[0], interfaces[1:]
    comm = K.comm
    entries = n_z = None
    if children or cfg.craig_bampton_modes > 0:  # rank 0 sends each rank its rows of T_c
        entries, n_z = _scatter_entries(comm, interfaces, space.node_points, K.part)
    if children:  # the clamped pencil of the free-floating children: its own solve
        omega2, shapes, residuals, Phi_C = _clamped_pencil_modes(cfg, entries, n_z,
                                                                 len(children), K, M)
    else:  # the clamped pencil is the run's: its modes
        omega2, shapes, residuals = modes.omega2, modes.shapes, modes.residuals
        Phi_C = np.zeros((0, omega2.size))
    L_P = shapes.gram(shapes.like(rigid_mass_rows(space.local, parent.point)))
    model, ss, lines = _model(cfg, interfaces, props, omega2, L_P, shapes, Phi_C, residuals)
    cb = None
    if cfg.craig_bampton_modes > 0:
        cb, basis = craig_bampton_on_ranks(cfg, space, K, M, entries, n_z,
                                           model.rigid.D_P)
        keep, names, units = craig_bampton_columns(cb, 0)
        inv = modes_invariants(space, K, M, basis.columns(keep), props.rigid_mass,
                               (craig_bampton_kind(cb), names, units))
        lines.append(craig_bampton_line(cfg))
    else:
        inv = modes_invariants(space, K, M, modes.shapes, props.rigid_mass)
    return _with(models, model, ss, cb, inv, _fe_shares(comm, space, K.part),
                 lines)


def _model(cfg, interfaces, props, omega2, L_P, shapes, Phi_C, residuals):
    """(the ConnectionModel, its state space, its summary lines) from the clamped
    solve's results; D_P = tau^T D_O tau (module)."""
    parent, children = interfaces[0], interfaces[1:]
    tau = twist_transform(parent.point, np.zeros(3))
    rigid = rigid_properties_from_mass(tau.T @ props.rigid_mass @ tau, parent.point)
    model = model_from_clamped(parent, children, rigid, np.asarray(omega2, dtype=float), L_P,
                               shapes, Phi_C, np.asarray(residuals))
    ss, lines = connection_outputs(cfg, model)
    return model, ss, lines


def _fe_shares(comm, space, part: RowPartition) -> tuple:
    """The unsupported K and M (``/fe``) as each rank's share: the elements whose mass
    its part sums, and its rows of the added masses (their upper triangle; the DOF of
    every PETSc row, gathered for it: the added masses' columns are any rank's rows)."""
    mesh = space.local
    K, M = element_share(mesh, space.n_dofs)
    if mesh.added is not None:
        dof = part.whole(comm).dofs
        A = mesh.added.tocoo()
        rows, cols = dof[mesh.lo + A.row], dof[A.col]
        up = rows <= cols
        M = (M + sp.csr_matrix((A.data[up], (rows[up], cols[up])), shape=M.shape)).tocsr()
    return SummedCsr(comm, K), SummedCsr(comm, M)


def _with(models, model, ss, cb, inv, fe, lines):
    models = models if models is not None else Models()
    return replace(models, connection=model, connection_statespace=ss, craig_bampton=cb,
                   ffrf=inv, fe_matrices=fe, summary=models.summary + tuple(lines))


def _unsupported_models(cfg: Config, space, props, K: RowMatrix,
                        M: RowMatrix, modes, models):
    """:func:`connection_models` on the unsupported pair (module): the run's K and M when
    no DOF is held (``space.unsupported.mesh`` None), else a second pair assembled on
    the partition of every DOF and freed after the clamped solve and the invariants."""
    interfaces = space.connections
    parent, children = interfaces[0], interfaces[1:]
    comm, un = K.comm, space.unsupported
    own = un.mesh is not None
    if own:
        K, M = assemble_pair(comm, un)
        space = replace(space, local=un.mesh)
    try:
        entries, n_z = _scatter_entries(comm, interfaces, space.node_points, K.part)
        omega2, shapes, residuals, Phi_C = _clamped_pencil_modes(cfg, entries, n_z,
                                                                 len(children), K, M)
        R_P = shapes.like(interface_rows(space.local, shapes, parent, every=True))
        L_P = shapes.gram(M.apply(R_P))  # M R_P: M holds every DOF, the added masses too
        model, ss, lines = _model(cfg, interfaces, props, omega2, L_P, shapes, Phi_C,
                                  residuals)
        cb = None
        if cfg.craig_bampton_modes > 0:  # on the same pair, nothing held
            cb, basis = craig_bampton_on_ranks(cfg, space, K, M, entries, n_z, None)
            keep, names, units = craig_bampton_columns(cb, 0)
            inv = modes_invariants(space, K, M, basis.columns(keep), props.rigid_mass,
                                   (craig_bampton_kind(cb), names, units))
            lines.append(craig_bampton_line(cfg))
        else:  # of the run's elastic modes (serial /ffrf), zero on the held DOFs
            run = padded(modes.shapes, un.part) if own else modes.shapes
            keep = np.arange(modes.n_rigid, run.shape[1])
            inv = modes_invariants(space, K, M, run.columns(keep), props.rigid_mass,
                                   modes_basis_labels(keep, bool(cfg.supports)))
    finally:
        if own:
            K.petsc.destroy()
            M.petsc.destroy()
    return _with(models, model, ss, cb, inv, _fe_shares(comm, space, K.part),
                 lines)
