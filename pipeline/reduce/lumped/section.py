"""Beam cross-sections for the lumped chain (theory.md §7): area, second moments,
torsion constant (m^2, m^4) of a box or of a meshed section, the beam check
(principal axes along y and z, slenderness), and the checks of raw values shared by the
package (:mod:`pipeline.reduce.lumped`; conventions there).

Section axes: ``y`` along the section ``height``, ``z`` along its ``depth``; ``I_y`` is
``int z^2 dA``, ``I_z`` is ``int y^2 dA``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline._util import validate
from pipeline.errors import ConfigError

log = logging.getLogger(__name__)

__all__ = ["SLENDER_MIN", "SLENDER_WARN", "SectionProperties", "rectangle_torsion_constant",
           "box_section", "section_from_mesh", "check_beam", "raw_field", "positive",
           "poisson_ratio", "unit_direction"]

# Refused below this slenderness: L >= SLENDER_MIN * max(section height, depth).
SLENDER_MIN = 2.0
# Warned below this one: shear deformation and rotary inertia are no longer small.
SLENDER_WARN = 10.0


# --------------------------------------------------------------------------- checks
# Raw values from library callers go through the one field checker
# (pipeline._util.validate); values from a Config have passed it already. Shared by the
# modules of this package.
def raw_field(key: str, value: Any) -> dict:
    """The one-entry mapping the field checker reads; numpy scalars as Python numbers."""
    return {key: value.item() if isinstance(value, np.generic) else value}


def positive(value: Any, name: str) -> float:
    """``value`` as a finite float > 0 (ConfigError naming ``name`` otherwise)."""
    return validate.number(raw_field(name, value), name, "", lo=0.0, lo_open=True)


def poisson_ratio(value: Any, name: str = "material.nu") -> float:
    """``value`` as a Poisson's ratio in (-1, 0.5)."""
    return validate.number(raw_field(name, value), name, "", lo=-1.0, hi=0.5, lo_open=True,
                           hi_open=True)


def unit_direction(value: Any, name: str) -> np.ndarray:
    """A non-zero 3-vector, normalised to unit length, (3,)."""
    raw = value.tolist() if isinstance(value, np.ndarray) else value
    d = np.asarray(validate.vector(raw_field(name, raw), name, "", nonzero=True), dtype=float)
    return d / np.linalg.norm(d)


# --------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class SectionProperties:
    """Properties of a beam cross-section (the y-z plane), about its centroid.

    area: m^2. I_y: m^4, ``int z^2 dA`` (about y, bending in x-z). I_z: m^4,
    ``int y^2 dA`` (about z, bending in x-y). J: m^4, Saint-Venant torsion constant.
    I_p: m^4, polar moment ``I_y + I_z``. source: ``"analytic box"`` or
    ``"FE cross-section"``. height, depth: m, extent of the section along y and z (used
    by the slenderness check). centroid: (y, z) m, where the beam axis runs. I_yz: m^4,
    product of area ``int y z dA`` (0 when y and z are principal axes).
    """

    area: float
    I_y: float
    I_z: float
    J: float
    I_p: float
    source: str
    height: float
    depth: float
    centroid: tuple[float, float] = (0.0, 0.0)
    I_yz: float = 0.0

    def second_moment(self, axis: str) -> float:
        """``I_y`` for ``bending_y`` / ``bend_y``, ``I_z`` for ``bending_z`` / ``bend_z`` (m^4)."""
        if axis in ("bending_y", "bend_y"):
            return self.I_y
        if axis in ("bending_z", "bend_z"):
            return self.I_z
        raise ValueError(f"no bending axis {axis!r}")


def rectangle_torsion_constant(height: float, depth: float) -> float:
    """Saint-Venant torsion constant of a solid ``height`` x ``depth`` rectangle (m^4).

    With ``a >= b`` the long and short sides, the exact series solution (Timoshenko &
    Goodier, torsion of a rectangular bar) is
    ``J = a b^3 / 3 [1 - (192 / pi^5) (b / a) sum_{k odd} tanh(k pi a / (2 b)) / k^5]``.
    The series is summed to k = 4001 (tail below 1e-15 relative), not truncated to the
    usual one-term approximation.
    """
    a, b = max(height, depth), min(height, depth)
    k = np.arange(1, 4002, 2, dtype=float)
    series = np.sum(np.tanh(k * np.pi * a / (2.0 * b)) / k**5)
    return float(a * b**3 / 3.0 * (1.0 - 192.0 / np.pi**5 * (b / a) * series))


