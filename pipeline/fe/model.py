"""The finite-element stage record: :class:`FEModel`, built by :func:`build_fe_model`.

Config -> mesh (gmsh or a mesh file) -> P1/P2 vector space -> named regions -> K, M
assembled once -> body properties -> supports. K (N/m) and M (kg) are kept on the free
DOFs only (n_free x n_free, CSR); DOF 3*p+c is component c of mesh point p. The
unsupported matrices (n_dofs x n_dofs) are kept as well only when the config has
connection points, whose models need the free body.

Memory: K is assembled straight onto the free DOFs (the full K is never built for a
clamped body unless connections need it), and M is restricted in place when nothing
else needs the full M, so no two copies of a matrix are alive at once.
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ContextManager, Mapping

import numpy as np
import scipy.sparse as sp

from pipeline.config import Config
from pipeline.fe.assemble import assemble_on_nodes, restrict, whole_nodes
from pipeline.fe.pattern import element_slots, node_graph, stiffness_layout
from pipeline._util.sparse import csr_diagonal
from pipeline.fe.ports import check_gauges
from pipeline.fe.added_mass import added_mass_matrix, rigid_couplings
from pipeline.fe.body import (BodyProperties, body_properties, properties_from_rigid_mass,
                              rigid_body_modes)
from pipeline.fe.materials import ElementMaterials, config_materials
from pipeline.fe.mesh import body_shape, mesh_body
from pipeline.fe.mesh.estimate import DEFAULT_MODES, check_mesh_fits
from pipeline.fe.regions import check_region_uses, fixed_dofs, free_dofs, resolve_regions
from pipeline.fe.supports import (SOFT_SUPPORT, RigidFreedoms, SupportStiffness,
                                  rigid_freedoms, support_stiffness)
from pipeline.fe.constraints import Constraint, build_constraint
from pipeline._util.resources import check_memory
from pipeline.fe.space import FESpace, build_space

log = logging.getLogger(__name__)

#: progress(desc, total, unit) -> context manager yielding update(n) (tqdm-like bars)
ProgressFactory = Callable[[str, int | None, str], Any]
#: stage(name) -> context manager around one timed stage ("mesh", "assemble")
StageTimer = Callable[[str], ContextManager[Any]]


@dataclass(frozen=True)
class FEModel:
    """The discretised body, supported as the config says.

    space: the FE space (mesh points, elements, DOF numbering).
    regions: region name -> vertex cells (n, 3 | 2 | 1): a face, line or point region.
    fixed, free: sorted DOF indices (int64), fixed + free = all 3 * n_points DOFs.
    K, M: (n_free, n_free) CSR stiffness (N/m) and mass (kg) on the free DOFs; K holds
    the elastic supports (``support_stiffness``).
    K_full, M_full: (n_dofs, n_dofs) unsupported matrices, or None (kept only when
    connection points need them).
    props: mass, centre of mass, inertia and rigid mass matrix from M.
    rigid: the rigid-body motions the supports leave free; support_stiffness: the
    springs, bushings and held local directions on all DOFs (:mod:`pipeline.fe.supports`).
    constraint: u = T q on the free DOFs (:mod:`pipeline.fe.constraints`: components held
    in a local frame, rigid couplings of added masses), or None (u = q); K and M are the
    unconstrained ones (M with the added masses), and the modes stage solves T^T K T,
    T^T M T (on MPI ranks: each rank's rows of T,
    :class:`pipeline.distributed.constraints.DistributedConstraint`).
    mesh_path: the mesh file kept (None: not kept); mesh_sha256: SHA-256 of the mesh file
    the run read; n_elements: number of tetrahedra.
    materials: the material of every element (``material`` and ``materials``).
    """

    space: FESpace
    regions: Mapping[str, np.ndarray]
    fixed: np.ndarray
    free: np.ndarray
    K: sp.csr_matrix
    M: sp.csr_matrix
    props: BodyProperties
    mesh_path: Path | None
    n_elements: int
    K_full: sp.csr_matrix | None = None
    M_full: sp.csr_matrix | None = None
    mesh_sha256: str = ""
    rigid: RigidFreedoms | None = None
    support_stiffness: SupportStiffness | None = None

    @property
    def n_rigid(self) -> int:
        """Rigid-body modes the supports leave (6 for a free body), known before the
        eigen solve (:func:`pipeline.fe.supports.rigid_freedoms`)."""
        return 6 if self.rigid is None else self.rigid.count
    materials: ElementMaterials | None = None
    constraint: Constraint | None = None


@contextlib.contextmanager
def _no_progress(desc: str, total: int | None, unit: str):
    yield lambda n=1: None


def _untimed(name: str) -> ContextManager[Any]:
    return contextlib.nullcontext()


@dataclass(frozen=True)
class MeshedConfig:
    """A config's body on its mesh, before any assembly: the tetrahedra count, the mesh
    file (path or None, SHA-256), the FE space, the named regions (node indices), the
    element materials, the added masses ((n_dofs, n_dofs) kg, or None) and the
    supports' stiffness (springs, bushings, local-frame holds)."""

    n_tetrahedra: int
    mesh_path: Path | None
    mesh_sha256: str
    space: FESpace
    regions: Mapping[str, np.ndarray]
    materials: ElementMaterials
    added: sp.spmatrix | None
    supports: SupportStiffness


