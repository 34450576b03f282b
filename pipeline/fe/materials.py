"""The material of every element: the laws of ``material:`` and ``materials:`` resolved
onto the mesh (:func:`assign_materials`), as the assembly and the stress recovery use them.

Each law is a 6x6 stiffness D (Pa) in the GLOBAL frame, Voigt order [xx, yy, zz, yz, xz,
xy] with engineering shear strain (sigma = D gamma), and a density rho (kg/m^3). The
tensor form is C_ijkl = D[I(ij), J(kl)] (with this shear convention no factors appear).
A law given in a material frame Q (columns: material axes 1, 2, 3 in global coordinates)
is rotated as a fourth-order tensor, C'_ijkl = Q_ia Q_jb Q_kc Q_ld C_abcd.

Element assignment: the first entry of ``materials`` whose selector claims an element
gives its law (law index 1 + entry index; an entry in a cylindrical coordinate system
gets one law per element it claims, after the entries' laws, each rotated into the
frame at the element's centroid, :func:`cylindrical_frames`); elements no entry claims take ``material``
(law 0), which must then exist. An entry that claims no element (it selects nothing, or
earlier entries claimed all it selects) is refused: it is a mistake in the config.
Non-structural mass per volume (``masses`` of kind volume) adds its density to rho of the
elements it selects.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from pipeline.config import Material
from pipeline.config.materials import (AddedMass, ElementSelector, MaterialEntry,
                                       material_frame, orthotropic_compliance)
from pipeline.errors import RegionError
from pipeline.fe.kernels import lame_parameters
from pipeline.fe.space import FESpace

#: (i, j) tensor indices of each Voigt component (the order of pipeline.fe.strain)
VOIGT_INDEX = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))


def isotropic_stiffness(material: Material) -> np.ndarray:
    """(6, 6) isotropic D in Pa (engineering shear)."""
    lam, mu = lame_parameters(material)
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[[0, 1, 2], [0, 1, 2]] += 2.0 * mu
    D[[3, 4, 5], [3, 4, 5]] = mu
    return D


def voigt_to_tensor(D: np.ndarray) -> np.ndarray:
    """(..., 3, 3, 3, 3) C_ijkl = D[I(ij), J(kl)] of (..., 6, 6) D (engineering shear)."""
    D = np.asarray(D, dtype=float)
    C = np.empty(D.shape[:-2] + (3, 3, 3, 3))
    for I, (i, j) in enumerate(VOIGT_INDEX):
        for J, (k, m) in enumerate(VOIGT_INDEX):
            for a, b in {(i, j), (j, i)}:
                for c, d in {(k, m), (m, k)}:
                    C[..., a, b, c, d] = D[..., I, J]
    return C


def tensor_to_voigt(C: np.ndarray) -> np.ndarray:
    """(..., 6, 6) D of (..., 3, 3, 3, 3) C (inverse of :func:`voigt_to_tensor`)."""
    D = np.empty(C.shape[:-4] + (6, 6))
    for I, (i, j) in enumerate(VOIGT_INDEX):
        for J, (k, m) in enumerate(VOIGT_INDEX):
            D[..., I, J] = C[..., i, j, k, m]
    return D


def rotate_stiffness(D: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(6, 6) global D of the material-frame D, Q (3, 3) columns the material axes."""
    C = np.einsum("ia,jb,kc,ld,abcd->ijkl", Q, Q, Q, Q, voigt_to_tensor(D), optimize=True)
    return tensor_to_voigt(C)


def entry_stiffness(entry: MaterialEntry, frame: bool = True) -> np.ndarray:
    """(6, 6) global-frame D (Pa) of one ``materials`` entry (``frame`` False: in its
    material frame)."""
    if entry.kind == "isotropic":
        return isotropic_stiffness(Material(E=entry.E, nu=entry.nu, rho=entry.rho))
    if entry.kind == "anisotropic":
        D = np.array(entry.stiffness, dtype=float)
        D = 0.5 * (D + D.T)
    else:
        D = np.linalg.inv(orthotropic_compliance(entry.moduli, entry.poisson, entry.shear))
        D = 0.5 * (D + D.T)
    return rotate_stiffness(D, material_frame(entry.axes)) if frame else D


