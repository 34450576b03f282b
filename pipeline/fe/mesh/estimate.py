"""Mesh size estimate before meshing: refuse a mesh.size that would not fit in memory.

gmsh asked for billions of elements runs on for hours and ignores Ctrl-C; the memory
check after meshing (:func:`pipeline._util.resources.check_memory`) comes too late. From
the body's volume V (m^3), its boundary area S (m^2) and the target size h (m), with
t = 2 V / S the body's mean thickness (a plate's thickness, a third of a cube's side):

    n_tets     ~ TETS_PER_VOLUME * V / (h^2 min(h, t)) + TETS_PER_AREA * S / h^2
    n_vertices ~ VERTICES_PER_VOLUME * V / (h^2 min(h, t)) + VERTICES_PER_AREA * S / h^2
    n_nodes    = n_vertices (order 1), n_vertices + n_edges (order 2, the P2 nodes)

The volume term is the interior at about 3.8 tetrahedra per h^3; the area term is the
boundary layer, where gmsh's surface triangles (about 2.4 per h^2) each start tetrahedra
that do not fill a whole h^3: thin and slender bodies have more elements per volume
(the cantilever at h = 5 mm: 5.0 per h^3, at 1.16 mm 4.2). Through a plate thinner than
h gmsh still puts one layer of elements, so the volume term counts h^2 t per element
there. The coefficients are a least-squares fit (relative error) to gmsh HXT meshes of
five bodies, 23 meshes of 20k - 1.3M tetrahedra (``benchmarks/mesh_counts.py``): the
cantilever box 0.5 x 0.02 x 0.05 m (h = 5 - 1.16 mm), the 2 mm strip (h = 3 - 0.7 mm), a
0.1 m cube (h = 5 - 2.5 mm), the bracket STEP (h = 1.8 - 0.6 mm) and the 2 m slender beam
(h = 3 - 1.5 mm); the largest deviation is 12 % in tetrahedra, 9 % in P2 nodes (the
cantilever at 1.16 mm: 1.300M tetrahedra, 1.843M P2 nodes; estimated 1.289M and 1.828M).
Below about 20k tetrahedra gmsh's own refinement dominates (curvature: 12 elements per
full circle along the bracket's holes; fewer than two elements across the slender
beam's section) and the estimate can be off by a factor 2-3, where memory does not
matter. The peak memory of the whole run for that many nodes is
:func:`pipeline._util.resources.estimate_memory_bytes`; a request above the usable
memory is refused with the mesh.size that would fit.
"""

from __future__ import annotations

from dataclasses import dataclass

from pipeline._util import resources
from pipeline.config import MeshSpec
from pipeline.errors import ResourceError

TETS_PER_VOLUME = 3.78
TETS_PER_AREA = 1.48
VERTICES_PER_VOLUME = 0.593
VERTICES_PER_AREA = 0.904
#: P2 nodes (vertices and edge midpoints) per volume and area unit as above
P2_NODES_PER_VOLUME = 4.95
P2_NODES_PER_AREA = 4.51
#: the estimate is refused only when it exceeds the usable memory by this factor: the
#: node count is within 20 % on meshes that matter for memory, and the exact check after
#: meshing (:func:`pipeline._util.resources.check_memory`) judges borderline meshes
MARGIN = 1.25
#: modes assumed when the mode count is not known where meshing starts (the memory of
#: the eigensolve grows with it; the factor dominates up to hundreds of modes)
DEFAULT_MODES = 20


@dataclass(frozen=True)
class BodyShape:
    """What the estimate needs of a body: its volume (m^3) and boundary area (m^2)."""

    volume_m3: float
    area_m2: float

    @property
    def thickness_m(self) -> float:
        """Mean thickness 2 V / S (m): a plate's thickness, a third of a cube's side."""
        return 2.0 * self.volume_m3 / self.area_m2 if self.area_m2 > 0 else float("inf")

    @classmethod
    def box(cls, length: float, height: float, depth: float) -> "BodyShape":
        """The box length x height x depth (m)."""
        return cls(length * height * depth,
                   2.0 * (length * height + length * depth + height * depth))


