"""Plausibility of a config's physical values: unit slips and elements that lock.

Called from the one validator (:func:`pipeline.config.parse.config_from_dict`). Values
that pass the field checks can still be no engineering solid at all: a beam typed in
millimetres (500 "m" long), E typed in MPa or GPa, a density in g/cm^3 or t/mm^3. And
some valid materials make the chosen elements lock (too stiff without a word):

- Volumetric locking: linear tetrahedra cannot deform at constant volume, and with
  lambda / mu = 2 nu / (1 - 2 nu) large (nu -> 0.5) they bend far too stiffly (nu = 0.4999:
  3.7x beam theory). Quadratic tetrahedra tolerate it (nu = 0.4999 within 1 %).
- Shear locking at nu -> -1: mu / K_bulk = 3 (1 - 2 nu) / (2 (1 + nu)) diverges, and even
  quadratic tetrahedra are far too stiff (nu = -0.9999: 6.5x beam theory).

Geometry sizes outside what the pipeline can mesh are refused (:class:`ConfigError`
naming the key and the likely unit) *before* the mesh size is checked, so a length typed
in mm is not blamed on ``mesh.size``. Material values outside what engineering solids
have are warned about through :mod:`logging` (the CLI shows warnings), naming the key and
the likely unit: an unusual material is possible, a run is not refused for it.

Units: lengths m, E Pa, rho kg/m^3, mass kg.
"""

from __future__ import annotations

import logging

from pipeline.config.schema import Config, Geometry
from pipeline.errors import ConfigError

log = logging.getLogger(__name__)

#: largest and smallest body dimension (m) the pipeline meshes (as fe.mesh.common's
#: check_dimensions for drawn geometry)
MAX_EXTENT_M = 50.0
MIN_EXTENT_M = 1e-4
#: Young's modulus of engineering solids, Pa: soft elastomers (~0.1 MPa) to diamond
#: (1.2 TPa)
E_RANGE = (1e5, 1.2e12)
#: density of engineering solids, kg/m^3: structural foams and aerogels to osmium
RHO_RANGE = (5.0, 2.3e4)
#: mass of one body, kg
MASS_RANGE = (1e-9, 1e6)
#: linear tetrahedra lock from this lambda / mu on (nu = 0.4545: bending > 10 % too stiff
#: on the cantilever); quadratic ones from LOCKING_RATIO_P2
LOCKING_RATIO_P1 = 10.0
LOCKING_RATIO_P2 = 1e4
#: shear locking: mu / K_bulk above this (nu < -0.955)
SHEAR_LOCKING_RATIO = 100.0

_LENGTH_UNITS = ((1e-3, "mm"), (1e-2, "cm"), (1e-6, "micrometres"))


def check_geometry(geometry: Geometry) -> None:
    """Refuse box dimensions no machine part has (largest outside MIN_EXTENT_M to
    MAX_EXTENT_M), naming the key and the likely unit."""
    if geometry.kind != "box":
        return  # drawn geometry: checked after reading (fe.mesh.common.check_dimensions)
    dims = {"length": geometry.length, "height": geometry.height, "depth": geometry.depth}
    largest_key = max(dims, key=dims.get)
    largest = dims[largest_key]
    if largest < MIN_EXTENT_M:  # as drawn geometry (fe.mesh.common.check_dimensions)
        hint = _unit_hint(largest, MIN_EXTENT_M, MAX_EXTENT_M,
                          ((1e3, "km (lengths are in m)"),))
        raise ConfigError(
            f"config key 'geometry.{largest_key}': got {largest:g} m as the body's largest "
            f"dimension, expected at least {MIN_EXTENT_M:g} m (the smallest body the pipeline "
            f"meshes){hint}", key=f"geometry.{largest_key}", value=largest,
            expected=f"at least {MIN_EXTENT_M:g} m")
    if largest > MAX_EXTENT_M:
        hint = ""
        for factor, unit in _LENGTH_UNITS:
            if MIN_EXTENT_M <= largest * factor <= MAX_EXTENT_M:
                hint = (f"; it looks typed in {unit}: geometry lengths are in m, e.g. "
                        f"{largest_key}: {largest * factor:g}")
                break
        raise ConfigError(
            f"config key 'geometry.{largest_key}': got {largest:g} m, expected a body no "
            f"larger than {MAX_EXTENT_M:g} m{hint}",
            key=f"geometry.{largest_key}", value=largest,
            expected=f"at most {MAX_EXTENT_M:g} m")


