"""Configuration: load a YAML file, apply ``--set`` overrides, validate strictly.

This is the boundary of the pipeline: every key is checked here, once, and refused
with a :class:`~pipeline.errors.ConfigError` that names the dotted key path, the value
received and what was expected. Everything downstream receives frozen dataclasses and
trusts them.

Units are SI throughout (m, kg, s, N, Pa).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping, Sequence

from pipeline._util import validate as v
from pipeline._util.yamlio import parse_yaml
from pipeline.errors import ConfigError

__all__ = [
    "Config",
    "load_config",
    "config_from_dict",
    "apply_overrides",
    "config_to_yaml",
]


# --------------------------------------------------------------------------- records
@dataclass(frozen=True)
class Geometry:
    """The body.

    ``box``: x in [0, length], y in [0, height], z in [0, depth] (m).
    ``step`` (STEP/IGES file), ``geo`` (gmsh script), ``mesh`` (a mesh file meshio reads):
    ``path`` to the file (relative paths are relative to the config file), ``scale``
    multiplies its coordinates into metres (0.001 for CAD drawn in mm).
    """

    kind: str = "box"
    length: float = 0.5
    height: float = 0.02
    depth: float = 0.05
    path: str = ""
    scale: float = 1.0

    def largest_dimension(self) -> float | None:
        """Largest box dimension (m), or None where only the file knows it."""
        if self.kind != "box":
            return None
        return max(self.length, self.height, self.depth)


@dataclass(frozen=True)
class MeshSpec:
    """gmsh settings: element ``order`` 1 or 2, target element ``size`` in m."""

    order: int = 2
    size: float = 0.005
    algorithm: str = "hxt"  # gmsh 3D algorithm: delaunay | hxt | frontal


@dataclass(frozen=True)
class Material:
    """Isotropic linear elastic material: E in Pa, nu dimensionless, rho in kg/m^3."""

    E: float = 69.0e9
    nu: float = 0.33
    rho: float = 2700.0


@dataclass(frozen=True)
class Support:
    """Fix the displacement components ``fix`` (subset of x, y, z) on a region."""

    region: str
    fix: tuple[str, ...] = ("x", "y", "z")


@dataclass(frozen=True)
class Constraints:
    """``in_plane``: u_z = 0 at every node (the body bends only in the x-y plane)."""

    in_plane: bool = False


@dataclass(frozen=True)
class Modes:
    """Eigen-solution: the lowest ``count`` modes, sparse factorisation ``solver``."""

    count: int = 10
    solver: str = "auto"
    tolerance: float = 0.0  # relative residual of the shift-inverted problem; 0: 1e-10 for block Lanczos (1e-8 from 100k free DOFs), machine precision for ARPACK


@dataclass(frozen=True)
class RegionSelector:
    """A geometric region: boundary facets whose vertices all satisfy the selector.

    kind ``plane``: |(x - point) . normal| <= tolerance;
    kind ``box``: lower <= x <= upper component-wise;
    kind ``sphere``: |x - point| <= radius.
    """

    kind: str
    point: tuple[float, float, float] | None = None
    normal: tuple[float, float, float] | None = None
    tolerance: float = 1e-6
    lower: tuple[float, float, float] | None = None
    upper: tuple[float, float, float] | None = None
    radius: float | None = None


@dataclass(frozen=True)
class Port:
    """A named input (force, moment) or output (displacement, rotation) on a region."""

    name: str
    region: str
    kind: str
    direction: tuple[float, float, float]


@dataclass(frozen=True)
class Ports:
    inputs: tuple[Port, ...] = ()
    outputs: tuple[Port, ...] = ()


@dataclass(frozen=True)
class Damping:
    """Modal damping: ``uniform`` (ratio), ``per_mode`` (ratios), ``rayleigh`` (alpha, beta)."""

    kind: str = "uniform"
    ratio: float = 0.02
    ratios: tuple[float, ...] = ()
    alpha: float = 0.0
    beta: float = 0.0


@dataclass(frozen=True)
class Reduction:
    """Retain ``modes`` modes; ``static_correction`` none | residual | augment."""

    modes: int = 4
    static_correction: str = "residual"


@dataclass(frozen=True)
class Filter:
    """Loop-breaking low-pass filter: none | first_order | third_order, cutoff in Hz."""

    kind: str = "third_order"
    cutoff_hz: float = 2000.0


@dataclass(frozen=True)
class Lumped:
    """Lumped-parameter chain: ``elements`` rigid bodies, ``constants`` simple | refined."""

    elements: int = 10
    constants: str = "refined"


@dataclass(frozen=True)
class Connection:
    """A connection point: ``region`` tied to ``point`` (m) rigidly (RBE2) or by a
    distributing coupling (RBE3). The first connection is the parent point P."""

    name: str
    region: str
    point: tuple[float, float, float]
    coupling: str = "rigid"


@dataclass(frozen=True)
class Config:
    """The fully resolved, validated configuration of one run."""

    name: str
    geometry: Geometry = field(default_factory=Geometry)
    mesh: MeshSpec = field(default_factory=MeshSpec)
    material: Material = field(default_factory=Material)
    supports: tuple[Support, ...] = ()
    constraints: Constraints = field(default_factory=Constraints)
    modes: Modes = field(default_factory=Modes)
    regions: Mapping[str, RegionSelector] = field(default_factory=dict)
    ports: Ports = field(default_factory=Ports)
    damping: Damping = field(default_factory=Damping)
    reduction: Reduction | None = None
    filter: Filter = field(default_factory=lambda: Filter(kind="none"))
    lumped: Lumped | None = None
    connections: tuple[Connection, ...] = ()
    craig_bampton_modes: int = 0
    source: str = ""  # the file the config came from (not part of the YAML contract)


# --------------------------------------------------------------------------- constants
GEOMETRY_KINDS = ("box", "step", "geo", "mesh")
SOLVERS = ("auto", "pardiso", "cholmod", "mumps", "superlu")
BOX_FACES = ("root", "tip", "bottom", "top", "back", "front")


# --------------------------------------------------------------------------- sections
def _geometry(raw: Any, base_dir: str = "") -> Geometry:
    raw = v.mapping(raw, "geometry", ("kind", "length", "height", "depth", "path", "scale"),
                   ("kind",))
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
    extra = sorted(set(raw) - {"kind", "path", "scale"})
    if extra:
        raise ConfigError(f"config key 'geometry.{extra[0]}' does not apply to kind '{kind}'; "
                          "expected kind, path, scale")
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
    return Geometry(kind=kind, length=0.0, height=0.0, depth=0.0, path=str(resolved),
                    scale=v.number(raw, "scale", "geometry", 1.0, lo=0.0, lo_open=True, hi=1e3))


def _mesh(raw: Any, geometry: Geometry) -> MeshSpec:
    raw = v.mapping(raw, "mesh", ("order", "size", "algorithm"), ("size",))
    order = v.choice(raw, "order", "mesh", (1, 2), default=2)
    size = v.number(raw, "size", "mesh", lo=0.0, lo_open=True)
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
    algorithm = v.choice(raw, "algorithm", "mesh", ("delaunay", "hxt", "frontal"), default="hxt")
    return MeshSpec(order=order, size=size, algorithm=algorithm)


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
        raise v.fail("supports", raw, "a list of {region: NAME, fix: all | [x, y, z]}")
    out = []
    for i, item in enumerate(raw):
        path = f"supports[{i}]"
        item = v.mapping(item, path, ("region", "fix"), ("region",))
        region = v.name(item, "region", path)
        fix = item.get("fix", "all")
        if fix == "all":
            comps = ("x", "y", "z")
        elif (isinstance(fix, list) and fix and all(c in ("x", "y", "z") for c in fix)
              and len(set(fix)) == len(fix)):
            comps = tuple(sorted(fix))
        else:
            raise v.fail(f"{path}.fix", fix, "'all' or a list of distinct components from x, y, z")
        out.append(Support(region=region, fix=comps))
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
        kind = v.choice(sel, "kind", path, ("plane", "box", "sphere"))
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
    for side, kinds in (("inputs", ("force", "moment")), ("outputs", ("displacement", "rotation"))):
        items = []
        for i, item in enumerate(v.items(raw, side, "ports")):
            path = f"ports.{side}[{i}]"
            item = v.mapping(item, path, ("name", "region", "kind", "direction"),
                            ("name", "region", "kind", "direction"))
            name = v.name(item, "name", path)
            if name in seen:
                raise v.fail(f"{path}.name", name, f"a name not used already (it names {seen[name]})")
            seen[name] = path
            items.append(Port(name=name, region=v.name(item, "region", path),
                              kind=v.choice(item, "kind", path, kinds),
                              direction=v.vector(item, "direction", path, nonzero=True)))
        groups[side] = tuple(items)
    return Ports(**groups)


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


def _reduction(raw: Any, modes: Modes) -> Reduction | None:
    if raw is None:
        return None
    raw = v.mapping(raw, "reduction", ("modes", "static_correction"), ("modes",))
    n = v.integer(raw, "modes", "reduction", lo=1)
    if n > modes.count:
        raise v.fail("reduction.modes", n, f"at most modes.count = {modes.count}")
    return Reduction(modes=n, static_correction=v.choice(
        raw, "static_correction", "reduction", ("none", "residual", "augment"), default="residual"))


def _filter(raw: Any) -> Filter:
    if raw is None:
        return Filter(kind="none")
    raw = v.mapping(raw, "filter", ("kind", "cutoff_hz"), ("kind",))
    kind = v.choice(raw, "kind", "filter", ("none", "first_order", "third_order"))
    cutoff = v.number(raw, "cutoff_hz", "filter", 2000.0, lo=0.0, lo_open=True, hi=1e9)
    return Filter(kind=kind, cutoff_hz=cutoff)


def _lumped(raw: Any) -> Lumped | None:
    if raw is None:
        return None
    raw = v.mapping(raw, "lumped", ("elements", "constants"), ("elements",))
    return Lumped(elements=v.integer(raw, "elements", "lumped", lo=1, hi=10000),
                  constants=v.choice(raw, "constants", "lumped", ("simple", "refined"), "refined"))


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
                              coupling=v.choice(item, "coupling", path, ("rigid", "distributing"),
                                               "rigid")))
    return tuple(out)


TOP_KEYS = ("name", "geometry", "mesh", "material", "supports", "constraints", "modes", "regions",
            "ports", "damping", "reduction", "filter", "lumped", "connections",
            "craig_bampton")


def _section(raw: Mapping, key: str) -> Any:
    """An optional section: {} when absent or null, else the value (validated by the caller;
    ``modes: false`` or ``modes: []`` is refused, not read as the defaults)."""
    value = raw.get(key)
    return {} if value is None else value


def config_from_dict(raw: Any, source: str = "") -> Config:
    """Validate a raw mapping (as parsed from YAML) and return a :class:`Config`."""
    raw = v.mapping(raw, "", TOP_KEYS, ("name", "geometry", "mesh", "material"))
    geometry = _geometry(raw["geometry"], str(Path(source).parent) if source else "")
    constraints = v.mapping(_section(raw, "constraints"), "constraints", ("in_plane",))
    modes_raw = v.mapping(_section(raw, "modes"), "modes", ("count", "solver", "tolerance"))
    modes = Modes(count=v.integer(modes_raw, "count", "modes", 10, lo=1, hi=500),
                  solver=v.choice(modes_raw, "solver", "modes", SOLVERS, "auto"),
                  tolerance=v.number(modes_raw, "tolerance", "modes", 0.0, lo=0.0, hi=1e-2))
    regions = _regions(raw.get("regions"))
    for name in regions:
        if geometry.kind == "box" and name in BOX_FACES:
            raise v.fail(f"regions.{name}", name, f"a name other than the box's own faces "
                        f"({', '.join(BOX_FACES)})")
    cfg = Config(
        name=v.name(raw, "name", ""),
        geometry=geometry,
        mesh=_mesh(raw["mesh"], geometry),
        material=_material(raw["material"]),
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
        source=source,
    )
    known = set(regions) | (set(BOX_FACES) if geometry.kind == "box" else set())
    used = [(f"supports[{i}].region", s.region) for i, s in enumerate(cfg.supports)]
    used += [(f"ports.inputs[{i}].region", p.region) for i, p in enumerate(cfg.ports.inputs)]
    used += [(f"ports.outputs[{i}].region", p.region) for i, p in enumerate(cfg.ports.outputs)]
    used += [(f"connections[{i}].region", c.region) for i, c in enumerate(cfg.connections)]
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
    if cfg.lumped is not None and geometry.kind != "box":
        raise v.fail("lumped", raw.get("lumped"), "a box geometry (the lumped chain needs a "
                    f"straight beam; geometry.kind is '{geometry.kind}')")
    if cfg.damping.kind == "per_mode" and cfg.reduction is not None \
            and len(cfg.damping.ratios) < cfg.reduction.modes:
        raise v.fail("damping.ratios", list(cfg.damping.ratios),
                    f"at least reduction.modes = {cfg.reduction.modes} ratios")
    return cfg


# --------------------------------------------------------------------------- files
def _split_path(path: str) -> list[str]:
    parts = [p for p in re.split(r"\.|\[(\d+)\]", path) if p]
    if not parts or any(not re.fullmatch(r"[A-Za-z0-9_\-]+", p) for p in parts):
        shown = path if len(path) <= 80 and path.isprintable() else v.describe(path)[1:-1]
        raise ConfigError(f"override '{shown}': expected a dotted key path such as mesh.size")
    return parts


def apply_overrides(raw: Any, overrides: Sequence[str]) -> dict:
    """Apply ``KEY=VALUE`` overrides (VALUE parsed as YAML) to a raw config mapping.

    KEY is a dotted path (``mesh.size``); list items are addressed by index
    (``supports.0.region`` or ``supports[0].region``). Missing intermediate mappings are
    created, so the validator (not this function) decides whether a key is known.
    """
    import copy

    try:
        data = copy.deepcopy(raw) if isinstance(raw, Mapping) else raw
    except RecursionError:
        raise ConfigError("config: nested too deeply to be a config") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config: got {v.describe(raw)}, expected a mapping at the top level")
    for item in overrides:
        if not isinstance(item, str):
            raise ConfigError(f"override {v.describe(item)}: expected KEY=VALUE text")
        shown = item if len(item) <= 80 and item.isprintable() else v.describe(item)[1:-1]
        if "=" not in item:
            raise ConfigError(f"override '{shown}': expected KEY=VALUE, e.g. mesh.size=0.004")
        key, text = item.split("=", 1)
        parts = _split_path(key.strip())
        value = parse_yaml(text, f"override '{shown}'")
        node: Any = data
        for depth, part in enumerate(parts[:-1]):
            nxt = parts[depth + 1]
            if isinstance(node, list):
                idx = int(part) if part.isdigit() else -1
                if not 0 <= idx < len(node):
                    raise ConfigError(f"override '{shown}': index {part} is out of range "
                                      f"(the list has {len(node)} items)")
                node = node[idx]
                continue
            if not isinstance(node, dict):
                raise ConfigError(f"override '{shown}': '{part}' is not inside a mapping")
            if part not in node or node[part] is None:
                node[part] = [] if nxt.isdigit() else {}
            node = node[part]
        last = parts[-1]
        if isinstance(node, list):
            idx = int(last) if last.isdigit() else -1
            if not 0 <= idx < len(node):
                raise ConfigError(f"override '{shown}': index {last} is out of range")
            node[idx] = value
        elif isinstance(node, dict):
            node[last] = value
        else:
            raise ConfigError(f"override '{shown}': '{last}' is not inside a mapping")
    return data


def load_config(path: str | Path, overrides: Sequence[str] = ()) -> Config:
    """Read a YAML config file, apply ``--set`` overrides and validate it."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
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


