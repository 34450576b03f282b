"""The connection-point (hybrid-cantilever) model of :mod:`pipeline.reduce.connection` on
MPI ranks, for a parent point P whose region the supports clamp.

Serially the model clamps the parent interface of the UNSUPPORTED body (K_c = T_c^T K
T_c, M_c = T_c^T M T_c) and solves for its clamped modes Phi_c. With a rigid (RBE2)
parent coupling, clamping q_P = 0 holds every DOF of the parent region and nothing
else; when the supports hold exactly those DOFs (``supports: [{region: <parent
region>, fix: all}]``) the clamped pencil IS the run's supported (K, M) and Phi_c are
the run's modes, already on the ranks (a :class:`~pipeline.distributed.blocks.RowBlock`
of each rank's rows). What remains are products summed over the ranks:

    L_P = Phi_c^T M R_P = sum_r Phi_r^T (M R_P)_r       (N x 6)   RowBlock.gram
    D_P = R_P^T M R_P   = tau^T D_O tau                  (6 x 6)
    D_P0 = D_P - L_P^T L_P

with R_P the rigid-body modes about P (node x_j gets [I, -skew(x_j - P)]). (M R_P)_r
are rank r's rows (its free DOFs) of the unsupported M times R_P: the free rows of M
couple to the clamped DOFs too, so they are summed from the elements of r's part that
touch its nodes (M = N (x) I_3, N the node-level mass), with every column, held or
free. D_O = R_O^T M R_O is the body's rigid mass about the origin that the FE stage
sums over the ranks (``props.rigid_mass``) and tau = [[I, skew(P)], [0, I]] moves a
twist from P to the origin (R_P = R_O tau). The small dense algebra (the residual-mass
check, the state space, the tables) is the serial code's.

Not distributed yet (refused by :func:`check_connections`, one line each): child
points, Craig-Bampton data, a distributing (RBE3) parent coupling, a parent region that
is not exactly what the supports hold, added masses, a rotating body. The
floating-frame invariants (``/ffrf``) and the unsupported body's FE matrices (``/fe``)
that the serial run writes beside a connection model are not written on ranks: the
latter is the whole K and M.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from pipeline.config import Config
from pipeline.distributed.assemble import local_node_mass
from pipeline.distributed.blocks import RowBlock
from pipeline.errors import ConfigError, RegionError
from pipeline.fe.body import rigid_body_modes
from pipeline.reduce.build import connection_outputs
from pipeline.reduce.connection import ConnectionModel, check_residual_mass
from pipeline.reduce.models import Models
from pipeline.reduce.interfaces import (Interface, make_interface, rigid_properties_from_mass,
                                        twist_transform)

log = logging.getLogger(__name__)

__all__ = ["check_connections", "parent_interface", "rigid_mass_rows", "connection_models"]

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
    if len(cfg.connections) > 1:
        raise _refuse("connections[1]", "child points", cfg.connections[1].name,
                      "the parent point only, or another modes.solver")
    if cfg.craig_bampton_modes > 0:
        raise _refuse("craig_bampton.modes", "Craig-Bampton data", cfg.craig_bampton_modes,
                      "0, or another modes.solver")
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


def parent_interface(cfg: Config, space, regions, fixed: np.ndarray) -> Interface | None:
    """Rank 0, on the whole mesh: the parent interface of ``cfg.connections`` (None
    without), checked to tie exactly the ``fixed`` DOFs (the clamped pencil is then the
    supported one; RegionError otherwise)."""
    if not cfg.connections:
        return None
    c = cfg.connections[0]
    iface = make_interface(space, regions, c.name, c.region, c.point, c.coupling,
                           key="connections[0]")
    dofs = (3 * iface.nodes[:, None] + np.arange(3)).ravel()
    if not np.array_equal(np.sort(dofs), np.sort(np.asarray(fixed))):
        raise RegionError(f"connections[0].region: region '{c.region}' ties {dofs.size} DOFs "
                          f"but the supports hold {np.asarray(fixed).size} {SOLVER}; expected "
                          "the supports to hold exactly the parent region")
    return iface


def rigid_mass_rows(mesh, point) -> np.ndarray:
    """(hi - lo, 6) this rank's rows (PETSc order) of M R_P, M the unsupported body's
    consistent mass (kg) and R_P its rigid-body modes about ``point`` (3,) m: kg | kg m.

    ``mesh``: the rank's :class:`~pipeline.distributed.submesh.RankMesh`; its elements
    that touch an owned node give those nodes' whole rows of N (module)."""
    en = mesh.space.element_nodes
    elements = np.flatnonzero(mesh.owned_nodes[en].any(axis=1))
    N = local_node_mass(mesh, elements)
    points = mesh.space.node_points
    R = rigid_body_modes(points, np.asarray(point, dtype=float)).reshape(points.shape[0], 18)
    rows = (N @ R).reshape(-1, 6)  # local DOF 3 i + c
    owned = (mesh.dof_rows >= mesh.lo) & (mesh.dof_rows < mesh.hi)
    out = np.zeros((mesh.hi - mesh.lo, 6))
    out[mesh.dof_rows[owned] - mesh.lo] = rows[owned]
    return out


def connection_models(cfg: Config, space, props, modes, models):
    """``models`` (a :class:`~pipeline.reduce.models.Models` record) with the connection
    model at the parent point, its state space and summary lines, from the run's modes
    on the ranks (module; collective). ``space``: the
    :class:`~pipeline.distributed.submesh.DistributedSpace` with the parent interface;
    ``props``: the body's properties (``rigid_mass`` about the origin)."""
    parent = space.connection
    shapes: RowBlock = modes.shapes
    P = parent.point
    L_P = shapes.gram(shapes.like(rigid_mass_rows(space.local, P)))
    tau = twist_transform(P, np.zeros(3))
    rigid = rigid_properties_from_mass(tau.T @ props.rigid_mass @ tau, P)
    D_P0 = check_residual_mass(rigid.D_P - L_P.T @ L_P, parent.name)
    omega2 = np.asarray(modes.omega2, dtype=float)
    model = ConnectionModel(parent, (), rigid, omega2, L_P, D_P0, shapes,
                            np.zeros((0, omega2.size)), np.zeros((0, 6)),
                            np.asarray(modes.residuals))
    ss, lines = connection_outputs(cfg, model)
    log.info("connection '%s': %d clamped modes (the run's), %d rank(s)", parent.name,
             omega2.size, shapes.comm.size)
    models = models if models is not None else Models()
    return replace(models, connection=model, connection_statespace=ss,
                   summary=models.summary + tuple(lines))
