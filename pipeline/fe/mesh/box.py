"""The ``box`` source: gmsh meshes the box [0, L] x [0, H] x [0, D] (m) and names its six
faces (physical groups ``root``, ``tip``, ``bottom``, ``top``, ``back``, ``front``).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from pipeline.fe.mesh.estimate import BodyShape, check_mesh_fits
from pipeline._util.atomic import atomic_path
from pipeline.config import Geometry, MeshSpec
from pipeline.errors import MeshError, OutputError
from pipeline.fe.mesh.common import ALGORITHM_3D, BodyMesh, gmsh_error, gmsh_session
from pipeline.fe.mesh.read import read_mesh
from pipeline.fe.mesh.registry import SOURCES

log = logging.getLogger(__name__)


def box_faces(geometry: Geometry) -> dict[str, tuple[int, float]]:
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
    path = Path(path)
    with gmsh_session("body") as gmsh:
        return _generate(gmsh, geometry, spec, path)


def _generate(gmsh, geometry: Geometry, spec: MeshSpec, path: Path) -> Path:
    try:
        L, H, D = geometry.length, geometry.height, geometry.depth
        volume = gmsh.model.occ.addBox(0.0, 0.0, 0.0, L, H, D)
        gmsh.model.occ.synchronize()
        tol = 1e-9 * max(L, H, D)
        for name, (axis, coord) in box_faces(geometry).items():
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
        gmsh.option.setNumber("Mesh.Algorithm3D", ALGORITHM_3D[spec.algorithm])
        gmsh.option.setNumber("Mesh.Binary", 1)
        # the file holds the linear tetrahedra only: second-order elements are straight-
        # sided and pipeline.fe.space creates their edge midpoints (vectorised), which
        # read_mesh would drop from a gmsh setOrder mesh anyway (setOrder would take about
        # half of the mesh stage and double the file)
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
        raise MeshError(f"gmsh could not mesh geometry.kind '{geometry.kind}' with mesh.size = "
                        f"{spec.size:g} m: {gmsh_error(gmsh, exc)}") from None
    return path


def mesh_box(geometry: Geometry, spec: MeshSpec, out_path: Path) -> tuple[BodyMesh, Path]:
    """The ``box`` source: (mesh, its file ``out_path``)."""
    shape = BodyShape.box(geometry.length, geometry.height, geometry.depth)
    check_mesh_fits(shape, spec, "the box")  # before gmsh
    path = generate_mesh(geometry, spec, out_path)
    return dataclasses.replace(read_mesh(path), element_size=spec.size), path


SOURCES["box"] = mesh_box
