"""The FE and modes stages on MPI ranks (``modes.solver: slepc``): the same records as
the serial stages (:class:`~pipeline.fe.model.FEModel`, :class:`~pipeline.solve.modes.Modes`)
with K and M as :class:`~pipeline.distributed.operators.RowMatrix` stand-ins, so that
:func:`pipeline.run.run_pipeline` runs the reduce stage unchanged on every rank.

Per rank, memory: its part of the mesh and an FE space on it (rank 0 meshes the body
and sends each rank the elements touching its points, :mod:`pipeline.distributed.submesh`;
rank 0 alone keeps the whole mesh's points and elements, which it writes), its own
rows' free-DOF order (:meth:`~pipeline.distributed.partition.RowPartition.local`: the
free DOFs themselves only as their count, :class:`~pipeline.distributed.partition.FreeDofs`;
rank 0 the held DOFs it writes), its rows of K and M (1/size of them, plus one element
layer), its part of MUMPS' factor, and its rows of the mode shapes (a
:class:`RowBlock`, 8 n_free n_modes / size bytes); the reduce stage and the writer work from those rows
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

from pipeline.config import Config
from pipeline.errors import ConfigError
from pipeline.distributed.assemble import local_node_mass, local_rows, with_int32_indices
from pipeline.distributed.eigen import petsc_matrix, solve_eigen
from pipeline.distributed.mpi import allreduce_sum, log_resident, petsc, world
from pipeline.distributed.multigrid import lobpcg_modes, prolongation
from pipeline.distributed.operators import KspSolve, RowMatrix, of_diagonals
from pipeline.distributed.partition import (FreeDofs, cut_measures, graph_partition,
                                            partition_kind, slab_partition)
from pipeline.distributed.parts import (from_parts, parts_record,  # noqa: F401 (run.py's)
                                        read_parts_header)
from pipeline.distributed.whole import (SupportInputs, WholeMesh, added_rigid_mass,
                                        mesh_whole, support_inputs)
from pipeline.fe.body import (body_properties, node_volume_weights,
                              properties_from_rigid_mass)
from pipeline.fe.model import FEModel
from pipeline.fe.supports import SOFT_SUPPORT, rigid_freedoms
from pipeline.distributed.blocks import RowBlock
from pipeline.distributed.submesh import (DistributedSpace, MeshCounts, compact_nodes,
                                          scatter_parts, split_mesh)
from pipeline.distributed.prestress import (preload_ports,  # noqa: F401
                                            rotation_masses, rotation_model)  # (run.py's)
from pipeline.distributed.rigid import rigid_rows, with_rigid_rows
from pipeline.distributed.constraints import distribute_constraint
from pipeline.distributed.connection import (clamped_by_supports, connection_interfaces,
                                             connection_models as models_of_connections)
from pipeline.distributed.unsupported import pair_bytes, unsupported_parts
from pipeline.distributed.reduce import (build_statespace,  # noqa: F401 (run.py's)
                                         label_rows, rayleigh_ritz_rows, shapes_blocks,
                                         stress_blocks)
from pipeline._util.resources import lobpcg_guard
from pipeline.solve.eigen import (MULTIGRID_MAX_SWEEPS, MULTIGRID_START_TOLERANCE,
                                  MULTIGRID_TOLERANCE, default_shift)
from pipeline.solve.modes import Modes
from pipeline.solve.stage import check_count_above_rigid
from pipeline.store.schema import stress_modes_datasets

log = logging.getLogger(__name__)

#: the backend name the result file records (``/run`` solver, ``/modes`` backend)
BACKEND = "slepc"


def check_supported(cfg: Config) -> None:
    """One line for what the distributed path does not do yet (before any work)."""
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


def check_rank_memory(n_nodes: int, n_el: int, cfg: Config, comm, parts: bool = False) -> int:
    """Refuse, on every rank and before the assembly, a run whose ranks on one node would
    need more than the node has (ResourceError, one line). Per rank: the serial model of
    :mod:`pipeline._util.resources` for the whole problem (factor method; ``n_nodes``
    mesh points, ``n_el`` elements), its K, M and factor share and its three (n_dofs,
    n_modes) arrays of mode shapes divided by the rank count, plus what every rank holds
    (baseline); each rank's part of the mesh is the whole mesh / ranks. Rank 0 holds
    besides, from the assembly on, the whole mesh's points and elements it writes
    (:func:`kept_bytes`), and before that, while it meshes, partitions and cuts out the
    parts, what it holds of the whole mesh and its share of the partitioner's graph
    (:func:`handoff_meshes` serial mesh terms): its peak is the larger of the two
    phases; with a parts file (``parts``, ``mesh.parts``) it has no such phase.
    gmsh's library state after meshing (18 MB on rank 0 alone, a constant) is
    within the baseline. A rotation sweep (factor path, a
    speed other than 0) factorises K(Omega), K's pattern, while the run's factor of K
    is alive (the static correction solves with it afterwards): one more factor's share
    (:func:`~pipeline._util.resources.factor_bytes`). The other factors made after the
    modes stage come after the run's is freed and add nothing: the connection models'
    clamped and fixed-interface solves (:func:`connection_models`) and a free body's
    inertia relief (:func:`compute_modes`). This is the first gate: every factorisation
    is checked again after MUMPS' analysis, against MUMPS' own estimate
    (:mod:`pipeline.distributed.factor_memory`). Returns this rank's bytes."""
    from mpi4py import MPI

    from pipeline._util import resources as res
    from pipeline.errors import ResourceError

    count, n_dofs = cfg.modes.count, 3 * n_nodes
    mesh = res.MESH_BYTES_PER_NODE * n_nodes + 64 * n_el
    whole = res.estimate_memory_bytes(n_nodes, n_el, cfg.mesh.order, count, "factor",
                                      solver="pardiso")
    shapes = 3 * 8.0 * n_dofs * count
    rotation = cfg.rotation
    sweep = (rotation is not None and any(s != 0 for s in rotation.speeds_rad_s)
             and cfg.modes.method != "multigrid")
    second = res.factor_bytes(n_dofs) if sweep else 0.0
    divided = (whole - res.BASELINE_BYTES + shapes + second) / comm.size
    if cfg.connections and not clamped_by_supports(cfg):  # the connection model's own K, M
        divided += pair_bytes(n_nodes, cfg.mesh.order) / comm.size
    own = divided  # on one rank the whole mesh is its part
    if comm.rank == 0 and comm.size > 1:  # the hand-off, or the kept arrays from then on
        own = divided + kept_bytes(n_nodes, n_el, cfg)
        if not parts:
            own = max(handoff_meshes(comm.size) * mesh, own)
    per_rank = int(res.BASELINE_BYTES + own)
    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    node_ranks = node.size
    need = comm.allreduce(node.allreduce(per_rank), op=MPI.MAX)
    top = comm.allreduce(per_rank, op=MPI.MAX)
    node.Free()
    have = comm.allreduce(res.available_memory_bytes(), op=MPI.MIN)
    log.info("memory estimate %.2f GB per rank (%.2f GB of it the rotation sweep's "
             "factor), %d ranks on this node, %.2f GB available", per_rank / 1e9,
             second / comm.size / 1e9, node_ranks, have / 1e9)
    if need > res.HEADROOM * have:
        raise ResourceError(
            f"mesh with {n_dofs} DOFs on {comm.size} ranks needs about "
            f"{top / 1e9:.1f} GB per rank, {need / 1e9:.1f} GB for the {node_ranks} "
            f"ranks of one node, {res.beyond_usable(need, have)}; expected more "
            "nodes (fewer ranks per node) or a larger mesh.size")
    return per_rank


