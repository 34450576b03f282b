"""What every mesh source shares: the :class:`BodyMesh` record, plausibility checks of
the body's dimensions and of the element count, and the gmsh session helpers.

A :class:`BodyMesh` holds straight-sided tetrahedra (the corner nodes of the gmsh
elements) plus the cells of every named region (gmsh physical groups: boundary
triangles, edges or vertices) and the file's named node sets.
Higher-order nodes are re-created by the finite-element space
(:mod:`pipeline.fe.space`) at the edge midpoints, so a quadratic field lives on
straight-edged tetrahedra: exact for the box, and a faceted approximation of a curved
surface. Lengths are in metres.

Refused with a :class:`~pipeline.errors.ConfigError` naming the key: dimensions that
betray a unit mistake (largest dimension above :data:`MAX_EXTENT_M` or below
:data:`MIN_EXTENT_M` after scaling) and a ``mesh.size`` that would make more than
:data:`MAX_TETRAHEDRA` elements.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import signal
import tempfile
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from pipeline._util.atomic import atomic_path
from pipeline._util.resources import openmp_pools_kept
from pipeline.config import Geometry, MeshSpec
from pipeline.errors import ConfigError

log = logging.getLogger(__name__)

#: bits per axis of :func:`z_order`'s keys (3 x 21 = 63 bits of a uint64)
Z_ORDER_BITS = 21


def z_order(points: np.ndarray) -> np.ndarray:
    """The permutation that sorts ``points`` (n, 3) along the Z-order (Morton) curve of
    their bounding cube: points near each other in space get numbers near each other.

    Each coordinate is quantised to :data:`Z_ORDER_BITS` bits of the largest extent and
    the bits interleaved into one uint64 key; ties keep their order (stable sort).

    >>> pts = np.array([[1.0, 1, 1], [0, 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> z_order(pts).tolist()
    [1, 2, 3, 0]
    """
    p = np.asarray(points, dtype=np.float64)
    if p.shape[0] < 2:
        return np.arange(p.shape[0])
    lo = p.min(axis=0)
    extent = float(np.ptp(p, axis=0).max()) or 1.0
    q = ((p - lo) * ((2**Z_ORDER_BITS - 1) / extent)).astype(np.uint64)
    key = np.zeros(p.shape[0], dtype=np.uint64)
    for bit in range(Z_ORDER_BITS):
        for axis in range(3):
            key |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(key, kind="stable")


@dataclass(frozen=True)
class BodyMesh:
    """A tetrahedral mesh of the body with named regions.

    vertices: (n_v, 3) float64, m.
    tetrahedra: (n_t, 4) int64 vertex indices, positively oriented.
    regions: name -> int64 vertex indices of the region's cells: (n, 3) triangles (a
        face), (n, 2) edges (a line) or (n, 1) vertices (a point or node set).
    source: the file the mesh was read from.
    other_groups: name -> what it is, for the named groups of the file that are no
        region (a volume group: "a volume group of 120 tetrahedra").
    node_sets: name -> sorted vertex indices of the file's named node sets (Abaqus
        ``*NSET``), made into regions by :func:`pipeline.fe.regions.resolve_regions`;
        node_set_edges: name -> (n, 2) sorted vertex pairs of the edges whose mid-edge
        node a set holds (files of quadratic cells only).
    element_sets: name -> sorted indices of the tetrahedra of the file's named volume
        groups / element sets (:mod:`pipeline.fe.element_sets`).
    element_size: the ``mesh.size`` (m) gmsh meshed it with; None where the elements
        are the file's own (a mesh file, a gmsh script that meshes itself), which
        ``mesh.size`` does not change.
    """

    vertices: np.ndarray
    tetrahedra: np.ndarray
    regions: Mapping[str, np.ndarray] = field(default_factory=dict)
    source: str = ""
    other_groups: Mapping[str, str] = field(default_factory=dict)
    node_sets: Mapping[str, np.ndarray] = field(default_factory=dict)
    node_set_edges: Mapping[str, np.ndarray] = field(default_factory=dict)
    element_sets: Mapping[str, np.ndarray] = field(default_factory=dict)
    element_size: float | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_tetrahedra(self) -> int:
        return int(self.tetrahedra.shape[0])


#: A mesh source: (geometry, mesh spec, path for the mesh file) -> (mesh, its file).
MeshSource = Callable[[Geometry, MeshSpec, Path], tuple[BodyMesh, Path]]

#: Largest plausible body dimension (m) after scaling; above it we suspect a unit mistake.
MAX_EXTENT_M = 50.0
#: Smallest plausible largest-dimension (m) after scaling.
MIN_EXTENT_M = 1e-4
#: Refuse a mesh.size that would make more tetrahedra than this (estimate before meshing).
MAX_TETRAHEDRA = 3_000_000

CAD_SUFFIXES = (".step", ".stp", ".iges", ".igs", ".brep")
TET_TYPES = ("tetra", "tetra10")
VOLUME_TYPES = ("tetra", "tetra10", "hexahedron", "hexahedron20", "hexahedron24",
                 "hexahedron27", "wedge", "wedge12", "wedge15", "wedge18", "pyramid",
                 "pyramid13", "pyramid14", "polyhedron")
ALGORITHM_3D = {"delaunay": 1, "frontal": 4, "hxt": 10}
#: Elements per full circle along curved CAD faces.
ELEMENTS_PER_2PI = 12


# --------------------------------------------------------------------------- checks
def format_length(x: float) -> str:
    return f"{x * 1e3:.4g} mm" if x < 0.1 else f"{x:.4g} m"


def check_dimensions(extent, geometry: Geometry, what: str) -> None:
    """Refuse a body whose largest dimension (m, after scaling) betrays a unit mistake.

    ``extent``: the bounding-box size (3,) in m; ``what``: the file, for the message.
    """
    extent = np.asarray(extent, dtype=float)
    largest = float(extent.max())
    if MIN_EXTENT_M <= largest <= MAX_EXTENT_M:
        return
    dims = " x ".join(format_length(float(e)) for e in extent)
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
        f"{geometry.scale:g}; expected a largest dimension between {format_length(MIN_EXTENT_M)} and "
        f"{MAX_EXTENT_M:g} m{hint}")


def check_size(shape, spec: MeshSpec, what: str) -> None:
    """Refuse, before gmsh meshes, a mesh.size that would make more than MAX_TETRAHEDRA
    tetrahedra or a run that would not fit in memory (:mod:`pipeline.fe.mesh.estimate`);
    ``shape``: the body's :class:`~pipeline.fe.mesh.estimate.BodyShape`."""
    from pipeline.fe.mesh.estimate import check_mesh_fits, estimate_mesh, smallest_size

    estimate = estimate_mesh(shape, spec.size, spec.order).n_tetrahedra
    if estimate > MAX_TETRAHEDRA:
        smallest = smallest_size(shape, spec.order, MAX_TETRAHEDRA, "n_tetrahedra",
                                 start=spec.size)
        raise ConfigError(
            f"config key 'mesh.size': got {spec.size:g} m, which would make about "
            f"{estimate:.2g} tetrahedra for the body in '{what}' (volume "
            f"{shape.volume_m3:.4g} m^3); expected at least {smallest:.3g} m (at most "
            f"{MAX_TETRAHEDRA:.0e} tetrahedra)")
    check_mesh_fits(shape, spec, f"the body in '{what}'")


# --------------------------------------------------------------------------- gmsh session
@contextlib.contextmanager
def quiet_fd1():
    """Capture what C++ libraries (OpenCASCADE) print on file descriptor 1; log it."""
    try:
        fd = os.dup(1)
    except OSError:  # no usable stdout: nothing to silence
        yield
        return
    with tempfile.TemporaryFile(mode="w+b") as sink:
        try:
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


#: signals whose handling gmsh resets to the default when it starts and stops (SIGTERM
#: and SIGHUP would then kill a run with no cleanup, SIGPIPE would kill it silently)
KEPT_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP", "SIGPIPE")
                     if hasattr(signal, n))


