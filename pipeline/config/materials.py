"""Config records and parsing of the ``materials:`` and ``masses:`` sections.

``materials`` is a list of material laws, each claiming elements (tetrahedra) by an
element selector; the first entry that claims an element gives its material, elements no
entry claims take ``material:`` (the default). Laws (Pa, kg/m^3):

- ``isotropic``: E, nu;
- ``orthotropic``: E = [E1, E2, E3], nu = [nu12, nu13, nu23], G = [G12, G13, G23] in the
  material frame ``axes`` (x: material axis 1, y: axis 2 in global coordinates; axis 3 =
  1 x 2; or ``axes: <name>``, a system of ``coordinate_systems``, :mod:`pipeline.config.frames`);
  the compliance S (Voigt order 11, 22, 33, 23, 13, 12, engineering shear) has
  S_11 = 1/E1, S_12 = -nu12/E1, S_13 = -nu13/E1, S_23 = -nu23/E2, S_44 = 1/G23,
  S_55 = 1/G13, S_66 = 1/G12, and it must be positive definite;
- ``transversely_isotropic``: the orthotropic law with axis 1 the fibre and 2-3 the plane
  of isotropy: E = [E1, E2], nu = [nu12, nu23], G = G12 (E3 = E2, nu13 = nu12, G13 = G12,
  G23 = E2 / (2 (1 + nu23)));
- ``anisotropic``: ``stiffness``, the 6x6 D (Voigt order above, engineering shear strain:
  sigma = D gamma) in the material frame ``axes``, symmetric positive definite.

Element selectors (``elements``): ``all``; a name (a volume group or element set of the
mesh file); ``{kind: box, lower, upper}`` or ``{kind: sphere, point, radius}`` applied to
element centroids.

``masses`` is a list of added masses:

- ``kind: point`` (default): a rigid ``mass`` (kg) with ``inertia`` [Ixx, Iyy, Izz, Ixy,
  Ixz, Iyz] (kg m^2, about ``point``, products of inertia as tensor entries I_xy =
  -int x y dm) at ``point``, tied to the boundary ``region`` by a ``distributing`` coupling
  (RBE3: mass, no stiffness) or a ``rigid`` one (RBE2: the region's nodes follow the
  point's six motions exactly, :mod:`pipeline.fe.constraints`);
- ``kind: area``: ``density`` kg/m^2 spread over the boundary ``region``;
- ``kind: volume``: ``density`` kg/m^3 added to rho of the ``elements`` selected.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Mapping

import numpy as np

from pipeline._util import validate as v
from pipeline.errors import ConfigError

MaterialKind = Literal["isotropic", "orthotropic", "transversely_isotropic", "anisotropic"]
MATERIAL_KINDS = ("isotropic", "orthotropic", "transversely_isotropic", "anisotropic")
MassKind = Literal["point", "area", "volume"]
MASS_KINDS = ("point", "area", "volume")


@dataclass(frozen=True)
class ElementSelector:
    """Elements claimed: ``all``; ``group`` (``name``: a volume group of the mesh);
    ``box`` (lower <= centroid <= upper); ``sphere`` (|centroid - point| <= radius), m."""

    kind: Literal["all", "group", "box", "sphere"] = "all"
    name: str = ""
    lower: tuple[float, float, float] | None = None
    upper: tuple[float, float, float] | None = None
    point: tuple[float, float, float] | None = None
    radius: float | None = None


@dataclass(frozen=True)
class MaterialEntry:
    """One material of ``materials:`` (module docstring): ``name``, law ``kind``, ``rho``
    kg/m^3, the constants of the law (Pa) and the elements it claims.

    isotropic: E, nu. orthotropic: moduli (E1, E2, E3), poisson (nu12, nu13, nu23),
    shear (G12, G13, G23) (transversely isotropic entries are stored expanded to this).
    anisotropic: stiffness, 6 rows of 6 (Pa). axes: rows material axes 1, 2, 3 in global
    coordinates (unit, right-handed); frame: the ``coordinate_systems`` name they came
    from ("" when given inline).
    """

    name: str
    elements: ElementSelector
    rho: float
    kind: MaterialKind = "isotropic"
    E: float = 0.0
    nu: float = 0.0
    moduli: tuple[float, float, float] | None = None
    poisson: tuple[float, float, float] | None = None
    shear: tuple[float, float, float] | None = None
    stiffness: tuple[tuple[float, ...], ...] | None = None
    axes: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                                                    (0.0, 0.0, 1.0))
    frame: str = ""  # the coordinate system ``axes`` named ("": given inline)
    cylinder: tuple[tuple[float, ...], tuple[float, ...]] | None = None  # cylindrical frame: (unit axis, point m)


@dataclass(frozen=True)
class AddedMass:
    """One entry of ``masses:`` (module docstring). point: mass kg, inertia (Ixx, Iyy, Izz,
    Ixy, Ixz, Iyz) kg m^2 about ``point`` m, ``region``, ``coupling``; area: ``density``
    kg/m^2 on ``region``; volume: ``density`` kg/m^3 on ``elements``."""

    name: str
    kind: MassKind = "point"
    mass: float = 0.0
    inertia: tuple[float, ...] = (0.0,) * 6
    point: tuple[float, float, float] | None = None
    region: str = ""
    coupling: Literal["distributing", "rigid"] = "distributing"
    density: float = 0.0
    elements: ElementSelector | None = None


# --------------------------------------------------------------------------- laws
def orthotropic_compliance(moduli, poisson, shear) -> np.ndarray:
    """(6, 6) compliance S (1/Pa) in the material frame, Voigt order 11, 22, 33, 23, 13,
    12, engineering shear: gamma = S sigma."""
    E1, E2, E3 = moduli
    n12, n13, n23 = poisson
    G12, G13, G23 = shear
    S = np.zeros((6, 6))
    S[0, 0], S[1, 1], S[2, 2] = 1 / E1, 1 / E2, 1 / E3
    S[0, 1] = S[1, 0] = -n12 / E1
    S[0, 2] = S[2, 0] = -n13 / E1
    S[1, 2] = S[2, 1] = -n23 / E2
    S[3, 3], S[4, 4], S[5, 5] = 1 / G23, 1 / G13, 1 / G12
    return S


def material_frame(axes) -> np.ndarray:
    """(3, 3) Q with columns the material axes 1, 2, 3 in global coordinates."""
    return np.asarray(axes, dtype=float).T


def frame_axes(raw: Any, path: str) -> tuple[tuple[float, float, float], ...]:
    """Orthonormal axes from {x: axis 1, y: axis 2} (y made orthogonal to x by
    Gram-Schmidt only if it already is, to 1e-9: a skew y is refused)."""
    if raw is None:
        return MaterialEntry.axes
    raw = v.mapping(raw, path, ("x", "y"), ("x", "y"))
    a = np.array(v.vector(raw, "x", path, nonzero=True))
    b = np.array(v.vector(raw, "y", path, nonzero=True))
    a /= np.linalg.norm(a)
    b /= np.linalg.norm(b)
    if abs(a @ b) > 1e-9:
        raise v.fail(f"{path}.y", raw["y"], "a direction orthogonal to axes.x (material axis 2 "
                    "at right angles to axis 1)")
    c = np.cross(a, b)
    return tuple(tuple(float(t) for t in row) for row in (a, b, c))


def _triple(raw: Mapping, key: str, path: str, n: int = 3, lo: float | None = None,
            lo_open: bool = True) -> tuple[float, ...]:
    value = raw.get(key, v.MISSING)
    if value is v.MISSING:
        raise v.missing(f"{path}.{key}")
    if not isinstance(value, list) or len(value) != n:
        raise v.fail(f"{path}.{key}", value, f"a list of {n} numbers")
    return tuple(v.number({f"{key}[{i}]": x}, f"{key}[{i}]", path, lo=lo, lo_open=lo_open,
                          hi=1e13) for i, x in enumerate(value))


def check_positive_definite(D: np.ndarray, path: str, what: str) -> None:
    """Refuse a (6, 6) matrix that is not symmetric (to 1e-9 of its largest entry) or not
    positive definite, naming the smallest eigenvalue."""
    scale = float(np.max(np.abs(D))) or 1.0
    asym = float(np.max(np.abs(D - D.T)))
    if asym > 1e-9 * scale:
        i, j = np.unravel_index(int(np.argmax(np.abs(D - D.T))), D.shape)
        raise ConfigError(f"config key '{path}': the {what} is not symmetric (entry [{i}][{j}] = "
                          f"{D[i, j]:g} but [{j}][{i}] = {D[j, i]:g}); expected a symmetric "
                          "6x6 matrix", key=path, expected="a symmetric 6x6 matrix")
    w = np.linalg.eigvalsh(0.5 * (D + D.T))
    if not w[0] > 1e-12 * w[-1]:
        raise ConfigError(f"config key '{path}': the {what} has eigenvalue {w[0]:.6g} (largest "
                          f"{w[-1]:.6g}); expected a positive definite matrix (every eigenvalue "
                          "> 1e-12 x the largest)", key=path,
                          expected="a positive definite 6x6 matrix")


def _selector(raw: Any, path: str) -> ElementSelector:
    if raw == "all":
        return ElementSelector("all")
    if isinstance(raw, str):
        return ElementSelector("group", name=v.name({"elements": raw}, "elements",
                                                    path.rsplit(".", 1)[0]))
    raw = v.mapping(raw, path, ("kind", "lower", "upper", "point", "radius"), ("kind",))
    kind = v.choice(raw, "kind", path, ("box", "sphere"))
    keys = {"box": {"kind", "lower", "upper"}, "sphere": {"kind", "point", "radius"}}[kind]
    extra = sorted(set(raw) - keys)
    if extra:
        raise ConfigError(f"config key '{path}.{extra[0]}' does not apply to a '{kind}' element "
                          f"selector; expected one of: {', '.join(sorted(keys))}")
    if kind == "box":
        lower, upper = v.vector(raw, "lower", path), v.vector(raw, "upper", path)
        if any(a > b for a, b in zip(lower, upper)):
            raise v.fail(f"{path}.upper", list(upper), f"every component >= lower {list(lower)}")
        return ElementSelector("box", lower=lower, upper=upper)
    return ElementSelector("sphere", point=v.vector(raw, "point", path),
                           radius=v.number(raw, "radius", path, lo=0.0, lo_open=True))


_MATERIAL_KEYS = ("name", "kind", "E", "nu", "G", "rho", "axes", "stiffness", "elements")


def _entry_axes(raw: Any, path: str, systems: Mapping) -> tuple[tuple, str, tuple | None]:
    """(axes, name, cylinder) of an entry's ``axes``: inline {x, y} (name "") or the name
    of a ``coordinate_systems`` entry (its axes; cylinder: (axis, point) of a
    cylindrical system, else None)."""
    if not isinstance(raw, str):
        return frame_axes(raw, path), "", None
    if raw not in systems:
        raise v.fail(path, raw, "{x: [..], y: [..]} or the name of a coordinate system: "
                     + (", ".join(sorted(systems)) or "(coordinate_systems defines none)"))
    cs = systems[raw]
    return cs.axes, raw, ((cs.axis, cs.point) if cs.kind == "cylindrical" else None)


def _material_entry(raw: Any, path: str, systems: Mapping = {}) -> MaterialEntry:
    raw = v.mapping(raw, path, _MATERIAL_KEYS, ("name", "rho", "elements"))
    kind = v.choice(raw, "kind", path, MATERIAL_KINDS, "isotropic")
    allowed = {"isotropic": {"E", "nu"}, "orthotropic": {"E", "nu", "G", "axes"},
               "transversely_isotropic": {"E", "nu", "G", "axes"},
               "anisotropic": {"stiffness", "axes"}}[kind] | {"name", "kind", "rho", "elements"}
    extra = sorted(set(raw) - allowed)
    if extra:
        raise ConfigError(f"config key '{path}.{extra[0]}' does not apply to a '{kind}' "
                          f"material; expected one of: {', '.join(sorted(allowed))}")
    common = dict(name=v.name(raw, "name", path), kind=kind,
                  rho=v.number(raw, "rho", path, lo=0.0, lo_open=True, hi=1e6),
                  elements=_selector(raw["elements"], f"{path}.elements"))
    if kind == "isotropic":
        return MaterialEntry(**common, E=v.number(raw, "E", path, lo=0.0, lo_open=True, hi=1e13),
                             nu=v.number(raw, "nu", path, lo=-1.0, hi=0.5, lo_open=True,
                                         hi_open=True))
    axes, frame, cylinder = _entry_axes(raw.get("axes"), f"{path}.axes", systems)
    if kind == "anisotropic":
        rows = raw.get("stiffness", v.MISSING)
        if rows is v.MISSING:
            raise v.missing(f"{path}.stiffness")
        if not (isinstance(rows, list) and len(rows) == 6
                and all(isinstance(r, list) and len(r) == 6 for r in rows)):
            raise v.fail(f"{path}.stiffness", rows, "6 rows of 6 numbers (Pa, Voigt order xx, "
                        "yy, zz, yz, xz, xy, engineering shear)")
        D = tuple(_triple({"stiffness": r}, "stiffness", f"{path}.stiffness[{i}]", 6, lo=None)
                  for i, r in enumerate(rows))
        check_positive_definite(np.array(D), f"{path}.stiffness", "stiffness matrix")
        return MaterialEntry(**common, stiffness=D, axes=axes, frame=frame,
                             cylinder=cylinder)
    if kind == "orthotropic":
        moduli = _triple(raw, "E", path)
        poisson = _triple(raw, "nu", path, lo=-1e3, lo_open=False)
        shear = _triple(raw, "G", path)
    else:
        E1, E2 = _triple(raw, "E", path, 2)
        n12, n23 = _triple(raw, "nu", path, 2, lo=-1.0)
        G12 = v.number(raw, "G", path, lo=0.0, lo_open=True, hi=1e13)
        moduli, poisson, shear = (E1, E2, E2), (n12, n12, n23), (G12, G12, E2 / (2 * (1 + n23)))
    check_positive_definite(orthotropic_compliance(moduli, poisson, shear), path,
                            "compliance matrix of the engineering constants")
    common["kind"] = "orthotropic"  # transversely isotropic: stored as its expansion
    return MaterialEntry(**common, moduli=moduli, poisson=poisson,
                         shear=shear, axes=axes, frame=frame, cylinder=cylinder)


def parse_materials(raw: Any, systems: Mapping = {}) -> tuple[MaterialEntry, ...]:
    """The ``materials:`` list (None: none); ``systems``: the named coordinate systems
    (:mod:`pipeline.config.frames`) an entry's ``axes`` may name."""
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise v.fail("materials", raw, "a list of {name, E, nu, rho, elements, ...}")
    out, seen = [], {}
    for i, item in enumerate(raw):
        entry = _material_entry(item, f"materials[{i}]", systems)
        if entry.name in seen:
            raise v.fail(f"materials[{i}].name", entry.name, f"a name not used already (it "
                        f"names materials[{seen[entry.name]}])")
        seen[entry.name] = i
        out.append(entry)
    return tuple(out)


