"""Geometry sources other than the box: CAD files, gmsh scripts and existing meshes.

:func:`mesh_geometry` is the mesh stage for ``geometry.kind``:

``step``
    A STEP (``.step``/``.stp``), IGES (``.iges``/``.igs``) or BREP file, read by gmsh's
    OpenCASCADE kernel. STEP and IGES files declare their length unit; they are read
    **in metres** whatever unit they were drawn in (OpenCASCADE converts to mm, we to
    m), so ``scale`` stays 1 for them unless the file's unit declaration is wrong.
    (BREP has no unit: its numbers are taken as metres, times ``scale``.) Several solids are fused
    into one conforming mesh (boolean fragments). The mesh has one physical group,
    the volume ``body``; named surfaces come from the config's ``regions`` selectors.
``geo``
    A gmsh script (``.geo``). Its physical groups name the regions. The script's
    numbers are multiplied by ``scale`` (gmsh's ``Mesh.ScalingFactor``: draw in mm,
    set ``scale: 0.001``); ``mesh.size`` (m) caps the element size. A script that
    meshes itself (``Mesh 3;``) keeps its own mesh.
``mesh``
    An existing tetrahedral mesh any format meshio reads (``.msh``, ``.inp``,
    ``.vtu``, ``.med``, ...), read as it is by :func:`pipeline.fe.mesh.read_mesh` and
    multiplied by ``scale``; its triangle cell sets (gmsh physical groups) name
    regions. ``mesh.size`` does not apply.

Like the box, the finite-element space uses straight-sided tetrahedra (quadratic
fields on the corner nodes of the gmsh elements, see :mod:`pipeline.fe.mesh`), so gmsh
writes linear tetrahedra here; curved CAD faces are resolved by refining the mesh
along them (``Mesh.MeshSizeFromCurvature``), not by curved elements.

Refused, each with a :class:`~pipeline.errors.MeshError` or
:class:`~pipeline.errors.ConfigError` naming the file or key, the value and what was
expected: a file gmsh or meshio cannot read, a CAD file with no solid, a mesh with
element types we cannot assemble (hexahedra, wedges, ... or no volume cells at all),
dimensions that betray a unit mistake (largest dimension above :data:`MAX_EXTENT_M`
or below :data:`MIN_EXTENT_M` after scaling) and a ``mesh.size`` that would make more
than :data:`MAX_TETRAHEDRA` elements.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tempfile
from pathlib import Path

import numpy as np

from pipeline._util.atomic import atomic_path
from pipeline.config import Geometry, MeshSpec
from pipeline.errors import ConfigError, MeshError
from pipeline.fe.mesh import BodyMesh, read_mesh

log = logging.getLogger(__name__)

__all__ = ["mesh_geometry", "check_dimensions", "cad_volume", "MAX_EXTENT_M", "MIN_EXTENT_M",
           "MAX_TETRAHEDRA", "CAD_SUFFIXES", "TET_TYPES"]

#: Largest plausible body dimension (m) after scaling; above it we suspect a unit mistake.
MAX_EXTENT_M = 50.0
#: Smallest plausible largest-dimension (m) after scaling.
MIN_EXTENT_M = 1e-4
#: Refuse a mesh.size that would make more tetrahedra than this (estimate before meshing).
MAX_TETRAHEDRA = 3_000_000
#: gmsh makes about this many tetrahedra per size^3 of volume.
_TETS_PER_CUBE = 6.5

CAD_SUFFIXES = (".step", ".stp", ".iges", ".igs", ".brep")
TET_TYPES = ("tetra", "tetra10")
_VOLUME_TYPES = ("tetra", "tetra10", "hexahedron", "hexahedron20", "hexahedron24",
                 "hexahedron27", "wedge", "wedge12", "wedge15", "wedge18", "pyramid",
                 "pyramid13", "pyramid14", "polyhedron")
_ALGORITHM_3D = {"delaunay": 1, "frontal": 4, "hxt": 10}
#: Elements per full circle along curved CAD faces.
_ELEMENTS_PER_2PI = 12


# --------------------------------------------------------------------------- checks
def _fmt_len(x: float) -> str:
    return f"{x * 1e3:.4g} mm" if x < 0.1 else f"{x:.4g} m"


def check_dimensions(extent, geometry: Geometry, what: str) -> None:
    """Refuse a body whose largest dimension (m, after scaling) betrays a unit mistake.

    ``extent``: the bounding-box size (3,) in m; ``what``: the file, for the message.
    """
    extent = np.asarray(extent, dtype=float)
    largest = float(extent.max())
    if MIN_EXTENT_M <= largest <= MAX_EXTENT_M:
        return
    dims = " x ".join(_fmt_len(float(e)) for e in extent)
    hint = ""
    factors = (1e-3, 1e-6) if largest > MAX_EXTENT_M else (1e3, 1e6)
    for f in factors:
        if MIN_EXTENT_M <= largest * f <= MAX_EXTENT_M:
            unit = {1e-3: "drawn in mm", 1e-6: "drawn in micrometres",
                    1e3: "a length in km, or scale applied twice", 1e6: "scale applied twice"}[f]
            hint = f"; did you mean scale: {geometry.scale * f:g} ({unit})?"
            break
    if geometry.kind == "step" and geometry.scale != 1.0:
        hint += (" Note: STEP and IGES files declare their unit and are read in metres, so "
                 "scale: 1 is right for them unless that declaration is wrong")
    raise ConfigError(
        f"config key 'geometry.scale': the body in '{what}' measures {dims} with scale = "
        f"{geometry.scale:g}; expected a largest dimension between {_fmt_len(MIN_EXTENT_M)} and "
        f"{MAX_EXTENT_M:g} m{hint}")


def _check_size(volume_m3: float, spec: MeshSpec, what: str) -> None:
    estimate = _TETS_PER_CUBE * volume_m3 / spec.size ** 3
    if estimate > MAX_TETRAHEDRA:
        smallest = (_TETS_PER_CUBE * volume_m3 / MAX_TETRAHEDRA) ** (1.0 / 3.0)
        raise ConfigError(
            f"config key 'mesh.size': got {spec.size:g} m, which would make about "
            f"{estimate:.2g} tetrahedra for the body in '{what}' (volume {volume_m3:.4g} m^3); "
            f"expected at least {smallest:.3g} m (at most {MAX_TETRAHEDRA:.0e} tetrahedra)")


# --------------------------------------------------------------------------- gmsh session
@contextlib.contextmanager
def _quiet_fd1():
    """Capture what C++ libraries (OpenCASCADE) print on file descriptor 1; log it."""
    try:
        fd = os.dup(1)
    except OSError:  # no usable stdout: nothing to silence
        yield
        return
    with tempfile.TemporaryFile(mode="w+b") as sink:
        try:
            import sys

            sys.stdout.flush()
        except Exception:  # pragma: no cover - a closed stdout
            pass
        os.dup2(sink.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(fd, 1)
            os.close(fd)
            sink.seek(0)
            text = sink.read().decode("utf-8", "replace").strip()
            if text:
                log.debug("OpenCASCADE: %s", text)


@contextlib.contextmanager
def _gmsh_session(name: str):
    import gmsh

    if gmsh.isInitialized():
        gmsh.finalize()
    gmsh.initialize(interruptible=False)
    quiet = _quiet_fd1()
    quiet.__enter__()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 2)
        gmsh.option.setNumber("General.NumThreads", os.cpu_count() or 1)
        gmsh.logger.start()
        gmsh.model.add(name)
        yield gmsh
    finally:
        if gmsh.isInitialized():
            for line in gmsh.logger.get():
                log.debug("gmsh: %s", line)
            gmsh.logger.stop()
            gmsh.finalize()
        quiet.__exit__(None, None, None)


def _gmsh_error(gmsh, exc: Exception) -> str:
    errors = [m for m in gmsh.logger.get() if "rror" in m]
    return errors[-1] if errors else str(exc)


def _mesh_options(gmsh, spec: MeshSpec, unit: float, from_points: bool) -> None:
    """Element size ``spec.size`` (m) in model units (``unit`` m per model unit)."""
    size = spec.size / unit
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.option.setNumber("Mesh.MeshSizeMin", size / 10.0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 1 if from_points else 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", _ELEMENTS_PER_2PI)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
    gmsh.option.setNumber("Mesh.Algorithm3D", _ALGORITHM_3D[spec.algorithm])
    gmsh.option.setNumber("Mesh.ElementOrder", 1)
    gmsh.option.setNumber("Mesh.Binary", 1)


def _count_tets(gmsh) -> int:
    types, tags, _ = gmsh.model.mesh.getElements(3)
    return int(sum(len(t) for typ, t in zip(types, tags) if typ in (4, 11)))


def _write(gmsh, out_path: Path) -> Path:
    with atomic_path(out_path) as tmp:
        gmsh.write(str(tmp))
    return out_path


def _mesh_volume(body: BodyMesh) -> float:
    v = body.vertices
    t = body.tetrahedra
    a = v[t[:, 0]]
    return float(np.abs(np.einsum("ij,ij->i", np.cross(v[t[:, 1]] - a, v[t[:, 2]] - a),
                                  v[t[:, 3]] - a)).sum() / 6.0)


# --------------------------------------------------------------------------- sources
def cad_volume(path: str | Path, scale: float = 1.0) -> float:
    """Volume (m^3) of the solids in a STEP/IGES/BREP file as OpenCASCADE computes it."""
    path = Path(path)
    with _gmsh_session("cad_volume") as gmsh:
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
        with _quiet_fd1():
            entities = gmsh.model.occ.importShapes(str(path), highestDimOnly=False)
            gmsh.model.occ.synchronize()
    except Exception as exc:  # gmsh raises plain Exception with its own message
        raise MeshError(f"geometry.path '{path}': gmsh (OpenCASCADE) cannot read it "
                        f"({_gmsh_error(gmsh, exc)}); expected a valid STEP, IGES or BREP file "
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


def _extent(gmsh, unit: float = 1.0) -> np.ndarray:
    """Bounding-box size of the model's volumes, times ``unit``."""
    boxes = np.array([gmsh.model.getBoundingBox(3, tag) for _, tag in gmsh.model.getEntities(3)])
    return (boxes[:, 3:].max(axis=0) - boxes[:, :3].min(axis=0)) * unit