def mesh_config(cfg: Config, mesh_dir: str | Path | None = None,
                mark: Callable[[str], None] | None = None) -> MeshedConfig:
    """Mesh ``cfg``'s body (gmsh, or its mesh file) into ``mesh_dir``, build the space,
    resolve the regions (a region used where it cannot be is refused here, before any
    assembly), the materials, the added masses and the supports' stiffness. The serial
    FE stage and rank 0 of the distributed one both start here. ``mark(step)``, if
    given, is called after the mesh is read ("mesh read": gmsh has finalised) and after
    the space is built ("space built"; rank 0 logs its resident memory there)."""
    mark = mark or (lambda step: None)
    body, mesh_path, mesh_sha256 = mesh_body(cfg.geometry, cfg.mesh, mesh_dir, cfg.name)
    mark("mesh read")
    space = build_space(body, cfg.mesh.order)
    mark("space built")
    regions = resolve_regions(space, cfg.regions)
    check_region_uses(cfg, space, regions)
    return MeshedConfig(body.n_tetrahedra, mesh_path, mesh_sha256, space, regions,
                        config_materials(space, cfg),
                        added_mass_matrix(space, regions, cfg.masses),
                        support_stiffness(space, regions, cfg.supports))


def check_run_fits(cfg: Config) -> None:
    """Before gmsh meshes a box or a STEP body: refuse a run whose estimated memory
    would not fit, for the eigensolver its ``modes`` ask for. The mesh sources check the
    default run (``modes.method`` and ``modes.solver`` auto, 20 modes), which can need
    half of what another asks for: the cantilever at 2.8M DOFs about 16 GB factor-free,
    about 30 GB with ``method: factor``. A geo script may mesh itself and a mesh file is
    read, so ``mesh.size`` says nothing there."""
    modes = cfg.modes
    if cfg.geometry.kind not in ("box", "step") or (
            (modes.method, modes.solver, modes.count) == ("auto", "auto", DEFAULT_MODES)):
        return
    what = "the box" if cfg.geometry.kind == "box" else f"the body in '{cfg.geometry.path}'"
    check_mesh_fits(body_shape(cfg.geometry), cfg.mesh, what, modes.count,
                    method=modes.method, solver=modes.solver)


