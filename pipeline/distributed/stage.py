"""The FE and modes stages on MPI ranks (``modes.solver: slepc``): the same records as
the serial stages (:class:`~pipeline.fe.model.FEModel`, :class:`~pipeline.solve.modes.Modes`)
with K and M as :class:`~pipeline.distributed.operators.RowMatrix` stand-ins, so that
:func:`pipeline.run.run_pipeline` runs the reduce stage unchanged on every rank.

Per rank, memory: the mesh and FE space (every rank meshes the same body: O(n_points),
replicated), its rows of K and M (1/size of them, plus one element layer), its part of
MUMPS' factor, and its rows of the mode shapes (a :class:`RowBlock`, 8 n_free n_modes /
size bytes); the reduce stage and the writer work from those rows
(:mod:`pipeline.distributed.reduce`), rank 0 writing the shapes and stress modes one
block of points at a time (:class:`~pipeline.distributed.blocks.PointBlocks`).
"""

from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from pipeline.config import Config
from pipeline.errors import ConfigError
from pipeline.distributed.assemble import local_node_mass, local_rows
from pipeline.distributed.eigen import petsc_matrix, rigid_near_null_space, solve_eigen
from pipeline.distributed.mpi import petsc, world
from pipeline.distributed.operators import KspSolve, RowMatrix, SummedMatrix
from pipeline.distributed.partition import cut_measures, graph_partition, slab_partition
from pipeline.fe.assemble import whole_nodes
from pipeline.fe.added_mass import added_mass_matrix
from pipeline.fe.body import (body_properties, node_volume_weights,
                              properties_from_rigid_mass, rigid_body_modes)
from pipeline.fe.materials import config_materials
from pipeline.fe.ports import check_gauges
from pipeline.fe.mesh import mesh_body
from pipeline.fe.model import FEModel
from pipeline.fe.regions import check_region_uses, fixed_dofs, free_dofs, resolve_regions
from pipeline.fe.space import build_space
from pipeline.fe.supports import rigid_freedoms
from pipeline.distributed.blocks import PointBlocks, RowBlock
from pipeline.distributed.reduce import (build_statespace,  # noqa: F401 (run.py's)
                                         label_rows, rayleigh_ritz_rows, shapes_blocks,
                                         stress_blocks)
from pipeline.solve.eigen import default_shift
from pipeline.solve.modes import Modes
from pipeline.store.schema import stress_modes_datasets

log = logging.getLogger(__name__)

#: the backend name the result file records (``/run`` solver, ``/modes`` backend)
BACKEND = "slepc"


def check_supported(cfg: Config) -> None:
    """One line for what the distributed path does not do yet (before any work)."""
    if cfg.connections:
        raise ConfigError("connections with modes.solver: slepc: connection models need the "
                          "unsupported K on one process; expected no connections, or another "
                          "modes.solver", key="connections", value=len(cfg.connections),
                          expected="no connections with modes.solver: slepc")
    for i, s in enumerate(cfg.supports):
        if s.local_fix:
            raise ConfigError(f"supports[{i}].fix: components in a local frame with "
                              "modes.solver: slepc: the exact constraint u = T q is not "
                              "distributed yet; expected global x, y, z components, or "
                              "another modes.solver", key=f"supports[{i}].fix",
                              value=list(s.local_fix), expected="global components")
    for i, m in enumerate(cfg.masses):
        if m.kind == "point" and m.coupling == "rigid":
            raise ConfigError(f"masses[{i}].coupling: rigid with modes.solver: slepc: the "
                              "exact constraint u = T q is not distributed yet; expected "
                              "distributing, or another modes.solver",
                              key=f"masses[{i}].coupling", value="rigid",
                              expected="distributing")
    not_yet = [(key, what) for key, what, present in (
        ("rotation", "a rotating body", cfg.rotation is not None),
        ("supports", "elastic supports (spring, bushing)",
         any(s.spring is not None or s.bushing is not None for s in cfg.supports)))
        if present]
    if not_yet:
        key, what = not_yet[0]
        raise ConfigError(f"{key} with modes.solver: slepc: the distributed path does not "
                          f"handle {what} yet (each rank assembles its elements' materials "
                          "and masses, held or free); expected no such key, or another "
                          "modes.solver",
                          key=key, value=what, expected=f"no {key} with modes.solver: slepc")
    if cfg.reduction is not None and cfg.reduction.static_correction == "augment":
        raise ConfigError("reduction.static_correction: augment with modes.solver: slepc: "
                          "the Ritz basis of the static shapes is not distributed yet; "
                          "expected none or residual, or another modes.solver",
                          key="reduction.static_correction", value="augment",
                          expected="none or residual")
    if cfg.modes.precision == "mixed":
        raise ConfigError("modes.precision: mixed with modes.solver: slepc: expected auto or "
                          "double", key="modes.precision", value="mixed",
                          expected="auto or double")


