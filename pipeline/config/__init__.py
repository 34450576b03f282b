"""Configuration: load a YAML file, apply ``--set`` overrides, validate strictly.

This is the boundary of the pipeline: every key is checked here, once, and refused
with a :class:`~pipeline.errors.ConfigError` that names the dotted key path, the value
received and what was expected. Everything downstream receives frozen dataclasses and
trusts them.

Units are SI throughout (m, kg, s, N, Pa).
"""

from __future__ import annotations

import itertools
import math
import re
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping, Sequence

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


# --------------------------------------------------------------------------- helpers
_MISSING = object()
_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")  # use with fullmatch (no "\n")
GEOMETRY_KINDS = ("box", "step", "geo", "mesh")
SOLVERS = ("auto", "pardiso", "cholmod", "mumps", "superlu")
BOX_FACES = ("root", "tip", "bottom", "top", "back", "front")


def _short_repr(value: Any, depth: int = 0) -> str:
    """repr() bounded in depth, length and size: safe on hostile input (deep nesting,
    shared sub-lists that would expand exponentially, ints of thousands of digits)."""
    if isinstance(value, bool) or value is None or isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        if value.bit_length() <= 128:
            return repr(value)
        return f"<an integer of about {int(value.bit_length() * 0.30103) + 1} digits>"
    if isinstance(value, (str, bytes)):
        text = repr(value[:100])
        return text if len(value) <= 100 else text[:-1] + "..." + text[-1]
    if depth >= 3:
        return "[...]" if isinstance(value, (list, tuple)) else "{...}" \
            if isinstance(value, Mapping) else f"<{type(value).__name__}>"
    if isinstance(value, (list, tuple)):
        items = [_short_repr(v, depth + 1) for v in value[:6]]
        if len(value) > 6:
            items.append("...")
        body = ", ".join(items)
        if isinstance(value, list):
            return f"[{body}]"
        return f"({body},)" if len(value) == 1 else f"({body})"
    if isinstance(value, Mapping):
        items = [f"{_short_repr(k, depth + 1)}: {_short_repr(v, depth + 1)}"
                 for k, v in itertools.islice(value.items(), 6)]
        if len(value) > 6:
            items.append("...")
        return "{" + ", ".join(items) + "}"
    try:
        return repr(value)[:100]
    except Exception:  # a hostile __repr__ must not hide the config error
        return f"<{type(value).__name__}>"


def _describe(value: Any) -> str:
    text = _short_repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _key_text(key: Any) -> str:
    """A config key as it appears in a message: itself if short and printable, else
    escaped (no quotes, no newlines) and shortened."""
    if isinstance(key, str):
        text = key if key.isprintable() else key.encode("unicode_escape").decode("ascii")
        text = text.replace("'", "\\x27")
    elif key is None or isinstance(key, (bool, int, float)):
        text = _short_repr(key)
    else:
        text = f"<{type(key).__name__}>"
    return text if len(text) <= 64 else text[:61] + "..."


def _fail(path: str, value: Any, expected: str) -> ConfigError:
    return ConfigError(f"config key '{path}': got {_describe(value)}, expected {expected}")


def _mapping(raw: Any, path: str, allowed: Sequence[str], required: Sequence[str] = ()) -> dict:
    if not isinstance(raw, Mapping):
        raise _fail(path or "<root>", raw, "a mapping of keys to values")
    for key in raw:
        if not isinstance(key, str) or key not in allowed:
            where = f"{path}.{_key_text(key)}" if path else _key_text(key)
            raise ConfigError(
                f"config key '{where}' is not known; expected one of: {', '.join(allowed)}"
            )
    for key in required:
        if key not in raw:
            where = f"{path}.{key}" if path else key
            raise ConfigError(f"config key '{where}' is missing; it is required")
    return dict(raw)


