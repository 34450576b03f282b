"""Strain and stress from nodal displacements: element values, nodal recovery, gauges.

Conventions (SI): strain is dimensionless (m/m), stress in Pa. Six-component fields use
the Voigt order

    [xx, yy, zz, yz, xz, xy]

with ENGINEERING shear strain gamma_ij = 2 eps_ij in the strain vector (so that
sigma = D eps with the usual isotropic D) and the plain shear stress sigma_ij in the
stress vector.

Element values: the small strain eps = sym(grad u) is evaluated with scikit-fem's own
basis (``CellBasis`` of the vector Lagrange element on a chunk of elements, gradients at
its quadrature points) and averaged over each element with the quadrature weights:

    eps_e = (sum_q w_q |J| eps(x_q)) / V_e .

For P1 the strain is constant per element, for P2 linear, so a rule exact for linear
functions (intorder 1 or more) gives the exact element average.

Nodal recovery (:func:`nodal_strains`): each element evaluates its own strain at its own
nodes (scikit-fem basis with the quadrature points at the reference element's DOF
locations; for P2 the strain is linear in the element, so these are its exact nodal
values), and the values from the elements around a node (vertices and, for P2, edge
midpoints) are averaged with the element volumes as weights:

    s_n = sum_{e ni n} V_e s_e(x_n) / sum_{e ni n} V_e .

Averaging the element *averages* instead puts centroid values at the nodes and, at a
free surface where bending stress peaks, reads 19-35 % low on the cantilever at 2-4
elements through the height (measured; tests/test_stress.py); the element-nodal values
are exact for a quadratic displacement field, so the average only smooths the jumps
between elements.

Gauges (``gauge_row``): a strain or stress port is a linear functional of the nodal
displacement vector, g(u) = w . s(u), with w the Voigt weights of the symmetric dyad
A = (d1 d2^T + d2 d1^T) / 2 of its unit direction(s): the normal strain or stress along d
(d2 = d1) or the shear component between d1 and d2 (tensor shear for strain). The value
is, by default (``average="surface"``), the area-weighted mean of the surface strain over
the surface the gauge covers (a named boundary region, or a grid or disc around a point
on the surface; :mod:`pipeline.fe.gauges`); with ``average="volume"`` the
volume-weighted mean of the element averages over the gauge's elements (a named boundary
region: the elements with a face on it; or a sphere: the elements whose centroid lies
within it); or the value at a point (no radius, no grid) inside its element.
Shapes: the operator of ``element_strain_operator`` is (6 n_e, n_dofs) sparse, row
6 e + k is component k of element e; fields are (n_e | n_nodes, 6, n_shapes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pipeline.config import Material
from pipeline.errors import RegionError
from pipeline.fe.gauges import grid_patch, region_patch, strain_row
from pipeline._util.resources import usable_cores
from pipeline.fe.assemble import element_groups
from pipeline.fe.kernels import inverse_jacobians, scatter_add
from pipeline.fe.materials import isotropic_stiffness
from pipeline.fe.pattern import side_by_side
from pipeline.fe.space import FESpace

VOIGT = ("xx", "yy", "zz", "yz", "xz", "xy")
#: (i, j) tensor indices of each Voigt component
VOIGT_INDEX = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))
#: elements per scikit-fem basis (one basis holds 3 n_local gradients per quadrature point)
CHUNK = 20000
#: meshes from this many elements recover nodal strains in two halves side by side
#: (:func:`nodal_strains_at`; the cantilever at 1M DOFs, 222k elements, five shapes,
#: 2-core Xeon, 4 pairs: 1.14-1.68 -> 0.80-1.18 s, the same sums to 1.4e-16)
THREADED_ELEMENTS = 16 * (CHUNK // 10)


def elasticity_matrix(material: Material) -> np.ndarray:
    """(6, 6) isotropic D in Pa: sigma (Voigt) = D eps (Voigt, engineering shear)."""
    return isotropic_stiffness(material)


def shared_parts(space: FESpace) -> dict:
    """The mesh-wide parts every chunk's basis shares (the mapping and the DOF numbering):
    built once per call instead of once per chunk, where each chunk's basis would
    re-number the whole mesh's DOFs and map all its DOF locations again.

    The mapping is scikit-fem's public :class:`skfem.mapping.MappingAffine`: the one a
    :class:`skfem.Basis` builds itself for a mesh of straight-sided tetrahedra."""
    from skfem import Dofs
    from skfem.mapping import MappingAffine

    mesh, elem = space.skfem_mesh, space.skfem_element()
    return {"mapping": MappingAffine(mesh), "dofs": Dofs(mesh, elem), "disable_doflocs": True}


def _basis(space: FESpace, elements: np.ndarray, quadrature=None, shared: dict | None = None):
    from skfem import Basis

    shared = shared if shared is not None else shared_parts(space)
    if quadrature is None:
        return Basis(space.skfem_mesh, space.skfem_element(), intorder=2, elements=elements,
                     **shared)
    return Basis(space.skfem_mesh, space.skfem_element(), elements=elements,
                 quadrature=quadrature, **shared)


def _voigt_gradients(basis) -> np.ndarray:
    """(n_local, 6, n_e, n_q): engineering strain of each local basis function."""
    out = []
    for phi in basis.basis:
        g = phi[0].grad  # (3 components, 3 derivatives, n_e, n_q)
        out.append(np.stack([g[i, j] + g[j, i] if i != j else g[i, i]
                             for i, j in VOIGT_INDEX]))
    return np.stack(out)


def _operator_rows(space: FESpace, elements: np.ndarray, shared: dict | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Element-average strain operator of ``elements``: (values (n_e, 6, n_local),
    global dofs (n_e, n_local), volumes (n_e,))."""
    basis = _basis(space, elements, shared=shared)
    dx = basis.dx  # (n_e, n_q) quadrature weight times |J|
    vol = dx.sum(axis=1)
    G = _voigt_gradients(basis)  # (n_local, 6, n_e, n_q)
    avg = np.einsum("lkeq,eq->elk", G, dx) / vol[:, None, None]
    return avg.transpose(0, 2, 1).copy(), basis.element_dofs.T, vol


