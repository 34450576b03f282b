"""Parse and validate a raw config mapping (as read from YAML) into a :class:`Config`.

This is the boundary of the pipeline: every key is checked here, once, with the field
checker :mod:`pipeline._util.validate`, and refused with a
:class:`~pipeline.errors.ConfigError` that names the dotted key path, the value
received and what was expected. Cross-section rules (regions that exist, a reduced
model with ports, ...) are checked after the sections.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Mapping, Sequence, get_args

from pipeline._util import validate as v
from pipeline._util.yamlio import is_stream, parse_yaml, read_text_bounded
from pipeline.config.frames import parse_coordinate_systems
from pipeline.config.gauges import AREA_KEYS, gauge_area
from pipeline.config.numerics import check_box_thickness, check_numerics
from pipeline.config.materials import lumped_mass_problem, parse_masses, parse_materials
from pipeline.config.overrides import apply_overrides
from pipeline.config.plausibility import check_geometry, check_plausibility
from pipeline.config.rotation import parse_rotation
from pipeline.config.supports import parse_support
from pipeline.config.schema import (BOX_FACES, EIGEN_METHODS, UNIT_SYSTEMS, GAUGE_KINDS, GEOMETRY_KINDS,
                                    PRECISIONS, SOLVERS,
                                    Config, Connection, Constraints, Coupling, Damping, Filter,
                                    FilterKind,
                                    Geometry, InputKind, Lumped, LumpedConstants, Material,
                                    MeshAlgorithm, MeshSpec, ModesConfig, OutputKind, Port, Ports,
                                    Reduction, RegionSelector, SelectorKind, StaticCorrection,
                                    Support)
from pipeline.errors import ConfigError

log = logging.getLogger(__name__)

def _geometry(raw: Any, base_dir: str = "") -> Geometry:
    raw = v.mapping(raw, "geometry", ("kind", "length", "height", "depth", "path", "scale",
                                      "units"), ("kind",))
    kind = v.choice(raw, "kind", "geometry", GEOMETRY_KINDS)
    if kind == "box":
        extra = sorted(set(raw) - {"kind", "length", "height", "depth"})
        if extra:
            raise ConfigError(f"config key 'geometry.{extra[0]}' does not apply to a box; "
                              "expected kind, length, height, depth")
        return Geometry(
            kind=kind,
            length=v.number(raw, "length", "geometry", lo=0.0, lo_open=True, hi=1e3),
            height=v.number(raw, "height", "geometry", lo=0.0, lo_open=True, hi=1e3),
            depth=v.number(raw, "depth", "geometry", lo=0.0, lo_open=True, hi=1e3),
        )
    allowed = {"kind", "path", "scale"} | ({"units"} if kind == "mesh" else set())
    extra = sorted(set(raw) - allowed)
    if extra:
        raise ConfigError(f"config key 'geometry.{extra[0]}' does not apply to kind '{kind}'; "
                          f"expected {', '.join(sorted(allowed))}")
    path = raw.get("path", v.MISSING)
    if path is v.MISSING:
        raise ConfigError("config key 'geometry.path' is missing; it is required for kind "
                          f"'{kind}'")
    if not isinstance(path, str) or not path.strip() or "\0" in path:
        raise v.fail("geometry.path", path, "a file path")
    resolved = Path(path) if Path(path).is_absolute() or not base_dir else Path(base_dir) / path
    try:
        exists = resolved.is_file()
    except (OSError, ValueError):  # a name too long for the file system, ...
        exists = False
    if not exists:
        raise v.fail("geometry.path", path, f"an existing file (looked for "
                    f"'{v.describe(str(resolved))[1:-1]}')")
    scale = v.number(raw, "scale", "geometry", 1.0, lo=0.0, lo_open=True, hi=1e3)
    units = v.choice(raw, "units", "geometry", tuple(UNIT_SYSTEMS)) if "units" in raw else ""
    if units and "scale" in raw:
        raise v.fail("geometry.scale", raw["scale"], f"no scale with geometry.units "
                    f"'{units}' (the unit system gives the file's length unit, "
                    f"{UNIT_SYSTEMS[units]:g} m): give one of the two")
    return Geometry(kind=kind, length=0.0, height=0.0, depth=0.0, path=str(resolved),
                    scale=UNIT_SYSTEMS[units] if units else scale, units=units)


def _mesh(raw: Any, geometry: Geometry) -> MeshSpec:
    # a mesh file brings its elements: mesh.size (gmsh's element size) does not apply
    from_file = geometry.kind == "mesh"
    raw = v.mapping(raw, "mesh", ("order", "size", "algorithm", "parts"),
                    () if from_file else ("size",))
    order = v.choice(raw, "order", "mesh", (1, 2), default=2)
    size = v.number(raw, "size", "mesh", MeshSpec.size if from_file else v.MISSING, lo=0.0,
                    lo_open=True)
    if from_file and ("size" in raw or "algorithm" in raw):
        log.warning("config key 'mesh.%s' does not apply to geometry.kind 'mesh' (the file's "
                    "elements are used as they are): ignored",
                    "size" if "size" in raw else "algorithm")
    largest = geometry.largest_dimension()
    if largest is not None:
        if size > largest:
            raise v.fail("mesh.size", size, f"a size no larger than the body's largest dimension "
                        f"({largest:g} m)")
        smallest = min(geometry.length, geometry.height, geometry.depth)
        if size < smallest / 400.0 or largest / size > 5000:
            raise v.fail("mesh.size", size, f"a size of at least "
                        f"{max(smallest / 400, largest / 5000):g} m for this body (a finer mesh "
                        "would not fit any machine)")
    algorithm = v.choice(raw, "algorithm", "mesh", get_args(MeshAlgorithm), default="hxt")
    return MeshSpec(order=order, size=size, algorithm=algorithm, parts=_parts_file(raw))


def _parts_file(raw: Mapping) -> str:
    """``mesh.parts``: "" or the path of an existing file, relative to the working
    directory (it is an output of ``python -m pipeline partition``, as ``-o`` is)."""
    if "parts" not in raw or raw["parts"] is None:
        return ""
    path = raw["parts"]
    if not isinstance(path, str) or not path.strip() or "\0" in path:
        raise v.fail("mesh.parts", path, "a file path (a parts file of 'python -m pipeline "
                     "partition')")
    try:
        exists = Path(path).is_file()
    except (OSError, ValueError):  # a name too long for the file system, ...
        exists = False
    if not exists:
        raise v.fail("mesh.parts", path, "an existing parts file (made by 'python -m "
                     "pipeline partition')")
    return path


def _material(raw: Any) -> Material:
    raw = v.mapping(raw, "material", ("E", "nu", "rho"), ("E", "nu", "rho"))
    return Material(
        E=v.number(raw, "E", "material", lo=0.0, lo_open=True, hi=1e13),
        nu=v.number(raw, "nu", "material", lo=-1.0, hi=0.5, lo_open=True, hi_open=True),
        rho=v.number(raw, "rho", "material", lo=0.0, lo_open=True, hi=1e6),
    )


def _supports(raw: Any) -> tuple[Support, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise v.fail("supports", raw, "a list of {region: NAME, fix: all | [x, y, z]} (or "
                     "fix in a frame, spring or bushing: docs/config.md)")
    out = [Support(**parse_support(item, f"supports[{i}]")) for i, item in enumerate(raw)]
    return tuple(out)


def _regions(raw: Any) -> dict[str, RegionSelector]:
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise v.fail("regions", raw, "a mapping of region names to selectors")
    out = {}
    for name, sel in raw.items():
        path = f"regions.{name}"
        if not isinstance(name, str) or not v.NAME_RE.fullmatch(name):
            raise v.fail("regions", name, "region names of letters, digits, '_', '-' or '.'")
        sel = v.mapping(sel, path, ("kind", "point", "normal", "tolerance", "lower", "upper",
                                   "radius"), ("kind",))
        kind = v.choice(sel, "kind", path, get_args(SelectorKind))
        if kind == "plane":
            allowed = {"kind", "point", "normal", "tolerance"}
            r = RegionSelector(kind, point=v.vector(sel, "point", path),
                               normal=v.vector(sel, "normal", path, nonzero=True),
                               tolerance=v.number(sel, "tolerance", path, 1e-6, lo=0.0))
        elif kind == "box":
            allowed = {"kind", "lower", "upper"}
            lower, upper = v.vector(sel, "lower", path), v.vector(sel, "upper", path)
            if any(a > b for a, b in zip(lower, upper)):
                raise v.fail(f"{path}.upper", list(upper), f"every component >= lower {list(lower)}")
            r = RegionSelector(kind, lower=lower, upper=upper)
        else:
            allowed = {"kind", "point", "radius"}
            r = RegionSelector(kind, point=v.vector(sel, "point", path),
                               radius=v.number(sel, "radius", path, lo=0.0, lo_open=True))
        extra = set(sel) - allowed
        if extra:
            key = sorted(extra)[0]
            raise ConfigError(f"config key '{path}.{key}' does not apply to a '{kind}' selector; "
                              f"expected one of: {', '.join(sorted(allowed))}")
        out[name] = r
    return out


def _ports(raw: Any) -> Ports:
    if raw is None:
        return Ports()
    raw = v.mapping(raw, "ports", ("inputs", "outputs"))
    seen: dict[str, str] = {}
    groups = {}
    for side, kinds in (("inputs", get_args(InputKind)), ("outputs", get_args(OutputKind))):
        items = []
        for i, item in enumerate(v.items(raw, side, "ports")):
            path = f"ports.{side}[{i}]"
            gauge = isinstance(item, Mapping) and item.get("kind") in GAUGE_KINDS
            if gauge:
                port = _gauge_port(item, path)
            else:
                item = v.mapping(item, path, ("name", "region", "kind", "direction"),
                                ("name", "region", "kind", "direction"))
                port = Port(name=v.name(item, "name", path), region=v.name(item, "region", path),
                            kind=v.choice(item, "kind", path, kinds),
                            direction=v.vector(item, "direction", path, nonzero=True))
            name = port.name
            if name in seen:
                raise v.fail(f"{path}.name", name, f"a name not used already (it names {seen[name]})")
            if gauge and side == "inputs":
                raise v.fail(f"{path}.kind", port.kind, "force or moment (strain and stress "
                            "ports are outputs)")
            seen[name] = path
            items.append(port)
        groups[side] = tuple(items)
    return Ports(**groups)


def _gauge_port(raw: Mapping, path: str) -> Port:
    """A strain or stress output: name, kind, direction [, direction2] and either a
    boundary ``region`` or a ``point`` [, ``radius`` >= 0 m | ``length`` and ``width`` m]
    [, ``average``] (docs/stress.md, :mod:`pipeline.config.gauges`)."""
    item = v.mapping(raw, path, ("name", "region", "kind", "direction", "direction2", "point")
                     + AREA_KEYS, ("name", "kind", "direction"))
    if ("region" in item) == ("point" in item):
        raise v.fail(path, dict(item), "exactly one of 'region' (a boundary region the gauge "
                    "covers) or 'point' (with an optional 'radius', or 'length' and 'width', "
                    "in m)")
    area = gauge_area(item, path)
    d1 = v.vector(item, "direction", path, nonzero=True)
    d2 = v.vector(item, "direction2", path, None, nonzero=True)
    if d2 is not None:
        cos = sum(x * y for x, y in zip(d1, d2)) / math.hypot(*d1) / math.hypot(*d2)
        if abs(cos) > 1e-9:
            raise v.fail(f"{path}.direction2", list(d2), "a direction orthogonal to "
                        "'direction' (the shear component between them), or no direction2 "
                        "for the normal component along 'direction'")
    return Port(name=v.name(item, "name", path),
                region=v.name(item, "region", path) if "region" in item else "",
                kind=item["kind"], direction=d1, direction2=d2,
                point=v.vector(item, "point", path, None), **area)


def _damping(raw: Any) -> Damping:
    if raw is None:
        return Damping()
    raw = v.mapping(raw, "damping", ("kind", "ratio", "ratios", "alpha", "beta"), ("kind",))
    kind = v.choice(raw, "kind", "damping", ("uniform", "per_mode", "rayleigh", "none"))
    if kind == "uniform":
        return Damping(kind=kind, ratio=v.number(raw, "ratio", "damping", lo=0.0, hi=1.0, hi_open=True))
    if kind == "none":
        return Damping(kind="uniform", ratio=0.0)
    if kind == "per_mode":
        ratios = raw.get("ratios", v.MISSING)
        if ratios is v.MISSING:
            raise ConfigError("config key 'damping.ratios' is missing; it is required for per_mode")
        if not isinstance(ratios, list) or not ratios:
            raise v.fail("damping.ratios", ratios, "a non-empty list of ratios in [0, 1)")
        values = tuple(v.number({f"ratios[{i}]": r}, f"ratios[{i}]", "damping", lo=0.0, hi=1.0,
                               hi_open=True) for i, r in enumerate(ratios))
        return Damping(kind=kind, ratio=0.0, ratios=values)
    return Damping(kind=kind, ratio=0.0, alpha=v.number(raw, "alpha", "damping", lo=0.0),
                   beta=v.number(raw, "beta", "damping", lo=0.0))


def _reduction(raw: Any, modes: ModesConfig) -> Reduction | None:
    if raw is None:
        return None
    raw = v.mapping(raw, "reduction", ("modes", "static_correction"), ("modes",))
    n = v.integer(raw, "modes", "reduction", lo=1)
    if n > modes.count:
        raise v.fail("reduction.modes", n, f"at most modes.count = {modes.count}")
    return Reduction(modes=n, static_correction=v.choice(
        raw, "static_correction", "reduction", get_args(StaticCorrection), default="residual"))


def _filter(raw: Any) -> Filter:
    if raw is None:
        return Filter(kind="none")
    raw = v.mapping(raw, "filter", ("kind", "cutoff_hz"), ("kind",))
    kind = v.choice(raw, "kind", "filter", get_args(FilterKind))
    cutoff = v.number(raw, "cutoff_hz", "filter", 2000.0, lo=0.0, lo_open=True, hi=1e9)
    return Filter(kind=kind, cutoff_hz=cutoff)


#: Most lumped-chain elements: the chain's dense eigen-decomposition costs O(n^3) (on two
#: cores: seconds at 100 elements, minutes and gigabytes at 1000), and the refined chain
#: has converged to 0.1 % of beam theory by 20 elements.
MAX_LUMPED_ELEMENTS = 200


def _lumped(raw: Any) -> Lumped | None:
    if raw is None:
        return None
    raw = v.mapping(raw, "lumped", ("elements", "constants"), ("elements",))
    return Lumped(elements=v.integer(raw, "elements", "lumped", lo=1, hi=MAX_LUMPED_ELEMENTS),
                  constants=v.choice(raw, "constants", "lumped", get_args(LumpedConstants), "refined"))


def _connections(raw: Any) -> tuple[Connection, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise v.fail("connections", raw, "a list of {name, region, point, coupling}")
    out, seen = [], set()
    for i, item in enumerate(raw):
        path = f"connections[{i}]"
        item = v.mapping(item, path, ("name", "region", "point", "coupling"),
                        ("name", "region", "point"))
        name = v.name(item, "name", path)
        if name in seen:
            raise v.fail(f"{path}.name", name, "a name not used by another connection")
        seen.add(name)
        out.append(Connection(name=name, region=v.name(item, "region", path),
                              point=v.vector(item, "point", path),
                              coupling=v.choice(item, "coupling", path, get_args(Coupling),
                                               "rigid")))
    return tuple(out)


TOP_KEYS = ("name", "geometry", "mesh", "material", "supports", "constraints", "modes", "regions",
            "ports", "damping", "reduction", "filter", "lumped", "connections",
            "craig_bampton", "materials", "masses", "rotation", "coordinate_systems")


def _section(raw: Mapping, key: str) -> Any:
    """An optional section: {} when absent or null, else the value (validated by the caller;
    ``modes: false`` or ``modes: []`` is refused, not read as the defaults)."""
    value = raw.get(key)
    return {} if value is None else value


def config_from_dict(raw: Any, source: str = "") -> Config:
    """Validate a raw mapping (as parsed from YAML) and return a :class:`Config`."""
    raw = v.mapping(raw, "", TOP_KEYS, ("name", "geometry") + (
        () if isinstance(raw, Mapping) and raw.get("materials") else ("material",)))
    # relative paths: against the config's folder; a config read from a pipe or
    # /dev/stdin has none, so against the current directory
    base_dir = str(Path(source).parent) if source and not is_stream(source) else ""
    geometry = _geometry(raw["geometry"], base_dir)
    check_geometry(geometry)  # a length in mm is named here, not blamed on mesh.size
    check_box_thickness(geometry)  # a box too thin to mesh, before mesh.size is checked
    constraints = v.mapping(_section(raw, "constraints"), "constraints", ("in_plane",))
    modes_raw = v.mapping(_section(raw, "modes"), "modes", ("count", "solver", "tolerance",
                                                              "precision", "method"))
    modes = ModesConfig(count=v.integer(modes_raw, "count", "modes", 10, lo=1, hi=500),
                  solver=v.choice(modes_raw, "solver", "modes", SOLVERS, "auto"),
                  tolerance=v.number(modes_raw, "tolerance", "modes", 0.0, lo=0.0, hi=1e-2),
                  precision=v.choice(modes_raw, "precision", "modes", PRECISIONS, "auto"),
                  method=v.choice(modes_raw, "method", "modes", EIGEN_METHODS, "auto"))
    regions = _regions(raw.get("regions"))
    systems = parse_coordinate_systems(raw.get("coordinate_systems"))
    for name in regions:
        if geometry.kind == "box" and name in BOX_FACES:
            raise v.fail(f"regions.{name}", name, f"a name other than the box's own faces "
                        f"({', '.join(BOX_FACES)})")
    cfg = Config(
        name=v.name(raw, "name", ""),
        geometry=geometry,
        mesh=_mesh(_section(raw, "mesh"), geometry),
        material=_material(raw["material"]) if "material" in raw else None,
        supports=_supports(raw.get("supports")),
        constraints=Constraints(in_plane=v.boolean(constraints, "in_plane", "constraints", False)),
        modes=modes,
        regions=regions,
        ports=_ports(raw.get("ports")),
        damping=_damping(raw.get("damping")),
        reduction=_reduction(raw.get("reduction"), modes),
        filter=_filter(raw.get("filter")),
        lumped=_lumped(raw.get("lumped")),
        connections=_connections(raw.get("connections")),
        craig_bampton_modes=v.integer(v.mapping(_section(raw, "craig_bampton"), "craig_bampton",
                                              ("modes",)), "modes", "craig_bampton", 0,
                                     lo=0, hi=500),
        materials=parse_materials(raw.get("materials"), systems),
        masses=parse_masses(raw.get("masses")),
        source=source,
        rotation=parse_rotation(raw.get("rotation")),
        coordinate_systems=systems,
    )
    # a box's and a CAD file's region names are all known here (its faces, the selectors);
    # a mesh file's or a .geo script's named groups are checked where the mesh is read,
    # before assembly (pipeline.fe.regions.check_region_uses)
    known = (set(regions) | (set(BOX_FACES) if geometry.kind == "box" else set())
             if geometry.kind in ("box", "step") else set())
    used = [(f"supports[{i}].region", s.region) for i, s in enumerate(cfg.supports)]
    used += [(f"ports.inputs[{i}].region", p.region) for i, p in enumerate(cfg.ports.inputs)]
    used += [(f"ports.outputs[{i}].region", p.region) for i, p in enumerate(cfg.ports.outputs)
             if p.region]
    used += [(f"connections[{i}].region", c.region) for i, c in enumerate(cfg.connections)]
    used += [(f"masses[{i}].region", m.region) for i, m in enumerate(cfg.masses) if m.region]
    for path, region in used:
        if known and region not in known:
            raise v.fail(path, region, "a region the geometry names or 'regions' defines: "
                        + ", ".join(sorted(known)))
    if cfg.reduction is not None and not (cfg.ports.inputs and cfg.ports.outputs):
        raise v.fail("reduction", raw.get("reduction"), "ports with at least one input and one "
                    "output (a reduced model needs both)")
    if cfg.reduction is not None and not cfg.supports \
            and cfg.reduction.static_correction != "none":
        raise v.fail("reduction.static_correction", cfg.reduction.static_correction,
                    "'none' for a body without supports (its stiffness matrix is singular: a "
                    "free body has no static deflection to correct with); add supports, e.g. "
                    "supports: [{region: root, fix: all}], or set "
                    "reduction.static_correction: none")
    if cfg.lumped is not None and (cfg.materials or cfg.material is None):
        raise v.fail("lumped", raw.get("lumped"), "no lumped chain with 'materials' (the "
                    "chain is built from one material)")
    if cfg.lumped is not None and geometry.kind == "box" and cfg.masses:
        problem = lumped_mass_problem(geometry.height, geometry.depth, cfg.masses)
        if problem is not None:
            raise v.fail(*problem)
    if cfg.lumped is not None and geometry.kind != "box":
        raise v.fail("lumped", raw.get("lumped"), "a box geometry (the lumped chain needs a "
                    f"straight beam; geometry.kind is '{geometry.kind}')")
    if cfg.damping.kind == "per_mode" and cfg.reduction is not None \
            and len(cfg.damping.ratios) < cfg.reduction.modes:
        raise v.fail("damping.ratios", list(cfg.damping.ratios),
                    f"at least reduction.modes = {cfg.reduction.modes} ratios")
    if cfg.modes.method == "multigrid" and cfg.mesh.order != 2:
        raise v.fail("modes.method", "multigrid", "'auto' or 'factor' with mesh.order "
                    f"{cfg.mesh.order} (the multigrid solver's coarse space is the linear "
                    "space inside a quadratic mesh: set mesh.order: 2)")
    if cfg.modes.method == "multigrid" and cfg.modes.precision == "mixed":
        raise v.fail("modes.precision", "mixed", "'auto' or 'double' with modes.method: "
                    "multigrid (mixed precision is a property of a sparse factor; the "
                    "multigrid solver has none)")
    if cfg.rotation is not None and not cfg.supports:
        raise v.fail("rotation", raw.get("rotation"), "a body with supports (the static "
                    "centrifugal stress of a free body has no equilibrium to solve for)")
    rigid = [i for i, m in enumerate(cfg.masses) if m.kind == "point" and m.coupling == "rigid"]
    if cfg.rotation is not None and rigid:
        raise v.fail(f"masses[{rigid[0]}].coupling", "rigid", "distributing with `rotation` "
                    "(a rigidly coupled mass moves as coordinates of the constraint u = T q, "
                    "where its centrifugal load, softening and own geometric stiffness have "
                    "no place yet)")
    if cfg.rotation is not None and cfg.rotation.correction_shapes > cfg.modes.count:
        raise v.fail("rotation.correction_shapes", cfg.rotation.correction_shapes,
                    f"at most modes.count = {cfg.modes.count} (one per mode)")
    if cfg.mesh.parts and cfg.modes.solver != "slepc":
        raise v.fail("mesh.parts", cfg.mesh.parts, "a parts file only with modes.solver: "
                     f"slepc (the MPI ranks read it; modes.solver is '{cfg.modes.solver}')")
    check_numerics(cfg)  # what double precision cannot carry: refused
    check_plausibility(cfg)  # unit slips and locking: warnings, logged
    return cfg


def load_config(path: str | Path, overrides: Sequence[str] = ()) -> Config:
    """Read a YAML config file, apply ``--set`` overrides and validate it."""
    path = Path(path)
    try:
        text = read_text_bounded(path, "config file")  # regular file, bounded size
    except FileNotFoundError:
        raise ConfigError(f"config file '{path}': not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file '{path}': cannot be read ({exc})") from None
    raw = parse_yaml(text, f"config file '{path}'")
    if raw is None:
        raise ConfigError(f"config file '{path}': is empty, expected a mapping of config keys")
    if not isinstance(raw, Mapping):
        raise ConfigError(f"config file '{path}': got {v.describe(raw)}, expected a mapping of "
                          "config keys at the top level")
    raw = apply_overrides(raw, overrides)
    try:
        return config_from_dict(raw, source=str(path))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
