"""The registry of mesh sources: ``geometry.kind`` -> the function that meshes it.

Each source module (:mod:`~pipeline.fe.mesh.box`, :mod:`~pipeline.fe.mesh.cad`,
:mod:`~pipeline.fe.mesh.geo`, :mod:`~pipeline.fe.mesh.read`) ends with the line that
registers its source here; importing :mod:`pipeline.fe.mesh` imports them all. A source
is called as ``source(geometry, spec, out_path) -> (BodyMesh, path of the mesh file)``.
"""

from __future__ import annotations

from pipeline.fe.mesh.common import MeshSource

SOURCES: dict[str, MeshSource] = {}