def rank_and_size() -> tuple[int, int]:
    """(this rank, number of ranks) of COMM_WORLD."""
    comm = world()
    return comm.rank, comm.size


@contextlib.contextmanager
def abort_on_failure():
    """On more than one rank, an exception on any rank stops every rank (MPI_Abort with
    the exception's exit code) instead of leaving the others waiting in a collective;
    the file is written atomically by rank 0, so nothing partial remains."""
    try:
        yield
    except BaseException as exc:
        try:
            comm = world()
        except Exception:  # no MPI: nothing to stop but this process
            raise exc from None
        if comm.size > 1:
            import sys

            code = getattr(exc, "exit_code", 1)
            print(f"error on rank {comm.rank} of {comm.size}: {exc}", file=sys.stderr, flush=True)
            comm.Abort(code)
        raise


def check_rank_memory(space, cfg: Config, comm) -> int:
    """Refuse, on every rank and before the assembly, a run whose ranks on one node would
    need more than the node has (ResourceError, one line). Per rank: the serial model of
    :mod:`pipeline._util.resources` for the whole problem (factor method), its K, M and
    factor share and its three (n_dofs, n_modes) arrays of mode shapes divided by the
    rank count, plus what every rank holds (baseline, mesh). Returns the bytes per rank."""
    from mpi4py import MPI

    from pipeline._util import resources as res
    from pipeline.errors import ResourceError

    n_nodes, n_el, count = space.n_nodes, space.body.n_tetrahedra, cfg.modes.count
    mesh = res.MESH_BYTES_PER_NODE * n_nodes + 64 * n_el
    whole = res.estimate_memory_bytes(n_nodes, n_el, space.order, count, "factor",
                                      solver="pardiso")
    replicated = res.BASELINE_BYTES + mesh
    shapes = 3 * 8.0 * space.n_dofs * count
    per_rank = int(replicated + (whole - res.BASELINE_BYTES - mesh + shapes) / comm.size)
    node_ranks = comm.Split_type(MPI.COMM_TYPE_SHARED).size
    need = comm.allreduce(per_rank * node_ranks, op=MPI.MAX)
    have = comm.allreduce(res.available_memory_bytes(), op=MPI.MIN)
    log.info("memory estimate %.2f GB per rank, %d ranks on this node, %.2f GB available",
             per_rank / 1e9, node_ranks, have / 1e9)
    if need > res.HEADROOM * have:
        raise ResourceError(
            f"mesh with {space.n_dofs} DOFs on {comm.size} ranks needs about "
            f"{per_rank / 1e9:.1f} GB per rank, {need / 1e9:.1f} GB for the {node_ranks} "
            f"ranks of one node, but only {have / 1e9:.1f} GB is available; expected more "
            "nodes (fewer ranks per node) or a larger mesh.size")
    return per_rank


