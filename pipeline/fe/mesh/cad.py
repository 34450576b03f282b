"""The ``step`` source: a STEP (``.step``/``.stp``), IGES (``.iges``/``.igs``) or BREP
file, read by gmsh's OpenCASCADE kernel.

STEP and IGES files declare their length unit; they are read **in metres** whatever
unit they were drawn in (OpenCASCADE converts to mm, we to m), so ``scale`` stays 1 for
them unless the file's unit declaration is wrong. (BREP has no unit: its numbers are
taken as metres, times ``scale``.) Several solids are fused into one conforming mesh
(boolean fragments). The mesh has one physical group, the volume ``body``; named
surfaces come from the config's ``regions`` selectors. gmsh writes linear tetrahedra;
curved CAD faces are resolved by refining the mesh along them
(``Mesh.MeshSizeFromCurvature``), not by curved elements. The mesh volume is compared
with the CAD volume (a warning beyond 1%).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from pipeline.config import Geometry, MeshSpec
from pipeline.errors import ConfigError, MeshError
from pipeline.fe.mesh.common import (CAD_SUFFIXES, BodyMesh, boundary_area, check_dimensions,
                                     check_size, count_tets, extent, gmsh_error, gmsh_session, mesh_options,
                                     mesh_volume, quiet_fd1, write_gmsh)
from pipeline.fe.mesh.estimate import BodyShape
from pipeline.fe.mesh.read import read_mesh
from pipeline.fe.mesh.registry import SOURCES

log = logging.getLogger(__name__)


def cad_volume(path: str | Path, scale: float = 1.0) -> float:
    """Volume (m^3) of the solids in a STEP/IGES/BREP file as OpenCASCADE computes it."""
    path = Path(path)
    with gmsh_session("cad_volume") as gmsh:
        return _import_cad(gmsh, path, Geometry(kind="step", path=str(path), scale=scale))[1]


def _import_cad(gmsh, path: Path, geometry: Geometry) -> tuple[list[int], float]:
    """Import the solids of a CAD file into the OCC model, in metres: (tags, volume m^3)."""
    if path.suffix.lower() not in CAD_SUFFIXES:
        raise ConfigError(f"config key 'geometry.path': got '{path}' for kind 'step'; expected "
                          f"a CAD file ending in {', '.join(CAD_SUFFIXES)}")
    # OpenCASCADE converts STEP/IGES coordinates to its unit from the file's declaration.
    # That unit is process-wide state of OpenCASCADE (it outlives gmsh.finalize), so set
    # it to OpenCASCADE's own default, millimetres, and convert to metres ourselves.
    gmsh.option.setString("Geometry.OCCTargetUnit", "MM")
    to_metres = 1.0 if path.suffix.lower() == ".brep" else 1e-3
    try:
        with quiet_fd1():
            entities = gmsh.model.occ.importShapes(str(path), highestDimOnly=False)
            gmsh.model.occ.synchronize()
    except Exception as exc:  # gmsh raises plain Exception with its own message
        raise MeshError(f"geometry.path '{path}': gmsh (OpenCASCADE) cannot read it "
                        f"({gmsh_error(gmsh, exc)}); expected a valid STEP, IGES or BREP file "
                        "with at least one solid") from None
    vols = [tag for dim, tag in gmsh.model.getEntities(3)]
    if not vols:
        counts = {d: len(gmsh.model.getEntities(d)) for d in (2, 1, 0)}
        raise MeshError(f"geometry.path '{path}': has no solid (found {counts[2]} surfaces, "
                        f"{counts[1]} curves, {counts[0]} points); expected at least one closed "
                        "volume: export solids, not surfaces, from the CAD tool")
    if len(vols) > 1:  # several solids: one conforming mesh, shared faces merged
        gmsh.model.occ.fragment([(3, v) for v in vols[:1]], [(3, v) for v in vols[1:]])
        gmsh.model.occ.synchronize()
        vols = [tag for dim, tag in gmsh.model.getEntities(3)]
    s = to_metres * geometry.scale
    # the volume before scaling: OpenCASCADE integrates a scaled shape less exactly
    volume = float(sum(gmsh.model.occ.getMass(3, v) for v in vols)) * s ** 3
    if s != 1.0:
        gmsh.model.occ.dilate([(3, v) for v in vols], 0.0, 0.0, 0.0, s, s, s)
        gmsh.model.occ.synchronize()
    del entities
    return vols, volume


def _mesh_step(geometry: Geometry, spec: MeshSpec, out_path: Path) -> BodyMesh:
    path = Path(geometry.path)
    with gmsh_session("body") as gmsh:
        vols, volume = _import_cad(gmsh, path, geometry)
        check_dimensions(extent(gmsh), geometry, str(path))
        check_size(BodyShape(volume, boundary_area(gmsh, vols)), spec, str(path))
        gmsh.model.addPhysicalGroup(3, vols, name="body")
        mesh_options(gmsh, spec, 1.0, from_points=False)
        try:
            gmsh.model.mesh.generate(3)
        except Exception as exc:
            raise MeshError(f"gmsh could not mesh '{path}' with mesh.size = {spec.size:g} m: "
                            f"{gmsh_error(gmsh, exc)}") from None
        n = count_tets(gmsh)
        if n == 0:
            raise MeshError(f"gmsh made no tetrahedra for '{path}' with mesh.size = "
                            f"{spec.size:g} m")
        log.info("'%s': %d solid(s), CAD volume %.6g m^3, %d tetrahedra", path.name, len(vols),
                 volume, n)
        write_gmsh(gmsh, out_path)
    body = dataclasses.replace(read_mesh(out_path), element_size=spec.size)
    _compare_volume(body, volume, path)
    return body


def _compare_volume(body: BodyMesh, cad: float, path: Path) -> None:
    mesh = mesh_volume(body)
    rel = (mesh - cad) / cad
    level = logging.WARNING if abs(rel) > 0.01 else logging.INFO
    log.log(level, "'%s': mesh volume %.6g m^3 is %+.3f%% of the CAD volume%s", path.name, mesh,
            100 * rel, " (refine mesh.size to follow the curved faces)" if abs(rel) > 0.01 else "")


def mesh_step(geometry: Geometry, spec: MeshSpec, out_path: Path) -> tuple[BodyMesh, Path]:
    """The ``step`` source: (mesh, its file ``out_path``)."""
    return _mesh_step(geometry, spec, out_path), out_path


SOURCES["step"] = mesh_step