#: rank 0's peak while it meshes, partitions and cuts out the parts, in serial mesh terms
#: (:data:`pipeline._util.resources.MESH_BYTES_PER_NODE` a point, 64 bytes an element),
#: HANDOFF_WHOLE + HANDOFF_GRAPH / ranks, at least HANDOFF_FLOOR (:func:`handoff_meshes`):
#: what it holds of the whole mesh, and its share of the partitioner's graph (its slab's
#: rows and PETSc's and PT-Scotch's copies of them), which divides; cutting out the parts
#: stays within it. Measured above the stack and its constant 21 MB at 100k, 250k and
#: 620k DOFs on 2 and 4 ranks: 108 + 284 / P bytes a free DOF, 0.50 + 1.32 / P mesh
#: terms, and 0.56-0.62 on 8 and 16 ranks (docs/distributed.md, "Rank 0's memory"), which
#: the floor covers beyond the ranks measured; these carry a fifth more. Those are the
#: point graph's (``-pipeline_partition_graph points``); the default vertex graph's
#: phase is lower (93 + 199 / P bytes a free DOF), so they bound either
HANDOFF_WHOLE, HANDOFF_GRAPH, HANDOFF_FLOOR = 0.6, 1.6, 0.8


def handoff_meshes(ranks: int) -> float:
    """Rank 0's mesh phase on ``ranks`` ranks in serial mesh terms (above)."""
    return max(HANDOFF_WHOLE + HANDOFF_GRAPH / ranks, HANDOFF_FLOOR)