_MASS_KEYS = {"point": ("name", "kind", "mass", "inertia", "point", "region", "coupling"),
              "area": ("name", "kind", "density", "region"),
              "volume": ("name", "kind", "density", "elements")}


def parse_masses(raw: Any) -> tuple[AddedMass, ...]:
    """The ``masses:`` list (None: none)."""
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise v.fail("masses", raw, "a list of {name, mass, inertia, point, region, coupling}")
    out, seen = [], set()
    for i, item in enumerate(raw):
        path = f"masses[{i}]"
        kind = v.choice(v.mapping(item, path, sorted(set().union(*_MASS_KEYS.values()))),
                        "kind", path, MASS_KINDS, "point")
        required = {"point": ("name", "mass", "point", "region"), "area": ("name", "density",
                    "region"), "volume": ("name", "density", "elements")}[kind]
        item = v.mapping(item, path, _MASS_KEYS[kind], required)
        name = v.name(item, "name", path)
        if name in seen:
            raise v.fail(f"{path}.name", name, "a name not used by another mass")
        seen.add(name)
        if kind == "point":
            inertia = _triple(item, "inertia", path, 6, lo=None) if "inertia" in item else (0.0,) * 6
            J = np.array([[inertia[0], inertia[3], inertia[4]], [inertia[3], inertia[1],
                          inertia[5]], [inertia[4], inertia[5], inertia[2]]])
            w = np.linalg.eigvalsh(J)  # principal moments: >= 0, I1 + I2 >= I3 (a body)
            tol = 1e-9 * max(1e-30, float(np.abs(J).max()))
            if w[0] < -tol or w[0] + w[1] < w[2] - tol:
                raise v.fail(f"{path}.inertia", list(inertia), "an inertia tensor that is "
                            "positive semi-definite (Ixx, Iyy, Izz >= 0 satisfying the "
                            "triangle inequalities)")
            coupling = v.choice(item, "coupling", path, ("distributing", "rigid"), "distributing")
            point = v.vector(item, "point", path)
            if max(abs(c) for c in point) > 1e6:  # its rigid fit would overflow
                raise v.fail(f"{path}.point", list(point), "a point within 1e6 m of the origin")
            out.append(AddedMass(name=name, kind=kind,
                                 mass=v.number(item, "mass", path, lo=0.0, lo_open=True, hi=1e9),
                                 inertia=inertia, point=point,
                                 region=v.name(item, "region", path), coupling=coupling))
        elif kind == "area":
            out.append(AddedMass(name=name, kind=kind, region=v.name(item, "region", path),
                                 density=v.number(item, "density", path, lo=0.0, lo_open=True,
                                                  hi=1e9)))
        else:
            out.append(AddedMass(name=name, kind=kind, elements=_selector(
                item["elements"], f"{path}.elements"), density=v.number(
                item, "density", path, lo=0.0, lo_open=True, hi=1e6)))
    return tuple(out)