def element_strain_operator(space: FESpace, elements: np.ndarray | None = None
                            ) -> tuple[sp.csr_matrix, np.ndarray]:
    """(E, volumes): E (6 n_sel, n_dofs) maps nodal displacements (m) to the element-average
    engineering strains of ``elements`` (default all), row 6 i + k = component k of the
    i-th selected element; volumes (n_sel,) m^3."""
    elements = np.arange(space.element_nodes.shape[0]) if elements is None \
        else np.asarray(elements, dtype=np.int64)
    parts, vols = [], []
    shared = shared_parts(space)
    for start in range(0, elements.size, CHUNK):
        sel = elements[start:start + CHUNK]
        vals, dofs, vol = _operator_rows(space, sel, shared)
        n, n_loc = dofs.shape
        rows = np.repeat((6 * (start + np.arange(n)))[:, None] + np.arange(6)[None, :],
                         n_loc, axis=1).reshape(n, 6, n_loc)
        cols = np.broadcast_to(dofs[:, None, :], (n, 6, n_loc))
        parts.append((vals.ravel(), rows.ravel(), cols.ravel()))
        vols.append(vol)
    data, rows, cols = (np.concatenate(p) for p in zip(*parts)) if parts else \
        (np.zeros(0), np.zeros(0, int), np.zeros(0, int))
    E = sp.csr_matrix((data, (rows, cols)), shape=(6 * elements.size, space.n_dofs))
    return E, np.concatenate(vols) if vols else np.zeros(0)