def _number(raw: Mapping, key: str, path: str, default: Any = _MISSING, *, lo: float | None = None,
            hi: float | None = None, lo_open: bool = False, hi_open: bool = False) -> float:
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is _MISSING:
        raise ConfigError(f"config key '{where}' is missing; it is required")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(where, value, "a number")
    try:
        value = float(value)
    except OverflowError:  # an int beyond the float range
        raise _fail(where, value, "a finite number") from None
    if not math.isfinite(value):
        raise _fail(where, value, "a finite number")
    lo_ok = lo is None or (value > lo if lo_open else value >= lo)
    hi_ok = hi is None or (value < hi if hi_open else value <= hi)
    if not (lo_ok and hi_ok):
        left = "" if lo is None else ("(" if lo_open else "[") + f"{lo:g}"
        right = "" if hi is None else f"{hi:g}" + (")" if hi_open else "]")
        if lo is not None and hi is not None:
            rng = f"a number in {left}, {right}"
        elif lo is not None:
            rng = f"a number {'>' if lo_open else '>='} {lo:g}"
        else:
            rng = f"a number {'<' if hi_open else '<='} {hi:g}"
        raise _fail(where, value, rng)
    return value


def _integer(raw: Mapping, key: str, path: str, default: Any = _MISSING, *, lo: int | None = None,
             hi: int | None = None) -> int:
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is _MISSING:
        raise ConfigError(f"config key '{where}' is missing; it is required")
    if isinstance(value, bool) or not isinstance(value, int):
        raise _fail(where, value, "an integer")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        bounds = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise _fail(where, value, f"an integer {bounds}")
    return value


def _choice(raw: Mapping, key: str, path: str, choices: Sequence[Any], default: Any = _MISSING) -> Any:
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is _MISSING:
        raise ConfigError(f"config key '{where}' is missing; it is required")
    if isinstance(value, bool) and not any(isinstance(c, bool) for c in choices):
        raise _fail(where, value, "one of " + " | ".join(map(str, choices)))
    if not any(type(value) is type(c) and value == c for c in choices):
        raise _fail(where, value, "one of " + " | ".join(map(str, choices)))
    return value


def _boolean(raw: Mapping, key: str, path: str, default: bool) -> bool:
    value = raw.get(key, default)
    if not isinstance(value, bool):
        raise _fail(f"{path}.{key}", value, "true or false")
    return value


def _name(raw: Mapping, key: str, path: str, default: Any = _MISSING) -> str:
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is _MISSING:
        raise ConfigError(f"config key '{where}' is missing; it is required")
    if not isinstance(value, str) or not _NAME_RE.fullmatch(value):
        raise _fail(where, value, "a name of 1-64 letters, digits, '_', '-' or '.', "
                    "starting with a letter or digit")
    return value


