"""What double precision can compute: config values the field checks accept but no
floating-point run can carry through, refused before any meshing or assembly.

Each bound follows from the arithmetic of the pipeline, not from what engineering solids
are (that is :mod:`pipeline.config.plausibility`, which only warns):

- **Relative tolerances.** A double carries 53 bits (eps = 2.2e-16). An eigen residual or
  an integrator's local error is a difference of quantities of size ~1 computed with at
  least a few hundred roundings (a sparse solve, one Runge-Kutta step of many terms), so a
  relative tolerance below :data:`MIN_RELATIVE_TOLERANCE` = 1e-13 (about 450 eps) cannot be
  met: the iteration then runs to its step limit and fails (``modes.tolerance = 1e-300``:
  block Lanczos ran 261 steps to a residual of 1.5e-16 and gave up; an integrator's
  ``rtol = 1e-14`` took minutes).
- **Products that must stay normal doubles.** Element stiffness entries scale as E h,
  mass entries as rho h^3, eigenvalues as omega^2 ~ E / (rho h^2) (h: an element's size,
  from half the mesh size (quadratic nodes) up to the body's extent). The solvers form
  norms and Rayleigh quotients, i.e. squares of these, so each must lie within
  [:data:`FLOAT_FLOOR`, :data:`FLOAT_CEILING`] = [1e-150, 1e150], whose squares are normal
  doubles (2.2e-308 to 1.8e308) with margin for sums over n terms. A density of 1e-300
  (rho h^3 ~ 1e-306, subnormal) failed in the dense eigen solve; E = 1e-300 likewise.
  Inside the range a run is exact up to scaling: frequencies follow sqrt(E / rho) / L
  (``tests/test_hostile_values.py`` checks E and rho scaled by 1e-135 together).
- **Element shapes.** gmsh's OpenCASCADE kernel merges points closer than 1e-7 m, so a
  body dimension below :data:`MIN_THICKNESS_M` = 1e-6 m cannot be drawn (a box 1e-7 m thin:
  "OpenCASCADE exception"). An element of size s across a layer of thickness t has aspect
  ratio s / t; its stiffness spreads as (s / t)^2, on top of the mesh's own (L / s)^2 <=
  5000^2, and above :data:`MAX_ASPECT` = 1000 the factorisation of K loses the digits that
  hold the body together (a 0.5 m box 1e-6 m thin at mesh.size 0.02: aspect 2e4, "the
  stiffness system is singular"; aspect 2000 still solved). So mesh.size <= 1000 t, and as
  mesh.size >= L / 5000, the thinnest dimension t >= L / 5e6.
- **Filter gains.** The third-order filter's gains are K, K^2, K^3 (K = 2 pi cutoff_hz):
  K^3 >= FLOAT_FLOOR, so cutoff_hz >= 1.6e-51 Hz (1e-300 Hz underflowed its poles to 0).
- **Points.** Selector, gauge and connection coordinates (and radii, tolerances) up to
  :data:`MAX_COORDINATE_M` = 1e150 m, whose squares stay finite (a gauge point at 1e300 m
  ended in an IndexError, a selector at 1e300 m in an overflow warning); a connection
  point within :data:`MAX_CONNECTION_REACH` = 1e4 body sizes.
- **Near-incompressible materials.** lambda / mu = 2 nu / (1 - 2 nu): above
  :data:`MAX_LAMBDA_OVER_MU` = 1e8 the shear stiffness mu is below 1e-8 of the volumetric
  stiffness in every element and is lost in the factorisation's roundoff together with the
  mesh's own conditioning (nu = 0.5 - 6e-17: "the stiffness matrix is singular"). So
  nu <= 0.499999995.

Units: lengths m, E Pa, rho kg/m^3, omega rad/s.
"""

from __future__ import annotations

import math

from pipeline.config.plausibility import MAX_EXTENT_M, MIN_EXTENT_M
from pipeline.config.schema import Config, Geometry
from pipeline.errors import ConfigError