def _unit_hint(value: float, lo: float, hi: float, units: tuple[tuple[float, str], ...]
               ) -> str:
    fits = [unit for factor, unit in units if lo <= value * factor <= hi]
    return f"; likely typed in {' or '.join(fits)}" if fits else ""


def material_warnings(cfg: Config) -> list[str]:
    """Warnings on E, rho and the box mass outside engineering solids, and on locking."""
    mat = cfg.material
    out = []
    if mat is None:  # ``materials`` claim every element: their ranges were checked on parsing
        return out
    if not E_RANGE[0] <= mat.E <= E_RANGE[1]:
        hint = _unit_hint(mat.E, *E_RANGE, ((1e6, "MPa (E is in Pa: multiply by 1e6)"),
                                            (1e9, "GPa (E is in Pa: multiply by 1e9)"),
                                            (1e3, "kPa")))
        out.append(f"config key 'material.E' = {mat.E:g} Pa is outside what engineering "
                   f"solids have ({E_RANGE[0]:g} to {E_RANGE[1]:g} Pa){hint}")
    if not RHO_RANGE[0] <= mat.rho <= RHO_RANGE[1]:
        hint = _unit_hint(mat.rho, *RHO_RANGE,
                          ((1e3, "g/cm^3 (rho is in kg/m^3: multiply by 1000)"),
                           (1e12, "t/mm^3 (rho is in kg/m^3: multiply by 1e12)")))
        out.append(f"config key 'material.rho' = {mat.rho:g} kg/m^3 is outside what "
                   f"engineering solids have ({RHO_RANGE[0]:g} to {RHO_RANGE[1]:g} kg/m^3)"
                   f"{hint}")
    g = cfg.geometry
    if g.kind == "box":
        mass = mat.rho * g.length * g.height * g.depth
        if not MASS_RANGE[0] <= mass <= MASS_RANGE[1]:
            out.append(f"the body's mass rho * length * height * depth = {mass:.3g} kg is "
                       f"outside {MASS_RANGE[0]:g} to {MASS_RANGE[1]:g} kg: check the units "
                       "of 'material.rho' (kg/m^3) and the geometry lengths (m)")
    nu = mat.nu
    lam_over_mu = 2 * nu / (1 - 2 * nu)
    limit = LOCKING_RATIO_P1 if cfg.mesh.order == 1 else LOCKING_RATIO_P2
    if lam_over_mu > limit:
        out.append(f"config key 'material.nu' = {nu:g} with mesh.order {cfg.mesh.order}: "
                   f"nearly incompressible (lambda/mu = {lam_over_mu:.3g}), the "
                   + ("linear tetrahedra lock and the body comes out far too stiff (nu = "
                      "0.4999: 3.7x); use mesh.order: 2"
                      if cfg.mesh.order == 1 else
                      "quadratic tetrahedra start to lock; use nu <= 0.4999")
                   + " (a truly incompressible solid needs a mixed formulation this "
                   "pipeline does not have)")
    mu_over_k = 3 * (1 - 2 * nu) / (2 * (1 + nu))
    if mu_over_k > SHEAR_LOCKING_RATIO:
        out.append(f"config key 'material.nu' = {nu:g}: shear modulus / bulk modulus = "
                   f"{mu_over_k:.3g}, the elements lock and the body comes out far too stiff "
                   "(nu = -0.9999: 6.5x beam theory); no engineering solid has nu < -0.9, "
                   "use a value above -0.95")
    return out