def config_to_dict(cfg: Config) -> dict:
    """The resolved config as plain YAML-ready data (tuples become lists)."""

    def plain(value: Any) -> Any:
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        return value

    out = {}
    for f in fields(cfg):
        if f.name == "source":
            continue
        value = getattr(cfg, f.name)
        if value is None:
            continue
        if f.name == "regions":
            value = {k: {kk: vv for kk, vv in asdict(v).items() if vv is not None}
                     for k, v in value.items()}
        elif f.name == "craig_bampton_modes":
            if value:
                out["craig_bampton"] = {"modes": value}
            continue
        elif f.name == "connections":
            value = [asdict(c) for c in value]
        elif f.name == "supports":
            value = [{"region": s.region, "fix": "all" if s.fix == ("x", "y", "z") else list(s.fix)}
                     for s in value]
        elif f.name == "geometry":
            keep = ("kind", "length", "height", "depth") if value.kind == "box" else \
                ("kind", "path", "scale")
            value = {k: getattr(value, k) for k in keep}
        elif hasattr(value, "__dataclass_fields__"):
            value = asdict(value)
        out[f.name] = plain(value)
    if cfg.damping.kind != "per_mode":
        out["damping"].pop("ratios", None)
    return out


def config_to_yaml(cfg: Config) -> str:
    """The resolved config as YAML text; ``load`` of it gives back an equal Config."""
    import yaml

    return yaml.safe_dump(config_to_dict(cfg), sort_keys=False)
