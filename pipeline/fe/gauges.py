"""Surface gauges: the part of the body's surface a gauge covers, and the strain there.

A foil strain gauge reads the strain of the surface it is bonded to, averaged over its
grid area S:

    g(u) = (1 / |S|) int_S w . eps(u)(x) dA ,

with w the Voigt weights of the gauge's direction(s) (:func:`pipeline.fe.strain.voigt_weights`)
and eps(x) the strain of the element whose boundary face carries x, evaluated on that
face (not an average over the element, which in bending reads the strain half an element
below the surface). The strain is constant in a P1 element and linear in a P2 one, so
on every flat piece P of S (a boundary triangle, or the convex polygon of one that lies
under the grid) the integral is exact with one point,

    int_P eps dA = |P| eps(c_P),   c_P the centroid of P,

and g(u) = sum_P |P| w . eps_{e(P)}(c_P) / sum_P |P|, one row of T per gauge.

The surface S:

- a boundary ``region``: its triangles, whole;
- a ``point`` p on the surface with a grid ``length`` l and ``width`` b: the rectangle
  |(x - p) . e1| <= l / 2, |(x - p) . e2| <= b / 2, with n the outward surface normal
  at p (:func:`surface_normal`: the vertex normals of the boundary triangle nearest to p
  interpolated at p), e1 the gauge direction projected on the plane normal to n (the
  grid's measuring axis) and e2 = n x e1;
- a ``point`` with a ``radius`` r: the disc |x - p| <= r in that plane, taken as the
  regular 32-gon of the same area (apothem r sqrt(pi / (32 tan(pi / 32)))).

The grid's bounding planes contain n, so they cut a curved surface too (a gauge bent
over a fillet); S is the connected patch of boundary triangles around p cut by them,
grown across shared edges from the triangle nearest p through triangles that face the
same side (n_t . n > 0.1), so that a grid never wraps around a sharp edge onto another
face. A grid bent over a curved surface measures along the surface: on the piece of a
face with normal n_t its directions d are R_t d, R_t the smallest rotation taking n to
n_t (about n x n_t; R_t = I on a flat face), so a grid along a fillet's arc reads the
strain along the arc at every point, as the bonded foil does. A region's directions are
the same on all its faces.

Point p must lie on the surface: within a quarter of the longest edge h of the nearest
boundary triangle (the chords of a curved face of radius R lie up to h^2 / (8 R) off the
true surface, at most h / 8 where the mesh resolves the curve, h <= R).

Shapes: points (n_p, 3) m, areas (n_p,) m^2, rows (n_dofs,) per unit nodal displacement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pipeline.errors import RegionError
from pipeline.fe.kernels import inverse_jacobians
from pipeline.fe.space import FESpace

#: sides of the polygon that stands for a round gauge (area kept equal to the disc's)
DISC_SIDES = 32
#: a triangle joins the gauge's patch if its outward normal is within ~84 deg of the
#: normal at the gauge's point (n_t . n > 0.1): a 90 deg edge stops the patch
SAME_SIDE = 0.1
#: a gauge's point may lie this fraction of the nearest boundary triangle's longest edge
#: off the faceted surface
ON_SURFACE = 0.25
#: a grid direction more than 45 deg off the surface's tangent plane is refused
MIN_TANGENT = math.cos(math.radians(45.0))


@dataclass(frozen=True)
class SurfacePatch:
    """Flat pieces of surface under a gauge: pieces k = 0..n_p-1 lie on a boundary face of
    element ``elements[k]`` with area ``areas[k]`` (m^2) and centroid ``points[k]`` (m).

    rotations: (n_p, 3, 3) or None: R_k carries the gauge's directions from its point to
    piece k (the grid bent over a curved surface; module docstring); None: the
    directions are the same on every piece (a region)."""

    elements: np.ndarray
    points: np.ndarray
    areas: np.ndarray
    rotations: np.ndarray | None = None


@dataclass(frozen=True)
class BoundaryFaces:
    """The boundary triangles of a mesh with what a gauge needs of them.

    triangles (n_bf, 3) vertex indices; owners (n_bf,) the element each is a face of;
    normals (n_bf, 3) unit outward normals; areas (n_bf,) m^2; centroids (n_bf, 3) m.
    """

    triangles: np.ndarray
    owners: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    centroids: np.ndarray


def boundary_faces(space: FESpace) -> BoundaryFaces:
    """The mesh's boundary triangles (scikit-fem's boundary facets) with their owner
    elements and outward normals (away from the owner's fourth vertex)."""
    mesh = space.skfem_mesh
    bf = mesh.boundary_facets()
    tris = mesh.facets[:, bf].T.astype(np.int64)
    owners = mesh.f2t[0, bf].astype(np.int64)
    tets = space.body.tetrahedra[owners]
    opposite = tets.sum(axis=1) - tris.sum(axis=1)  # the owner's vertex not on the face
    v = space.body.vertices
    a, b, c = (v[tris[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    twice_area = np.linalg.norm(cross, axis=1)
    normals = cross / np.where(twice_area > 0, twice_area, 1.0)[:, None]
    inward = np.einsum("ij,ij->i", v[opposite] - a, normals) > 0
    normals[inward] *= -1.0
    return BoundaryFaces(tris, owners, normals, 0.5 * twice_area, (a + b + c) / 3.0)


def _keys(tris: np.ndarray) -> np.ndarray:
    s = np.sort(np.asarray(tris, dtype=np.int64), axis=1)
    return np.ascontiguousarray(s).view([("a", np.int64), ("b", np.int64), ("c", np.int64)]).ravel()


def region_patch(space: FESpace, triangles: np.ndarray, key: str) -> SurfacePatch:
    """The whole boundary ``triangles`` (n_f, 3) of a region, one piece each."""
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise RegionError(f"config key '{key}.region': a gauge covers a face region; got "
                          f"cells of {triangles.shape[-1]} vertices (a line or point region)")
    faces = boundary_faces(space)
    table = _keys(faces.triangles)
    order = np.argsort(table)
    query = _keys(triangles)
    pos = np.searchsorted(table[order], query).clip(max=order.size - 1)
    found = table[order][pos] == query
    if not found.all():
        raise RegionError(f"config key '{key}.region': {int((~found).sum())} of its triangles "
                          "are not boundary faces of the mesh (an inner surface); expected a "
                          "boundary region, or 'average: volume' for the elements on it")
    idx = order[pos]
    return SurfacePatch(faces.owners[idx], faces.centroids[idx], faces.areas[idx])


def _point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
                             ) -> np.ndarray:
    """(n,) distance (m) from the point p (3,) to each triangle (a, b, c) (n, 3)."""
    n = np.cross(b - a, c - a)
    nn = np.einsum("ij,ij->i", n, n)
    nn = np.where(nn > 0, nn, 1.0)
    t = np.einsum("ij,ij->i", p - a, n) / nn
    q = p - t[:, None] * n  # projection on the triangle's plane
    inside = np.ones(a.shape[0], dtype=bool)
    for u, w in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(w - u, q - u), n) >= 0
    dist = np.abs(t) * np.sqrt(nn)
    edge = np.full(a.shape[0], np.inf)
    for u, w in ((a, b), (b, c), (c, a)):
        e = w - u
        s = np.clip(np.einsum("ij,ij->i", p - u, e) / np.maximum(np.einsum("ij,ij->i", e, e),
                                                                1e-300), 0.0, 1.0)
        edge = np.minimum(edge, np.linalg.norm(p - (u + s[:, None] * e), axis=1))
    return np.where(inside, dist, edge)


def _edge_neighbours(tris: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(n_bf, n_bf) adjacency of triangles that share an edge."""
    pairs = tris[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    key = pairs.min(axis=1) * n_vertices + pairs.max(axis=1)
    owner = np.repeat(np.arange(tris.shape[0]), 3)
    order = np.argsort(key, kind="stable")
    same = key[order][1:] == key[order][:-1]
    i, j = owner[order][:-1][same], owner[order][1:][same]
    n = tris.shape[0]
    adj = sp.coo_matrix((np.ones(2 * i.size), (np.concatenate([i, j]), np.concatenate([j, i]))),
                        shape=(n, n))
    return adj.tocsr()


def _clip(polygon: np.ndarray, origin: np.ndarray, planes: np.ndarray, offsets: np.ndarray
          ) -> np.ndarray:
    """The part of the convex ``polygon`` (m, 3) where (x - origin) . planes[k] <= offsets[k]
    for every k (Sutherland-Hodgman); (0, 3) when nothing is left."""
    for u, h in zip(planes, offsets):
        if polygon.shape[0] == 0:
            break
        s = (polygon - origin) @ u - h
        if (s <= 0).all():
            continue
        out = []
        for k in range(polygon.shape[0]):
            x0, x1, s0, s1 = polygon[k], polygon[(k + 1) % polygon.shape[0]], s[k], \
                s[(k + 1) % polygon.shape[0]]
            if s0 <= 0:
                out.append(x0)
            if (s0 < 0 < s1) or (s1 < 0 < s0):
                out.append(x0 + (s0 / (s0 - s1)) * (x1 - x0))
        polygon = np.array(out).reshape(-1, 3)
    return polygon


def _area_centroid(polygon: np.ndarray) -> tuple[float, np.ndarray]:
    """Area (m^2) and centroid (3,) of a flat convex polygon (m, 3), fanned from vertex 0."""
    if polygon.shape[0] < 3:
        return 0.0, polygon.mean(axis=0) if polygon.size else np.zeros(3)
    v0, v1, v2 = polygon[0], polygon[1:-1], polygon[2:]
    areas = 0.5 * np.linalg.norm(np.cross(v1 - v0, v2 - v0), axis=1)
    total = float(areas.sum())
    if total <= 0:
        return 0.0, polygon.mean(axis=0)
    return total, ((v0 + v1 + v2) / 3.0 * areas[:, None]).sum(axis=0) / total


def grid_planes(normal: np.ndarray, direction, length: float, width: float, radius: float,
                key: str) -> tuple[np.ndarray, np.ndarray]:
    """The bounding planes of a gauge's grid at a surface point with outward ``normal``:
    (unit plane normals (k, 3), offsets (k,) m); see the module docstring."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    e1 = d - (d @ normal) * normal
    along = float(np.linalg.norm(e1))
    if length > 0:
        if along < MIN_TANGENT:
            raise RegionError(
                f"config key '{key}.direction': {list(map(float, direction))} is "
                f"{math.degrees(math.acos(min(along, 1.0))):.0f} deg off the surface at the "
                f"gauge's point (outward normal {np.round(normal, 3).tolist()}); expected a "
                "direction along the surface (within 45 deg of it) for a grid's length")
        e1 /= along
        e2 = np.cross(normal, e1)
        return np.array([e1, -e1, e2, -e2]), np.array([length, length, width, width]) / 2.0
    if along < 1e-6:  # a round gauge has no axis: any tangent will do
        e1 = np.cross(normal, np.eye(3)[int(np.argmin(np.abs(normal)))])
        along = float(np.linalg.norm(e1))
    e1 /= along
    e2 = np.cross(normal, e1)
    theta = 2.0 * np.pi * np.arange(DISC_SIDES) / DISC_SIDES
    planes = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    apothem = radius * math.sqrt(math.pi / (DISC_SIDES * math.tan(math.pi / DISC_SIDES)))
    return planes, np.full(DISC_SIDES, apothem)


def surface_normal(faces: BoundaryFaces, seed: int, point: np.ndarray, vertices: np.ndarray
                   ) -> np.ndarray:
    """(3,) unit outward normal of the surface at ``point`` on boundary triangle ``seed``:
    the vertex normals of its corners (area-weighted means of the normals of the faces
    around each corner that turn less than 45 deg from the seed's: a sharp edge is not
    smoothed) interpolated with the point's barycentric coordinates. On a flat face it is
    the face's normal; on a curved one it is off the true normal by O((h / R)^2) instead
    of the single facet's O(h / R)."""
    corners = faces.triangles[seed]
    n0 = faces.normals[seed]
    a, b, c = vertices[corners]
    cross = np.cross(b - a, c - a)
    q = point - a
    # barycentric coordinates of the point's projection on the seed's plane, clamped
    lam = np.array([np.cross(c - b, point - b) @ cross, np.cross(a - c, point - c) @ cross,
                    np.cross(b - a, q) @ cross]) / (cross @ cross)
    lam = np.clip(lam, 0.0, None)
    lam /= lam.sum()
    near = faces.normals @ n0 > MIN_TANGENT  # faces within 45 deg of the seed's
    n = np.zeros(3)
    for weight, corner in zip(lam, corners):
        ring = near & (faces.triangles == corner).any(axis=1)
        vertex = (faces.areas[ring, None] * faces.normals[ring]).sum(axis=0)
        n += weight * vertex / np.linalg.norm(vertex)
    return n / np.linalg.norm(n)


def grid_patch(space: FESpace, point, direction, length: float = 0.0, width: float = 0.0,
               radius: float = 0.0, key: str = "ports.outputs") -> SurfacePatch:
    """The surface under a gauge at ``point`` (on the surface) with a ``length`` x
    ``width`` grid along ``direction`` or a ``radius`` (m; module docstring)."""
    faces = boundary_faces(space)
    v = space.body.vertices
    p = np.asarray(point, float)
    tris = faces.triangles
    dist = _point_triangle_distance(p, v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]])
    seed = int(np.argmin(dist))
    edges = v[tris[seed]] - v[tris[seed][[1, 2, 0]]]
    tolerance = ON_SURFACE * float(np.linalg.norm(edges, axis=1).max())
    if dist[seed] > tolerance:
        raise RegionError(
            f"config key '{key}.point': {p.tolist()} lies {dist[seed]:.3g} m from the body's "
            f"surface; expected a point on the surface (within {tolerance:.3g} m, a quarter "
            "of the local element size) for a surface gauge, or 'average: volume' for the "
            "mean over the elements around a point inside the body")
    normal = surface_normal(faces, seed, p, v)
    planes, offsets = grid_planes(normal, direction, length, width, radius, key)
    nominal = length * width if length > 0 else math.pi * radius * radius  # m^2 (flat)
    neighbours = _edge_neighbours(tris, space.body.n_vertices)
    pieces, elements, points, areas = [], [], [], []
    seen = {seed}
    stack = [seed]
    while stack:
        t = stack.pop()
        piece = _clip(v[tris[t]], p, planes, offsets)
        area, centroid = _area_centroid(piece)
        if not area > 1e-12 * min(nominal, faces.areas[t]):  # nothing, or a sliver
            continue
        pieces.append(t)
        elements.append(faces.owners[t])
        points.append(centroid)
        areas.append(area)
        for u in neighbours.indices[neighbours.indptr[t]:neighbours.indptr[t + 1]]:
            if u not in seen and faces.normals[u] @ normal > SAME_SIDE:
                seen.add(int(u))
                stack.append(int(u))
    if not areas:
        size = f"{length:g} m x {width:g} m" if length > 0 else f"radius {radius:g} m"
        raise RegionError(f"config key '{key}': the gauge's grid ({size}) covers no surface "
                          f"at {p.tolist()}; expected a grid larger than the round-off of the "
                          "coordinates (1e-9 of the body's size or more)")
    return SurfacePatch(np.array(elements, dtype=np.int64), np.array(points), np.array(areas),
                        smallest_rotations(normal, faces.normals[np.array(pieces)]))


def smallest_rotations(n0: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations R_k with R_k n0 = normals[k] (unit vectors, n0 . n_k > -1), each
    about the axis n0 x n_k (Rodrigues: R = I + [v]x + [v]x^2 / (1 + c), v = n0 x n_k,
    c = n0 . n_k)."""
    v = np.cross(n0, normals)
    c = normals @ n0
    vx = np.zeros((normals.shape[0], 3, 3))
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    vx -= vx.transpose(0, 2, 1)
    return np.eye(3) + vx + (vx @ vx) / (1.0 + c)[:, None, None]


def strain_row(space: FESpace, patch: SurfacePatch, weights: np.ndarray) -> np.ndarray:
    """(n_dofs,) row r with r . U = sum_k a_k w_k . eps_{e_k}(x_k) / sum_k a_k: the
    area-weighted mean over the patch's pieces (a_k their areas, x_k their points) of the
    Voigt-weighted engineering strain (``weights`` (6,) or one row per piece (n_p, 6),
    VOIGT order: a stress gauge's D_k^T w where pieces differ in material) of the nodal
    displacements U (m), each piece's strain from its own element's shape functions.

    On a straight-sided element x_k maps to reference coordinates xi = G (x_k - x_0),
    G = J^-1, and grad phi_b(x_k) = G^T dphi_b/dxi (xi); with W the symmetric 3x3 matrix of
    the weights (engineering shear: W_ij = w_ij off the diagonal), w . eps = sum_ij W_ij
    du_i/dx_j, so node b's component c gets (W grad phi_b)_c.
    """
    e = patch.elements
    G, _ = inverse_jacobians(space, e)  # (n_p, 3, 3): G[p, k, i] = d xi_k / d x_i
    origin = space.body.vertices[space.body.tetrahedra[e, 0]]
    xi = np.einsum("pki,pi->pk", G, patch.points - origin)
    ref = space.skfem_element().elem
    n_loc = space.element_nodes.shape[1]
    dref = np.stack([np.broadcast_to(ref.lbasis(xi.T, b)[1], (3, e.size))
                     for b in range(n_loc)])  # (b, k, n_p)
    grad = np.einsum("bkp,pki->pbi", dref, G)  # (n_p, b, i) 1/m
    w = np.broadcast_to(np.asarray(weights, float), (e.size, 6))
    W = w[:, [[0, 5, 4], [5, 1, 3], [4, 3, 2]]]  # (n_p, 3, 3) symmetric
    share = patch.areas / patch.areas.sum()
    values = (grad @ W) * share[:, None, None]  # (n_p, b, c)
    dofs = 3 * space.element_nodes[e][:, :, None] + np.arange(3)
    return np.bincount(dofs.ravel(), weights=values.ravel(), minlength=space.n_dofs)