def kept_bytes(n_nodes: int, n_el: int, cfg: Config) -> float:
    """Bytes of the whole mesh that rank 0 keeps from the hand-off to the writer
    (:func:`handed_off`): the points (float64, 24 bytes a point), the elements (int32,
    4 bytes a node of an element) and, where ``/materials`` stores them, each element's
    law and density (12 bytes an element)."""
    nodes = 10 if cfg.mesh.order == 2 else 4
    written = cfg.materials or cfg.masses
    return 24.0 * n_nodes + (4.0 * nodes + (12.0 if written else 0.0)) * n_el


def supports_rigid_freedoms(inputs: SupportInputs | None, node_points: np.ndarray, props,
                            K: RowMatrix, M: RowMatrix, comm):
    """The rigid motions that the held DOFs and the springs leave free, as the serial
    FE stage judges them (:func:`pipeline.fe.supports.rigid_freedoms` with the body's
    centre of mass, rigid mass and the floor SOFT_SUPPORT * median(K_ii / M_ii) of K
    before the springs): evaluated on rank 0 (``inputs``, and every point at
    ``node_points`` (n_points, 3) m, from R's rows at the held DOFs and the springs'
    alone), the same on every rank, which receives them without their (n_dofs, r)
    fields (:meth:`~pipeline.fe.supports.RigidFreedoms.without_fields`: each rank
    evaluates them on its own points)."""
    median = of_diagonals(lambda Kd, Md: float(np.median(
        Kd.diagonal() / np.maximum(Md.diagonal(), np.finfo(float).tiny))), K, M)
    left = None
    if inputs is not None:
        left = rigid_freedoms(node_points, props.center_of_mass, inputs.fixed,
                              inputs.springs, inputs.held, props.rigid_mass,
                              SOFT_SUPPORT * median if inputs.any_free else 0.0,
                              fields=False)  # no (n_dofs, 6) array on rank 0
    return comm.bcast(left, root=0)