def lumped_mass_problem(height: float, depth: float, masses) -> tuple[str, Any, str] | None:
    """(key, value, expected) of the first ``masses`` entry the lumped chain cannot carry,
    or None: the chain takes point masses on the beam axis (y = height/2, z = depth/2)
    with principal inertia along x, y, z (they keep its joint families uncoupled)."""
    tol = 1e-9 * max(height, depth)
    for i, m in enumerate(masses):
        if m.kind != "point":
            return (f"masses[{i}].kind", m.kind, "point with a lumped chain (it carries "
                    "point masses only)")
        if abs(m.point[1] - height / 2) > tol or abs(m.point[2] - depth / 2) > tol:
            return (f"masses[{i}].point", list(m.point), f"a point on the beam axis (y = "
                    f"{height / 2:g}, z = {depth / 2:g}) with a lumped chain")
        if any(m.inertia[3:]):
            return (f"masses[{i}].inertia", list(m.inertia), "no products of inertia with a "
                    "lumped chain (principal axes along x, y, z)")
    return None


# --------------------------------------------------------------------------- YAML back
def selector_dict(sel: ElementSelector) -> Any:
    """An element selector as its YAML value."""
    if sel.kind == "all":
        return "all"
    if sel.kind == "group":
        return sel.name
    if sel.kind == "box":
        return {"kind": "box", "lower": list(sel.lower), "upper": list(sel.upper)}
    return {"kind": "sphere", "point": list(sel.point), "radius": sel.radius}


def material_dict(m: MaterialEntry) -> dict:
    """A material entry as its YAML keys (load of it gives back an equal entry)."""
    out: dict[str, Any] = {"name": m.name, "kind": m.kind}
    if m.kind == "isotropic":
        out.update(E=m.E, nu=m.nu)
    elif m.kind == "orthotropic":
        out.update(E=list(m.moduli), nu=list(m.poisson), G=list(m.shear))
    else:
        out["stiffness"] = [list(r) for r in m.stiffness]
    if m.kind != "isotropic":
        out["axes"] = m.frame or {"x": list(m.axes[0]), "y": list(m.axes[1])}
    out.update(rho=m.rho, elements=selector_dict(m.elements))
    return out


def mass_dict(m: AddedMass) -> dict:
    """An added mass as its YAML keys."""
    if m.kind == "point":
        return {"name": m.name, "kind": "point", "mass": m.mass, "inertia": list(m.inertia),
                "point": list(m.point), "region": m.region, "coupling": m.coupling}
    if m.kind == "area":
        return {"name": m.name, "kind": "area", "density": m.density, "region": m.region}
    return {"name": m.name, "kind": "volume", "density": m.density,
            "elements": selector_dict(m.elements)}