def build_fe_model(cfg: Config, mesh_dir: str | Path | None, stage) -> FEModel:
    """Mesh (every rank, the same mesh), regions, supports, this rank's rows of K and M
    (PETSc's slab partition), the body's mass properties (summed over the ranks)."""
    check_supported(cfg)
    comm = world()
    with stage("mesh"):
        body, mesh_path, mesh_sha256 = mesh_body(cfg.geometry, cfg.mesh,
                                                 mesh_dir if comm.rank == 0 else None, cfg.name)
        space = build_space(body, cfg.mesh.order)
        regions = resolve_regions(space, cfg.regions)
        check_region_uses(cfg, space, regions)
        materials = config_materials(space, cfg)
        added = added_mass_matrix(space, regions, cfg.masses)
        log.info("%d elements (%s), %d nodes, %d DOFs on %d ranks", body.n_tetrahedra,
                 space.cell_type, space.n_nodes, space.n_dofs, comm.size)
    check_gauges(space, regions, cfg.ports, materials)
    check_rank_memory(space, cfg, comm)
    with stage("assemble"):
        fixed = fixed_dofs(space, regions, cfg.supports, cfg.constraints.in_plane)
        free = free_dofs(space.n_dofs, fixed)
        left = None  # a free body: six rigid-body modes (FEModel.n_rigid)
        if cfg.supports:  # partly held: its rigid modes need the serial path's handling
            left = rigid_freedoms(space.node_points, space.node_points.mean(axis=0), fixed)
            if left.count:
                raise ConfigError(
                    f"supports with modes.solver: slepc: the supports leave {left.count} "
                    f"rigid-body motion(s) free ({', '.join(left.names)}); a partly held "
                    "body is not distributed yet; expected supports that hold every rigid "
                    "motion, no supports (a free body), or another modes.solver",
                    key="supports", value=f"{left.count} rigid motion(s) left",
                    expected="a fully held or a free body")
        part = partition(space, free, comm)
        rows = local_rows(space, materials, free, part, comm.rank, added=added)
        cut, halo = cut_measures(rows.K, rows.lo, rows.hi)
        log.info("rank %d: rows %d:%d of %d, %d elements, K %d entries (%d cut, %d halo "
                 "columns)", comm.rank, rows.lo, rows.hi, free.size, rows.n_elements,
                 rows.K.nnz, cut, halo)
        props = body_properties(
            SummedMatrix(comm, local_node_mass(space, materials, comm.rank, comm.size)),
            space.node_points)
        if added is not None:  # point and area masses: in the rigid properties too
            props = properties_from_rigid_mass(props.rigid_mass + added_rigid_mass(space, added))
        log.info("body mass %.6g kg; %d DOFs fixed, %d free", props.mass, fixed.size, free.size)
    return FEModel(space=space, regions=regions, fixed=fixed, free=free,
                   K=RowMatrix(comm, rows.K, part), M=RowMatrix(comm, rows.M, part),
                   props=props, mesh_path=mesh_path, mesh_sha256=mesh_sha256,
                   n_elements=body.n_tetrahedra, rigid=left, materials=materials)


