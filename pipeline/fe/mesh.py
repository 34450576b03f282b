"""Mesh stage: gmsh builds and meshes the body, meshio reads the mesh back.

The result is a :class:`BodyMesh`: straight-sided tetrahedra (the corner nodes of the
gmsh elements) plus the boundary triangles of every named region (gmsh physical
groups). Higher-order nodes are re-created by the finite-element space
(:mod:`pipeline.fe.space`) at the edge midpoints, so a quadratic field lives on
straight-edged tetrahedra: exact for the box, and a faceted approximation of a curved
surface.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from pipeline.config import Geometry, MeshSpec
from pipeline._util.atomic import atomic_path
from pipeline.errors import MeshError, OutputError

log = logging.getLogger(__name__)

_ALGORITHM_3D = {"delaunay": 1, "frontal": 4, "hxt": 10}


@dataclass(frozen=True)
class BodyMesh:
    """A tetrahedral mesh of the body with named boundary regions.

    vertices: (n_v, 3) float64, m.
    tetrahedra: (n_t, 4) int64 vertex indices, positively oriented.
    regions: name -> (n_f, 3) int64 vertex indices of the boundary triangles.
    source: the file the mesh was read from.
    """

    vertices: np.ndarray
    tetrahedra: np.ndarray
    regions: Mapping[str, np.ndarray] = field(default_factory=dict)
    source: str = ""

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_tetrahedra(self) -> int:
        return int(self.tetrahedra.shape[0])


def _box_faces(geometry: Geometry) -> dict[str, tuple[int, float]]:
    """Face name -> (axis, coordinate) of the box's six faces."""
    L, H, D = geometry.length, geometry.height, geometry.depth
    return {"root": (0, 0.0), "tip": (0, L), "bottom": (1, 0.0), "top": (1, H),
            "back": (2, 0.0), "front": (2, D)}


def generate_mesh(geometry: Geometry, spec: MeshSpec, path: str | Path) -> Path:
    """Mesh ``geometry`` with gmsh and write it (format 4.1, binary) to ``path``.

    Physical groups: the volume ``body`` and, for the box, its faces ``root`` (x=0),
    ``tip`` (x=L), ``bottom`` (y=0), ``top`` (y=H), ``back`` (z=0), ``front`` (z=D).
    The file is written to a temporary name and renamed, so a failed run never leaves
    a partial mesh under ``path``. gmsh runs on one thread, which makes the mesh
    reproducible (the same config gives the same mesh, so cached results stay valid);
    ``PIPELINE_GMSH_THREADS=N`` trades that for threads.
    """
    import gmsh

    path = Path(path)
    threads = int(os.environ.get("PIPELINE_GMSH_THREADS", "1"))
    if gmsh.isInitialized():
        gmsh.finalize()
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 2)
        gmsh.option.setNumber("General.NumThreads", threads)
        gmsh.logger.start()
        gmsh.model.add("body")
        if geometry.kind != "box":  # validated in config; kept as a guard for library use
            raise MeshError(f"geometry.kind '{geometry.kind}': expected 'box'")
        L, H, D = geometry.length, geometry.height, geometry.depth
        volume = gmsh.model.occ.addBox(0.0, 0.0, 0.0, L, H, D)
        gmsh.model.occ.synchronize()
        tol = 1e-9 * max(L, H, D)
        for name, (axis, coord) in _box_faces(geometry).items():
            tags = []
            for dim, tag in gmsh.model.getEntities(2):
                centre = gmsh.model.occ.getCenterOfMass(dim, tag)
                if abs(centre[axis] - coord) < tol:
                    tags.append(tag)
            if not tags:
                raise MeshError(f"gmsh: no face of the box lies at the '{name}' position")
            gmsh.model.addPhysicalGroup(2, tags, name=name)
        gmsh.model.addPhysicalGroup(3, [volume], name="body")
        gmsh.option.setNumber("Mesh.MeshSizeMax", spec.size)
        gmsh.option.setNumber("Mesh.MeshSizeMin", spec.size / 4)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
        gmsh.option.setNumber("Mesh.Algorithm3D", _ALGORITHM_3D[spec.algorithm])
        gmsh.option.setNumber("Mesh.Binary", 1)
        # the file holds the linear tetrahedra only: second-order elements are straight-
        # sided and pipeline.fe.space creates their edge midpoints (vectorised), which
        # read_mesh would drop from a gmsh setOrder mesh anyway (setOrder took 2.1 s of
        # the 4.5 s mesh stage at 1M DOFs, and doubled the file)
        gmsh.model.mesh.generate(3)
        _, elem_tags, _ = gmsh.model.mesh.getElements(3)
        if not elem_tags or sum(len(t) for t in elem_tags) == 0:
            raise MeshError(f"gmsh made no volume elements for geometry {geometry} with "
                            f"mesh.size = {spec.size:g} m")
        with atomic_path(path) as tmp:
            gmsh.write(str(tmp))
    except (MeshError, OutputError):
        raise
    except Exception as exc:  # gmsh raises plain Exception with its own message
        messages = [m for m in gmsh.logger.get() if "rror" in m]
        detail = messages[-1] if messages else str(exc)
        raise MeshError(f"gmsh could not mesh geometry.kind '{geometry.kind}' with mesh.size = "
                        f"{spec.size:g} m: {detail}") from None
    finally:
        for line in gmsh.logger.get() if gmsh.isInitialized() else []:
            log.debug("gmsh: %s", line)
        if gmsh.isInitialized():
            gmsh.logger.stop()
            gmsh.finalize()
    return path


