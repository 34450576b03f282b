"""The configuration records: frozen dataclasses, one per config section, and the
choices of every ``kind``-like key as ``Literal`` types (with their tuples of values).

The records do not validate themselves: :mod:`pipeline.config.parse` builds them from
checked values, and everything downstream trusts them. Units are SI throughout
(m, kg, s, N, Pa).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, Mapping, get_args

if TYPE_CHECKING:
    from pipeline.config.rotation import Rotation

from pipeline.config.frames import CoordinateSystem
from pipeline.config.materials import AddedMass, MaterialEntry
from pipeline.config.supports import BushingSpec, SpringSpec, SupportFrame

GeometryKind = Literal["box", "step", "geo", "mesh"]
MeshAlgorithm = Literal["delaunay", "hxt", "frontal"]
Component = Literal["x", "y", "z"]
Solver = Literal["auto", "pardiso", "cholmod", "superlu", "cudss", "slepc"]
SelectorKind = Literal["plane", "box", "sphere"]
InputKind = Literal["force", "moment"]
OutputKind = Literal["displacement", "rotation", "strain", "stress"]
PortKind = Literal["force", "moment", "displacement", "rotation", "strain", "stress"]
#: output kinds read inside the body (gauges) rather than as the motion of a surface region
GAUGE_KINDS: tuple[str, ...] = ("strain", "stress")
#: what a gauge with an area averages: the strain on the surface it covers, or the
#: element averages of the elements around it (docs/stress.md)
GaugeAverage = Literal["surface", "volume"]
DampingKind = Literal["uniform", "per_mode", "rayleigh"]
StaticCorrection = Literal["none", "residual", "augment"]
FilterKind = Literal["none", "first_order", "third_order"]
LumpedConstants = Literal["simple", "refined"]
Coupling = Literal["rigid", "distributing"]
BoxFace = Literal["root", "tip", "bottom", "top", "back", "front"]

GEOMETRY_KINDS: tuple[str, ...] = get_args(GeometryKind)
SOLVERS: tuple[str, ...] = get_args(Solver)
Precision = Literal["auto", "double", "mixed"]
PRECISIONS: tuple[str, ...] = get_args(Precision)
EigenMethod = Literal["auto", "factor", "multigrid"]
EIGEN_METHODS: tuple[str, ...] = get_args(EigenMethod)
BOX_FACES: tuple[str, ...] = get_args(BoxFace)
#: unit systems a mesh file may be in (``geometry.units``): length-mass-time -> metres per
#: length unit. Only the coordinates are converted: the config's material stays SI.
UNIT_SYSTEMS: dict[str, float] = {"m-kg-s": 1.0, "mm-t-s": 1e-3, "mm-kg-ms": 1e-3,
                                  "mm-g-ms": 1e-3, "cm-g-s": 1e-2, "in-lbf-s": 0.0254,
                                  "ft-lbf-s": 0.3048}


@dataclass(frozen=True)
class Geometry:
    """The body.

    ``box``: x in [0, length], y in [0, height], z in [0, depth] (m).
    ``step`` (STEP/IGES file), ``geo`` (gmsh script), ``mesh`` (a mesh file meshio reads):
    ``path`` to the file (relative paths are relative to the config file), ``scale``
    multiplies its coordinates into metres (0.001 for CAD drawn in mm); ``units`` (kind
    ``mesh`` only): the file's unit system, a key of :data:`UNIT_SYSTEMS`, which sets
    ``scale`` to its length unit (the material stays SI).
    """

    kind: GeometryKind = "box"
    length: float = 0.5
    height: float = 0.02
    depth: float = 0.05
    path: str = ""
    scale: float = 1.0
    units: str = ""  # kind mesh: the file's unit system (UNIT_SYSTEMS); scale is its length unit in m

    def largest_dimension(self) -> float | None:
        """Largest box dimension (m), or None where only the file knows it."""
        if self.kind != "box":
            return None
        return max(self.length, self.height, self.depth)


@dataclass(frozen=True)
class MeshSpec:
    """gmsh settings: element ``order`` 1 or 2, target element ``size`` in m; ``parts``:
    a partitioned mesh file of ``python -m pipeline partition`` that the ranks of a
    ``modes.solver: slepc`` run read instead of meshing ("" for none)."""

    order: Literal[1, 2] = 2
    size: float = 0.005
    algorithm: MeshAlgorithm = "hxt"  # gmsh 3D algorithm: delaunay | hxt | frontal
    parts: str = ""


@dataclass(frozen=True)
class Material:
    """Isotropic linear elastic material: E in Pa, nu dimensionless, rho in kg/m^3."""

    E: float = 69.0e9
    nu: float = 0.33
    rho: float = 2700.0


@dataclass(frozen=True)
class Support:
    """Fix the displacement components ``fix`` (subset of x, y, z) on a region; or the
    components ``local_fix`` of a local ``frame``; or ground the region through a
    ``spring`` or a ``bushing`` (:mod:`pipeline.config.supports`)."""

    region: str
    fix: tuple[Component, ...] = ("x", "y", "z")
    frame: SupportFrame | None = None
    local_fix: tuple[str, ...] = ()
    spring: SpringSpec | None = None
    bushing: BushingSpec | None = None


@dataclass(frozen=True)
class Constraints:
    """``in_plane``: u_z = 0 at every node (the body bends only in the x-y plane)."""

    in_plane: bool = False


@dataclass(frozen=True)
class ModesConfig:
    """Eigen-solution: the lowest ``count`` modes, sparse factorisation ``solver``."""

    count: int = 10
    solver: Solver = "auto"
    tolerance: float = 0.0  # relative residual of the shift-inverted problem; 0: 1e-10 for block Lanczos (1e-8 from 100k free DOFs), machine precision for ARPACK; method multigrid (one process or ranks): LOBPCG's preconditioned residual, 0: 1e-6
    precision: Precision = "auto"  # factor precision: double; mixed (float32 factor, double refinement); auto: mixed only when a double factor does not fit
    method: EigenMethod = "auto"  # factor: shift-invert with a sparse factor of K; multigrid: factor-free LOBPCG with a two-grid preconditioner (mesh.order 2); auto: multigrid from 500k free DOFs (a factor instead when it converges slowly) or when no factor fits in memory


@dataclass(frozen=True)
class RegionSelector:
    """A geometric region: boundary facets whose vertices all satisfy the selector.

    kind ``plane``: |(x - point) . normal| <= tolerance;
    kind ``box``: lower <= x <= upper component-wise;
    kind ``sphere``: |x - point| <= radius.
    """

    kind: SelectorKind
    point: tuple[float, float, float] | None = None
    normal: tuple[float, float, float] | None = None
    tolerance: float = 1e-6
    lower: tuple[float, float, float] | None = None
    upper: tuple[float, float, float] | None = None
    radius: float | None = None


@dataclass(frozen=True)
class Port:
    """A named input (force, moment) or output (displacement, rotation) on a region, or a
    gauge output (strain, stress; docs/stress.md).

    A gauge reads sym(d1 d2^T) : eps (strain, tensor shear) or : sigma (stress, Pa) with
    d1 = ``direction``, d2 = ``direction2`` (default d1: the normal strain / stress along
    d1). With ``average`` "surface" (the default) it is the area-weighted mean of the
    surface value over ``region``, or over the surface around ``point`` covered by a grid
    of ``length`` (along d1) x ``width`` (m) or a disc of ``radius`` (m); with "volume"
    the volume-weighted mean of the element averages over the elements with a face on
    ``region`` or whose centroid lies within ``radius`` of ``point``; with neither a grid
    nor a radius the value at ``point`` itself (``region`` is "" for a point).
    """

    name: str
    region: str
    kind: PortKind
    direction: tuple[float, float, float]
    direction2: tuple[float, float, float] | None = None
    point: tuple[float, float, float] | None = None
    radius: float = 0.0
    length: float = 0.0
    width: float = 0.0
    average: GaugeAverage = "surface"


@dataclass(frozen=True)
class Ports:
    """The model's inputs (force, moment) and outputs (displacement, rotation)."""

    inputs: tuple[Port, ...] = ()
    outputs: tuple[Port, ...] = ()