def added_rigid_mass(space, added) -> np.ndarray:
    """(6, 6) R^T A R of the added masses A (n_dofs, n_dofs) about the origin, from the
    rows of the points they touch only (R: the rigid-body modes of those points)."""
    dofs = np.unique(sp.csr_matrix(added).nonzero()[0] // 3)
    dofs = (3 * dofs[:, None] + np.arange(3)).ravel()
    R = rigid_body_modes(space.node_points[dofs[::3] // 3])
    return R.T @ (sp.csr_matrix(added)[dofs][:, dofs] @ R)


def partition(space, free, comm):
    """The rows of each rank: PT-Scotch's graph partition of the points
    (:func:`~pipeline.distributed.partition.graph_partition`), or slabs along the
    longest extent on one rank or with the PETSc option ``-pipeline_partition slab``."""
    PETSc, _ = petsc()
    kind = PETSc.Options().getString("pipeline_partition", "graph")
    if kind not in ("graph", "slab"):
        raise ConfigError(f"PETSc option -pipeline_partition: {kind!r}; expected graph or "
                          "slab", key="-pipeline_partition", value=kind,
                          expected="graph or slab")
    if comm.size == 1 or kind == "slab":
        return slab_partition(space.node_points, free, comm.size)
    return graph_partition(PETSc, comm, space.element_nodes, space.node_points, free)


def compute_modes(fe: FEModel, cfg: Config) -> Modes:
    """The ``cfg.modes.count`` lowest modes of the distributed (K, M) with SLEPc (module
    :mod:`pipeline.distributed.eigen`), gathered, Rayleigh-Ritz-exact, labelled; the
    factor of K kept for the static correction (factor path)."""
    PETSc, SLEPc = petsc()
    t0 = time.perf_counter()
    K, M = fe.K, fe.M
    n = K.shape[0]
    count = cfg.modes.count
    if count >= n:
        raise ConfigError(f"modes.count: {count} modes of a body with {n} free DOFs; expected "
                          f"fewer than {n}", key="modes.count", value=count,
                          expected=f"< {n}")
    Kp, Mp = petsc_matrix(PETSc, K.local, n), petsc_matrix(PETSc, M.local, n)
    method = "multigrid" if cfg.modes.method == "multigrid" else "factor"
    near_null = None
    if method == "multigrid" and whole_nodes(fe.free, fe.space.n_nodes) is not None:
        # whole points on every rank (the partition keeps them): their coordinates give
        # GAMG the rigid-body modes; otherwise GAMG runs without (slower, still right)
        rows = np.asarray(fe.free)[fe.K.part.owned_free(world().rank)]
        near_null = rigid_near_null_space(PETSc, Kp, fe.space.node_points[rows[::3] // 3])
    tolerance = cfg.modes.tolerance or 1e-10  # SLEPc's relative residual test
    supported = bool(cfg.supports)
    shift = default_shift(K, M, supported)
    omega2, local, stats = solve_eigen(PETSc, SLEPc, Kp, Mp, count, tolerance, method,
                                       near_null, shift)
    eps, ksp = stats.pop("eps"), stats.pop("ksp")
    comm = world()
    K.petsc, M.petsc = Kp, Mp  # the products of the Rayleigh-Ritz step and the reduce stage
    omega2, shapes, residuals = rayleigh_ritz_rows(K, M, RowBlock(comm, K.part, local), shift)
    del local
    # a free body's rigid-body modes: zero to round-off of the shift (as the serial path)
    rigid = np.zeros(omega2.size, dtype=bool) if supported else \
        np.abs(omega2) < 1e-6 * abs(shift)
    omega2 = np.maximum(np.where(rigid, 0.0, omega2), 0.0)
    stats.update(ranks=comm.size, tolerance=tolerance)
    # the spectral transformation's solver (shift 0: its operator is K) solves the
    # static correction's K x = F; a free body's operator is K - sigma M, not K: no
    # solver then. The PETSc objects (and K's and M's) are freed with it, when the
    # pipeline drops K (every rank at the same point: PETSc's destroy is collective)
    factor: Any = KspSolve(ksp if supported else None, K,
                           keep=[eps, Kp, Mp] + ([near_null] if near_null else []))
    # the shapes stay distributed: ``shapes`` is a RowBlock (this rank's rows), and
    # ``shapes_full`` the (n_points, 3, m) dataset rank 0 writes block by block
    n_rigid = int(rigid.sum())
    labels = label_rows(fe.space, fe.free, shapes, n_rigid, node_volume_weights(fe.space))
    for f, lab in zip(np.sqrt(omega2) / (2 * np.pi), labels):
        log.info("mode %-14s %12.4f Hz", lab, f)
    return Modes(omega2=omega2, frequencies_hz=np.sqrt(omega2) / (2 * np.pi), shapes=shapes,
                 residuals=residuals, n_rigid=n_rigid, backend=BACKEND, shift=shift,
                 seconds=time.perf_counter() - t0, stats=stats, factorization=factor,
                 labels=tuple(labels), shapes_full=shapes_blocks(fe.space, fe.free, shapes))


def stress_modes_tree(cfg: Config, space, free, models) -> dict:
    """The ``stress_modes`` group from the distributed basis (rank 0 writes it block by
    block, :func:`pipeline.distributed.reduce.stress_blocks`)."""
    stress, strain = stress_blocks(config_materials(space, cfg), space, free, models.reduced)
    return stress_modes_datasets(stress, strain, models.reduced, models.input_units)


def drain_blocks(tree: dict) -> None:
    """On the ranks that do not write: take part in writing every block-written dataset
    of ``tree``, in the writer's (sorted) order."""
    for name in sorted(tree):
        data = tree[name].data
        if isinstance(data, PointBlocks):
            data.drain()