def _orient(vertices: np.ndarray, tets: np.ndarray, source: str) -> np.ndarray:
    """Return ``tets`` with positive orientation; refuse degenerate elements."""
    a, b, c, d = (vertices[tets[:, i]] for i in range(4))
    vol6 = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)
    scale = np.abs(vol6).mean() if vol6.size else 0.0
    bad = np.abs(vol6) <= 1e-10 * scale
    if scale == 0.0 or bad.any():
        idx = int(np.flatnonzero(bad)[0]) if bad.any() else 0
        raise MeshError(f"mesh '{source}': {int(bad.sum()) or tets.shape[0]} tetrahedra have zero "
                        f"volume (first: element {idx}); expected non-degenerate elements")
    neg = vol6 < 0
    if neg.any():
        log.info("mesh '%s': re-oriented %d of %d tetrahedra", source, neg.sum(), len(tets))
        tets = tets.copy()
        tets[neg, 2], tets[neg, 3] = tets[neg, 3].copy(), tets[neg, 2].copy()
    return tets


def read_mesh(path: str | Path) -> BodyMesh:
    """Read a tetrahedral mesh (any format meshio reads) with its named boundary regions.

    Accepts ``tetra`` and ``tetra10`` cells (higher-order nodes are dropped: see the
    module docstring); named regions are the triangle cell sets (gmsh physical
    groups). Unused nodes are removed and vertices renumbered 0..n_v-1.
    """
    import meshio

    path = Path(path)
    if not path.exists():
        raise MeshError(f"mesh file '{path}': not found")
    try:
        mesh = meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types, and sys.exit(1)
        detail = str(exc) if not isinstance(exc, SystemExit) else "unknown or corrupt format"
        raise MeshError(f"mesh file '{path}': meshio cannot read it ({detail})") from None
    tet_blocks = [(i, b) for i, b in enumerate(mesh.cells) if b.type in ("tetra", "tetra10")]
    if not tet_blocks:
        kinds = sorted({b.type for b in mesh.cells}) or ["none"]
        raise MeshError(f"mesh file '{path}': has no tetrahedra (cell types: {', '.join(kinds)}); "
                        "expected tetra or tetra10 volume cells")
    tets = np.concatenate([b.data[:, :4] for _, b in tet_blocks]).astype(np.int64)
    used = np.unique(tets)
    renumber = np.full(mesh.points.shape[0], -1, dtype=np.int64)
    renumber[used] = np.arange(used.size)
    vertices = np.ascontiguousarray(mesh.points[used, :3], dtype=np.float64)
    tets = _orient(vertices, renumber[tets], str(path))

    regions: dict[str, np.ndarray] = {}
    for name, per_block in (mesh.cell_sets or {}).items():
        if name.startswith("gmsh:"):
            continue
        tris = []
        for block, ids in zip(mesh.cells, per_block):
            if block.type in ("triangle", "triangle6") and ids is not None and len(ids):
                tris.append(block.data[np.asarray(ids), :3])
        if tris:
            tri = renumber[np.concatenate(tris).astype(np.int64)]
            if (tri < 0).any():
                raise MeshError(f"mesh file '{path}': region '{name}' has triangles whose nodes "
                                "belong to no tetrahedron")
            regions[name] = tri
    log.info("mesh '%s': %d vertices, %d tetrahedra, regions: %s", path.name, vertices.shape[0],
             tets.shape[0], ", ".join(sorted(regions)) or "none")
    return BodyMesh(vertices=vertices, tetrahedra=tets, regions=regions, source=str(path))


def mesh_body(geometry: Geometry, spec: MeshSpec, mesh_dir: str | Path, name: str
              ) -> tuple[BodyMesh, Path]:
    """The mesh stage for any geometry kind: (mesh, path of the mesh file).

    ``box`` is meshed here; ``step`` and ``geo`` are meshed by :mod:`pipeline.fe.geometry`;
    ``mesh`` files are read as they are (scaled by ``geometry.scale``).
    """
    out = Path(mesh_dir) / f"{name}.msh"
    if geometry.kind == "box":
        path = generate_mesh(geometry, spec, out)
        return read_mesh(path), path
    from pipeline.fe import geometry as geo_sources

    return geo_sources.mesh_geometry(geometry, spec, out)
