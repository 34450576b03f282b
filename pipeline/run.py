"""The whole pipeline for one config: mesh -> assemble -> modes -> reduce -> HDF5.

:func:`run_pipeline` chains the stage functions and is what the CLI, the Makefile,
batch runs and the benchmarks call. It logs what each stage does and how long it took.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import resource
import threading
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.config import Config, config_to_yaml
from pipeline._util import resources
from pipeline.fe.added_mass import refuse_rigid_couplings
from pipeline.fe.model import build_fe_model
from pipeline.fe.supports import refuse_grounded_supports, support_summary
from pipeline.reduce.build import build_connection_models, build_models, static_loads
from pipeline.solve.backends.pardiso import PatternAnalysis
from pipeline.solve.factorization import resolve_backend
from pipeline.solve.stage import ModesInput, compute_modes, expects_factor
from pipeline.store.h5file import write_file
from pipeline.store.layout import ROOT
from pipeline.fe.materials import ElementMaterials, config_materials
from pipeline.fe.strain import modal_stress_fields
from pipeline.store.schema import (core_datasets, core_group_attrs, materials_datasets,
                                   models_tree, run_group_attrs, stress_modes_datasets)
from pipeline.store.tree import Dataset
from pipeline.reduce.rotation import rotation_model
from pipeline.store.schema_rotation import rotation_tree

log = logging.getLogger(__name__)

ProgressFactory = Callable[[str, int | None, str], Any]  # same as pipeline.fe.model's


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def estimate_memory_bytes(n_nodes: int, n_elements: int, order: int, n_modes: int) -> int:
    """Peak bytes of :func:`run_pipeline` on a mesh of ``n_nodes`` nodes and ``n_elements``
    tetrahedra of ``order`` with ``n_modes`` modes (the model of
    :mod:`pipeline._util.resources`), for callers above the FE layer (batch scheduling)."""
    return resources.estimate_memory_bytes(n_nodes, n_elements, order, n_modes)


def estimate_box_mesh(length: float, height: float, depth: float, size: float,
                      order: int) -> tuple[int, int]:
    """(nodes, tetrahedra) gmsh will make for the box length x height x depth (m) at
    ``size`` m with elements of ``order`` (:mod:`pipeline.fe.mesh.estimate`), for callers
    above the FE layer (batch scheduling)."""
    from pipeline.fe.mesh.estimate import BodyShape, estimate_mesh

    est = estimate_mesh(BodyShape.box(length, height, depth), size, order)
    return int(np.ceil(est.n_nodes)), int(np.ceil(est.n_tetrahedra))


def available_memory_bytes() -> int:
    """Bytes this process may use: MemAvailable, capped by a cgroup limit if any."""
    return resources.available_memory_bytes()


#: the modules :func:`run_pipeline` imports when it runs (see :func:`preload_stage_modules`)
STAGE_MODULES = ("numpy", "scipy.sparse", "scipy.sparse.linalg", "scipy.linalg", "h5py",
                 "meshio", "skfem", "yaml", "gmsh", "pipeline.fe.mesh", "pipeline.fe.space",
                 "pipeline.fe.assemble", "pipeline.fe.body", "pipeline.fe.model",
                 "pipeline.solve.eigen", "pipeline.solve.stage", "pipeline.fe.regions",
                 "pipeline._util.resources", "pipeline.store.h5file", "pipeline.solve.factorization",
                 "pipeline.reduce.build")


#: the third-party modules the stages after gmsh import on first use (the mesh reader,
#: the FE space, the HDF5 writer; about 0.2 s): :func:`_run` imports them on a second
#: thread while gmsh meshes on one (its calls release the GIL)
AFTER_MESH_MODULES = ("meshio", "skfem", "h5py", "yaml", "threadpoolctl")


def preload_stage_modules(names: tuple[str, ...] = STAGE_MODULES) -> None:
    """Import every module a run needs (heavy: gmsh, scikit-fem, MKL), so that processes
    forked afterwards (batch cases) start at once; ``names``: these instead. A module
    that cannot be imported is skipped: the run itself reports real problems."""
    import importlib

    for name in names:
        try:
            importlib.import_module(name)
        except Exception:  # an optional module (e.g. no PARDISO)
            log.debug("preload: %s not importable", name)


@contextlib.contextmanager
def _stage(name: str, times: dict[str, float]):
    t0 = time.perf_counter()
    log.info("%s ...", name)
    yield
    times[name] = time.perf_counter() - t0
    log.info("%s done in %.2f s (peak memory %.0f MB)", name, times[name], peak_memory_mb())


@contextlib.contextmanager
def _no_progress(desc: str, total: int | None, unit: str):
    yield lambda n=1: None


@dataclass(frozen=True)
class RunResult:
    """What one run produced (the HDF5 file holds all of it)."""

    config: Config
    output: Path
    n_dofs: int
    n_free: int
    n_elements: int
    frequencies_hz: np.ndarray
    labels: list[str]
    mass: float
    times: dict[str, float]
    peak_memory_mb: float
    backend: str
    extras: dict[str, Any] = field(default_factory=dict)
    n_rigid: int = 0


def run_pipeline(cfg: Config, output: str | Path, mesh_dir: str | Path | None = None,
                 progress: ProgressFactory | None = None) -> RunResult:
    """Run every stage for ``cfg`` and write the HDF5 file ``output``.

    The mesh is made in a private temporary folder; ``mesh_dir``, if given, keeps a copy
    as ``<mesh_dir>/<name>.<sha256[:12]>.msh`` (see :func:`pipeline.fe.mesh.mesh_body`).

    ``progress(desc, total, unit)``, if given, is a context manager yielding an
    ``update(n)`` callable (the CLI passes tqdm bars).
    """
    progress = progress or _no_progress
    if cfg.modes.solver == "slepc":  # MPI ranks: pipeline.distributed
        from pipeline.distributed.stage import abort_on_failure

        with abort_on_failure():
            return _run(cfg, output, mesh_dir, progress)
    resolve_backend(cfg.modes.solver)  # a solver that is not installed: one line, before meshing
    return _run(cfg, output, mesh_dir, progress)


def _run(cfg: Config, output: str | Path, mesh_dir: str | Path | None,
         progress: ProgressFactory) -> RunResult:
    distributed = _distributed_stages(cfg)
    times: dict[str, float] = {}
    output = Path(output)
    tree: dict[str, Dataset] = {}
    group_attrs: dict[str, dict[str, Any]] = {}

    # PARDISO's analysis of K's pattern runs beside the element loop when the solve
    # stage will factorise K (it needs the pattern only); released below in any case
    ahead: list[PatternAnalysis] = []

    def analyse_ahead(indptr, indices) -> None:
        if expects_factor(indptr.size - 1, cfg.modes, supported=bool(cfg.supports)):
            ahead.append(PatternAnalysis(indptr, indices))

    try:
        if distributed is not None:
            fe = distributed.build_fe_model(cfg, mesh_dir, lambda name: _stage(name, times))
        else:
            importing = threading.Thread(target=preload_stage_modules,
                                         args=(AFTER_MESH_MODULES,), name="pipeline-imports",
                                         daemon=True)
            importing.start()
            try:
                fe = build_fe_model(cfg, mesh_dir, progress,
                                    stage=lambda name: _stage(name, times),
                                    on_stiffness_pattern=analyse_ahead)
            finally:
                # also when the mesh is refused: a thread still importing C extensions
                # (h5py, scikit-fem) while the interpreter exits can crash it, and the
                # command then ends by SIGSEGV instead of the error's exit code
                importing.join()
        with _stage("modes", times):
            # the factorisation and the eigensolver report their own progress (with
            # totals and expected durations) through pipeline._util.progress
            # the input record is a temporary: it must not keep K alive past `del fe`
            if distributed is not None:
                modes = distributed.compute_modes(fe, cfg)
            else:
                modes = compute_modes(
                    ModesInput.from_fe(fe, cfg.modes, supported=bool(cfg.supports),
                                       loads=static_loads(cfg, fe.space, fe.regions,
                                                          fe.free)),
                    cfg.modes, keep=cfg.reduction is not None or cfg.rotation is not None,
                    analysis=ahead[0] if ahead else None)
    finally:
        for analysis in ahead:
            analysis.release()  # nothing to free when the factorisation took it
    if modes.factorization is not None:
        # the kept factor of K (for the static correction) lives exactly as long as K:
        # freed when the reduce stage drops K, before the connection models factorise
        # the unsupported K; released explicitly after the reduce stage in any case
        weakref.finalize(fe.K, modes.release_factorization)
    # the stages below hold the matrices by these names only (the reduce stage frees
    # K, M and full by deleting them), so the FEModel record is dropped here
    space, regions, fixed, free, props, mesh_path = (fe.space, fe.regions, fe.fixed,
                                                     fe.free, fe.props, fe.mesh_path)
    mesh_sha256, materials = fe.mesh_sha256, fe.materials
    support_lines = support_summary(fe, modes) if cfg.supports else []
    body = space.body
    K, M = fe.K, fe.M
    full = (fe.K_full, fe.M_full) if fe.K_full is not None else None
    del fe
    shapes, labels = modes.shapes_full, list(modes.labels)

    if cfg.rotation is not None:
        with _stage("rotation", times):
            rotation_datasets, rotation_attrs = rotation_tree((
                rotation_model if distributed is None else distributed.rotation_model)(
                cfg, space, regions, free, K, M, modes))
            tree.update(rotation_datasets)
            group_attrs.update(rotation_attrs)

    models = None
    with _stage("reduce", times):
        if cfg.reduction is not None or cfg.lumped is not None:
            models = build_models(cfg, space, regions, K, M, free, modes, props, labels,
                                  solve=modes.solve, statespace=None if distributed is None
                                  else distributed.build_statespace)
        if distributed is not None and cfg.connections:  # from the ranks' K, M and modes
            models = distributed.connection_models(cfg, space, props, free, K, M, modes,
                                                   models)
        del K, M
        if models is not None and models.reduced is not None:
            tree.update((_stress_modes_tree if distributed is None
                         else distributed.stress_modes_tree)(cfg, space, free, models))
        if full is not None:
            models = build_connection_models(cfg, space, regions, *full, modes, shapes, models)
        if models is not None:
            model_tree, model_attrs = models_tree(models)
            tree.update(model_tree)
            group_attrs.update(model_attrs)
            del model_tree
            # the tree holds the CSR copies now: the full matrices are not kept alive
            models = dataclasses.replace(models, fe_matrices=None)
        del full

    modes.release_factorization()  # idempotent: freed when K was dropped
    tree.update(core_datasets(space, regions, fixed, props, modes, shapes, labels))
    if cfg.materials or cfg.masses:
        tree.update(materials_datasets(materials if materials is not None
                                       else config_materials(space, cfg)))
    multigrid = modes.stats and modes.stats.get("method") == "multigrid-lobpcg"
    group_attrs.update(core_group_attrs(
        space, cfg.mesh.order, free.size, "" if mesh_path is None else str(mesh_path),
        mesh_sha256, modes, min(modes.stats["history"]) if multigrid else None))
    with _stage("write", times):
        group_attrs.update(run_group_attrs(times, peak_memory_mb(), modes.backend,
                                           ranks=None if distributed is None
                                           else distributed.rank_and_size()[1],
                                           parts=None if distributed is None
                                           else distributed.parts_record(cfg)))
        if distributed is None or distributed.rank_and_size()[0] == 0:  # rank 0 writes
            write_file(output, tree, group_attrs, {ROOT.name: cfg.name,
                                                   ROOT.config_yaml: config_to_yaml(cfg)})
        else:  # the others send their rows of the block-written datasets
            distributed.drain_blocks(tree)
        if distributed is not None:
            distributed.world().Barrier()  # the file exists when any rank returns
    extras: dict[str, Any] = {"summary": support_lines} if support_lines else {}
    if models is not None:
        extras["summary"] = support_lines + list(models.summary)
        if models.reduced is not None:
            extras.update(reduced=models.reduced, filtered=models.filtered)
    return RunResult(cfg, output, space.n_dofs, int(free.size), body.n_tetrahedra,
                     modes.frequencies_hz, labels, props.mass, times, peak_memory_mb(),
                     modes.backend, extras, modes.n_rigid)


def _distributed_stages(cfg: Config):
    """The stage module of the MPI path (``modes.solver: slepc``), or None."""
    if cfg.modes.solver != "slepc":
        return None
    from pipeline.distributed import stage

    stage.check_supported(cfg)
    return stage


def _stress_modes_tree(cfg: Config, space, free, models) -> dict[str, Dataset]:
    """The ``stress_modes`` group: stress and strain of the reduced basis and of the
    residual-flexibility shapes, recovered to the mesh points (pipeline.fe.strain)."""
    reduced = models.reduced
    fields = modal_stress_fields(space, config_materials(space, cfg), free, reduced.basis,
                                 reduced.correction_shapes)
    log.info("stress modes: %d shapes at %d mesh points", fields.stress.shape[2], space.n_nodes)
    return stress_modes_datasets(fields.stress, fields.strain, reduced, models.input_units)


def stored_fe_data(path: str | Path, assemble: bool | None = None):
    """What ``export --to exudyn`` needs beyond a result file, rebuilt on its stored mesh
    with its stored config (never re-meshing): :class:`pipeline.fe.stored.StoredFE` with
    K and M of the unsupported body (when ``assemble``; None: when the file has no ``/fe``)
    and the input-port loads F (for the exporter's static modes)."""
    import yaml

    from pipeline.config.parse import config_from_dict
    from pipeline.config import BOX_FACES
    from pipeline.fe.stored import matrices_of_stored_mesh
    from pipeline.store.read import read_materials, read_stored_mesh

    mesh = read_stored_mesh(path)
    if assemble is None:
        assemble = not mesh.has_fe
        if assemble:
            log.info("%s has no /fe: re-assembling M and K from its stored config and mesh",
                     path)
    raw = yaml.safe_load(mesh.config_yaml) or {}
    if not isinstance(raw, dict):
        raw = {}
    refuse_grounded_supports(raw.get("supports"), path)
    refuse_rigid_couplings(raw.get("masses"), path)
    # only the material and the ports matter here: the stored mesh replaces the geometry (a
    # CAD file need not be here any more; a box of the mesh's extent keeps the size checks
    # meaningful) and holds the regions the selectors made (named here by plain selectors)
    extent = np.ptp(mesh.points, axis=0)
    # materials by box or sphere selector resolve on the stored mesh as in the run
    laws = {k: raw[k] for k in ("material", "materials", "masses") if raw.get(k)}
    if not laws.get("materials"):
        laws["material"] = raw.get("material", {})
    raw = {"name": raw.get("name", "stored"), **laws,
           "ports": raw.get("ports") or {},
           "geometry": {"kind": "box", "length": float(extent[0]), "height": float(extent[1]),
                        "depth": float(extent[2])},
           "mesh": {"order": 2 if mesh.cells.shape[1] == 10 else 1,
                    "size": float(extent.min())},
           "regions": {name: {"kind": "plane", "point": [0.0, 0.0, 0.0],
                              "normal": [0.0, 0.0, 1.0]} for name in mesh.regions
                       if name not in BOX_FACES}}
    cfg = config_from_dict(raw, source="")
    stored = read_materials(path)  # the run's own element assignment, where it was stored
    materials = None if stored is None else ElementMaterials(
        stored.names, stored.stiffness, stored.density, stored.element_material,
        stored.element_density, None)
    return matrices_of_stored_mesh(cfg, mesh.points, mesh.cells, mesh.regions, str(path),
                                   assemble=assemble, materials=materials)