def stresses_from_strains(strains: np.ndarray, material: Material) -> np.ndarray:
    """sigma (Pa) = D eps along axis 1 of ``strains`` (..., 6, ...)."""
    return np.einsum("ij,ej...->ei...", elasticity_matrix(material), strains)


def _reference_node_gradients(space: FESpace) -> np.ndarray:
    """(n_loc points q, n_loc functions b, 3 k): d phi_b / d xi_k of the scalar reference
    element at its own node locations (scikit-fem's element, local node order)."""
    elem = space.skfem_element().elem
    X = elem.doflocs.T  # (3, n_loc) reference node locations
    dphi = np.stack([elem.lbasis(X, b)[1] for b in range(X.shape[1])])  # (b, k, q)
    return np.ascontiguousarray(dphi.transpose(2, 0, 1))


def _element_nodal_chunks(space: FESpace, U: np.ndarray, elements: np.ndarray | None = None,
                          node_row: np.ndarray | None = None):
    """Yield (elements (n_sel,), values (n_sel, n_local_nodes, 6, n_s)): the engineering
    strain of U (n_dofs, n_s) evaluated by each element at its own nodes (local order of
    ``space.element_nodes``), a chunk of elements at a time: of ``elements`` (default
    all); with ``node_row`` (n_nodes,), U is (3 n_rows, n_s) and node p's displacement
    is its row ``node_row[p]``.

    On straight-sided elements the physical gradients at the nodes are the reference
    ones times the element's constant J^-1: grad u (x_q) = sum_b u_b (x) (G^T dphi_b(q)),
    two batched matrix products per chunk, instead of a scikit-fem basis per chunk (which
    the element averages still use: it evaluates every basis function at every point).
    """
    en = space.element_nodes
    n_e, n_loc = en.shape
    n_s = U.shape[1]
    elements = np.arange(n_e) if elements is None else np.asarray(elements, dtype=np.int64)
    dref = _reference_node_gradients(space).reshape(1, n_loc * n_loc, 3)  # (1, q b, k)
    chunk = max(1, CHUNK // n_loc)
    for start in range(0, elements.size, chunk):
        sel = elements[start:start + chunk]
        e = sel.size
        D = np.matmul(dref, inverse_jacobians(space, sel)[0])  # (e, q b, i): d phi_b/d x_i
        D = D.reshape(e, n_loc, n_loc, 3).transpose(0, 1, 3, 2).reshape(e, 3 * n_loc, n_loc)
        rows = en[sel] if node_row is None else node_row[en[sel]]
        Ue = U.reshape(-1, 3, n_s)[rows].reshape(e, n_loc, 3 * n_s)  # (e, b, c s)
        g = np.matmul(D, Ue).reshape(e, n_loc, 3, 3, n_s)  # (e, q, i derivative, c, s)
        out = np.empty((e, n_loc, 6, n_s))
        for k, (i, j) in enumerate(VOIGT_INDEX):
            if i == j:
                out[:, :, k] = g[:, :, i, i]
            else:  # engineering shear: du_i/dx_j + du_j/dx_i
                np.add(g[:, :, j, i], g[:, :, i, j], out=out[:, :, k])
        yield sel, out


def element_volumes(space: FESpace) -> np.ndarray:
    """(n_e,) m^3, volumes of the (straight-sided) tetrahedra: |det(edge vectors)| / 6,
    :data:`CHUNK` elements at a time (each determinant is its own matrix's, so the values
    do not depend on the chunks; the corner coordinates and edge vectors of all the
    elements at once would be 168 bytes an element)."""
    tets, points = space.body.tetrahedra, space.body.vertices
    out = np.empty(tets.shape[0])
    for start in range(0, tets.shape[0], CHUNK):
        v = points[tets[start:start + CHUNK]]  # (n, 4 corners, 3)
        part = out[start:start + v.shape[0]]
        np.abs(np.linalg.det(v[:, 1:] - v[:, :1]), out=part)
        part /= 6.0
    return out


def node_volumes(space: FESpace, volumes: np.ndarray | None = None) -> np.ndarray:
    """(n_nodes,) m^3: at each node the sum of the ``volumes`` (n_e,) m^3 (default
    :func:`element_volumes`) of the elements around it. The sums are added a chunk of
    elements at a time in element order, so each node's sum is the one
    ``np.bincount(element_nodes.ravel(), weights=np.repeat(volumes, n_local))`` adds up,
    bit for bit, without that call's element-node weights (8 bytes a node of an element)."""
    en = space.element_nodes
    vol = element_volumes(space) if volumes is None else volumes
    out = np.zeros(space.n_nodes)
    for start in range(0, en.shape[0], CHUNK):
        part = en[start:start + CHUNK]
        np.add.at(out, part.ravel(), np.repeat(vol[start:start + part.shape[0]], part.shape[1]))
    return out


def nodal_strains(space: FESpace, U: np.ndarray, element_D=None) -> np.ndarray:
    """(n_nodes, 6, n_s): the volume-weighted average (module docstring) at every node of
    the element-nodal strains of U (n_dofs, n_s); memory: the nodal result plus one chunk.
    ``element_D``, if given, maps element indices (n,) to their stiffness (n, 6, 6) Pa:
    then the element-nodal STRESSES D_e eps_e(x_n) are averaged (Pa; several materials:
    a node on an interface gets the volume-weighted mean of both sides' stresses)."""
    U = np.asarray(U, dtype=float)
    U = U[:, None] if U.ndim == 1 else U
    return nodal_strains_at(space, U, np.arange(space.n_nodes), element_D=element_D)


def nodal_strains_at(space: FESpace, U: np.ndarray, nodes: np.ndarray,
                     elements: np.ndarray | None = None, node_row: np.ndarray | None = None,
                     element_D=None, node_weight: np.ndarray | None = None) -> np.ndarray:
    """(p, 6, n_s): :func:`nodal_strains` at the sorted ``nodes`` (p,), summed over
    ``elements`` only (default all; then exact at every node): V_e s_e(x_n) / sum V_e,
    the denominator over all the elements around n. The sum is linear in U, so shares of
    U (the distributed path: each rank's own DOFs, ``node_row`` as in
    :func:`_element_nodal_chunks`, over the elements that touch them) add up to the whole.
    ``node_weight`` (p,) m^3, if given, is the denominator sum V_e at ``nodes`` (a part of
    a mesh: the whole mesh's sums, which the part's own elements may not all reach)."""
    en = space.element_nodes
    vol = element_volumes(space)
    weight = node_volumes(space, vol)[nodes] if node_weight is None else node_weight
    whole = nodes.size == space.n_nodes
    out = np.zeros((nodes.size, 6 * U.shape[1]))

    def add(group: np.ndarray | None) -> None:
        for sel, values in _element_nodal_chunks(space, U, group, node_row):
            if element_D is not None:
                values = np.einsum("eij,eqjs->eqis", element_D(sel), values)
            values *= vol[sel, None, None, None]
            at = en[sel].ravel() if whole else np.searchsorted(nodes, en[sel].ravel())
            # each (element, node) row added onto its node's row in place: a bincount
            # per column would pass over all n_nodes once per column
            scatter_add(at, values.reshape(sel.size * en.shape[1], -1), out)

    if elements is None and whole and en.shape[0] >= THREADED_ELEMENTS:
        # the two halves of the mesh write disjoint node rows: side by side on two
        # threads, then the layer between them (the same sums in the same order
        # whatever the thread count)
        lower, upper, cut = element_groups(space)
        side_by_side([lambda: add(lower), lambda: add(upper)], usable_cores())
        add(cut)
    else:
        add(elements)
    out /= np.where(weight > 0, weight, 1.0)[:, None]
    return out.reshape(nodes.size, 6, U.shape[1])


@dataclass(frozen=True)
class StressFields:
    """Strain and stress of a set of displacement fields, recovered to the mesh nodes.

    strain: (n_nodes, 6, n_s) engineering strain, Voigt order VOIGT; stress: (n_nodes, 6,
    n_s) Pa (:func:`nodal_strains`).
    """

    strain: np.ndarray
    stress: np.ndarray


def stress_fields(space: FESpace, material, U: np.ndarray) -> StressFields:
    """Nodal strain and stress of the displacement fields U (n_dofs, n_s), m; ``material``:
    a Material or the per-element :class:`~pipeline.fe.materials.ElementMaterials`."""
    eps = nodal_strains(space, U)
    if getattr(material, "uniform", material) is None:  # several laws: each element its own
        return StressFields(eps, nodal_strains(space, U, material.element_D))
    return StressFields(eps, stresses_from_strains(eps, getattr(material, "uniform", material)))


# --------------------------------------------------------------------------- gauges
def voigt_weights(kind: str, direction, direction2=None) -> np.ndarray:
    """(6,) w with w . s = A : tensor(s), A = sym(d1 d2^T), for ``kind`` "strain" (s holds
    engineering shear) or "stress"."""
    d1 = np.asarray(direction, float) / np.linalg.norm(direction)
    d2 = d1 if direction2 is None else np.asarray(direction2, float) / np.linalg.norm(direction2)
    A = 0.5 * (np.outer(d1, d2) + np.outer(d2, d1))
    shear = 1.0 if kind == "strain" else 2.0
    return np.array([A[i, j] * (1.0 if i == j else shear) for i, j in VOIGT_INDEX])


def _face_keys(tris: np.ndarray) -> np.ndarray:
    s = np.sort(np.asarray(tris, dtype=np.int64), axis=1)
    return np.ascontiguousarray(s).view([("a", np.int64), ("b", np.int64), ("c", np.int64)]).ravel()


def elements_on_surface(space: FESpace, triangles: np.ndarray) -> np.ndarray:
    """Indices of the elements with a face among the boundary ``triangles`` (n_f, 3)."""
    tets = space.body.tetrahedra
    faces = np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]],
                            tets[:, [1, 2, 3]]])
    hit = np.isin(_face_keys(faces), _face_keys(triangles))
    return np.unique(np.flatnonzero(hit) % tets.shape[0])