def box_section(height: float, depth: float, centroid: tuple[float, float] = (0.0, 0.0)
                ) -> SectionProperties:
    """Solid rectangular section: ``height`` along y, ``depth`` along z (m).

    Returns area = h d, I_z = d h^3 / 12, I_y = h d^3 / 12, J from
    :func:`rectangle_torsion_constant`, source ``"analytic box"``. ``centroid`` (y, z)
    places the beam axis (e.g. (h/2, d/2) for a box spanning y in [0, h], z in [0, d]).
    """
    h = positive(height, "geometry.height")
    d = positive(depth, "geometry.depth")
    c = (float(centroid[0]), float(centroid[1]))
    I_y = h * d**3 / 12.0
    I_z = d * h**3 / 12.0
    return SectionProperties(area=h * d, I_y=I_y, I_z=I_z, J=float(rectangle_torsion_constant(h, d)),
                             I_p=I_y + I_z, source="analytic box", height=h, depth=d, centroid=c)


def section_from_mesh(points2d: Any, triangles: Any, source: str = "FE cross-section"
                      ) -> SectionProperties:
    """Section properties of an arbitrary cross-section from its 2D triangle mesh.

    points2d: (n_p, 2) m, the (y, z) coordinates of the vertices. triangles: (n_t, 3)
    vertex indices (any orientation; straight-sided). The section may have holes but must
    be one connected piece.

    Area, centroid and second moments are integrated exactly (polynomials on straight
    triangles, quadrature of degree 4). The torsion constant comes from the warping
    function ``w`` (u_x = theta' w), solved with scikit-fem P2 triangles:
    ``int grad w . grad v dA = int (z dv/dy - y dv/dz) dA`` for all v (traction-free
    boundary, natural; holes need nothing special), w fixed at one node, and
    ``J = I_p - int |grad w|^2 dA`` (coordinates about the centroid). The discrete J
    converges from above as the mesh is refined.
    """
    from scipy.sparse.csgraph import connected_components
    import scipy.sparse as sp
    from skfem import Basis, BilinearForm, ElementTriP2, Functional, LinearForm, MeshTri, condense, solve

    p = np.asarray(points2d, dtype=float)
    t = np.asarray(triangles)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 3 or not np.all(np.isfinite(p)):
        raise ConfigError(f"section mesh points: got an array of shape {p.shape}, expected "
                          "(n_points >= 3, 2) finite (y, z) coordinates in m")
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] < 1 or not np.issubdtype(t.dtype, np.integer):
        raise ConfigError(f"section mesh triangles: got an array of shape {t.shape} "
                          f"({t.dtype}), expected (n_triangles >= 1, 3) integer vertex indices")
    if t.min() < 0 or t.max() >= p.shape[0]:
        raise ConfigError(f"section mesh triangles: vertex indices span [{t.min()}, {t.max()}], "
                          f"expected indices in [0, {p.shape[0] - 1}]")
    used, t = np.unique(t, return_inverse=True)
    t = t.reshape(-1, 3)
    p = p[used]
    e1 = p[t[:, 1]] - p[t[:, 0]]
    e2 = p[t[:, 2]] - p[t[:, 0]]
    signed = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    scale = max(np.ptp(p[:, 0]), np.ptp(p[:, 1])) ** 2
    flat = np.flatnonzero(np.abs(signed) <= 1e-14 * scale)
    if flat.size:
        raise ConfigError(f"section mesh: {flat.size} degenerate (zero-area) triangles, e.g. "
                          f"triangle {int(flat[0])}; expected a valid triangulation")
    t[signed < 0] = t[signed < 0][:, [0, 2, 1]]
    rows = np.repeat(t, 3, axis=1).ravel()
    cols = np.tile(t, 3).ravel()
    graph = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(p.shape[0],) * 2)
    n_parts, _ = connected_components(graph, directed=False)
    if n_parts != 1:
        raise ConfigError(f"section mesh: got {n_parts} disconnected pieces, expected one "
                          "connected cross-section")

    mesh = MeshTri(p.T.copy(), t.T.copy())
    basis = Basis(mesh, ElementTriP2(), intorder=4)
    area = Functional(lambda w: 1.0 + 0.0 * w.x[0]).assemble(basis)
    yc = Functional(lambda w: w.x[0]).assemble(basis) / area
    zc = Functional(lambda w: w.x[1]).assemble(basis) / area
    I_z = Functional(lambda w: (w.x[0] - yc) ** 2).assemble(basis)
    I_y = Functional(lambda w: (w.x[1] - zc) ** 2).assemble(basis)
    I_yz = Functional(lambda w: (w.x[0] - yc) * (w.x[1] - zc)).assemble(basis)

    @BilinearForm
    def laplace(u, v, w):
        return u.grad[0] * v.grad[0] + u.grad[1] * v.grad[1]

    @LinearForm
    def load(v, w):
        y, z = w.x[0] - yc, w.x[1] - zc
        return z * v.grad[0] - y * v.grad[1]

    K = laplace.assemble(basis)
    f = load.assemble(basis)
    warp = solve(*condense(K, f, D=np.array([0])))
    J = I_y + I_z - float(warp @ (K @ warp))
    log.info("section from %d triangles (%d P2 DOFs): A = %.6g m^2, I_y = %.6g, I_z = %.6g, "
             "J = %.6g m^4", t.shape[0], basis.N, area, I_y, I_z, J)
    return SectionProperties(area=float(area), I_y=float(I_y), I_z=float(I_z), J=float(J),
                             I_p=float(I_y + I_z), source=source, height=float(np.ptp(p[:, 0])),
                             depth=float(np.ptp(p[:, 1])), centroid=(float(yc), float(zc)),
                             I_yz=float(I_yz))


