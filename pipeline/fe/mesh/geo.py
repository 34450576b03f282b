"""The ``geo`` source: a gmsh script (``.geo``) whose physical groups name the regions.

The script's numbers are multiplied by ``geometry.scale`` (gmsh's
``Mesh.ScalingFactor``: draw in mm, set ``scale: 0.001``); ``mesh.size`` (m) caps the
element size. A script that meshes itself (``Mesh 3;``) keeps its own mesh.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from pipeline.config import Geometry, MeshSpec
from pipeline.errors import ConfigError, MeshError
from pipeline.fe.mesh.common import (BodyMesh, boundary_area, check_dimensions, check_size,
                                     count_tets, extent, gmsh_error, gmsh_session, mesh_options,
                                     quiet_fd1, write_gmsh)
from pipeline.fe.mesh.estimate import BodyShape
from pipeline.fe.mesh.read import read_mesh
from pipeline.fe.mesh.registry import SOURCES

log = logging.getLogger(__name__)


def _mesh_geo(geometry: Geometry, spec: MeshSpec, out_path: Path) -> bool:
    """Write the script's mesh to ``out_path``; True where ``mesh.size`` set its
    element size (False: the script meshes itself)."""
    path = Path(geometry.path)
    if path.suffix.lower() != ".geo":
        raise ConfigError(f"config key 'geometry.path': got '{path}' for kind 'geo'; expected a "
                          "gmsh script ending in .geo")
    with gmsh_session("body") as gmsh:
        try:
            with quiet_fd1():
                gmsh.open(str(path))
        except Exception as exc:
            raise MeshError(f"geometry.path '{path}': gmsh cannot run this script "
                            f"({gmsh_error(gmsh, exc)}); expected a valid .geo file") from None
        vols = [tag for _, tag in gmsh.model.getEntities(3)]
        if not vols:
            raise MeshError(f"geometry.path '{path}': the script defines no volume; expected at "
                            "least one (Volume, Box, Extrude ...)")
        scale = geometry.scale
        check_dimensions(extent(gmsh, scale), geometry, str(path))
        if not any(d == 3 for d, _ in gmsh.model.getPhysicalGroups()):
            # gmsh saves only elements of physical groups when there are any
            gmsh.model.addPhysicalGroup(3, vols, name="body")
        premeshed = count_tets(gmsh) > 0
        if premeshed:
            log.info("'%s' meshes itself; its own element sizes are kept (mesh.size ignored)",
                     path.name)
        else:
            try:
                volume = float(sum(gmsh.model.occ.getMass(3, v) for v in vols)) * scale ** 3
                shape = BodyShape(volume, boundary_area(gmsh, vols, scale))
            except Exception:  # built-in kernel entities: no OCC volume: the bounding box
                shape = BodyShape.box(*extent(gmsh, scale))
            check_size(shape, spec, str(path))
            mesh_options(gmsh, spec, scale, from_points=True)
            try:
                gmsh.model.mesh.generate(3)
            except Exception as exc:
                raise MeshError(f"gmsh could not mesh '{path}' with mesh.size = {spec.size:g} m: "
                                f"{gmsh_error(gmsh, exc)}") from None
        gmsh.option.setNumber("Mesh.ElementOrder", 1)
        gmsh.option.setNumber("Mesh.Binary", 1)
        gmsh.option.setNumber("Mesh.ScalingFactor", scale)
        if count_tets(gmsh) == 0:
            raise MeshError(f"gmsh made no tetrahedra for '{path}'; expected a tetrahedral "
                            "volume mesh")
        write_gmsh(gmsh, out_path)
    return not premeshed


def mesh_geo(geometry: Geometry, spec: MeshSpec, out_path: Path) -> tuple[BodyMesh, Path]:
    """The ``geo`` source: (mesh, its file ``out_path``)."""
    sized = _mesh_geo(geometry, spec, out_path)
    return (dataclasses.replace(read_mesh(out_path), element_size=spec.size if sized else None),
            out_path)


SOURCES["geo"] = mesh_geo