def build_fe_model(cfg: Config, mesh_dir: str | Path | None = None,
                   progress: ProgressFactory | None = None,
                   stage: StageTimer | None = None, on_stiffness_pattern=None) -> FEModel:
    """Mesh, space, regions (stage ``mesh``), memory check, assembly and supports (stage
    ``assemble``) for ``cfg``; the mesh file goes to ``mesh_dir``.

    ``progress(desc, total, unit)``, if given, is a context manager yielding an
    ``update(n)`` callable; ``stage(name)``, if given, wraps each of the two stages (the
    pipeline times them). ``on_stiffness_pattern(indptr, indices)``, if given, receives
    the CSR structure of the final K (on the free DOFs) before its values are summed,
    where K is assembled straight onto the free DOFs (not called otherwise).
    """
    progress = progress or _no_progress
    stage = stage or _untimed
    with stage("mesh"):
        check_run_fits(cfg)
        meshed = mesh_config(cfg, mesh_dir)
        space, regions, materials = meshed.space, meshed.regions, meshed.materials
        added, extra, n_tetrahedra = meshed.added, meshed.supports, meshed.n_tetrahedra
        mesh_path, mesh_sha256 = meshed.mesh_path, meshed.mesh_sha256
        del meshed
        log.info("%d elements (%s), %d nodes, %d DOFs", n_tetrahedra, space.cell_type,
                 space.n_nodes, space.n_dofs)
    check_gauges(space, regions, cfg.ports, materials)  # a misplaced gauge: before assembly
    check_memory(space, cfg.modes.count, method=cfg.modes.method, solver=cfg.modes.solver)

    with stage("assemble"):
        fixed = fixed_dofs(space, regions, cfg.supports, cfg.constraints.in_plane)
        free = free_dofs(space.n_dofs, fixed)
        constraint = _constraint(space, regions, cfg, free, extra)  # refusals: before K
        # connection-point models need the unsupported body: then K is assembled whole
        # and restricted to a copy; else straight onto the free DOFs when the supports
        # clamp whole nodes (the full K is never built), or restricted in place
        nodes = None if cfg.connections else whole_nodes(free, space.n_nodes)
        # springs and held local directions change K after its assembly, and a body its supports
        # leave free to move is solved with a shift: no pattern analysis of K ahead
        grounded = any(s.spring or s.bushing or s.local_fix for s in cfg.supports)
        # a constraint u = T q: the factorised matrix is T^T K T, not K's pattern
        grounded = grounded or any(m.kind == "point" and m.coupling == "rigid"
                                   for m in cfg.masses)
        if not grounded and cfg.supports and rigid_freedoms(
                space.node_points, space.node_points.mean(axis=0), fixed).count:
            on_stiffness_pattern = None
        # K's structure comes from the node graph alone: the solver's analysis of it
        # (on_stiffness_pattern) starts before the element pairs are looked up in the
        # graph, so that it runs beside that look-up and the whole element loop
        graph = node_graph(space)
        layout = stiffness_layout(graph, nodes)
        if on_stiffness_pattern is not None and nodes is not None and not grounded:
            on_stiffness_pattern(layout.indptr, layout.indices)
        pattern = element_slots(graph, space)
        del graph
        with progress("assemble", n_tetrahedra, "elem") as update:
            assembled = assemble_on_nodes(space, materials, nodes, pattern=pattern,
                                          progress=update, layout=layout)
        del pattern, layout
        props = body_properties(assembled.node_mass, space.node_points)
        K, M = assembled.K, assembled.M
        del assembled
        if added is not None:  # point and area masses: in M and in the rigid properties
            R = rigid_body_modes(space.node_points)
            props = properties_from_rigid_mass(props.rigid_mass + R.T @ (added @ R))
            M = M + (added if M.shape[0] == space.n_dofs else
                     added[nodes_dofs(nodes)][:, nodes_dofs(nodes)])
        if cfg.connections:
            full = (K, M)
            K, M = restrict(K, free), restrict(M, free)
        else:
            full = (None, None)
            if K.shape[0] != free.size:
                K, M = restrict(K, free, overwrite=True), restrict(M, free, overwrite=True)
        diagonal = np.zeros(space.n_dofs)
        diagonal[free] = csr_diagonal(K)
        if extra.springs is not None:
            K = (K + restrict(extra.springs, free)).tocsr()
        ratio = diagonal[free] / np.maximum(csr_diagonal(M), np.finfo(float).tiny)
        rigid = rigid_freedoms(space.node_points, props.center_of_mass, fixed, extra.springs,
                               extra.constraint, props.rigid_mass,
                               SOFT_SUPPORT * float(np.median(ratio)) if free.size else 0.0)
        log.info("body mass %.6g kg; %d DOFs fixed, %d free; %d rigid-body mode(s) left "
                 "free%s", props.mass, fixed.size, free.size, rigid.count,
                 f" ({', '.join(rigid.names)})" if 0 < rigid.count < 6 else "")
    return FEModel(space=space, regions=regions, fixed=fixed, free=free, K=K, M=M,
                   props=props, mesh_path=mesh_path, mesh_sha256=mesh_sha256, n_elements=n_tetrahedra,
                   K_full=full[0], M_full=full[1], rigid=rigid, support_stiffness=extra,
                   materials=materials, constraint=constraint)


def _constraint(space: FESpace, regions, cfg: Config, free: np.ndarray,
                extra: SupportStiffness) -> Constraint | None:
    """u = T q of the components held in a local frame and the rigid couplings of added
    masses (:mod:`pipeline.fe.constraints`), or None when there are none."""
    inputs = constraint_inputs(space, regions, cfg, free, extra)
    return None if inputs is None else build_constraint(free, space.n_dofs, *inputs)


def constraint_inputs(space: FESpace, regions, cfg: Config, free: np.ndarray,
                      extra: SupportStiffness):
    """(the held local directions ((n_c, n_dofs) CSR) or None, the rigid couplings
    (:func:`pipeline.fe.added_mass.rigid_couplings`), what they hold) of u = T q, or None
    when there are none; a misplaced rigid coupling is refused here (RegionError)."""
    held = None if extra.constraint is None else \
        (3 * (extra.constraint.indices // 3)[:, None] + np.arange(3)).ravel()
    rigid = rigid_couplings(space, regions, cfg.masses, free, held)
    if extra.constraint is None and not rigid:
        return None
    what = " and ".join(w for w, on in (("local-frame supports", extra.constraint is not None),
                                         (f"{len(rigid)} rigid mass coupling(s)", rigid)) if on)
    return extra.constraint, rigid, what


def nodes_dofs(nodes: np.ndarray) -> np.ndarray:
    """All three DOFs 3 p + c of the sorted ``nodes``, sorted."""
    return (3 * np.asarray(nodes, dtype=np.int64)[:, None] + np.arange(3)).ravel()
