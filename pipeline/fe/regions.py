"""Named regions of the body and the supports that act on them.

A region is a set of cells of one dimension, given by their vertex indices: boundary
triangles (n, 3), a face; edges (n, 2), a line; vertices (n, 1), a point or node set.
Its dimension is the number of columns less one
(:func:`~pipeline.fe.space.region_dimension`); its nodes are the cells' vertices and, for
quadratic elements, the midpoints of the cells' edges
(:func:`~pipeline.fe.space.region_nodes`). Regions come from the mesh's named groups
(gmsh physical groups of dimension 2, 1 and 0) and from the geometric selectors of the
config (:class:`~pipeline.config.RegionSelector`): a selector takes the boundary
triangles whose three vertices it contains; where there are none, the boundary edges
whose two vertices it contains (a box or plane shrunk onto an edge of the body); where
there are none either, the boundary vertices it contains (a vertex, a node set).
"""

from __future__ import annotations

import logging
from typing import Mapping, Sequence

import numpy as np

from pipeline.config import Config, RegionSelector, Support
from pipeline.errors import RegionError
from pipeline.fe.space import (REGION_KINDS, TRI_EDGES, FESpace, boundary_edges,
                               boundary_triangles, region_dimension, region_nodes)

log = logging.getLogger(__name__)

COMPONENT = {"x": 0, "y": 1, "z": 2}


def _inside(x: np.ndarray, selector: RegionSelector) -> np.ndarray:
    """(n,) whether each point of ``x`` (n, 3) m satisfies ``selector``."""
    if selector.kind == "plane":
        n = np.asarray(selector.normal) / np.linalg.norm(selector.normal)
        return np.abs((x - np.asarray(selector.point)) @ n) <= selector.tolerance
    if selector.kind == "box":
        return np.all((x >= np.asarray(selector.lower)) & (x <= np.asarray(selector.upper)), 1)
    return np.linalg.norm(x - np.asarray(selector.point), axis=1) <= selector.radius


def select_triangles(space: FESpace, selector: RegionSelector) -> np.ndarray:
    """(n_f, 3) boundary triangles whose three vertices satisfy ``selector``."""
    tris = boundary_triangles(space)
    return tris[_inside(space.body.vertices, selector)[tris].all(axis=1)]


def select_region(space: FESpace, selector: RegionSelector) -> np.ndarray:
    """The region ``selector`` picks on the boundary, of the highest dimension it can:
    boundary triangles (n, 3) inside it, else boundary edges (n, 2), else boundary vertices
    (n, 1); (0, 3) when it contains no boundary vertex."""
    inside = _inside(space.body.vertices, selector)
    tris = boundary_triangles(space)
    faces = tris[inside[tris].all(axis=1)]
    if faces.shape[0]:
        return faces
    edges = boundary_edges(space)
    lines = edges[inside[edges].all(axis=1)]
    if lines.shape[0]:
        return lines
    verts = np.unique(tris)
    return verts[inside[verts]][:, None] if inside[verts].any() else faces


def _keys(pairs: np.ndarray, n: int) -> np.ndarray:
    p = np.sort(np.asarray(pairs, dtype=np.int64).reshape(-1, 2), axis=1)
    return p[:, 0] * n + p[:, 1]


def node_set_region(space: FESpace, name: str, vertices: np.ndarray,
                    edge_pairs: np.ndarray | None = None) -> np.ndarray:
    """The boundary region a mesh file's node set spans: its boundary triangles (n, 3) if
    they hold every boundary vertex of the set, else its boundary edges (n, 2) if they
    do, else its boundary vertices (n, 1). A triangle or edge belongs to the set when its
    vertices do and, where the file's mid-edge nodes are known (``edge_pairs`` (m, 2),
    the edges whose mid-edge node the set holds), its edges' mid-edge nodes do too (so
    that a set along two edges of a face does not take the triangle across its corner).
    What is left out (interior vertices; a point set's mid-edge nodes) is logged."""
    n_v = space.body.n_vertices
    inside = np.zeros(n_v, dtype=bool)
    inside[vertices] = True
    tris = boundary_triangles(space)
    edges = boundary_edges(space)
    on_boundary = np.unique(tris)
    wanted = on_boundary[inside[on_boundary]]
    tri_ok = inside[tris].all(axis=1)
    edge_ok = inside[edges].all(axis=1)
    if edge_pairs is not None:
        known = np.isin(_keys(edges, n_v), _keys(edge_pairs, n_v))
        edge_ok &= known
        tri_ok &= np.isin(_keys(tris[:, TRI_EDGES], n_v),
                          _keys(edge_pairs, n_v)).reshape(-1, 3).all(axis=1)
    cells = np.zeros((0, 1), dtype=np.int64)
    for candidate in (tris[tri_ok], edges[edge_ok], wanted[:, None]):
        if candidate.shape[0] and np.isin(wanted, candidate).all():
            cells = candidate
            break
    left = vertices.size - wanted.size
    if cells.shape[0] == 0:
        log.info("node set '%s': none of its %d vertices is on the boundary: not a region",
                 name, vertices.size)
    else:
        mids = (edge_pairs.shape[0] if edge_pairs is not None and cells.shape[1] == 1
                else 0)
        log.info("node set '%s': a %s%s%s", name, describe_region(cells),
                 f"; {left} interior vertices left out" if left else "",
                 f"; its {mids} mid-edge nodes left out" if mids else "")
    return cells