@contextlib.contextmanager
def signals_kept():
    """Give back, after gmsh started and when it stops, the signal handling the process had
    before (the CLI's SIGTERM handler, Python's ignored SIGPIPE). Yields the function that
    re-installs it. Outside the main thread (handlers cannot be set there) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    saved = {sig: signal.getsignal(sig) for sig in KEPT_SIGNALS}

    def restore() -> None:
        for sig, handler in saved.items():
            if handler is not None:
                signal.signal(sig, handler)

    try:
        yield restore
    finally:
        restore()


def gmsh_threads() -> int:
    """gmsh's thread count: 1 unless ``PIPELINE_GMSH_THREADS`` says otherwise.

    On one thread gmsh is deterministic: the same config gives the same mesh, bit for bit
    (so a kept mesh's SHA-256 and cached results stay valid). On two threads its parallel
    surface and volume meshing of CAD geometry is not: the bracket STEP gives a different
    tetrahedron count from run to run. The price is small beside the solve: one thread
    meshes a 2M-DOF body about 1.5 times slower than two."""
    return max(1, int(os.environ.get("PIPELINE_GMSH_THREADS", "1")))


#: every gmsh option the package sets, by kind; a session inside the host's own gmsh puts
#: them back afterwards (tests/test_geometry.py checks that no other option is set)
GMSH_OPTIONS = {
    "General.Terminal": "number", "General.Verbosity": "number",
    "General.NumThreads": "number", "Mesh.Algorithm3D": "number", "Mesh.Binary": "number",
    "Mesh.ElementOrder": "number", "Mesh.MeshSizeExtendFromBoundary": "number",
    "Mesh.MeshSizeFromCurvature": "number", "Mesh.MeshSizeFromPoints": "number",
    "Mesh.MeshSizeMax": "number", "Mesh.MeshSizeMin": "number",
    "Mesh.ScalingFactor": "number", "Geometry.OCCTargetUnit": "string",
}


@contextlib.contextmanager
def gmsh_session(name: str):
    """gmsh, ready for one model named ``name``, quiet, on :func:`gmsh_threads` threads.

    When this process has not initialised gmsh, the session initialises and finalises it.
    When the host program already has (its own models and options), the session is a
    guest: it adds a model of its own, and on exit removes it, makes the host's model
    current again and puts back every option of :data:`GMSH_OPTIONS`; the host's logger is
    left alone (error messages then come from gmsh's exception alone). Options the host
    set that this package does not set (a random seed, an optimiser) still apply to the
    guest's mesh. Either way, OpenMP pools that gmsh resizes are put back
    (:func:`pipeline._util.resources.openmp_pools_kept`)."""
    import gmsh

    with openmp_pools_kept(), signals_kept() as restore:
        owned = not gmsh.isInitialized()
        if owned:
            gmsh.initialize(interruptible=False)
            restore()
        with _gmsh_session(gmsh, name, owned):
            yield gmsh


def _get_option(gmsh, option: str):
    kind = GMSH_OPTIONS[option]
    return gmsh.option.getString(option) if kind == "string" else gmsh.option.getNumber(option)


def _set_option(gmsh, option: str, value) -> None:
    if GMSH_OPTIONS[option] == "string":
        gmsh.option.setString(option, value)
    else:
        gmsh.option.setNumber(option, value)


@contextlib.contextmanager
def _gmsh_session(gmsh, name: str, owned: bool):
    saved = {} if owned else {option: _get_option(gmsh, option) for option in GMSH_OPTIONS}
    host_model = None if owned else gmsh.model.getCurrent()
    model = name if owned else f"{name}-pipeline-{os.getpid()}-{threading.get_ident()}"
    quiet = quiet_fd1()
    quiet.__enter__()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 2)
        gmsh.option.setNumber("General.NumThreads", gmsh_threads())
        if owned:
            gmsh.logger.start()
        gmsh.model.add(model)
        yield gmsh
    finally:
        if owned and gmsh.isInitialized():
            for line in gmsh.logger.get():
                log.debug("gmsh: %s", line)
            gmsh.logger.stop()
            gmsh.finalize()
        elif not owned:
            with contextlib.suppress(Exception):  # the guest's model, if it was made
                if model in gmsh.model.list():
                    gmsh.model.setCurrent(model)
                    gmsh.model.remove()
            with contextlib.suppress(Exception):
                gmsh.model.setCurrent(host_model)
            for option, value in saved.items():
                _set_option(gmsh, option, value)
        quiet.__exit__(None, None, None)


def gmsh_error(gmsh, exc: Exception) -> str:
    errors = [m for m in gmsh.logger.get() if "rror" in m]
    return errors[-1] if errors else str(exc)


def mesh_options(gmsh, spec: MeshSpec, unit: float, from_points: bool) -> None:
    """Element size ``spec.size`` (m) in model units (``unit`` m per model unit)."""
    size = spec.size / unit
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.option.setNumber("Mesh.MeshSizeMin", size / 10.0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 1 if from_points else 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", ELEMENTS_PER_2PI)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
    gmsh.option.setNumber("Mesh.Algorithm3D", ALGORITHM_3D[spec.algorithm])
    gmsh.option.setNumber("Mesh.ElementOrder", 1)
    gmsh.option.setNumber("Mesh.Binary", 1)


def count_tets(gmsh) -> int:
    types, tags, _ = gmsh.model.mesh.getElements(3)
    return int(sum(len(t) for typ, t in zip(types, tags) if typ in (4, 11)))


def write_gmsh(gmsh, out_path: Path) -> Path:
    """Write gmsh's mesh to ``out_path`` atomically (temporary name, then rename)."""
    with atomic_path(out_path) as tmp:
        gmsh.write(str(tmp))
    return out_path


def mesh_volume(body: BodyMesh) -> float:
    v = body.vertices
    t = body.tetrahedra
    a = v[t[:, 0]]
    return float(np.abs(np.einsum("ij,ij->i", np.cross(v[t[:, 1]] - a, v[t[:, 2]] - a),
                                  v[t[:, 3]] - a)).sum() / 6.0)


def boundary_area(gmsh, volumes: list[int], unit: float = 1.0) -> float:
    """Area (m^2) of the surfaces bounding the OCC ``volumes``, in model units times
    ``unit``; a face two volumes share counts once (gmsh meshes it once)."""
    faces = {abs(tag) for _, tag in gmsh.model.getBoundary([(3, v) for v in volumes],
                                                           combined=False, oriented=False)}
    return float(sum(gmsh.model.occ.getMass(2, f) for f in faces)) * unit ** 2


def extent(gmsh, unit: float = 1.0) -> np.ndarray:
    """Bounding-box size of the model's volumes, times ``unit``."""
    boxes = np.array([gmsh.model.getBoundingBox(3, tag) for _, tag in gmsh.model.getEntities(3)])
    return (boxes[:, 3:].max(axis=0) - boxes[:, :3].min(axis=0)) * unit
