"""Named regions of the body and the supports that act on them.

A region is a set of boundary triangles: a gmsh physical group of the mesh, or a
geometric selector of the config (:class:`~pipeline.config.RegionSelector`) applied
to the boundary facets of the mesh.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from pipeline.config import RegionSelector, Support
from pipeline.errors import RegionError
from pipeline.fe.space import FESpace, boundary_triangles, region_nodes

COMPONENT = {"x": 0, "y": 1, "z": 2}


def select_triangles(space: FESpace, selector: RegionSelector) -> np.ndarray:
    """(n_f, 3) boundary triangles whose three vertices satisfy ``selector``."""
    tris = boundary_triangles(space)
    x = space.body.vertices
    if selector.kind == "plane":
        n = np.asarray(selector.normal) / np.linalg.norm(selector.normal)
        inside = np.abs((x - np.asarray(selector.point)) @ n) <= selector.tolerance
    elif selector.kind == "box":
        inside = np.all((x >= np.asarray(selector.lower)) & (x <= np.asarray(selector.upper)), 1)
    else:
        inside = np.linalg.norm(x - np.asarray(selector.point), axis=1) <= selector.radius
    return tris[inside[tris].all(axis=1)]


def resolve_regions(space: FESpace, selectors: Mapping[str, RegionSelector]
                    ) -> dict[str, np.ndarray]:
    """All named regions: the mesh's physical groups plus the config's selectors."""
    regions = dict(space.body.regions)
    for name, sel in selectors.items():
        tris = select_triangles(space, sel)
        if tris.shape[0] == 0:
            raise RegionError(f"config key 'regions.{name}': the {sel.kind} selector matches no "
                              f"boundary facet of the mesh '{space.body.source}'; expected at "
                              "least one (check its position, size and tolerance)")
        regions[name] = tris
    return regions


def get_region(regions: Mapping[str, np.ndarray], name: str, key: str) -> np.ndarray:
    """Triangles of region ``name``, or a RegionError naming the config ``key``."""
    if name not in regions:
        raise RegionError(f"config key '{key}': region '{name}' does not exist in the mesh; "
                          f"expected one of: {', '.join(sorted(regions)) or '(none)'}")
    tris = regions[name]
    if tris.shape[0] == 0:
        raise RegionError(f"config key '{key}': region '{name}' is empty")
    return tris


def fixed_dofs(space: FESpace, regions: Mapping[str, np.ndarray], supports: Sequence[Support],
               in_plane: bool) -> np.ndarray:
    """Sorted DOF indices removed by the supports and the in-plane constraint."""
    fixed = []
    for i, support in enumerate(supports):
        nodes = region_nodes(space, get_region(regions, support.region, f"supports[{i}].region"))
        for comp in support.fix:
            fixed.append(3 * nodes + COMPONENT[comp])
    if in_plane:
        fixed.append(3 * np.arange(space.n_nodes) + 2)
    if not fixed:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate(fixed))


def free_dofs(n_dofs: int, fixed: np.ndarray) -> np.ndarray:
    """The complement of ``fixed`` in 0..n_dofs-1, sorted."""
    mask = np.ones(n_dofs, dtype=bool)
    mask[fixed] = False
    return np.flatnonzero(mask)
