"""The whole pipeline for one config: mesh -> assemble -> modes -> reduce -> HDF5.

:func:`run_pipeline` chains the stage functions and is what the CLI, the Makefile,
batch runs and the benchmarks call. It logs what each stage does and how long it took.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.config import Config, config_to_yaml
from pipeline.store.schema import models_tree
from pipeline.store.tree import Dataset

log = logging.getLogger(__name__)

ProgressFactory = Callable[[str, int | None, str], Any]


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


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


def run_pipeline(cfg: Config, output: str | Path, mesh_dir: str | Path = "meshes",
                 progress: ProgressFactory | None = None) -> RunResult:
    """Run every stage for ``cfg`` and write the HDF5 file ``output``.

    ``progress(desc, total, unit)``, if given, is a context manager yielding an
    ``update(n)`` callable (the CLI passes tqdm bars).
    """
    from pipeline.fe.assemble import assemble_blocks, block_pattern, mass_csr, restrict, stiffness_csr
    from pipeline.fe.body import body_properties, label_modes, node_volume_weights
    from pipeline.fe.space import build_space
    from pipeline.fe.mesh import mesh_body
    from pipeline.solve.eigen import solve_modes
    from pipeline.fe.regions import fixed_dofs, free_dofs, resolve_regions
    from pipeline.fe.resources import check_memory

    progress = progress or _no_progress
    times: dict[str, float] = {}
    output = Path(output)
    tree: dict[str, Dataset] = {}
    group_attrs: dict[str, dict[str, Any]] = {}

    with _stage("mesh", times):
        body, mesh_path = mesh_body(cfg.geometry, cfg.mesh, mesh_dir, cfg.name)
        space = build_space(body, cfg.mesh.order)
        regions = resolve_regions(space, cfg.regions)
        log.info("%d elements (%s), %d nodes, %d DOFs", body.n_tetrahedra, space.cell_type,
                 space.n_nodes, space.n_dofs)
    check_memory(space, cfg.modes.count)

    with _stage("assemble", times):
        pattern = block_pattern(space)
        with progress("assemble", body.n_tetrahedra, "elem") as update:
            kcomp, mblock = assemble_blocks(space, cfg.material, pattern=pattern,
                                            progress=update)
        M = mass_csr(pattern, mblock)
        del mblock
        props = body_properties(M, space.node_points)
        fixed = fixed_dofs(space, regions, cfg.supports, cfg.constraints.in_plane)
        free = free_dofs(space.n_dofs, fixed)
        # connection-point models need the unsupported body: keep it only then
        full = (stiffness_csr(pattern, kcomp), M) if cfg.connections else None
        # K straight onto the free DOFs (the full K is never built for a clamped body);
        # M restricted in place when nothing else needs it: never two copies alive
        K = stiffness_csr(pattern, kcomp, free)
        del kcomp, pattern
        M = restrict(M, free, overwrite=full is None)
        log.info("body mass %.6g kg; %d DOFs fixed, %d free", props.mass, fixed.size, free.size)

    with _stage("modes", times):
        with progress("eigensolve", None, "solve") as update:
            modes = solve_modes(K, M, cfg.modes.count, supported=bool(cfg.supports),
                                backend=cfg.modes.solver, tolerance=cfg.modes.tolerance,
                                progress=update)
        shapes = np.zeros((space.n_dofs, modes.omega2.size))
        shapes[free] = modes.shapes
        shapes = shapes.reshape(space.n_nodes, 3, -1)
        labels = label_modes(space.node_points, shapes, modes.n_rigid,
                             node_volume_weights(space))
        for f, lab in zip(modes.frequencies_hz, labels):
            log.info("mode %-14s %12.4f Hz", lab, f)

    models = None
    with _stage("reduce", times):
        if cfg.reduction is not None or cfg.lumped is not None:
            from pipeline.reduce.build import build_models

            models = build_models(cfg, space, regions, K, M, free, modes, props, labels)
        del K, M
        if full is not None:
            from pipeline.reduce.build import build_connection_models

            models = build_connection_models(cfg, space, regions, *full, modes, shapes, models)
        if models is not None:
            model_tree, model_attrs = models_tree(models)
            tree.update(model_tree)
            group_attrs.update(model_attrs)
            del model_tree
            # the tree holds the CSR copies now: the full matrices are not kept alive
            models = dataclasses.replace(models, fe_matrices=None)
        del full

    tree.update(_core_tree(space, regions, fixed, props, modes, shapes, labels))
    group_attrs["modes"] = {"count": int(modes.omega2.size), "n_rigid": modes.n_rigid,
                            "solver": modes.backend, "shift_rad2_s2": modes.shift}
    group_attrs["mesh"] = {"cell_type": space.cell_type, "element_order": cfg.mesh.order,
                           "source": str(mesh_path), "n_dofs": space.n_dofs,
                           "n_free_dofs": int(free.size)}
    with _stage("write", times):
        group_attrs["run"] = {f"{k}_s": v for k, v in times.items()}
        group_attrs["run"]["peak_memory_mb"] = peak_memory_mb()
        group_attrs["run"]["solver"] = modes.backend
        from pipeline.store.h5file import write_file

        write_file(output, tree, group_attrs, {"name": cfg.name,
                                               "config_yaml": config_to_yaml(cfg)})
    extras: dict[str, Any] = {}
    if models is not None:
        extras["summary"] = list(models.summary)
        if models.reduced is not None:
            extras.update(reduced=models.reduced, filtered=models.filtered)
    return RunResult(cfg, output, space.n_dofs, int(free.size), body.n_tetrahedra,
                     modes.frequencies_hz, labels, props.mass, times, peak_memory_mb(),
                     modes.backend, extras)


def _core_tree(space, regions, fixed, props, modes, shapes, labels) -> dict[str, Dataset]:
    tree = {
        "mesh/points": Dataset(space.node_points, "m", "node coordinates (vertices, then edge "
                               "midpoints for quadratic elements)"),
        f"mesh/cells/{space.cell_type}": Dataset(space.element_nodes.astype(np.int64), "1",
                                                 "node indices per element, meshio order"),
        "mesh/fixed_dofs": Dataset(fixed.astype(np.int64), "1",
                                   "constrained DOFs; DOF 3*node+c is component c of node"),
        "body/mass": Dataset(np.float64(props.mass), "kg", "total mass from the FE mass matrix"),
        "body/center_of_mass": Dataset(props.center_of_mass, "m", "centre of mass"),
        "body/inertia": Dataset(props.inertia, "kg m^2", "inertia tensor about the centre of mass"),
        "body/rigid_mass_matrix": Dataset(props.rigid_mass, "mixed",
                                          "R^T M R at the origin, twist order [v; omega]",
                                          {"units_blocks": "kg | kg m ; kg m | kg m^2"}),
        "modes/frequencies_hz": Dataset(modes.frequencies_hz, "Hz", "natural frequencies"),
        "modes/omega2": Dataset(modes.omega2, "rad^2/s^2", "eigenvalues omega^2"),
        "modes/labels": Dataset(list(labels), "1", "dominant motion of each mode"),
        "modes/shapes": Dataset(shapes, "kg^-1/2", "M-orthonormal mode shapes, "
                                "(n_points, 3, n_modes): displacement of every mesh point"),
        "modes/residuals": Dataset(modes.residuals, "1",
                                   "||K phi - omega^2 M phi|| / ||K phi|| per mode"),
    }
    for name, tris in regions.items():
        tree[f"mesh/regions/{name}"] = Dataset(tris.astype(np.int64), "1",
                                               "boundary triangles (vertex node indices)")
    return tree