def _mesh_step(geometry: Geometry, spec: MeshSpec, out_path: Path) -> BodyMesh:
    path = Path(geometry.path)
    with _gmsh_session("body") as gmsh:
        vols, volume = _import_cad(gmsh, path, geometry)
        check_dimensions(_extent(gmsh), geometry, str(path))
        _check_size(volume, spec, str(path))
        gmsh.model.addPhysicalGroup(3, vols, name="body")
        _mesh_options(gmsh, spec, 1.0, from_points=False)
        try:
            gmsh.model.mesh.generate(3)
        except Exception as exc:
            raise MeshError(f"gmsh could not mesh '{path}' with mesh.size = {spec.size:g} m: "
                            f"{_gmsh_error(gmsh, exc)}") from None
        n = _count_tets(gmsh)
        if n == 0:
            raise MeshError(f"gmsh made no tetrahedra for '{path}' with mesh.size = "
                            f"{spec.size:g} m")
        log.info("'%s': %d solid(s), CAD volume %.6g m^3, %d tetrahedra", path.name, len(vols),
                 volume, n)
        _write(gmsh, out_path)
    body = read_mesh(out_path)
    _compare_volume(body, volume, path)
    return body


def _compare_volume(body: BodyMesh, cad: float, path: Path) -> None:
    mesh = _mesh_volume(body)
    rel = (mesh - cad) / cad
    level = logging.WARNING if abs(rel) > 0.01 else logging.INFO
    log.log(level, "'%s': mesh volume %.6g m^3 is %+.3f%% of the CAD volume%s", path.name, mesh,
            100 * rel, " (refine mesh.size to follow the curved faces)" if abs(rel) > 0.01 else "")