def build_fe_model(cfg: Config, mesh_dir: str | Path | None, stage) -> FEModel:
    """Rank 0 meshes and evaluates the whole mesh once (:func:`mesh_whole`), partitions
    the points and sends every rank its part (:mod:`pipeline.distributed.submesh`); each
    rank assembles its rows of K and M from its part, and the body's mass properties are
    summed over the ranks. Only rank 0 ever holds the whole mesh, and only until the
    parts and the small results are sent: it then keeps what the writer stores
    (:func:`handed_off`) and what judging the supports needs (:class:`SupportInputs`),
    and drops the rest before it assembles its rows.

    With ``mesh.parts`` (a file of ``python -m pipeline partition``,
    :func:`~pipeline.distributed.parts.write_partitioned`) no rank meshes: each reads its
    own part from the file (:mod:`pipeline.distributed.parts_file`), rank 0 besides what
    it keeps; the file is
    refused in one line (the mesh stage) when it does not fit the run."""
    check_supported(cfg)
    comm = world()
    whole = shared = None
    with stage("mesh"):
        if cfg.mesh.parts:  # every rank reads (and verifies) its part: no rank meshes
            shared = read_parts_header(cfg, comm)
            n_nodes, mesh_counts = shared.n_nodes, shared.counts
            (mesh, part, space, regions, materials, fixed, judge,
             constraint) = from_parts(cfg, shared, comm)
        else:
            if comm.rank == 0:
                whole = mesh_whole(cfg, mesh_dir)
                log_resident(log, comm, "whole mesh evaluated")
                space = whole.space
                log.info("%d elements (%s), %d nodes, %d DOFs on %d ranks",
                         space.body.n_tetrahedra, space.cell_type, space.n_nodes,
                         space.n_dofs, comm.size)
                counts = (space.n_nodes,
                          MeshCounts(space.body.n_tetrahedra, space.body.n_vertices))
            n_nodes, mesh_counts = comm.bcast(counts if comm.rank == 0 else None, root=0)
    check_rank_memory(n_nodes, mesh_counts.n_tetrahedra, cfg, comm, parts=shared is not None)
    with stage("assemble"):
        if shared is not None:
            n_free, ports, added_rigid = shared.n_free, shared.ports, shared.added_rigid
            mesh_path = Path(shared.mesh_path) if shared.mesh_path else None
            mesh_sha256 = shared.mesh_sha256
        else:
            whole_part, part = partition(whole, comm)  # the whole one on rank 0 only
            log_resident(log, comm, "partitioned")
            parts = None if whole is None else split_mesh(whole.space, whole.materials,
                                                          whole.free, whole_part, comm.size,
                                                          whole.added, whole.springs)
            mesh = scatter_parts(comm, parts)
            del parts
            log_resident(log, comm, "parts sent")
            small = None if whole is None else (
                whole.free.size, whole.ports, whole.mesh_path, whole.mesh_sha256,
                None if whole.added is None else added_rigid_mass(whole.space, whole.added))
            n_free, ports, mesh_path, mesh_sha256, added_rigid = comm.bcast(small, root=0)
            # every rank holds the count of the free DOFs and its own rows' (``part``);
            # rank 0 the held DOFs, which it writes
            fixed = np.zeros(0, np.int64) if whole is None else whole.fixed
            spin_masses = comm.bcast(None if whole is None else
                                     rotation_masses(cfg, whole.space, whole.regions), root=0)
            interfaces = comm.bcast(None if whole is None else connection_interfaces(
                cfg, whole.space, whole.regions), root=0)
            unsupported = None  # the connection model's own pair (K, M): its part
            if cfg.connections and not clamped_by_supports(cfg):
                unsupported = unsupported_parts(comm, whole, whole_part)
            del whole_part
            # u = T q: each rank builds its own rows of T (pipeline.distributed.constraints)
            constraint = distribute_constraint(comm, None if whole is None
                                               else whole.constraint, 3 * n_nodes, part)
            judge = None  # rank 0: what judging the supports needs after the assembly
            if whole is not None:  # rank 0 keeps what it writes, compact (handed_off)
                space, regions, materials = handed_off(cfg, whole, n_nodes, mesh_counts, mesh,
                                                       ports, spin_masses, interfaces,
                                                       unsupported)
                judge = support_inputs(whole)
            else:
                nb = mesh.space.element_nodes.shape[1]
                space = DistributedSpace(mesh.space.order, n_nodes, mesh_counts,
                                         np.zeros((0, 3)), np.zeros((0, nb), np.int64), mesh,
                                         ports, rotation_masses=spin_masses,
                                         connections=interfaces, unsupported=unsupported)
                regions, materials = {}, mesh.materials
            del whole  # the whole mesh: gone before the assembly (tests/test_mpi_rank0.py)
            log_resident(log, comm, "whole mesh dropped")
        free = FreeDofs(n_free)
        log.info("rank %d holds %d of %d points, %d of %d elements", comm.rank,
                 mesh.points.size, n_nodes, mesh.space.element_nodes.shape[0],
                 mesh_counts.n_tetrahedra)
        log_resident(log, comm, "small results sent")
        rows = local_rows(mesh)
        log_resident(log, comm, "rows assembled")
        cut, halo = cut_measures(rows.K, rows.lo, rows.hi)
        log.info("rank %d: rows %d:%d of %d, %d elements, K %d entries (%d cut, %d halo "
                 "columns)", comm.rank, rows.lo, rows.hi, free.size, rows.n_elements,
                 rows.K.nnz, cut, halo)
        rigid_mass = body_properties(local_node_mass(mesh), mesh.space.node_points).rigid_mass
        rigid_mass = allreduce_sum(comm, rigid_mass)
        if added_rigid is not None:  # point and area masses: in the rigid properties too
            rigid_mass = rigid_mass + added_rigid
        props = properties_from_rigid_mass(rigid_mass)
        K = RowMatrix(comm, rows.K, part)
        left = None  # a free body: six rigid-body modes (FEModel.n_rigid)
        if cfg.supports:  # the motions they leave: the serial FE stage's judgement
            left = supports_rigid_freedoms(judge, space.node_points, props, K,
                                           RowMatrix(comm, rows.M, part), comm)
        if mesh.springs is not None:  # springs and bushings: its owned rows added to K
            K = RowMatrix(comm, with_int32_indices(rows.K + mesh.springs), part)
        log.info("body mass %.6g kg; %d DOFs fixed, %d free", props.mass,
                 3 * n_nodes - free.size, free.size)
    return FEModel(space=space, regions=regions, fixed=fixed, free=free,
                   K=K, M=RowMatrix(comm, rows.M, part),
                   props=props, mesh_path=mesh_path, mesh_sha256=mesh_sha256,
                   n_elements=mesh_counts.n_tetrahedra, rigid=left, materials=materials,
                   constraint=constraint)


