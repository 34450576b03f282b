"""The connection-point (hybrid-cantilever) model of :mod:`pipeline.reduce.connection` on
MPI ranks, for a rigid parent point P whose region the supports clamp, with optional
child points.

Serially the model clamps the parent interface of the UNSUPPORTED body (K_c = T_c^T K
T_c, M_c = T_c^T M T_c, s = T_c [z; q_C]: the interface change of coordinates without
the parent's q_P) and solves for its clamped modes Phi_c. With a rigid (RBE2) parent
coupling, q_P = 0 holds every DOF of the parent region and nothing else; when the
supports hold exactly those DOFs (``supports: [{region: <parent region>, fix: all}]``)
the clamped problem lives on the run's free DOFs, with the run's distributed K and M:

- no child point: T_c is the identity, Phi_c are the run's modes, already on the ranks
  (a :class:`~pipeline.distributed.blocks.RowBlock` of each rank's rows);
- child points (RBE2 or RBE3): T_c is an exact constraint u = T_c q of the kind
  :class:`~pipeline.distributed.constraints.DistributedConstraint` handles: rank 0
  builds it with the serial :func:`~pipeline.reduce.interfaces.interface_transformation`
  and sends each rank its own rows (its free DOFs; a column belongs to the rank of its
  first row), PETSc's PtAP makes (K_c, M_c), SLEPc solves it on MUMPS, and
  Phi_C (6 n_c x N) are the clamped modes' rows at the q_C coordinates.

What remains are products summed over the ranks:

    L_P = Phi_c^T M R_P = sum_r Phi_r^T (M R_P)_r       (N x 6)   RowBlock.gram
    D_P = R_P^T M R_P   = tau^T D_O tau                  (6 x 6)
    D_P0 = D_P - L_P^T L_P

with R_P the rigid-body modes about P (node x_j gets [I, -skew(x_j - P)]). (M R_P)_r
are rank r's rows (its free DOFs) of the unsupported M times R_P: the free rows of M
couple to the clamped DOFs too, so they are summed from the elements of r's part that
touch its nodes (M = N (x) I_3, N the node-level mass), with every column, held or
free (:func:`~pipeline.distributed.assemble.rigid_mass_rows`). D_O = R_O^T M R_O is the body's rigid mass about the origin that the FE stage
sums over the ranks (``props.rigid_mass``) and tau = [[I, skew(P)], [0, I]] moves a
twist from P to the origin (R_P = R_O tau). The small dense algebra (the residual-mass
check, the child transports, the state space, the tables) is the serial code's.

Craig-Bampton data (``craig_bampton.modes`` > 0) are
:mod:`pipeline.distributed.craig_bampton`'s, the floating-frame invariants (``/ffrf``)
of the run's modes or of the Craig-Bampton basis :mod:`pipeline.distributed.ffrf`'s.

Not distributed yet (refused by :func:`check_connections`, one line each): a
distributing (RBE3) parent coupling, a parent region that is not exactly what the
supports hold, added masses, a rotating body. The unsupported body's FE matrices
(``/fe``) are summed from each rank's elements and written by rank 0 block by block
(:mod:`pipeline.distributed.fe_matrices`).
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

import scipy.sparse as sp

from pipeline.config import Config
from pipeline.distributed.assemble import element_share, rigid_mass_rows
from pipeline.distributed.constraints import from_entries
from pipeline.distributed.craig_bampton import clamped_solve, craig_bampton_on_ranks
from pipeline.distributed.fe_matrices import SummedCsr
from pipeline.distributed.ffrf import modes_invariants
from pipeline.distributed.mpi import petsc
from pipeline.distributed.operators import RowMatrix
from pipeline.distributed.partition import RowPartition
from pipeline.errors import ConfigError, RegionError
from pipeline.reduce.build import connection_outputs, craig_bampton_line
from pipeline.reduce.connection import model_from_clamped
from pipeline.reduce.ffrf import craig_bampton_columns, craig_bampton_kind
from pipeline.reduce.interfaces import (Interface, interface_transformation, make_interfaces,
                                        rigid_properties_from_mass, twist_transform)
from pipeline.reduce.models import Models

log = logging.getLogger(__name__)

__all__ = ["check_connections", "connection_interfaces", "clamped_entries", "connection_models"]

SOLVER = "with modes.solver: slepc"


def _refuse(key: str, what: str, value, expected: str) -> ConfigError:
    return ConfigError(f"{key}: {what} {SOLVER}: not distributed yet; expected {expected}",
                       key=key, value=value, expected=expected)


def check_connections(cfg: Config) -> None:
    """Refuse, before any work, the connection configs the ranks do not handle yet
    (module): one line naming the key."""
    if not cfg.connections:
        return
    parent = cfg.connections[0]
    if parent.coupling != "rigid":
        raise _refuse("connections[0].coupling", f"a {parent.coupling} parent coupling",
                      parent.coupling, "rigid, or another modes.solver")
    held = [(s.region, tuple(sorted(s.fix)), s.frame, s.spring, s.bushing)
            for s in cfg.supports]
    if held != [(parent.region, ("x", "y", "z"), None, None, None)] \
            or cfg.constraints.in_plane:
        raise _refuse("supports", "supports other than the parent region held (fix: all)",
                      len(cfg.supports), f"[{{region: {parent.region}, fix: all}}], or "
                      "another modes.solver")
    if cfg.masses:
        raise _refuse("masses", "added masses beside connections", len(cfg.masses),
                      "no masses, or another modes.solver")
    if cfg.rotation is not None:
        raise _refuse("rotation", "a rotating body with connections", "rotation",
                      "no rotation, or another modes.solver")


def connection_interfaces(cfg: Config, space, regions, fixed: np.ndarray
                          ) -> tuple[Interface, ...] | None:
    """Rank 0, on the whole mesh: the interfaces of ``cfg.connections``, parent first
    (None without), checked (:func:`~pipeline.reduce.interfaces.make_interfaces`) and
    the parent's to tie exactly the ``fixed`` DOFs (the clamped pencil is then the
    supported one; RegionError otherwise)."""
    if not cfg.connections:
        return None
    interfaces = tuple(make_interfaces(space, regions, cfg.connections))
    parent = interfaces[0]
    dofs = (3 * parent.nodes[:, None] + np.arange(3)).ravel()
    if not np.array_equal(np.sort(dofs), np.sort(np.asarray(fixed))):
        raise RegionError(f"connections[0].region: region '{parent.region}' ties {dofs.size} "
                          f"DOFs but the supports hold {np.asarray(fixed).size} {SOLVER}; "
                          "expected the supports to hold exactly the parent region")
    return interfaces


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


def connection_models(cfg: Config, space, props, free: np.ndarray, K: RowMatrix,
                      M: RowMatrix, modes, models):
    """``models`` (a :class:`~pipeline.reduce.models.Models` record) with the connection
    model at the parent point, its state space and summary lines (module; collective).
    ``space``: the :class:`~pipeline.distributed.submesh.DistributedSpace` with the
    interfaces (rank 0: the whole mesh's points); ``props``: the body's properties
    (``rigid_mass`` about the origin); ``free`` (n_free,) the free DOFs; ``K``, ``M``:
    the run's distributed matrices with their PETSc matrices; ``modes``: the run's."""
    interfaces = space.connections
    parent, children = interfaces[0], interfaces[1:]
    comm = K.comm
    entries = n_z = None
    if children or cfg.craig_bampton_modes > 0:  # rank 0 sends each rank its rows of T_c
        sources, n_z = (clamped_entries(interfaces, space.node_points, free, K.part)
                        if comm.rank == 0 else (None, None))
        n_z = comm.bcast(n_z, root=0)
        entries = comm.scatter(sources, root=0)
    if children:  # the clamped pencil of the free-floating children: its own solve
        con = from_entries(comm, entries, K.part, "clamped interfaces")
        PETSc, _ = petsc()
        con.project(PETSc, K, M)
        try:
            omega2, coords, residuals, eps = clamped_solve(cfg, con, cfg.modes.count)
            eps.destroy()
            shapes = con.from_q(coords)
        finally:
            con.destroy()
        pick = np.arange(6 * len(children))
        Phi_C = coords.sensor_product(sp.csr_matrix(
            (np.ones(pick.size), (pick, n_z + pick)), shape=(pick.size, con.n_q)))
    else:  # the clamped pencil is the run's: its modes
        omega2, shapes, residuals = modes.omega2, modes.shapes, modes.residuals
        Phi_C = np.zeros((0, omega2.size))
    P = parent.point
    L_P = shapes.gram(shapes.like(rigid_mass_rows(space.local, P)))
    tau = twist_transform(P, np.zeros(3))
    rigid = rigid_properties_from_mass(tau.T @ props.rigid_mass @ tau, P)
    model = model_from_clamped(parent, children, rigid, np.asarray(omega2, dtype=float), L_P,
                               shapes, Phi_C, np.asarray(residuals))
    ss, lines = connection_outputs(cfg, model)
    cb = None
    if cfg.craig_bampton_modes > 0:
        cb, basis = craig_bampton_on_ranks(cfg, space, free, K, M, entries, n_z, rigid.D_P)
        keep, names, units = craig_bampton_columns(cb, 0)
        inv = modes_invariants(space, free, K, M, basis.columns(keep), props.rigid_mass,
                               (craig_bampton_kind(cb), names, units))
        lines.append(craig_bampton_line(cfg))
    else:
        inv = modes_invariants(space, free, K, M, modes.shapes, props.rigid_mass)
    fe = tuple(SummedCsr(comm, A) for A in element_share(space.local, space.n_dofs))
    models = models if models is not None else Models()
    return replace(models, connection=model, connection_statespace=ss, craig_bampton=cb,
                   ffrf=inv, fe_matrices=fe, summary=models.summary + tuple(lines))