#: smallest relative tolerance of an eigen residual or an integrator step (see above)
MIN_RELATIVE_TOLERANCE = 1e-13
#: E h, rho h^3 and omega^2 stay within this range (their squares are normal doubles)
FLOAT_FLOOR = 1e-150
FLOAT_CEILING = 1e150
#: thinnest body dimension gmsh/OpenCASCADE draws (10x its 1e-7 m confusion tolerance)
MIN_THICKNESS_M = 1e-6
#: largest element aspect ratio (mesh.size over the thinnest dimension) K stays solvable at
MAX_ASPECT = 1000.0
#: finest mesh relative to the body (as pipeline.config.parse's mesh.size check)
MAX_ELEMENTS_ALONG = 5000.0
#: finest element of drawn or read geometry: half of the smallest body (1e-4 m) over
#: MAX_ELEMENTS_ALONG
MIN_ELEMENT_M = 0.5 * MIN_EXTENT_M / MAX_ELEMENTS_ALONG
#: largest |coordinate| (m) of a selector, gauge or connection point: squared distances
#: (|x - p|^2, the selectors' test) must stay finite doubles
MAX_COORDINATE_M = 1e150
#: a connection point at distance r from a body of size L gives it the inertia m r^2
#: next to the body's own ~m L^2; the residual mass D_P - L_P^T L_P cancels (r / L)^2 of
#: its digits, so r <= 1e4 L keeps 8 of them
MAX_CONNECTION_REACH = 1e4
#: lambda / mu beyond which the shear stiffness is lost in roundoff
MAX_LAMBDA_OVER_MU = 1e8
#: the largest nu that keeps lambda / mu <= MAX_LAMBDA_OVER_MU
MAX_NU = MAX_LAMBDA_OVER_MU / (2.0 * (MAX_LAMBDA_OVER_MU + 1.0))


def check_box_thickness(geometry: Geometry) -> None:
    """Refuse a box dimension too thin to mesh (see the module docstring), naming it."""
    if geometry.kind != "box":
        return
    dims = {"length": geometry.length, "height": geometry.height, "depth": geometry.depth}
    key = min(dims, key=dims.get)
    thinnest, largest = dims[key], max(dims.values())
    need = max(MIN_THICKNESS_M, largest / (MAX_ELEMENTS_ALONG * MAX_ASPECT))
    if thinnest < need:
        raise ConfigError(
            f"config key 'geometry.{key}': got {thinnest:g} m, expected at least {need:g} m "
            f"(gmsh cannot draw a body thinner than {MIN_THICKNESS_M:g} m, and elements of "
            f"the finest mesh.size allowed, {largest:g} / {MAX_ELEMENTS_ALONG:g} m, flatter "
            f"than {MAX_ASPECT:g}:1 make the stiffness matrix singular)",
            key=f"geometry.{key}", value=thinnest, expected=f"at least {need:g} m")


def check_numerics(cfg: Config) -> None:
    """Refuse, naming the key, the value and the range that works, what double precision
    cannot carry: mesh elements too flat, E, rho and omega^2 outside [1e-150, 1e150],
    nu too close to 0.5, an eigen tolerance below 1e-13 (see the module docstring)."""
    _check_aspect(cfg)
    _check_material(cfg)
    _check_points(cfg)
    _check_filter(cfg)
    tol = cfg.modes.tolerance
    if 0.0 < tol < MIN_RELATIVE_TOLERANCE:
        raise ConfigError(
            f"config key 'modes.tolerance': got {tol:g}, expected 0 (the solver's default) "
            f"or a relative residual of at least {MIN_RELATIVE_TOLERANCE:g} (double precision "
            "cannot resolve less: the solver would run to its step limit)",
            key="modes.tolerance", value=tol, expected=f"0 or >= {MIN_RELATIVE_TOLERANCE:g}")