@dataclass(frozen=True)
class Damping:
    """Modal damping: ``uniform`` (ratio), ``per_mode`` (ratios), ``rayleigh`` (alpha, beta)."""

    kind: DampingKind = "uniform"
    ratio: float = 0.02
    ratios: tuple[float, ...] = ()
    alpha: float = 0.0
    beta: float = 0.0


@dataclass(frozen=True)
class Reduction:
    """Retain ``modes`` modes; ``static_correction`` none | residual | augment."""

    modes: int = 4
    static_correction: StaticCorrection = "residual"


@dataclass(frozen=True)
class Filter:
    """Loop-breaking low-pass filter: none | first_order | third_order, cutoff in Hz."""

    kind: FilterKind = "third_order"
    cutoff_hz: float = 2000.0


@dataclass(frozen=True)
class Lumped:
    """Lumped-parameter chain: ``elements`` rigid bodies, ``constants`` simple | refined."""

    elements: int = 10
    constants: LumpedConstants = "refined"


@dataclass(frozen=True)
class Connection:
    """A connection point: ``region`` tied to ``point`` (m) rigidly (RBE2) or by a
    distributing coupling (RBE3). The first connection is the parent point P."""

    name: str
    region: str
    point: tuple[float, float, float]
    coupling: Coupling = "rigid"


@dataclass(frozen=True)
class Config:
    """The fully resolved, validated configuration of one run."""

    name: str
    geometry: Geometry = field(default_factory=Geometry)
    mesh: MeshSpec = field(default_factory=MeshSpec)
    material: Material | None = field(default_factory=Material)  # None: ``materials`` claim every element
    supports: tuple[Support, ...] = ()
    constraints: Constraints = field(default_factory=Constraints)
    modes: ModesConfig = field(default_factory=ModesConfig)
    regions: Mapping[str, RegionSelector] = field(default_factory=dict)
    ports: Ports = field(default_factory=Ports)
    damping: Damping = field(default_factory=Damping)
    reduction: Reduction | None = None
    filter: Filter = field(default_factory=lambda: Filter(kind="none"))
    lumped: Lumped | None = None
    connections: tuple[Connection, ...] = ()
    craig_bampton_modes: int = 0
    materials: tuple[MaterialEntry, ...] = ()  # first match wins; the rest take ``material``
    masses: tuple[AddedMass, ...] = ()
    source: str = ""  # the file the config came from (not part of the YAML contract)
    rotation: "Rotation | None" = None  # pipeline.config.rotation
    coordinate_systems: Mapping[str, CoordinateSystem] = field(default_factory=dict)  # named material frames