def _mesh_geo(geometry: Geometry, spec: MeshSpec, out_path: Path) -> Path:
    path = Path(geometry.path)
    if path.suffix.lower() != ".geo":
        raise ConfigError(f"config key 'geometry.path': got '{path}' for kind 'geo'; expected a "
                          "gmsh script ending in .geo")
    with _gmsh_session("body") as gmsh:
        try:
            with _quiet_fd1():
                gmsh.open(str(path))
        except Exception as exc:
            raise MeshError(f"geometry.path '{path}': gmsh cannot run this script "
                            f"({_gmsh_error(gmsh, exc)}); expected a valid .geo file") from None
        vols = [tag for _, tag in gmsh.model.getEntities(3)]
        if not vols:
            raise MeshError(f"geometry.path '{path}': the script defines no volume; expected at "
                            "least one (Volume, Box, Extrude ...)")
        scale = geometry.scale
        check_dimensions(_extent(gmsh, scale), geometry, str(path))
        if not any(d == 3 for d, _ in gmsh.model.getPhysicalGroups()):
            # gmsh saves only elements of physical groups when there are any
            gmsh.model.addPhysicalGroup(3, vols, name="body")
        premeshed = _count_tets(gmsh) > 0
        if premeshed:
            log.info("'%s' meshes itself; its own element sizes are kept (mesh.size ignored)",
                     path.name)
        else:
            try:
                volume = float(sum(gmsh.model.occ.getMass(3, v) for v in vols)) * scale ** 3
            except Exception:  # built-in kernel entities: no OCC volume to estimate with
                volume = float(np.prod(_extent(gmsh, scale)))
            _check_size(volume, spec, str(path))
            _mesh_options(gmsh, spec, scale, from_points=True)
            try:
                gmsh.model.mesh.generate(3)
            except Exception as exc:
                raise MeshError(f"gmsh could not mesh '{path}' with mesh.size = {spec.size:g} m: "
                                f"{_gmsh_error(gmsh, exc)}") from None
        gmsh.option.setNumber("Mesh.ElementOrder", 1)
        gmsh.option.setNumber("Mesh.Binary", 1)
        gmsh.option.setNumber("Mesh.ScalingFactor", scale)
        if _count_tets(gmsh) == 0:
            raise MeshError(f"gmsh made no tetrahedra for '{path}'; expected a tetrahedral "
                            "volume mesh")
        _write(gmsh, out_path)
    return out_path