def handed_off(cfg: Config, whole: WholeMesh, n_nodes: int, mesh_counts: MeshCounts,
               mesh, ports, spin_masses, interfaces, unsupported):
    """Rank 0's (DistributedSpace, regions, element materials) once the parts are sent:
    of the whole mesh only what the writer stores, compact, so that nothing else of
    ``whole`` (the FE space with its scikit-fem mesh and edges, gmsh's body, the nodal
    volume weights, the int64 elements) is alive when rank 0 assembles its rows: the
    points (n_points, 3) float64 (the writer's, the labels' and the connection models'
    exact positions), the elements (:func:`~pipeline.distributed.submesh.compact_nodes`:
    int32 up to 2^31 points, 40 bytes a quadratic element instead of 80), the regions
    (surface cells) and
    the element materials where ``/materials`` stores them (``materials`` or ``masses``
    in the config; else the part's, as on the other ranks). The body's label frame is
    made here from every point and its volume weight (a few numbers a slice)."""
    from pipeline.solve.labels import label_frame

    space = whole.space
    frame = label_frame(space.node_points, node_volume_weights(space))
    kept = DistributedSpace(space.order, n_nodes, mesh_counts, space.node_points,
                            compact_nodes(space.element_nodes, n_nodes), mesh, ports,
                            label_frame=frame, rotation_masses=spin_masses,
                            connections=interfaces, unsupported=unsupported)
    written = cfg.materials or cfg.masses
    return kept, whole.regions, whole.materials if written else mesh.materials