def check_beam(section: SectionProperties, length: float) -> float:
    """Refuse a body that is not a beam; return the length (m).

    Rules: section area, I_y, I_z, J > 0; principal axes along y and z
    (``|I_yz| <= 1e-6 sqrt(I_y I_z)``); slenderness ``L >= 2 max(height, depth)``
    (:data:`SLENDER_MIN`). Below ``L = 10 max(height, depth)`` a warning is logged: shear
    deformation, which neither the chain nor Euler-Bernoulli theory has, is then no
    longer small.
    """
    L = positive(length, "geometry.length")
    for name in ("area", "I_y", "I_z", "J"):
        positive(getattr(section, name), f"section.{name}")
    if abs(section.I_yz) > 1e-6 * math.sqrt(section.I_y * section.I_z):
        angle = 0.5 * math.degrees(math.atan2(-2.0 * section.I_yz, section.I_z - section.I_y))
        raise ConfigError(
            f"section.I_yz: got {section.I_yz:g} m^4, expected 0 (principal axes along y and z); "
            f"the principal axes are rotated by about {angle:.3g} deg, rotate the section",
            key="section.I_yz", value=section.I_yz, expected="0 (principal axes along y and z)")
    size = max(section.height, section.depth)
    if L < SLENDER_MIN * size:
        raise ConfigError(
            f"geometry.length: got {L:g} m, expected a beam: length >= {SLENDER_MIN:g} x the "
            f"largest section dimension {size:g} m (rule L >= {SLENDER_MIN:g} max(height, depth)); "
            "this body is not slender enough for a lumped beam model",
            key="geometry.length", value=L,
            expected=f"length >= {SLENDER_MIN:g} max(height, depth) = {SLENDER_MIN * size:g} m")
    if L < SLENDER_WARN * size:
        log.warning("lumped model of a stocky beam: L / max(height, depth) = %.3g < %g; shear "
                    "deformation is not small and the chain (Euler-Bernoulli) will be too stiff",
                    L / size, SLENDER_WARN)
    return L