def _check_aspect(cfg: Config) -> None:
    """mesh.size: at most MAX_ASPECT x a box's thinnest dimension; for drawn geometry at
    least the finest element of the smallest body (2 MIN_ELEMENT_M = 2e-8 m; the volume
    over size^3 that estimates the tetrahedra stays finite)."""
    g = cfg.geometry
    if g.kind in ("step", "geo") and cfg.mesh.size < 2 * MIN_ELEMENT_M:
        _refuse("mesh.size", cfg.mesh.size, f"at least {2 * MIN_ELEMENT_M:g} m", "(the "
                f"smallest body the pipeline meshes, {MIN_EXTENT_M:g} m, in at most "
                f"{MAX_ELEMENTS_ALONG:g} elements along)")
    if g.kind != "box":
        return
    thinnest = min(g.length, g.height, g.depth)
    if cfg.mesh.size > MAX_ASPECT * thinnest:
        raise ConfigError(
            f"config key 'mesh.size': got {cfg.mesh.size:g} m, expected at most "
            f"{MAX_ASPECT * thinnest:g} m ({MAX_ASPECT:g} x the body's thinnest dimension "
            f"{thinnest:g} m: flatter elements make the stiffness matrix singular)",
            key="mesh.size", value=cfg.mesh.size,
            expected=f"at most {MAX_ASPECT * thinnest:g} m")


def element_sizes(cfg: Config) -> tuple[float, float]:
    """(smallest, largest) element or body length h (m) the run's matrices scale with:
    for a box half the mesh size (or of its thinnest dimension) up to its largest
    dimension; where only the file knows the body, from the finest element the pipeline
    meshes (:data:`MIN_ELEMENT_M`; a finer mesh.size is refused by the tetrahedra count
    after reading) up to the largest body (MAX_EXTENT_M)."""
    g = cfg.geometry
    if g.kind == "box":
        small = 0.5 * min(cfg.mesh.size, g.length, g.height, g.depth)
        return small, max(g.length, g.height, g.depth)
    return max(0.5 * cfg.mesh.size, MIN_ELEMENT_M), MAX_EXTENT_M


def _laws(cfg: Config):
    """(key, smallest modulus, largest modulus, rho, nu or None) of every material law of
    the config: the default ``material`` and each ``materials`` entry (orthotropic: its
    Young's and shear moduli; anisotropic: the diagonal of its stiffness)."""
    if cfg.material is not None:
        m = cfg.material
        yield "material", m.E, m.E, m.rho, m.nu
    for i, entry in enumerate(cfg.materials):
        key = f"materials[{i}]"
        if entry.kind == "isotropic":
            yield key, entry.E, entry.E, entry.rho, entry.nu
        elif entry.kind == "anisotropic":
            diagonal = [abs(entry.stiffness[k][k]) for k in range(6)]
            yield key, min(diagonal), max(diagonal), entry.rho, None
        else:
            moduli = tuple(entry.moduli or ()) + tuple(entry.shear or ())
            yield key, min(moduli), max(moduli), entry.rho, None


def _check_material(cfg: Config) -> None:
    h_min, h_max = element_sizes(cfg)
    lo, hi = FLOAT_FLOOR, FLOAT_CEILING
    why = (f"so that stiffness (E h), mass (rho h^3) and omega^2 = E / (rho h^2) stay within "
           f"[{lo:g}, {hi:g}] for element sizes h of {h_min:g} to {h_max:g} m (their squares "
           "must be normal doubles)")
    for key, E_low, E_high, rho, nu in _laws(cfg):
        if E_low * h_min < lo:
            _refuse(f"{key}.E", E_low, f"at least {lo / h_min:.3g} Pa", why)
        if rho * h_min ** 3 < lo:
            _refuse(f"{key}.rho", rho, f"at least {lo / h_min ** 3:.3g} kg/m^3", why)
        if E_high / rho / h_min ** 2 > hi:
            _refuse(f"{key}.E", E_high, f"E / rho at most {hi * h_min ** 2:.3g} m^2/s^2 (here "
                    f"rho = {rho:g} kg/m^3: E at most {hi * h_min ** 2 * rho:.3g} Pa)", why)
        if E_low / rho / h_max ** 2 < lo:
            _refuse(f"{key}.E", E_low, f"E / rho at least {lo * h_max ** 2:.3g} m^2/s^2 (here "
                    f"rho = {rho:g} kg/m^3: E at least {lo * h_max ** 2 * rho:.3g} Pa)", why)
        if nu is not None and nu > MAX_NU:
            _refuse(f"{key}.nu", nu, f"at most {MAX_NU:.9f}", "(lambda / mu = "
                    f"{2 * nu / (1 - 2 * nu):.3g} above {MAX_LAMBDA_OVER_MU:g}: the shear "
                    "stiffness is lost in the roundoff of the volumetric stiffness; a truly "
                    "incompressible solid needs a mixed formulation this pipeline does not "
                    "have)")