def partition(whole: WholeMesh | None, comm):
    """The rows of each rank (collective; ``whole`` on rank 0, None elsewhere): PT-Scotch's
    graph partition of the points
    (:func:`~pipeline.distributed.partition.graph_partition`), or slabs along the
    longest extent on one rank or with the PETSc option ``-pipeline_partition slab``.
    Returns (the whole partition on rank 0, None elsewhere; this rank's own
    :meth:`~pipeline.distributed.partition.RowPartition.local`, sent by rank 0)."""
    PETSc, _ = petsc()
    kind = partition_kind(PETSc)
    if comm.size == 1 or kind == "slab":
        part = None if whole is None else \
            slab_partition(whole.space.node_points, whole.free, comm.size)
    elif whole is None:
        part = graph_partition(PETSc, comm, None, None, None)
    else:
        part = graph_partition(PETSc, comm, whole.space.element_nodes,
                               whole.space.node_points, whole.free)
    own = comm.scatter(None if part is None else [part.local(r) for r in range(comm.size)],
                       root=0)
    return part, own


def compute_modes(fe: FEModel, cfg: Config) -> Modes:
    """The ``cfg.modes.count`` lowest modes of the distributed (K, M) with SLEPc (module
    :mod:`pipeline.distributed.eigen`), gathered, Rayleigh-Ritz-exact, labelled; the
    factor of K kept for the static correction (factor path)."""
    PETSc, SLEPc = petsc()
    t0 = time.perf_counter()
    K, M = fe.K, fe.M
    n = K.shape[0]
    count = cfg.modes.count
    Kp, Mp = petsc_matrix(PETSc, K.local, n), petsc_matrix(PETSc, M.local, n)
    con = fe.constraint  # u = T q: the pencil (K_q, M_q) on the coordinates q
    if con is not None:
        K.petsc, M.petsc = Kp, Mp  # the reduce stage's products on the free DOFs
        K, M = con.project(PETSc, K, M)
        Kp, Mp, n = K.petsc, M.petsc, con.n_q
    if count >= n:
        raise ConfigError(f"modes.count: {count} modes of a body with {n} free DOFs; expected "
                          f"fewer than {n}", key="modes.count", value=count,
                          expected=f"< {n}")
    # the factor-free path: the config allows modes.method multigrid with quadratic
    # elements only (the two-grid cycle's coarse space is the P1 space inside P2)
    two_grid = cfg.modes.method == "multigrid"
    tolerance = cfg.modes.tolerance or 1e-10  # SLEPc's relative residual test
    # a partly held body (supports that leave rigid motions) is solved as a free one,
    # at the negative shift, its first fe.n_rigid modes those motions (the serial path)
    supported = fe.n_rigid == 0
    partly = fe.rigid is not None and fe.n_rigid > 0
    if partly:
        check_count_above_rigid(count, fe.n_rigid, fe.rigid.names)
    shift = of_diagonals(lambda Kd, Md: default_shift(Kd, Md, supported), K, M)
    if two_grid:  # LOBPCG preconditioned by the two-grid cycle: no factor of K
        P = prolongation(PETSc, fe.space, fe.K.part, world())
        if con is not None:  # the coarse space on q: T^T P (the serial path's)
            P_u, P = P, con.T.transposeMatMult(P)
            P_u.destroy()
        tolerance = cfg.modes.tolerance or MULTIGRID_TOLERANCE
        _, local, stats, ksp = lobpcg_modes(
            PETSc, SLEPc, Kp, Mp, P, count, count + lobpcg_guard(count), shift, tolerance,
            MULTIGRID_START_TOLERANCE, MULTIGRID_MAX_SWEEPS)
        owned = [ksp, *stats.pop("keep")]
    else:
        omega2, local, stats = solve_eigen(PETSc, SLEPc, Kp, Mp, count, tolerance, shift)
        eps, ksp = stats.pop("eps"), stats.pop("ksp")
        owned = [eps, ksp]  # SLEPc's solver holds its KSP (and MUMPS' factor) too
    comm = world()
    K.petsc, M.petsc = Kp, Mp  # the products of the Rayleigh-Ritz step and the reduce stage
    omega2, shapes, residuals = rayleigh_ritz_rows(K, M, RowBlock(comm, K.part, local), shift)
    del local
    # a free body's rigid-body modes: zero to round-off of the shift (as the serial path);
    # a partly held body's: its first fe.n_rigid, exact null vectors of K
    rigid = np.zeros(omega2.size, dtype=bool) if supported else \
        np.abs(omega2) < 1e-6 * abs(shift)
    rigid[:fe.n_rigid if partly else 0] = True
    omega2 = np.maximum(np.where(rigid, 0.0, omega2), 0.0)
    n_rigid = int(rigid.sum())
    names: list[str] = []
    if partly:  # the motions themselves, from each rank's own points
        R = rigid_rows(fe.rigid, fe.space.local,
                       RowBlock(comm, fe.K.part, np.zeros((fe.K.hi - fe.K.lo, 0))))
        omega2, shapes = with_rigid_rows(omega2, shapes, M,
                                         R if con is None else con.coordinates(R),
                                         n_rigid, fe.rigid.names)
        n_rigid = fe.n_rigid
        names = [f"rigid_{name}" for name in fe.rigid.names]
    if con is not None:  # phi = T psi
        shapes = con.from_q(shapes)
    stats.update(ranks=comm.size, tolerance=tolerance)
    # the spectral transformation's solver (shift 0: its operator is K) solves the
    # static correction's K x = F; a free or partly held body's operator is K - sigma M,
    # not K: no solver then (the inertia relief makes its own, as the serial path).
    # The PETSc objects (and K's and M's) are freed with it, when the pipeline drops K
    # (every rank at the same point: PETSc's destroy is collective)
    factor: Any = KspSolve(ksp if supported else None, K, keep=owned,
                           matrices=([P] if two_grid else [])
                           + ([Kp, Mp] if con is None else [con, fe.K.petsc, fe.M.petsc]),
                           prolongation=P if two_grid else None)
    if not supported:  # its factor solves nothing more: freed before the relief's own
        factor.release_solver()
    # the shapes stay distributed: ``shapes`` is a RowBlock (this rank's rows), and
    # ``shapes_full`` the (n_points, 3, m) dataset rank 0 writes block by block
    labels = label_rows(fe.space, shapes, n_rigid)
    labels[:len(names)] = names
    for f, lab in zip(np.sqrt(omega2) / (2 * np.pi), labels):
        log.info("mode %-14s %12.4f Hz", lab, f)
    return Modes(omega2=omega2, frequencies_hz=np.sqrt(omega2) / (2 * np.pi), shapes=shapes,
                 residuals=residuals, n_rigid=n_rigid, backend=BACKEND, shift=shift,
                 seconds=time.perf_counter() - t0, stats=stats, factorization=factor,
                 labels=tuple(labels), shapes_full=shapes_blocks(fe.space.n_nodes, shapes),
                 constraint=con)