def elements_in_sphere(space: FESpace, point, radius: float) -> np.ndarray:
    """Indices of the elements whose centroid lies within ``radius`` of ``point``."""
    c = space.body.vertices[space.body.tetrahedra].mean(axis=1)
    return np.flatnonzero(np.linalg.norm(c - np.asarray(point, float), axis=1) <= radius)


def _point_strain_row(space: FESpace, point, key: str) -> np.ndarray:
    """(6, n_dofs) engineering strain at ``point`` inside its element (P2: linear there)."""
    mesh = space.skfem_mesh
    p = np.asarray(point, float)
    try:
        e = int(mesh.element_finder()(*[np.array([v]) for v in p])[0])
    except ValueError:
        raise RegionError(f"config key '{key}': point {p.tolist()} lies outside the mesh; expected "
                          "a point inside the body (or set a radius > 0)") from None
    X = mesh.mapping().invF(p[:, None, None], tind=np.array([e]))[:, 0, :]  # (3, 1) local
    basis = _basis(space, np.array([e]), quadrature=(X, np.array([1.0])))
    G = _voigt_gradients(basis)[:, :, 0, 0]  # (n_local, 6)
    row = np.zeros((6, space.n_dofs))
    np.add.at(row.T, basis.element_dofs[:, 0], G)
    return row