def _read_foreign(geometry: Geometry) -> BodyMesh:
    import meshio

    path = Path(geometry.path)
    try:
        mesh = meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types, and sys.exit(1)
        if isinstance(exc, SystemExit):
            exc = RuntimeError(f"no reader of '{path.suffix}' files could parse it")
        raise MeshError(f"geometry.path '{path}': meshio cannot read it ({type(exc).__name__}: "
                        f"{exc}); expected a mesh file meshio reads (.msh, .inp, .vtu, .med, "
                        "...)") from None
    counts: dict[str, int] = {}
    for block in mesh.cells:
        counts[block.type] = counts.get(block.type, 0) + len(block.data)
    other = {k: n for k, n in counts.items() if k in _VOLUME_TYPES and k not in TET_TYPES}
    if other:
        listing = ", ".join(f"{k} ({n} cells)" for k, n in sorted(other.items()))
        raise MeshError(f"geometry.path '{path}': has element types we cannot assemble: "
                        f"{listing}; expected tetrahedra only (tetra or tetra10): re-mesh the "
                        "body with tetrahedra")
    if not any(k in TET_TYPES for k in counts):
        listing = ", ".join(sorted(counts)) or "none"
        raise MeshError(f"geometry.path '{path}': has no volume cells (cell types: {listing}); "
                        "expected a tetrahedral volume mesh (tetra or tetra10)")
    body = read_mesh(path)
    if geometry.scale != 1.0:
        body = BodyMesh(vertices=body.vertices * geometry.scale, tetrahedra=body.tetrahedra,
                        regions=body.regions, source=body.source)
    extent = body.vertices.max(axis=0) - body.vertices.min(axis=0)
    check_dimensions(extent, geometry, str(path))
    return body


def mesh_geometry(geometry: Geometry, spec: MeshSpec, out_path: str | Path
                  ) -> tuple[BodyMesh, Path]:
    """The mesh stage for ``geometry.kind`` step | geo | mesh: (mesh, its file).

    step and geo write the gmsh mesh (in metres) to ``out_path``; mesh returns the
    file it read (``out_path`` is not written) with vertices multiplied by ``scale``.
    """
    out_path = Path(out_path)
    path = Path(geometry.path)
    if not path.is_file():
        raise ConfigError(f"config key 'geometry.path': got '{path}', expected an existing file")
    if not (math.isfinite(geometry.scale) and geometry.scale > 0):
        raise ConfigError(f"config key 'geometry.scale': got {geometry.scale!r}, expected a "
                          "positive number")
    if geometry.kind == "step":
        return _mesh_step(geometry, spec, out_path), out_path
    if geometry.kind == "geo":
        return read_mesh(_mesh_geo(geometry, spec, out_path)), out_path
    if geometry.kind == "mesh":
        return _read_foreign(geometry), path
    raise ConfigError(f"config key 'geometry.kind': got {geometry.kind!r}, expected step, geo "
                      "or mesh here (the box is meshed by pipeline.fe.mesh)")