def check_plausibility(cfg: Config) -> tuple[str, ...]:
    """Refuse ports that act on nothing (:func:`check_ports`); log every plausibility
    warning for ``cfg`` (logging.WARNING) and return them."""
    check_ports(cfg)
    warnings = tuple(material_warnings(cfg) + check_lumped(cfg) + materials_warnings(cfg))
    for message in warnings:
        log.warning("%s", message)
    return warnings


def check_ports(cfg: Config) -> None:
    """Refuse, before any work, a port that can load or measure nothing: on a region the
    supports hold in every direction, or a force/displacement along z alone when
    constraints.in_plane removes u_z. (The reduce stage checks the assembled port
    matrices as well, for the cases only the mesh shows.)"""
    held = {s.region for s in cfg.supports if set(s.fix) >= {"x", "y", "z"}}
    for side, items in (("inputs", cfg.ports.inputs), ("outputs", cfg.ports.outputs)):
        for port in items:
            why = ""
            if port.region in held:
                why = f"region '{port.region}' is held by the supports in every direction"
            elif (cfg.constraints.in_plane and port.kind in ("force", "displacement")
                  and abs(port.direction[0]) == 0 and abs(port.direction[1]) == 0):
                why = "its direction is z, which constraints.in_plane removes (u_z = 0)"
            if why:
                verb = "loads" if side == "inputs" else "measures"
                raise ConfigError(
                    f"config key 'ports.{side}' ({side[:-1]} port '{port.name}'): this port "
                    f"{verb} nothing ({why}); put it on a region that can move, along a "
                    "direction the supports and constraints leave free",
                    key=f"ports.{side}", value=port.name)


def check_lumped(cfg: Config) -> list[str]:
    """The lumped chain is a beam clamped at the root face (x = 0). Refuse it beside a free
    body (no supports): the file would hold a clamped chain next to a free body. Other
    supports than root fixed in all directions give a warning (returned)."""
    if cfg.lumped is None:
        return []
    if not cfg.supports:
        raise ConfigError(
            "config key 'lumped': a lumped chain for a body without supports; the chain is "
            "a beam clamped at its root face, not the free body this config describes: "
            "remove 'lumped' (lumped: null) or clamp the body (supports: [{region: root, "
            "fix: all}])", key="lumped", value="set", expected="supports or no lumped chain")
    if [(s.region, set(s.fix)) for s in cfg.supports] != [("root", {"x", "y", "z"})]:
        return ["config key 'lumped': the chain is a beam clamped at root in all directions, "
                "but this body's supports differ; its comparison with the FE body is not "
                "like for like"]
    return []


def materials_warnings(cfg: Config) -> list[str]:
    """Warnings on the moduli and densities of ``materials`` entries outside engineering
    solids (a unit slip: MPa or GPa for Pa, g/cm^3 for kg/m^3)."""
    out = []
    for i, m in enumerate(cfg.materials):
        key = f"materials[{i}]"
        moduli = {"isotropic": [("E", m.E)], "orthotropic": list(zip(("E[0]", "E[1]", "E[2]"),
                  m.moduli or ()))}.get(m.kind, [])
        for name, E in moduli:
            if not E_RANGE[0] <= E <= E_RANGE[1]:
                out.append(f"config key '{key}.{name}' = {E:g} Pa is outside what engineering "
                           f"solids have ({E_RANGE[0]:g} to {E_RANGE[1]:g} Pa)"
                           + _unit_hint(E, *E_RANGE, ((1e6, "MPa (multiply by 1e6)"),
                                                      (1e9, "GPa (multiply by 1e9)"))))
        if not RHO_RANGE[0] <= m.rho <= RHO_RANGE[1]:
            out.append(f"config key '{key}.rho' = {m.rho:g} kg/m^3 is outside what "
                       f"engineering solids have ({RHO_RANGE[0]:g} to {RHO_RANGE[1]:g} kg/m^3)"
                       + _unit_hint(m.rho, *RHO_RANGE, ((1e3, "g/cm^3 (multiply by 1000)"),)))
    return out
