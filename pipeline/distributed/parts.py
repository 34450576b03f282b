"""The partitioned mesh file's two ends, so that each rank reads its own part instead
of rank 0 meshing the whole body in the run: ``python -m pipeline partition`` runs
rank 0's mesh phase for N ranks once, on one process (on any node: its memory is the
whole mesh's phase, apart from the ranks'), and writes it (:func:`write_partitioned`); a run with ``mesh.parts``
reads it, each rank its own part and rank 0 what it keeps (:func:`read_parts_header`,
:func:`from_parts`). The file's layout: :mod:`pipeline.distributed.parts_file`.
Features whose rank-0 work needs the whole mesh during the run are refused both ways
(:func:`check_partitionable`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from pipeline.config import Config
from pipeline.distributed.mpi import log_resident, petsc
from pipeline.distributed.partition import graph_partition, partition_kind, slab_partition
from pipeline.distributed.submesh import (DistributedSpace, MeshCounts, compact_nodes,
                                          split_mesh)
from pipeline.distributed.whole import (WholeMesh, added_rigid_mass, mesh_whole,
                                        support_inputs)
from pipeline.errors import ConfigError, SolverError
from pipeline.fe.body import node_volume_weights

log = logging.getLogger(__name__)


#: config keys whose rank-0 work needs the whole mesh during the run: refused with
#: ``mesh.parts`` and by the partition command (:func:`check_partitionable`)
WHOLE_MESH_KEYS = ("connections", "craig_bampton.modes", "supports[i].local_fix",
                   "masses[i].coupling: rigid")


def check_partitionable(cfg: Config) -> None:
    """One line (ConfigError naming the key) for a feature whose rank-0 work needs the
    whole mesh during the run (:data:`WHOLE_MESH_KEYS`): the connection models and
    Craig-Bampton (their interfaces and the unsupported pair), the exact constraint
    u = T q of local-frame supports and rigidly coupled masses. Before any meshing. (A
    rotating body's preloads are port matrices and its added masses a small record,
    both in the file's shared group.)"""
    found = None
    if cfg.connections:
        found = ("connections", "connection models")
    elif cfg.craig_bampton_modes:
        found = ("craig_bampton.modes", "Craig-Bampton models")
    else:
        for i, s in enumerate(cfg.supports):
            if s.local_fix:
                found = (f"supports[{i}].local_fix", "supports held in a local frame")
                break
        for i, m in enumerate(cfg.masses):
            if found is None and m.kind == "point" and m.coupling == "rigid":
                found = (f"masses[{i}].coupling", "rigidly coupled masses")
    if found is not None:
        key, what = found
        raise ConfigError(f"config key '{key}': {what} need the whole mesh on rank 0 during "
                          "the run; expected a run without a parts file (mesh.parts) for "
                          "them (docs/distributed.md, 'Not distributed yet')", key=key,
                          value=what, expected="no partitioned mesh")


def partition_parts(whole: WholeMesh, n_parts: int):
    """(the whole :class:`~pipeline.distributed.partition.RowPartition` of ``whole``'s
    points into ``n_parts`` parts, its kind) on one process: PT-Scotch through PETSc on
    COMM_SELF when petsc4py imports (:func:`~pipeline.distributed.partition.graph_partition`
    with ``parts``), else, or with the PETSc option ``-pipeline_partition slab``, the
    slabs along the longest extent (logged which)."""
    try:
        PETSc, _ = petsc()
    except SolverError:
        PETSc = None
    kind = "slab" if PETSc is None or n_parts == 1 else partition_kind(PETSc)
    space = whole.space
    if kind == "slab":
        log.info("partition into %d parts: slabs along the longest extent%s", n_parts,
                 " (no petsc4py)" if PETSc is None else "")
        return slab_partition(space.node_points, whole.free, n_parts), kind
    log.info("partition into %d parts: PT-Scotch (PETSc's MatPartitioning on one process)",
             n_parts)
    part = graph_partition(PETSc, PETSc.COMM_SELF.tompi4py(), space.element_nodes,
                           space.node_points, whole.free, parts=n_parts)
    return part, kind


def write_partitioned(cfg: Config, ranks: int, output: str | Path,
                      mesh_dir: str | Path | None = None) -> Path:
    """Rank 0's mesh phase for a run on ``ranks`` ranks, on one process, written to the
    parts file ``output`` (:mod:`pipeline.distributed.parts_file`): mesh and evaluate
    the whole mesh (:func:`mesh_whole`), partition it (:func:`partition_parts`), cut out
    every part (:func:`~pipeline.distributed.submesh.split_mesh`, one at a time, each
    written as it is made) and keep the small results and what rank 0 keeps
    (:func:`~pipeline.distributed.stage.handed_off`,
    :class:`~pipeline.distributed.whole.SupportInputs`). Returns the path."""
    from pipeline.distributed.parts_file import Kept, Shared, canonical_config, write_parts
    from pipeline.distributed.prestress import rotation_masses
    from pipeline.solve.labels import label_frame

    check_partitionable(cfg)
    whole = mesh_whole(cfg, mesh_dir, SimpleNamespace(rank=0, size=1))
    space = whole.space
    n_nodes = space.n_nodes
    log.info("%d elements (%s), %d nodes, %d DOFs into %d parts", space.body.n_tetrahedra,
             space.cell_type, n_nodes, space.n_dofs, ranks)
    whole_part, kind = partition_parts(whole, ranks)
    shared = Shared(ranks=ranks, n_nodes=n_nodes,
                    counts=MeshCounts(space.body.n_tetrahedra, space.body.n_vertices),
                    order=space.order, n_free=int(whole.free.size), ports=whole.ports,
                    mesh_path="" if whole.mesh_path is None else str(whole.mesh_path),
                    mesh_sha256=whole.mesh_sha256,
                    added_rigid=None if whole.added is None
                    else added_rigid_mass(space, whole.added),
                    partition=kind, config=canonical_config(cfg),
                    spin_masses=rotation_masses(cfg, space, whole.regions))
    written = cfg.materials or cfg.masses
    kept = Kept(node_points=space.node_points,
                element_nodes=compact_nodes(space.element_nodes, n_nodes),
                regions=dict(whole.regions), materials=whole.materials if written else None,
                label_frame=label_frame(space.node_points, node_volume_weights(space)),
                support=support_inputs(whole))
    parts = split_mesh(space, whole.materials, whole.free, whole_part, ranks, whole.added,
                       whole.springs)
    return write_parts(output, shared, kept,
                       ((mesh, whole_part.local(r)) for r, mesh in enumerate(parts)))


def parts_record(cfg: Config) -> tuple[str, str] | None:
    """(path, content_sha256) of the run's parts file for ``/run``, or None without one."""
    if not cfg.mesh.parts:
        return None
    from pipeline.distributed.parts_file import parts_digest

    return str(cfg.mesh.parts), parts_digest(cfg.mesh.parts)


def read_parts_header(cfg: Config, comm):
    """The shared group of the run's parts file (``mesh.parts``), on every rank: rank 0
    reads and checks it (:func:`pipeline.distributed.parts_file.read_shared`: one line,
    on rank 0 alone, when the file does not fit the run) and sends it."""
    from pipeline.distributed.parts_file import read_shared

    check_partitionable(cfg)
    shared = read_shared(cfg.mesh.parts, cfg, comm.size) if comm.rank == 0 else None
    shared = comm.bcast(shared, root=0)
    log.info("parts file %s: %d nodes, %d elements, %d free DOFs in %d parts (%s partition)",
             cfg.mesh.parts, shared.n_nodes, shared.counts.n_tetrahedra, shared.n_free,
             shared.ranks, shared.partition)
    return shared


def from_parts(cfg: Config, shared, comm):
    """This rank's (RankMesh, own RowPartition, DistributedSpace, regions, element
    materials, held DOFs, SupportInputs or None, constraint None) read from the parts
    file: its own group only; rank 0 besides what it keeps (the whole mesh's points and
    int32 elements, regions, written materials, label frame, support inputs)."""
    from pipeline.distributed.parts_file import read_kept, read_rank

    mesh, part = read_rank(cfg.mesh.parts, comm.rank)
    log_resident(log, comm, "part read")
    judge, regions, materials = None, {}, mesh.materials
    fixed = np.zeros(0, np.int64)
    if comm.rank == 0:
        kept = read_kept(cfg.mesh.parts)
        space = DistributedSpace(mesh.space.order, shared.n_nodes, shared.counts,
                                 kept.node_points, kept.element_nodes, mesh, shared.ports,
                                 label_frame=kept.label_frame,
                                 rotation_masses=shared.spin_masses)
        regions, judge, fixed = kept.regions, kept.support, kept.support.fixed
        if kept.materials is not None:
            materials = kept.materials
        log_resident(log, comm, "kept read")
    else:
        nb = mesh.space.element_nodes.shape[1]
        space = DistributedSpace(mesh.space.order, shared.n_nodes, shared.counts,
                                 np.zeros((0, 3)), np.zeros((0, nb), np.int64), mesh,
                                 shared.ports, rotation_masses=shared.spin_masses)
    return mesh, part, space, regions, materials, fixed, judge, None