def describe_region(cells: np.ndarray) -> str:
    """'face of 12 triangles', 'line of 4 edges', 'point set of 1 vertex'."""
    n = int(cells.shape[0])
    dim = region_dimension(cells)
    unit = {2: ("triangle", "triangles"), 1: ("edge", "edges"), 0: ("vertex", "vertices")}[dim]
    what = REGION_KINDS[dim][0] + (" set" if dim == 0 else "")
    return f"{what} of {n} {unit[n != 1]}"


def resolve_regions(space: FESpace, selectors: Mapping[str, RegionSelector]
                    ) -> dict[str, np.ndarray]:
    """All named regions: the mesh's named groups plus the config's selectors, each an
    int64 array of vertex cells (n, 3 | 2 | 1) (module docstring)."""
    regions = dict(space.body.regions)
    for name, verts in space.body.node_sets.items():
        if name in regions:  # a cell set of the same name (Abaqus: *ELSET and *NSET) wins
            continue
        cells = node_set_region(space, name, verts, space.body.node_set_edges.get(name))
        if cells.shape[0]:
            regions[name] = cells
    for name, sel in selectors.items():
        cells = select_region(space, sel)
        if cells.shape[0] == 0:
            raise RegionError(f"config key 'regions.{name}': the {sel.kind} selector matches no "
                              f"boundary facet, edge or vertex of the mesh '{space.body.source}'; expected at "
                              "least one (check its position, size and tolerance)")
        if region_dimension(cells) < 2:
            log.info("region '%s': the %s selector matches no boundary facet; it is a %s",
                     name, sel.kind, describe_region(cells))
        regions[name] = cells
    return regions


def get_region(regions: Mapping[str, np.ndarray], name: str, key: str) -> np.ndarray:
    """Cells of region ``name`` (n, 3 | 2 | 1), or a RegionError naming the config ``key``."""
    if name not in regions:
        raise RegionError(f"config key '{key}': region '{name}' does not exist in the mesh; "
                          f"expected one of: {', '.join(sorted(regions)) or '(none)'}")
    cells = regions[name]
    if cells.shape[0] == 0:
        raise RegionError(f"config key '{key}': region '{name}' is empty")
    return cells


def region_uses(cfg: Config) -> list[tuple[str, str, int]]:
    """(config key, region name, lowest dimension it needs) of every region the config
    names: supports, forces, moments, displacement and rotation outputs and connections act
    on a region of any dimension (a point region: that node); a gauge reads the elements
    under a face, so its region must be one."""
    uses = [(f"supports[{i}].region", s.region, 0) for i, s in enumerate(cfg.supports)]
    for side in ("inputs", "outputs"):
        for i, p in enumerate(getattr(cfg.ports, side)):
            if p.region:
                uses.append((f"ports.{side}[{i}].region", p.region,
                             2 if p.kind in ("strain", "stress") else 0))
    uses += [(f"connections[{i}].region", c.region, 0) for i, c in enumerate(cfg.connections)]
    return uses


def check_region_uses(cfg: Config, space: FESpace, regions: Mapping[str, np.ndarray]) -> None:
    """Refuse, before assembly, a region name that names no region of the mesh or of
    ``regions:`` (one line naming the config key; a mesh group that is no region, such as
    a volume group, is named as what it is), and a region of too low a dimension for its
    use (a gauge on a line)."""
    other = space.body.other_groups
    for key, name, lowest in region_uses(cfg):
        if name not in regions and name in other:
            raise RegionError(f"config key '{key}': '{name}' is {other[name]} of the mesh "
                              f"'{space.body.source}', not a region; expected a face, line or "
                              f"point region: {', '.join(sorted(regions)) or '(none)'}")
        cells = get_region(regions, name, key)
        if region_dimension(cells) < lowest:
            raise RegionError(f"config key '{key}': region '{name}' is a "
                              f"{describe_region(cells)}; expected a face region (a gauge "
                              "reads the elements under a surface)")


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