def gauge_row(space: FESpace, material, kind: str, direction, direction2=None,
              triangles: np.ndarray | None = None, point=None, radius: float = 0.0,
              key: str = "ports.outputs", length: float = 0.0, width: float = 0.0,
              average: str = "surface") -> np.ndarray:
    """(n_dofs,) sensor row of a strain (1) or stress (Pa) gauge per metre of nodal
    displacement; located on a boundary region (``triangles``), around a ``point`` on the
    surface (a ``length`` x ``width`` grid along ``direction`` or a disc of ``radius``, m),
    in a sphere (``point``, ``radius`` > 0, ``average="volume"``) or at a ``point``
    (module docstring). ``material``: a Material, the per-element
    :class:`~pipeline.fe.materials.ElementMaterials`, or None (strain only)."""
    w0 = voigt_weights(kind, direction, direction2)
    laws = None  # per-element stiffness where the elements' laws differ
    D = np.eye(6)
    if kind == "stress":
        if material is None:
            raise ValueError(f"{key}: a stress gauge needs the material (pass material=)")
        uniform = material if isinstance(material, Material) else material.uniform
        if uniform is None:
            laws = material
        else:
            D = elasticity_matrix(uniform)
    w = D.T @ w0  # w . (D eps) = (D^T w) . eps

    def per_element(weights: np.ndarray, elements: np.ndarray) -> np.ndarray:
        """(n, 6): D_e^T w_e of each element's own law (rows of ``weights`` or one row)."""
        rows = np.broadcast_to(weights, (elements.size, 6))
        return np.einsum("eji,ej->ei", laws.element_D(elements), rows)

    if triangles is None and radius == 0.0 and length == 0.0:
        row = _point_strain_row(space, point, key)
        if laws is not None:
            mesh = space.skfem_mesh
            e = mesh.element_finder()(*[np.array([c]) for c in np.asarray(point, float)])
            w = per_element(w0, np.asarray(e, dtype=np.int64)[:1])[0]
        return w @ row
    if average == "surface":
        patch = region_patch(space, triangles, key) if triangles is not None else \
            grid_patch(space, point, direction, length, width, radius, key)
        if patch.rotations is not None:  # each piece's own directions (pipeline.fe.gauges)
            d2 = direction if direction2 is None else direction2
            w0 = np.stack([voigt_weights(kind, R @ direction, R @ d2)
                           for R in patch.rotations])
            w = w0 @ D
        if laws is not None:
            w = per_element(w0, patch.elements)
        return strain_row(space, patch, w)
    elements = _gauge_elements(space, triangles, point, radius, key)
    E, vol = element_strain_operator(space, elements)
    if laws is not None:
        weights = ((vol / vol.sum())[:, None] * per_element(w0, elements)).ravel()
    else:
        weights = np.kron(vol / vol.sum(), w)  # (6 n_sel,)
    return np.asarray(E.T @ weights).ravel()


def _gauge_elements(space: FESpace, triangles, point, radius: float, key: str) -> np.ndarray:
    """The elements a region or sphere gauge averages over (RegionError if none)."""
    if triangles is not None:
        elements = elements_on_surface(space, triangles)
        where = "has no element face on it"
    else:
        elements = elements_in_sphere(space, point, radius)
        where = (f"contains no element centroid (radius {radius:g} m; a radius of about "
                     "the element size or more catches some)")
    if elements.size == 0:
        raise RegionError(f"config key '{key}': the gauge region {where}; expected at least "
                          "one element (enlarge the radius or pick a boundary region)")
    return elements


def modal_stress_fields(space: FESpace, material, free: np.ndarray,
                        basis: np.ndarray, correction: np.ndarray | None = None
                        ) -> StressFields:
    """Stress and strain of the reduced basis (n_free, n_b) and of the static correction
    shapes (n_free, n_u) given on the ``free`` DOFs (fixed DOFs move by 0): fields with
    n_b + n_u shapes, basis first."""
    cols = [basis] if correction is None else [basis, correction]
    U = np.zeros((space.n_dofs, sum(c.shape[1] for c in cols)))
    U[free] = np.hstack(cols)
    return stress_fields(space, material, U)