def connection_models(cfg: Config, space, props, free, K: RowMatrix, M: RowMatrix,
                      modes: Modes, models):
    """:func:`pipeline.distributed.connection.connection_models` (run.py's) after the
    run's factor of K is freed: the static correction is made, and the clamped and
    fixed-interface solves factorise their own pencils, so two factors of K's size are
    never alive at once on a rank (cantilever_connection.yaml, 100k DOFs, 2 ranks: a
    rank's resident memory 593 -> 290 MB here, rank peaks 1318 / 1257 -> 882 / 886 MB)."""
    if modes.factorization is not None:
        modes.factorization.release_solver()
    return models_of_connections(cfg, space, props, K, M, modes, models)


def stress_modes_tree(cfg: Config, space, free, models) -> dict:
    """The ``stress_modes`` group from the distributed basis (rank 0 writes it block by
    block, :func:`pipeline.distributed.reduce.stress_blocks`)."""
    stress, strain = stress_blocks(space.local, space.n_nodes, models.reduced)
    return stress_modes_datasets(stress, strain, models.reduced, models.input_units)


def drain_blocks(tree: dict) -> None:
    """On the ranks that do not write: take part in writing every block-written dataset
    of ``tree``, in the writer's (sorted) order."""
    for name in sorted(tree):
        data = tree[name].data
        if hasattr(data, "drain"):  # PointBlocks, the /fe matrices' CSR arrays
            data.drain()