def _check_filter(cfg: Config) -> None:
    """The loop-breaking filter's gains are K, K^2, K^3 (K = 2 pi cutoff_hz, rad/s): K^3
    must reach FLOAT_FLOOR (below it the filter's poles underflow to 0 and it is no low
    pass); the field check already caps cutoff_hz at 1e9 (K^3 ~ 2.5e29)."""
    if cfg.filter.kind == "none":
        return
    lowest = FLOAT_FLOOR ** (1.0 / 3.0) / (2.0 * math.pi)
    if cfg.filter.cutoff_hz < lowest:
        _refuse("filter.cutoff_hz", cfg.filter.cutoff_hz, f"at least {lowest:.3g} Hz",
                f"(the filter's gain (2 pi cutoff)^3 must stay above {FLOAT_FLOOR:g}; a "
                "loop-breaking filter belongs at 5x the highest retained mode)")


def _check_points(cfg: Config) -> None:
    """Selector, gauge and connection points with finite squared distances; connection
    points within MAX_CONNECTION_REACH body sizes of the body (a box's centre; the largest
    body where only the file knows it)."""
    points: list[tuple[str, tuple[float, ...] | None]] = []
    for name, sel in cfg.regions.items():
        points += [(f"regions.{name}.{k}", getattr(sel, k)) for k in ("point", "lower", "upper")]
        for k in ("radius", "tolerance"):
            value = getattr(sel, k)
            if value is not None and value > MAX_COORDINATE_M:
                _refuse(f"regions.{name}.{k}", value, f"at most {MAX_COORDINATE_M:g} m",
                        "(its square must be a finite double)")
    for side in ("inputs", "outputs"):
        for i, port in enumerate(getattr(cfg.ports, side)):
            points.append((f"ports.{side}[{i}].point", port.point))
            if port.radius > MAX_COORDINATE_M:
                _refuse(f"ports.{side}[{i}].radius", port.radius,
                        f"at most {MAX_COORDINATE_M:g} m", "(its square must be a finite double)")
    points += [(f"connections[{i}].point", c.point) for i, c in enumerate(cfg.connections)]
    for key, point in points:
        if point is not None and max(abs(x) for x in point) > MAX_COORDINATE_M:
            _refuse(key, list(point), f"coordinates within +-{MAX_COORDINATE_M:g} m",
                    "(squared distances to it must be finite doubles)")
    g = cfg.geometry
    if g.kind == "box":
        size, centre = max(g.length, g.height, g.depth), (g.length / 2, g.height / 2,
                                                          g.depth / 2)
    else:
        size, centre = MAX_EXTENT_M, (0.0, 0.0, 0.0)
    for i, c in enumerate(cfg.connections):
        reach = math.dist(c.point, centre)
        if reach > MAX_CONNECTION_REACH * size:
            _refuse(f"connections[{i}].point", list(c.point), f"a point within "
                    f"{MAX_CONNECTION_REACH * size:g} m of the body ({MAX_CONNECTION_REACH:g} x "
                    f"its size {size:g} m; this one is {reach:.3g} m away)", "(the body's "
                    "inertia about a farther point cancels the digits of its residual mass)")


def _refuse(key: str, value: float, expected: str, why: str) -> None:
    raise ConfigError(f"config key '{key}': got {value!r}, expected {expected} {why}",
                      key=key, value=value, expected=expected)