@dataclass(frozen=True)
class MeshEstimate:
    """Expected tetrahedra, nodes and peak bytes of a run on the mesh."""

    n_tetrahedra: float
    n_nodes: float
    peak_bytes: float


def estimate_mesh(shape: BodyShape, size: float, order: int,
                  n_modes: int = DEFAULT_MODES, method: str = "auto",
                  solver: str = "auto") -> MeshEstimate:
    """The estimate of the module doc for ``shape`` meshed at ``size`` m, elements of
    ``order`` 1 or 2; the run's peak for ``modes.method`` and ``modes.solver``
    (:func:`pipeline._util.resources.eigensolve_bytes`)."""
    through = min(size, shape.thickness_m)
    bulk = shape.volume_m3 / (size * size * through)
    skin = shape.area_m2 / (size * size)
    n_tets = TETS_PER_VOLUME * bulk + TETS_PER_AREA * skin
    if order == 1:
        n_nodes = VERTICES_PER_VOLUME * bulk + VERTICES_PER_AREA * skin
    else:
        n_nodes = P2_NODES_PER_VOLUME * bulk + P2_NODES_PER_AREA * skin
    # estimate_memory_bytes works in integers; clip astronomically large requests
    cap = 1e15
    peak = float(resources.estimate_memory_bytes(int(min(n_nodes, cap)), int(min(n_tets, cap)),
                                                 order, n_modes, method, solver=solver))
    return MeshEstimate(n_tets, n_nodes, peak)


def smallest_size(shape: BodyShape, order: int, limit: float, what: str = "peak_bytes",
                  start: float | None = None, n_modes: int = DEFAULT_MODES,
                  method: str = "auto", solver: str = "auto") -> float:
    """The smallest mesh.size (m) whose estimated ``what`` (a field of
    :class:`MeshEstimate`) stays within ``limit``; found by bisection (the estimate
    decreases with the size) from ``start`` (a size that exceeds it)."""
    def over(h: float) -> bool:
        return getattr(estimate_mesh(shape, h, order, n_modes, method, solver), what) > limit

    lo = hi = start if start is not None else shape.thickness_m
    while over(hi) and hi < 1e6:
        hi *= 2.0
    while not over(lo) and lo > 1e-9:
        lo *= 0.5
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if over(mid):
            lo = mid
        else:
            hi = mid
    return hi


def check_mesh_fits(shape: BodyShape, spec: MeshSpec, what: str,
                    n_modes: int = DEFAULT_MODES, available: int | None = None,
                    method: str = "auto", solver: str = "auto") -> MeshEstimate:
    """Refuse (ResourceError naming mesh.size) a mesh whose estimated run would not fit in
    the usable memory (HEADROOM of what is available), with the smallest size that fits;
    the run with ``modes.method`` ``method`` and ``modes.solver`` ``solver`` (the mesh
    sources check the default run; :func:`pipeline.fe.model.build_fe_model` checks a
    run that asks for another before gmsh starts)."""
    est = estimate_mesh(shape, spec.size, spec.order, n_modes, method, solver)
    have = resources.available_memory_bytes() if available is None else available
    usable = resources.HEADROOM * have
    floor = estimate_mesh(shape, float("inf"), spec.order, n_modes, method, solver).peak_bytes
    if est.peak_bytes <= MARGIN * usable or floor >= usable:
        # fits (or borderline: the exact check after meshing decides), or not even an
        # empty mesh fits (no mesh.size helps: that check reports the memory)
        return est
    fits = smallest_size(shape, spec.order, usable, start=spec.size, n_modes=n_modes,
                         method=method, solver=solver)
    run = "" if (method, solver) == ("auto", "auto") else (
        f" with modes.method {method}" + ("" if solver == "auto" else f", modes.solver {solver}"))
    raise ResourceError(
        f"config key 'mesh.size': got {spec.size:g} m, which would make about "
        f"{est.n_tetrahedra:.2g} tetrahedra ({3 * est.n_nodes:.2g} DOFs with order "
        f"{spec.order}) for {what}, needing about {est.peak_bytes / 1e9:.3g} GB{run}; "
        f"{usable / 1e9:.3g} GB are usable here: expected mesh.size >= {fits:.3g} m",
        key="mesh.size", value=spec.size, expected=f">= {fits:.3g} m")
