"""Mesh stage: the body as a tetrahedral :class:`BodyMesh`, from one of the geometry
sources of ``geometry.kind``, each in its own module and registered in :data:`SOURCES`:

``box``  (:mod:`~pipeline.fe.mesh.box`)
    gmsh meshes the box L x H x D and names its six faces.
``step`` (:mod:`~pipeline.fe.mesh.cad`)
    A STEP, IGES or BREP file, read by gmsh's OpenCASCADE kernel, in metres.
``geo``  (:mod:`~pipeline.fe.mesh.geo`)
    A gmsh script; its physical groups name the regions.
``mesh`` (:mod:`~pipeline.fe.mesh.read`)
    An existing tetrahedral mesh any format meshio reads, scaled by ``geometry.scale``.

gmsh and meshio are imported only when a source runs. The shared record, checks and
gmsh helpers are in :mod:`~pipeline.fe.mesh.common`.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline._util.atomic import atomic_path, private_folder
from pipeline._util.paths import file_sha256
from pipeline.config import Geometry, MeshSpec
from pipeline.errors import ConfigError
from pipeline.fe.mesh.box import box_faces, generate_mesh, mesh_box
from pipeline.fe.mesh.cad import cad_volume, mesh_step
from pipeline.fe.mesh.common import (CAD_SUFFIXES, MAX_EXTENT_M, MAX_TETRAHEDRA, MIN_EXTENT_M,
                                     TET_TYPES, BodyMesh, MeshSource, check_dimensions)
from pipeline.fe.mesh.geo import mesh_geo
from pipeline.fe.mesh.read import mesh_file, read_mesh
from pipeline.fe.mesh.registry import SOURCES

__all__ = ["SOURCES", "BodyMesh", "MeshSource", "body_shape", "mesh_body", "mesh_geometry", "generate_mesh",
           "read_mesh", "box_faces", "cad_volume", "check_dimensions", "mesh_box", "mesh_step",
           "mesh_geo", "mesh_file", "CAD_SUFFIXES", "MAX_EXTENT_M", "MAX_TETRAHEDRA",
           "MIN_EXTENT_M", "TET_TYPES"]


def mesh_geometry(geometry: Geometry, spec: MeshSpec, out_path: str | Path
                  ) -> tuple[BodyMesh, Path]:
    """The mesh stage for ``geometry.kind``: (mesh, its file).

    box, step and geo write the gmsh mesh (in metres) to ``out_path``; mesh returns the
    file it read (``out_path`` is not written) with vertices multiplied by ``scale``.
    """
    source = SOURCES.get(geometry.kind)
    if source is None:
        raise ConfigError.field("geometry.kind", geometry.kind, f"one of {', '.join(SOURCES)}")
    if geometry.kind != "box" and not Path(geometry.path).is_file():
        # checked when the config was read; the file may have gone since
        raise ConfigError(f"config key 'geometry.path': got '{geometry.path}', expected an "
                          "existing file")
    return source(geometry, spec, Path(out_path))


def body_shape(geometry: Geometry):
    """The :class:`~pipeline.fe.mesh.estimate.BodyShape` (volume, boundary area) of a box,
    STEP or geo body, as its mesh source measures it before meshing (OpenCASCADE; the
    bounding box for a geo script without OCC entities)."""
    from pipeline.fe.mesh.cad import _import_cad
    from pipeline.fe.mesh.common import boundary_area, extent, gmsh_session
    from pipeline.fe.mesh.estimate import BodyShape

    if geometry.kind == "box":
        return BodyShape.box(geometry.length, geometry.height, geometry.depth)
    if geometry.kind not in ("step", "geo"):
        raise ConfigError.field("geometry.kind", geometry.kind, "box, step or geo")
    with gmsh_session("shape") as gmsh:
        if geometry.kind == "step":
            vols, volume = _import_cad(gmsh, Path(geometry.path), geometry)
            return BodyShape(volume, boundary_area(gmsh, vols))
        gmsh.open(str(geometry.path))
        vols = [tag for _, tag in gmsh.model.getEntities(3)]
        s = geometry.scale
        try:
            volume = float(sum(gmsh.model.occ.getMass(3, v) for v in vols)) * s ** 3
            return BodyShape(volume, boundary_area(gmsh, vols, s))
        except Exception:  # built-in kernel entities: no OCC volume
            return BodyShape.box(*extent(gmsh, s))


def mesh_body(geometry: Geometry, spec: MeshSpec, mesh_dir: str | Path | None, name: str
              ) -> tuple[BodyMesh, Path | None, str]:
    """The mesh stage of a run: (mesh, the mesh file kept, SHA-256 of the mesh file).

    A run's mesh is its own: gmsh writes it into a private temporary folder and the mesh
    is read from there, so runs started together (even of configs of the same name) never
    read each other's mesh. With ``mesh_dir`` a copy is kept, content-addressed, as
    ``<mesh_dir>/<name>.<sha256[:12]>.msh``: a later run never changes the content of a
    file an earlier result names (the same name means the same bytes). Without it no file
    is kept (None; the HDF5 file holds the mesh). For kind ``mesh`` the user's file read is
    returned (it is an input, never written).
    """
    if geometry.kind == "mesh":
        body, path = mesh_geometry(geometry, spec, Path(geometry.path))
        return body, Path(path), file_sha256(Path(path))
    with private_folder(f"pipeline-mesh-{name}-") as work:
        body, path = mesh_geometry(geometry, spec, work / f"{name}.msh")
        sha = file_sha256(path)
        if mesh_dir is None:
            return body, None, sha
        kept = Path(mesh_dir) / f"{name}.{sha[:12]}.msh"
        with atomic_path(kept) as tmp:
            shutil.copyfile(path, tmp)
    return body, kept, sha
