"""Mesh size estimate before meshing: refuse a mesh.size that would not fit in memory.

gmsh asked for billions of elements runs on for hours and ignores Ctrl-C; the memory
check after meshing (:func:`pipeline._util.resources.check_memory`) comes too late. From
the body's volume V (m^3), its smallest dimension t (m, the thickness of a plate or
strip; gmsh puts at least one element through it) and the target size h (m):

    n_tets  ~ TETS_PER_VOLUME * V / (h^2 min(h, t))
    n_nodes ~ NODES_PER_TET[order] * n_tets

TETS_PER_VOLUME = 6.5 bounds what gmsh (HXT) made on boxes (measured: 4.1 - 5.0 tets per
h^3 on solid boxes, 18 per h^2 t on a 2 mm strip with h = 5 mm, i.e. 6.5 per h^2 t);
NODES_PER_TET: linear elements have 0.20 - 0.36 vertices per tetrahedron, quadratic ones
add the edge midpoints (about 1.2 edges per tetrahedron). The peak memory of the whole
run for that many nodes is :func:`pipeline._util.resources.estimate_memory_bytes`; a
request above the usable memory is refused with the mesh.size that would fit.
"""

from __future__ import annotations

from dataclasses import dataclass

from pipeline._util import resources
from pipeline.config import MeshSpec
from pipeline.errors import ResourceError

TETS_PER_VOLUME = 6.5
NODES_PER_TET = {1: 0.36, 2: 1.6}
#: the estimate is refused only when it exceeds the usable memory by this factor: it is
#: rough (gmsh's element count varies by ~1.5x with the shape), and the exact check after
#: meshing (:func:`pipeline._util.resources.check_memory`) judges borderline meshes
MARGIN = 2.0
#: modes assumed when the mode count is not known where meshing starts (the memory of
#: the eigensolve grows with it; the factor dominates up to hundreds of modes)
DEFAULT_MODES = 20


@dataclass(frozen=True)
class MeshEstimate:
    """Expected tetrahedra, nodes and peak bytes of a run on the mesh."""

    n_tetrahedra: float
    n_nodes: float
    peak_bytes: float


def estimate_mesh(volume_m3: float, smallest_m: float, size: float, order: int,
                  n_modes: int = DEFAULT_MODES) -> MeshEstimate:
    """The estimate of the module doc for a body of ``volume_m3`` whose smallest dimension
    is ``smallest_m`` (use the largest for a compact body), meshed at ``size`` m."""
    through = min(size, smallest_m) if smallest_m > 0 else size
    n_tets = TETS_PER_VOLUME * volume_m3 / (size * size * through)
    n_nodes = NODES_PER_TET.get(order, NODES_PER_TET[2]) * n_tets
    # estimate_memory_bytes works in integers; clip astronomically large requests
    cap = 1e15
    peak = float(resources.estimate_memory_bytes(int(min(n_nodes, cap)), int(min(n_tets, cap)),
                                                 order, n_modes))
    return MeshEstimate(n_tets, n_nodes, peak)


def check_mesh_fits(volume_m3: float, smallest_m: float, spec: MeshSpec, what: str,
                    n_modes: int = DEFAULT_MODES, available: int | None = None) -> MeshEstimate:
    """Refuse (ResourceError naming mesh.size) a mesh whose estimated run would not fit in
    the usable memory (HEADROOM of what is available), with the smallest size that fits."""
    est = estimate_mesh(volume_m3, smallest_m, spec.size, spec.order, n_modes)
    have = resources.available_memory_bytes() if available is None else available
    usable = resources.HEADROOM * have
    floor = estimate_mesh(volume_m3, smallest_m, float("inf"), spec.order, n_modes).peak_bytes
    if est.peak_bytes <= MARGIN * usable or floor >= usable:
        # fits (or borderline: the exact check after meshing decides), or not even an
        # empty mesh fits (no mesh.size helps: that check reports the memory)
        return est
    lo, hi = spec.size, spec.size
    while estimate_mesh(volume_m3, smallest_m, hi, spec.order, n_modes).peak_bytes > usable:
        hi *= 2.0
        if hi > 1e6:
            break
    for _ in range(60):  # bisection: the estimate decreases with the size
        mid = 0.5 * (lo + hi)
        if estimate_mesh(volume_m3, smallest_m, mid, spec.order, n_modes).peak_bytes > usable:
            lo = mid
        else:
            hi = mid
    raise ResourceError(
        f"config key 'mesh.size': got {spec.size:g} m, which would make about "
        f"{est.n_tetrahedra:.2g} tetrahedra ({3 * est.n_nodes:.2g} DOFs with order "
        f"{spec.order}) for {what}, needing about {est.peak_bytes / 1e9:.3g} GB; "
        f"{usable / 1e9:.3g} GB are usable here: expected mesh.size >= {hi:.3g} m",
        key="mesh.size", value=spec.size, expected=f">= {hi:.3g} m")
