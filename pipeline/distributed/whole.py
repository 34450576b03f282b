"""Rank 0's whole mesh on the distributed path (``modes.solver: slepc``): meshing and
evaluating once what needs the whole body (:func:`mesh_whole`: regions, supports,
materials, added masses, ports, the exact constraint's inputs), what judging the
supports needs after the hand-off (:class:`SupportInputs`) and the added masses'
rigid mass (:func:`added_rigid_mass`). Used by the run that meshes
(:func:`pipeline.distributed.stage.build_fe_model`) and by the partition command
(:func:`pipeline.distributed.parts.write_partitioned`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import scipy.sparse as sp

from pipeline.config import Config
from pipeline.distributed.mpi import log_resident, world
from pipeline.distributed.prestress import preload_ports
from pipeline.errors import SolverError
from pipeline.fe.body import rigid_body_modes
from pipeline.fe.model import constraint_inputs, mesh_config
from pipeline.fe.ports import check_gauges, port_matrices
from pipeline.fe.regions import fixed_dofs, free_dofs

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WholeMesh:
    """What rank 0 evaluates on the whole mesh before the parts are sent (the others
    receive the parts, the counts and the small results): the space, its regions, the
    element materials, the added masses (or None), the held and the free DOFs, the port
    matrices (None: no reduction), the mesh file kept, its SHA-256, the springs' and
    bushings' stiffness ((n_dofs, n_dofs) N/m, or None) and the inputs of the exact
    constraint u = T q (:func:`pipeline.fe.model.constraint_inputs`, or None). The
    rigid motions the supports leave are judged after the assembly
    (:func:`~pipeline.distributed.stage.supports_rigid_freedoms`)."""

    space: Any
    regions: dict
    materials: Any
    added: Any
    fixed: np.ndarray
    free: np.ndarray
    ports: Any
    mesh_path: Path | None
    mesh_sha256: str
    springs: Any = None
    constraint: Any = None


def mesh_whole(cfg: Config, mesh_dir: str | Path | None, comm=None) -> WholeMesh:
    """Rank 0: mesh the body (gmsh), resolve the regions, materials, added masses, ports
    and supports on the whole mesh; every misplaced region or gauge is refused here,
    before any rank assembles. ``comm``: the run's communicator (its rank names the
    memory log lines); None: COMM_WORLD, or one process without MPI (the partition
    command, :func:`~pipeline.distributed.parts.write_partitioned`)."""
    if comm is None:
        try:
            comm = world()
        except SolverError:  # no petsc4py: one process, rank 0
            comm = SimpleNamespace(rank=0, size=1)
    meshed = mesh_config(cfg, mesh_dir, lambda step: log_resident(log, comm, step))
    space, regions, materials = meshed.space, meshed.regions, meshed.materials
    added, springs, extra = meshed.added, meshed.supports.springs, meshed.supports
    mesh_path, mesh_sha256 = meshed.mesh_path, meshed.mesh_sha256
    del meshed
    check_gauges(space, regions, cfg.ports, materials)
    fixed = fixed_dofs(space, regions, cfg.supports, cfg.constraints.in_plane)
    free = free_dofs(space.n_dofs, fixed)
    constraint = constraint_inputs(space, regions, cfg, free, extra)  # refusals: before K
    ports = None if cfg.reduction is None else \
        port_matrices(space, regions, cfg.ports, material=materials)
    if ports is None and cfg.rotation is not None:  # a rotating body's preloads
        ports = port_matrices(space, regions, preload_ports(cfg))
    return WholeMesh(space, regions, materials, added, fixed, free, ports, mesh_path,
                     mesh_sha256, springs, constraint)


@dataclass(frozen=True)
class SupportInputs:
    """What rank 0 keeps of the whole mesh past the hand-off to judge, after the
    assembly, the rigid motions the supports leave
    (:func:`~pipeline.distributed.stage.supports_rigid_freedoms`):
    the held DOFs (n_c,), the springs' and bushings' stiffness ((n_dofs, n_dofs) N/m,
    nonzero at their points only, or None), the held local directions ((n_h, n_dofs)
    CSR, or None) and whether any DOF is free; the points are the kept space's."""

    fixed: np.ndarray
    springs: Any
    held: Any
    any_free: bool


def support_inputs(whole: WholeMesh) -> SupportInputs:
    """:class:`SupportInputs` of ``whole``."""
    return SupportInputs(whole.fixed, whole.springs,
                         None if whole.constraint is None else whole.constraint[0],
                         bool(whole.free.size))


def added_rigid_mass(space, added) -> np.ndarray:
    """(6, 6) R^T A R of the added masses A (n_dofs, n_dofs) about the origin, from the
    rows of the points they touch only (R: the rigid-body modes of those points)."""
    dofs = np.unique(sp.csr_matrix(added).nonzero()[0] // 3)
    dofs = (3 * dofs[:, None] + np.arange(3)).ravel()
    R = rigid_body_modes(space.node_points[dofs[::3] // 3])
    return R.T @ (sp.csr_matrix(added)[dofs][:, dofs] @ R)