def cylindrical_frames(points: np.ndarray, axis, point, key: str) -> np.ndarray:
    """(n, 3, 3) Q with columns the material axes radial, hoop, axial at ``points``
    (n, 3) m of a cylindrical system (unit ``axis``, ``point`` m on it); RegionError
    naming ``key`` for a point on the axis (no radial direction there)."""
    a = np.asarray(axis, dtype=float)
    d = points - np.asarray(point, dtype=float)
    r = d - np.outer(d @ a, a)
    norm = np.linalg.norm(r, axis=1)
    size = max(float(np.ptp(points, axis=0).max()) if len(points) else 0.0,
               float(np.abs(d).max()) if len(points) else 0.0, 1e-300)
    if len(points) and norm.min() <= 1e-9 * size:
        c = points[int(np.argmin(norm))]
        raise RegionError(f"config key '{key}': an element's centroid {c.round(6).tolist()} "
                          "m lies on the cylindrical system's axis (no radial direction); "
                          "expected elements off the axis (a tube, not a rod)")
    e_r = r / norm[:, None]
    return np.stack([e_r, np.cross(a, e_r), np.broadcast_to(a, e_r.shape)], axis=2)


def _rotate_many(D: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(n, 6, 6) global D of one material-frame D (6, 6) in the frames Q (n, 3, 3)."""
    C = np.einsum("nia,njb,nkc,nld,abcd->nijkl", Q, Q, Q, Q, voigt_to_tensor(D),
                  optimize=True)
    return tensor_to_voigt(C)


@dataclass(frozen=True)
class ElementMaterials:
    """The material of every element.

    names: (n_laws,) law names, law 0 the default ``material`` ("material"; present even
    when no element takes it; an entry in a cylindrical frame repeats its name on its
    per-element laws). D: (n_laws, 6, 6) global-frame stiffness, Pa.
    law_rho: (n_laws,) kg/m^3. index: (n_e,) int, the law of each element. rho: (n_e,)
    kg/m^3, each element's density with the non-structural mass per volume added.
    uniform: the one isotropic Material of every element (None when the elements differ or
    a law is not isotropic): the assembly's fast path, and bit for bit the single-material run.
    """

    names: tuple[str, ...]
    D: np.ndarray
    law_rho: np.ndarray
    index: np.ndarray
    rho: np.ndarray
    uniform: Material | None

    def element_D(self, elements: np.ndarray) -> np.ndarray:
        """(n, 6, 6) Pa, D of ``elements``."""
        return self.D[self.index[elements]]


def element_centroids(space: FESpace) -> np.ndarray:
    """(n_e, 3) m, centroids of the straight-sided tetrahedra."""
    return space.body.vertices[space.body.tetrahedra].mean(axis=1)


def select_elements(space: FESpace, selector: ElementSelector, key: str,
                    centroids: np.ndarray | None = None) -> np.ndarray:
    """(n_e,) bool, the elements ``selector`` claims (``key``: the config key, for errors);
    a name is one of the mesh file's element sets (``space.body.element_sets``)."""
    n_e = space.body.n_tetrahedra
    if selector.kind == "all":
        return np.ones(n_e, dtype=bool)
    if selector.kind == "group":
        groups = space.body.element_sets
        if selector.name not in groups:
            raise RegionError(f"config key '{key}': no volume group or element set named "
                              f"'{selector.name}' in the mesh '{space.body.source}'; expected "
                              f"one of: {', '.join(sorted(groups)) or '(none)'}, 'all', or a "
                              "box or sphere selector")
        mask = np.zeros(n_e, dtype=bool)
        mask[np.asarray(groups[selector.name], dtype=np.int64)] = True
        return mask
    c = element_centroids(space) if centroids is None else centroids
    if selector.kind == "box":
        return np.all((c >= np.asarray(selector.lower)) & (c <= np.asarray(selector.upper)), 1)
    return np.linalg.norm(c - np.asarray(selector.point), axis=1) <= selector.radius


def assign_materials(space: FESpace, default: Material | None,
                     entries: Sequence[MaterialEntry] = (),
                     masses: Sequence[AddedMass] = ()) -> ElementMaterials:
    """Resolve ``material`` (``default``), ``materials`` (``entries``, first match wins) and
    the volume ``masses`` onto the elements (module docstring); RegionError naming the
    config key for an entry that claims nothing or elements left without a material."""
    n_e = space.body.n_tetrahedra
    index = np.zeros(n_e, dtype=np.int32)
    free = np.ones(n_e, dtype=bool)
    centroids = element_centroids(space) if entries or masses else None
    for i, entry in enumerate(entries):
        key = f"materials[{i}].elements"
        claimed = select_elements(space, entry.elements, key, centroids)
        if not claimed.any():
            raise RegionError(f"config key '{key}': material '{entry.name}' selects no element "
                              f"of the mesh (by element centroid); expected at least one")
        claimed &= free
        if not claimed.any():
            raise RegionError(f"config key '{key}': every element material '{entry.name}' "
                              "selects is claimed by an earlier entry (first match wins); "
                              "expected it to claim at least one element (remove it or move "
                              "it up)")
        index[claimed] = i + 1
        free &= ~claimed
    if free.any() and default is None:
        c = (centroids if centroids is not None else element_centroids(space))[free][0]
        raise RegionError(f"config key 'materials': {int(free.sum())} element(s) have no "
                          f"material (one has its centroid at {c.round(6).tolist()} m); "
                          "expected an entry claiming them or a default 'material:'")
    base = default if default is not None else Material()
    D = np.stack([isotropic_stiffness(base)] + [entry_stiffness(e) for e in entries])
    law_rho = np.array([base.rho] + [e.rho for e in entries])
    names = ("material",) + tuple(e.name for e in entries)
    for i, entry in enumerate(entries):  # a cylindrical frame: one law per element
        if entry.cylinder is None:
            continue
        els = np.flatnonzero(index == i + 1)
        Q = cylindrical_frames(centroids[els], *entry.cylinder, f"materials[{i}].axes")
        index[els] = D.shape[0] + np.arange(els.size)
        D = np.concatenate([D, _rotate_many(entry_stiffness(entry, frame=False), Q)])
        law_rho = np.concatenate([law_rho, np.full(els.size, entry.rho)])
        names += (entry.name,) * els.size
    rho = law_rho[index]
    for i, m in enumerate(masses):
        if m.kind == "volume":
            sel = select_elements(space, m.elements, f"masses[{i}].elements", centroids)
            if not sel.any():
                raise RegionError(f"config key 'masses[{i}].elements': mass '{m.name}' selects "
                                  "no element of the mesh; expected at least one")
            rho = rho + np.where(sel, m.density, 0.0)
    uniform = None
    used = np.unique(index)
    if used.size == 1 and np.all(rho == law_rho[used[0]]):
        law = int(used[0])
        if law == 0:
            uniform = base
        elif law <= len(entries) and entries[law - 1].kind == "isotropic":
            e = entries[law - 1]
            uniform = Material(E=e.E, nu=e.nu, rho=e.rho)
    return ElementMaterials(names, D, law_rho, index, rho, uniform)


def config_materials(space: FESpace, cfg) -> ElementMaterials:
    """:func:`assign_materials` of a Config's ``material``, ``materials`` and ``masses``."""
    return assign_materials(space, cfg.material, cfg.materials, cfg.masses)