def _vector(raw: Mapping, key: str, path: str, default: Any = _MISSING, *, nonzero: bool = False):
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is _MISSING:
        raise ConfigError(f"config key '{where}' is missing; it is required")
    if value is None and default is None:
        return None
    expected = "a list of three finite numbers [x, y, z]"
    if not (isinstance(value, (list, tuple)) and len(value) == 3
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise _fail(where, value, expected)
    try:
        vec = tuple(float(v) for v in value)
    except OverflowError:  # an int beyond the float range
        raise _fail(where, value, expected) from None
    if not all(math.isfinite(v) for v in vec):
        raise _fail(where, value, expected)
    if nonzero:
        square = sum(v * v for v in vec)
        if not math.isfinite(square):  # |d|^2 overflows: normalising it would give 0
            raise _fail(where, value, "a direction whose squared length is a finite number "
                        "(scale it down)")
        if math.sqrt(square) < 1e-12:
            raise _fail(where, value, "a non-zero direction")
    return vec


def _list(raw: Mapping, key: str, path: str) -> list:
    value = raw.get(key, [])
    if value is None:
        return []
    if not isinstance(value, list):
        raise _fail(f"{path}.{key}" if path else key, value, "a list")
    return value


# --------------------------------------------------------------------------- sections
def _geometry(raw: Any, base_dir: str = "") -> Geometry:
    raw = _mapping(raw, "geometry", ("kind", "length", "height", "depth", "path", "scale"),
                   ("kind",))
    kind = _choice(raw, "kind", "geometry", GEOMETRY_KINDS)
    if kind == "box":
        extra = sorted(set(raw) - {"kind", "length", "height", "depth"})
        if extra:
            raise ConfigError(f"config key 'geometry.{extra[0]}' does not apply to a box; "
                              "expected kind, length, height, depth")
        return Geometry(
            kind=kind,
            length=_number(raw, "length", "geometry", lo=0.0, lo_open=True, hi=1e3),
            height=_number(raw, "height", "geometry", lo=0.0, lo_open=True, hi=1e3),
            depth=_number(raw, "depth", "geometry", lo=0.0, lo_open=True, hi=1e3),
        )
    extra = sorted(set(raw) - {"kind", "path", "scale"})
    if extra:
        raise ConfigError(f"config key 'geometry.{extra[0]}' does not apply to kind '{kind}'; "
                          "expected kind, path, scale")
    path = raw.get("path", _MISSING)
    if path is _MISSING:
        raise ConfigError("config key 'geometry.path' is missing; it is required for kind "
                          f"'{kind}'")
    if not isinstance(path, str) or not path.strip() or "\0" in path:
        raise _fail("geometry.path", path, "a file path")
    resolved = Path(path) if Path(path).is_absolute() or not base_dir else Path(base_dir) / path
    try:
        exists = resolved.is_file()
    except (OSError, ValueError):  # a name too long for the file system, ...
        exists = False
    if not exists:
        raise _fail("geometry.path", path, f"an existing file (looked for "
                    f"'{_describe(str(resolved))[1:-1]}')")
    return Geometry(kind=kind, length=0.0, height=0.0, depth=0.0, path=str(resolved),
                    scale=_number(raw, "scale", "geometry", 1.0, lo=0.0, lo_open=True, hi=1e3))


def _mesh(raw: Any, geometry: Geometry) -> MeshSpec:
    raw = _mapping(raw, "mesh", ("order", "size", "algorithm"), ("size",))
    order = _choice(raw, "order", "mesh", (1, 2), default=2)
    size = _number(raw, "size", "mesh", lo=0.0, lo_open=True)
    largest = geometry.largest_dimension()
    if largest is not None:
        if size > largest:
            raise _fail("mesh.size", size, f"a size no larger than the body's largest dimension "
                        f"({largest:g} m)")
        smallest = min(geometry.length, geometry.height, geometry.depth)
        if size < smallest / 400.0 or largest / size > 5000:
            raise _fail("mesh.size", size, f"a size of at least "
                        f"{max(smallest / 400, largest / 5000):g} m for this body (a finer mesh "
                        "would not fit any machine)")
    algorithm = _choice(raw, "algorithm", "mesh", ("delaunay", "hxt", "frontal"), default="hxt")
    return MeshSpec(order=order, size=size, algorithm=algorithm)


def _material(raw: Any) -> Material:
    raw = _mapping(raw, "material", ("E", "nu", "rho"), ("E", "nu", "rho"))
    return Material(
        E=_number(raw, "E", "material", lo=0.0, lo_open=True, hi=1e13),
        nu=_number(raw, "nu", "material", lo=-1.0, hi=0.5, lo_open=True, hi_open=True),
        rho=_number(raw, "rho", "material", lo=0.0, lo_open=True, hi=1e6),
    )


def _supports(raw: Any) -> tuple[Support, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise _fail("supports", raw, "a list of {region: NAME, fix: all | [x, y, z]}")
    out = []
    for i, item in enumerate(raw):
        path = f"supports[{i}]"
        item = _mapping(item, path, ("region", "fix"), ("region",))
        region = _name(item, "region", path)
        fix = item.get("fix", "all")
        if fix == "all":
            comps = ("x", "y", "z")
        elif (isinstance(fix, list) and fix and all(c in ("x", "y", "z") for c in fix)
              and len(set(fix)) == len(fix)):
            comps = tuple(sorted(fix))
        else:
            raise _fail(f"{path}.fix", fix, "'all' or a list of distinct components from x, y, z")
        out.append(Support(region=region, fix=comps))
    return tuple(out)


def _regions(raw: Any) -> dict[str, RegionSelector]:
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise _fail("regions", raw, "a mapping of region names to selectors")
    out = {}
    for name, sel in raw.items():
        path = f"regions.{name}"
        if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
            raise _fail("regions", name, "region names of letters, digits, '_', '-' or '.'")
        sel = _mapping(sel, path, ("kind", "point", "normal", "tolerance", "lower", "upper",
                                   "radius"), ("kind",))
        kind = _choice(sel, "kind", path, ("plane", "box", "sphere"))
        if kind == "plane":
            allowed = {"kind", "point", "normal", "tolerance"}
            r = RegionSelector(kind, point=_vector(sel, "point", path),
                               normal=_vector(sel, "normal", path, nonzero=True),
                               tolerance=_number(sel, "tolerance", path, 1e-6, lo=0.0))
        elif kind == "box":
            allowed = {"kind", "lower", "upper"}
            lower, upper = _vector(sel, "lower", path), _vector(sel, "upper", path)
            if any(a > b for a, b in zip(lower, upper)):
                raise _fail(f"{path}.upper", list(upper), f"every component >= lower {list(lower)}")
            r = RegionSelector(kind, lower=lower, upper=upper)
        else:
            allowed = {"kind", "point", "radius"}
            r = RegionSelector(kind, point=_vector(sel, "point", path),
                               radius=_number(sel, "radius", path, lo=0.0, lo_open=True))
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
    raw = _mapping(raw, "ports", ("inputs", "outputs"))
    seen: dict[str, str] = {}
    groups = {}
    for side, kinds in (("inputs", ("force", "moment")), ("outputs", ("displacement", "rotation"))):
        items = []
        for i, item in enumerate(_list(raw, side, "ports")):
            path = f"ports.{side}[{i}]"
            item = _mapping(item, path, ("name", "region", "kind", "direction"),
                            ("name", "region", "kind", "direction"))
            name = _name(item, "name", path)
            if name in seen:
                raise _fail(f"{path}.name", name, f"a name not used already (it names {seen[name]})")
            seen[name] = path
            items.append(Port(name=name, region=_name(item, "region", path),
                              kind=_choice(item, "kind", path, kinds),
                              direction=_vector(item, "direction", path, nonzero=True)))
        groups[side] = tuple(items)
    return Ports(**groups)


def _damping(raw: Any) -> Damping:
    if raw is None:
        return Damping()
    raw = _mapping(raw, "damping", ("kind", "ratio", "ratios", "alpha", "beta"), ("kind",))
    kind = _choice(raw, "kind", "damping", ("uniform", "per_mode", "rayleigh", "none"))
    if kind == "uniform":
        return Damping(kind=kind, ratio=_number(raw, "ratio", "damping", lo=0.0, hi=1.0, hi_open=True))
    if kind == "none":
        return Damping(kind="uniform", ratio=0.0)
    if kind == "per_mode":
        ratios = raw.get("ratios", _MISSING)
        if ratios is _MISSING:
            raise ConfigError("config key 'damping.ratios' is missing; it is required for per_mode")
        if not isinstance(ratios, list) or not ratios:
            raise _fail("damping.ratios", ratios, "a non-empty list of ratios in [0, 1)")
        values = tuple(_number({f"ratios[{i}]": r}, f"ratios[{i}]", "damping", lo=0.0, hi=1.0,
                               hi_open=True) for i, r in enumerate(ratios))
        return Damping(kind=kind, ratio=0.0, ratios=values)
    return Damping(kind=kind, ratio=0.0, alpha=_number(raw, "alpha", "damping", lo=0.0),
                   beta=_number(raw, "beta", "damping", lo=0.0))


def _reduction(raw: Any, modes: Modes) -> Reduction | None:
    if raw is None:
        return None
    raw = _mapping(raw, "reduction", ("modes", "static_correction"), ("modes",))
    n = _integer(raw, "modes", "reduction", lo=1)
    if n > modes.count:
        raise _fail("reduction.modes", n, f"at most modes.count = {modes.count}")
    return Reduction(modes=n, static_correction=_choice(
        raw, "static_correction", "reduction", ("none", "residual", "augment"), default="residual"))


def _filter(raw: Any) -> Filter:
    if raw is None:
        return Filter(kind="none")
    raw = _mapping(raw, "filter", ("kind", "cutoff_hz"), ("kind",))
    kind = _choice(raw, "kind", "filter", ("none", "first_order", "third_order"))
    cutoff = _number(raw, "cutoff_hz", "filter", 2000.0, lo=0.0, lo_open=True, hi=1e9)
    return Filter(kind=kind, cutoff_hz=cutoff)


def _lumped(raw: Any) -> Lumped | None:
    if raw is None:
        return None
    raw = _mapping(raw, "lumped", ("elements", "constants"), ("elements",))
    return Lumped(elements=_integer(raw, "elements", "lumped", lo=1, hi=10000),
                  constants=_choice(raw, "constants", "lumped", ("simple", "refined"), "refined"))


def _connections(raw: Any) -> tuple[Connection, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise _fail("connections", raw, "a list of {name, region, point, coupling}")
    out, seen = [], set()
    for i, item in enumerate(raw):
        path = f"connections[{i}]"
        item = _mapping(item, path, ("name", "region", "point", "coupling"),
                        ("name", "region", "point"))
        name = _name(item, "name", path)
        if name in seen:
            raise _fail(f"{path}.name", name, "a name not used by another connection")
        seen.add(name)
        out.append(Connection(name=name, region=_name(item, "region", path),
                              point=_vector(item, "point", path),
                              coupling=_choice(item, "coupling", path, ("rigid", "distributing"),
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
    raw = _mapping(raw, "", TOP_KEYS, ("name", "geometry", "mesh", "material"))
    geometry = _geometry(raw["geometry"], str(Path(source).parent) if source else "")
    constraints = _mapping(_section(raw, "constraints"), "constraints", ("in_plane",))
    modes_raw = _mapping(_section(raw, "modes"), "modes", ("count", "solver", "tolerance"))
    modes = Modes(count=_integer(modes_raw, "count", "modes", 10, lo=1, hi=500),
                  solver=_choice(modes_raw, "solver", "modes", SOLVERS, "auto"),
                  tolerance=_number(modes_raw, "tolerance", "modes", 0.0, lo=0.0, hi=1e-2))
    regions = _regions(raw.get("regions"))
    for name in regions:
        if geometry.kind == "box" and name in BOX_FACES:
            raise _fail(f"regions.{name}", name, f"a name other than the box's own faces "
                        f"({', '.join(BOX_FACES)})")
    cfg = Config(
        name=_name(raw, "name", ""),
        geometry=geometry,
        mesh=_mesh(raw["mesh"], geometry),
        material=_material(raw["material"]),
        supports=_supports(raw.get("supports")),
        constraints=Constraints(in_plane=_boolean(constraints, "in_plane", "constraints", False)),
        modes=modes,
        regions=regions,
        ports=_ports(raw.get("ports")),
        damping=_damping(raw.get("damping")),
        reduction=_reduction(raw.get("reduction"), modes),
        filter=_filter(raw.get("filter")),
        lumped=_lumped(raw.get("lumped")),
        connections=_connections(raw.get("connections")),
        craig_bampton_modes=_integer(_mapping(_section(raw, "craig_bampton"), "craig_bampton",
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
            raise _fail(path, region, "a region the geometry names or 'regions' defines: "
                        + ", ".join(sorted(known)))
    if cfg.reduction is not None and not (cfg.ports.inputs and cfg.ports.outputs):
        raise _fail("reduction", raw.get("reduction"), "ports with at least one input and one "
                    "output (a reduced model needs both)")
    if cfg.reduction is not None and not cfg.supports \
            and cfg.reduction.static_correction != "none":
        raise _fail("reduction.static_correction", cfg.reduction.static_correction,
                    "'none' for a body without supports (its stiffness matrix is singular: a "
                    "free body has no static deflection to correct with); add supports, e.g. "
                    "supports: [{region: root, fix: all}], or set "
                    "reduction.static_correction: none")
    if cfg.lumped is not None and geometry.kind != "box":
        raise _fail("lumped", raw.get("lumped"), "a box geometry (the lumped chain needs a "
                    f"straight beam; geometry.kind is '{geometry.kind}')")
    if cfg.damping.kind == "per_mode" and cfg.reduction is not None \
            and len(cfg.damping.ratios) < cfg.reduction.modes:
        raise _fail("damping.ratios", list(cfg.damping.ratios),
                    f"at least reduction.modes = {cfg.reduction.modes} ratios")
    return cfg


# --------------------------------------------------------------------------- files
def _safe_loader():
    """yaml.SafeLoader that also reads YAML 1.2 floats such as ``69.0e9`` and ``1e-3``.

    PyYAML follows YAML 1.1, where an exponent needs a sign and a dot, so ``69.0e9``
    would be a string. Safe loading only: no tag constructs a Python object.
    """
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    float_re = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""", re.X)
    Loader.yaml_implicit_resolvers = {k: list(v) for k, v in
                                      yaml.SafeLoader.yaml_implicit_resolvers.items()}
    for first in list("-+0123456789."):
        Loader.yaml_implicit_resolvers[first] = [
            (tag, regexp) for tag, regexp in Loader.yaml_implicit_resolvers.get(first, [])
            if tag != "tag:yaml.org,2002:float"]
    Loader.add_implicit_resolver("tag:yaml.org,2002:float", float_re, list("-+0123456789."))
    return Loader


def _parse_yaml(text: str, where: str) -> Any:
    import yaml

    try:
        return yaml.load(text, Loader=_safe_loader())  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        pos = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        first = (str(exc).splitlines() or [type(exc).__name__])[0]
        problem = getattr(exc, "problem", None) or first
        raise ConfigError(f"{where}: not valid YAML{pos}: {problem}") from None
    except RecursionError:
        raise ConfigError(f"{where}: not valid YAML: nested too deeply") from None
    except (ValueError, OverflowError, TypeError) as exc:
        # a scalar the safe constructors refuse: an int of more than 4300 digits, a date
        # such as 2020-02-30, ...
        problem = (str(exc).splitlines() or [type(exc).__name__])[0][:200]
        if "integer string conversion" in problem:
            problem = "an integer of more than 4300 digits"
        raise ConfigError(f"{where}: not valid YAML: a value cannot be read ({problem})") from None


def _split_path(path: str) -> list[str]:
    parts = [p for p in re.split(r"\.|\[(\d+)\]", path) if p]
    if not parts or any(not re.fullmatch(r"[A-Za-z0-9_\-]+", p) for p in parts):
        shown = path if len(path) <= 80 and path.isprintable() else _describe(path)[1:-1]
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
        raise ConfigError(f"config: got {_describe(raw)}, expected a mapping at the top level")
    for item in overrides:
        if not isinstance(item, str):
            raise ConfigError(f"override {_describe(item)}: expected KEY=VALUE text")
        shown = item if len(item) <= 80 and item.isprintable() else _describe(item)[1:-1]
        if "=" not in item:
            raise ConfigError(f"override '{shown}': expected KEY=VALUE, e.g. mesh.size=0.004")
        key, text = item.split("=", 1)
        parts = _split_path(key.strip())
        value = _parse_yaml(text, f"override '{shown}'")
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
    raw = _parse_yaml(text, f"config file '{path}'")
    if raw is None:
        raise ConfigError(f"config file '{path}': is empty, expected a mapping of config keys")
    if not isinstance(raw, Mapping):
        raise ConfigError(f"config file '{path}': got {_describe(raw)}, expected a mapping of "
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
