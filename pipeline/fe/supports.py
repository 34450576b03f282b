"""Supports beyond held global components: what the supports leave free, components held
in a local frame, and elastic supports (springs and bushings to ground).

**Rigid freedoms.** With R (n_dofs x 6) the rigid-body motions at the centre of mass G
(:func:`pipeline.fe.body.rigid_body_modes`, rotation columns divided by the body's rms
radius L so that the six columns move the body by comparable amounts), a twist t is a
motion the supports leave free when it moves no held DOF and strains no support spring:

    R_c t = 0 (c: the fixed DOFs),   t^T R^T S R t = 0 (S: the support stiffness below),

so the number of rigid-body modes of the supported body is n_rigid = 6 - rank of those
conditions, known before any eigen solve. The free twists are named greedily by the
unit twist (translation along or rotation about x, y, z) closest to what is left of
them (a rotation about an axis off the centre of mass, v . omega = 0, by its axis), and
their displacement fields R t are exact null vectors of the supported K.

**Components held in a local frame** (cylindrical: radial, tangential, axial about a
line; face: normal and tangential from the region's triangles) are held exactly: every
held unit direction e at node i is a row of C (C u = 0), and
:func:`pipeline.fe.constraints.local_frame_constraint` turns C into the coordinates
u = T q that satisfy it (node i's DOFs replaced by its kept unit directions); the
eigensolver and the static solves run on T^T K T, T^T M T.

**Springs to ground** on a region: per unit area, k (N/m^3) per frame component c with
unit vector e_c at node i, node i gets w_i sum_c k_c e_c e_c^T with w_i the integral of
its shape function over the region (:func:`pipeline.fe.space.weighted_region`: sum of
w_i = area), so a uniform displacement u meets the force k A u, exactly as the
continuous spring bed; a total stiffness K_c (N/m) is k_c = K_c / A.

**Bushing**: a 6x6 stiffness K_b at a point P tied to the region by a distributing
coupling (as a port's load, :mod:`pipeline.fe.ports`): the twist of P is
q = [u_bar + theta x (P - c); theta] with u_bar = sum w_i u_i / A and
theta = J^-1 sum w_i (r_i x u_i), r_i = x_i - c, J = sum w_i (|r_i|^2 I - r_i r_i^T);
q = W u, and the bushing adds W^T K_b W (a dense block on the region's DOFs).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from pipeline.config import Support
from pipeline.errors import RegionError
from pipeline.fe.body import rigid_body_modes, skew
from pipeline.fe.regions import get_region
from pipeline.fe.space import (REGION_KINDS, FESpace, region_nodes, triangle_nodes,
                               weighted_region)

log = logging.getLogger(__name__)

#: the most nodes a bushing's region may have: it couples all of their DOFs, a dense
#: (3 n)^2 block of K (3000 nodes: 81M entries, 1.3 GB with the CSR indices)
MAX_BUSHING_NODES = 3000
#: a twist is free when the conditions hold to this relative accuracy (round-off of
#: exact zeros is ~1e-16; the weakest real constraint is far above)
RIGID_TOL = 1e-9
#: springs that hold a rigid motion at omega^2 below this fraction of the stiffness
#: scale (median K_ii / M_ii) hold it no better than the eigensolver's rigid-mode test
#: (1e-6 of its free-body shift, itself 1e-7 of that scale): the motion counts as free
SOFT_SUPPORT = 1e-13
#: names of the six unit twists, in the column order of the rigid-body modes
TWIST_NAMES = ("translation_x", "translation_y", "translation_z",
               "rotation_x", "rotation_y", "rotation_z")


@dataclass(frozen=True)
class RigidFreedoms:
    """The rigid-body motions the supports leave free.

    names: (r,) ``translation_x`` ... ``rotation_z``, the unit twist each is closest to.
    fields: (n_dofs, r) nodal displacements of each motion (m), zero on the held DOFs;
    (0, r) in the form :meth:`without_fields` makes.
    twists: (r, 6) the twist [v; omega L] of each motion at ``center`` ((3,) m), L =
    ``length`` (m), so that ``fields`` = R_center diag(1, 1, 1, 1/L, 1/L, 1/L) twists^T
    (:meth:`fields_at`), or None.
    """

    names: tuple[str, ...]
    fields: np.ndarray
    twists: np.ndarray | None = None
    center: np.ndarray | None = None
    length: float = 1.0

    @property
    def count(self) -> int:
        return len(self.names)

    def fields_at(self, node_points: np.ndarray) -> np.ndarray:
        """(3 p, r) the displacements (m) of each motion at ``node_points`` (p, 3): the
        rows of ``fields`` of those points, from the twists (no (n_dofs, r) array)."""
        R = rigid_body_modes(node_points, self.center)
        R[:, 3:] /= self.length
        return R @ np.asarray(self.twists).T

    def without_fields(self) -> RigidFreedoms:
        """The same motions without the (n_dofs, r) ``fields`` (what an MPI rank is sent:
        it evaluates :meth:`fields_at` on its own points)."""
        return dataclasses.replace(self, fields=np.zeros((0, self.count)))


@dataclass(frozen=True)
class SupportStiffness:
    """The supports that add stiffness instead of removing DOFs, on all n_dofs DOFs.

    springs: (n_dofs, n_dofs) CSR N/m of the springs and bushings, or None.
    constraint: (n_c, n_dofs) CSR, one unit direction per held local component (the rows
    C of C u = 0, held exactly by :mod:`pipeline.fe.constraints`), or None.
    """

    springs: sp.csr_matrix | None = None
    constraint: sp.csr_matrix | None = None


def frame_axes(space: FESpace, triangles: np.ndarray, nodes: np.ndarray, frame,
               key: str) -> np.ndarray:
    """(n, 3, 3): at every node of ``nodes``, the unit vectors of ``frame``'s components
    as rows: global (x, y, z); cylindrical (radial, tangential, axial); face (normal and
    two tangents; the normal is the principal direction of the area-weighted sum of
    n n^T over the region's triangles at that node, which needs no consistent
    orientation of the triangles)."""
    x = space.node_points[nodes]
    if frame is None or frame.kind == "global":
        return np.broadcast_to(np.eye(3), (nodes.size, 3, 3)).copy()
    if frame.kind == "cylindrical":
        a = np.asarray(frame.axis, dtype=float)
        a = a / np.linalg.norm(a)
        r = x - np.asarray(frame.point, dtype=float)
        r -= np.outer(r @ a, a)
        dist = np.linalg.norm(r, axis=1)
        if dist.min() <= 1e-9 * max(dist.max(), 1e-300):
            raise RegionError(f"config key '{key}': a node of the region lies on the "
                              "cylindrical frame's axis, where radial and tangential are "
                              "undefined; expected a region away from the axis (check "
                              "frame.point and frame.axis)")
        er = r / dist[:, None]
        return np.stack([er, np.cross(a, er), np.broadcast_to(a, er.shape)], axis=1)
    v = space.body.vertices
    a, b, c = (v[triangles[:, i]] for i in range(3))
    n2 = np.cross(b - a, c - a)  # twice the area times the unit normal
    area = 0.5 * np.linalg.norm(n2, axis=1)
    outer = 0.25 * n2[:, :, None] * n2[:, None, :] / np.maximum(area, 1e-300)[:, None, None]
    tri_nodes = triangle_nodes(space, triangles)
    order = np.argsort(nodes)
    acc = np.zeros((nodes.size, 3, 3))
    for j in range(tri_nodes.shape[1]):
        at = np.searchsorted(nodes, tri_nodes[:, j], sorter=order).clip(max=nodes.size - 1)
        idx = order[at]
        ok = nodes[idx] == tri_nodes[:, j]
        np.add.at(acc, idx[ok], outer[ok])
    _, vec = np.linalg.eigh(acc)  # ascending: the normal is the last eigenvector
    return np.stack([vec[:, :, 2], vec[:, :, 1], vec[:, :, 0]], axis=1)


def _node_blocks(nodes: np.ndarray, blocks: np.ndarray, n_dofs: int) -> sp.csr_matrix:
    """(n_dofs, n_dofs) CSR with the (3, 3) ``blocks`` on the diagonal blocks of ``nodes``."""
    dofs = 3 * nodes[:, None] + np.arange(3)
    rows = np.repeat(dofs, 3, axis=1).ravel()
    cols = np.tile(dofs, (1, 3)).ravel()
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(n_dofs, n_dofs))


def _bushing_matrix(space: FESpace, region, support: Support, key: str) -> sp.csr_matrix:
    """W^T K_b W on the region's DOFs (module docstring)."""
    Kb = np.asarray(support.bushing.stiffness, dtype=float)
    w, c = region.weights, region.centroid
    P = c if support.bushing.point is None else np.asarray(support.bushing.point, dtype=float)
    r = space.node_points[region.nodes] - c
    n = region.nodes.size
    W = np.zeros((6, n, 3))
    W[0:3] = (np.eye(3)[:, None, :] * (w / region.measure)[None, :, None])
    needs_rotation = np.abs(Kb[3:]).max() > 0 or np.linalg.norm(P - c) > 0
    if needs_rotation:
        J = (w * (r * r).sum(1)).sum() * np.eye(3) - np.einsum("i,ij,ik->jk", w, r, r)
        eig = np.linalg.eigvalsh(J)
        if eig[0] <= 1e-10 * max(eig[-1], 1e-300):
            raise RegionError(f"config key '{key}': region '{region.name}' cannot carry a "
                              "rotation about every axis (its nodes lie on a line or a "
                              "point); expected a surface region, or 3 translational "
                              "stiffnesses at its centroid")
        Jinv = np.linalg.inv(J)
        # theta = J^-1 sum_i w_i skew(r_i) u_i
        W[3:6] = np.einsum("jk,i,ikl->jil", Jinv, w, np.stack([skew(ri) for ri in r]))
        # u_P = u_bar + theta x (P - c) = u_bar - skew(P - c) theta
        W[0:3] -= np.einsum("jk,kil->jil", skew(P - c), W[3:6])
    Wd = W.reshape(6, 3 * n)
    dofs = (3 * region.nodes[:, None] + np.arange(3)).ravel()
    block = Wd.T @ Kb @ Wd
    rows = np.repeat(dofs, dofs.size)
    cols = np.tile(dofs, dofs.size)
    return sp.csr_matrix((block.ravel(), (rows, cols)), shape=(space.n_dofs, space.n_dofs))


def support_stiffness(space: FESpace, regions: Mapping[str, np.ndarray],
                      supports: Sequence[Support]) -> SupportStiffness:
    """Springs and bushings of ``supports``, and the directions C of the components held
    in a local frame (module docstring). Needs no K: every error is found before the
    assembly."""
    springs, rows = [], []
    n_dofs = space.n_dofs
    for i, s in enumerate(supports):
        key = f"supports[{i}]"
        if s.spring is None and s.bushing is None and not s.local_fix:
            continue
        tris = get_region(regions, s.region, f"{key}.region")
        region = weighted_region(space, s.region, tris)
        needs_face = (s.spring is not None and s.spring.kind == "per_area") or \
            (s.frame is not None and s.frame.kind == "face")
        if needs_face and region.dimension != 2:
            what = "springs per unit area" if s.spring is not None and \
                s.spring.kind == "per_area" else "a face frame"
            raise RegionError(
                f"config key '{key}.region': region '{s.region}' is a "
                f"{REGION_KINDS[region.dimension][0]} region; {what} need a face "
                "region (use spring.total on a line or point region, or a cylindrical or "
                "global frame)")
        if s.bushing is not None:
            if region.nodes.size > MAX_BUSHING_NODES:
                raise RegionError(
                    f"config key '{key}.region': region '{s.region}' has "
                    f"{region.nodes.size} nodes; a bushing couples all of them (a dense "
                    f"block of K), expected at most {MAX_BUSHING_NODES} (a smaller region)")
            springs.append(_bushing_matrix(space, region, s, f"{key}.bushing"))
            continue
        if s.spring is not None:
            axes = frame_axes(space, tris, region.nodes, s.frame, f"{key}.frame")
            k = np.asarray(s.spring.values, dtype=float)
            if s.spring.kind == "total":
                k = k / region.measure
            if k.size == 2:  # face frame: normal, then both tangents
                k = k[[0, 1, 1]]
            blocks = np.einsum("n,c,nci,ncj->nij", region.weights, k, axes, axes)
            springs.append(_node_blocks(region.nodes, blocks, n_dofs))
            continue
        # every node of the region is held (a P2 vertex has zero area weight, but is on it)
        nodes = region_nodes(space, tris)
        axes = frame_axes(space, tris, nodes, s.frame, f"{key}.frame")
        names = ("normal", "tangential") if s.frame.kind == "face" else \
            ("radial", "tangential", "axial")
        held = [c for c in range(3) if names[min(c, len(names) - 1)] in s.local_fix]
        e = axes[:, held, :]  # (n, h, 3): one constraint row per node and held direction
        dofs = np.broadcast_to(3 * nodes[:, None, None] + np.arange(3), e.shape)
        rows.append((dofs.reshape(-1, 3), e.reshape(-1, 3)))
    constraint = None
    if rows:
        dofs = np.concatenate([r[0] for r in rows])
        values = np.concatenate([r[1] for r in rows])
        constraint = sp.csr_matrix((values.ravel(), dofs.ravel(), 3 * np.arange(dofs.shape[0] + 1)),
                                   shape=(dofs.shape[0], n_dofs))
    return SupportStiffness(sum(springs[1:], springs[0]).tocsr() if springs else None,
                            constraint)


def _null_space(G: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Orthonormal columns spanning {basis y : y^T basis^T G basis y ~ 0} (G symmetric
    positive semi-definite; ~0: below :data:`RIGID_TOL` of its largest eigenvalue)."""
    if basis.shape[1] == 0:
        return basis
    Gb = basis.T @ G @ basis
    lam, vec = np.linalg.eigh(0.5 * (Gb + Gb.T))
    scale = max(float(np.abs(np.linalg.eigvalsh(0.5 * (G + G.T))).max()), 1e-300)
    return basis @ vec[:, lam <= RIGID_TOL * scale]


def rigid_freedoms(node_points: np.ndarray, center: np.ndarray, fixed: np.ndarray,
                   springs: sp.spmatrix | None = None,
                   constraint: sp.spmatrix | None = None, rigid_mass: np.ndarray | None = None,
                   omega2_floor: float = 0.0, fields: bool = True) -> RigidFreedoms:
    """The rigid-body motions that move no DOF of ``fixed``, no held local direction (the
    rows of ``constraint``, (n_c, n_dofs)) and strain no spring of ``springs`` ((n_dofs,
    n_dofs) N/m), named (module docstring). Each kind is judged on its own scale.

    ``rigid_mass`` ((6, 6) R_O^T M R_O at the origin, :class:`BodyProperties`) and
    ``omega2_floor`` (rad^2/s^2): a rigid motion that the springs hold at omega^2 below
    the floor counts as free, with a warning (the eigensolver could not tell it from
    0 Hz: :data:`SOFT_SUPPORT`).

    ``fields`` False: the motions without their (n_dofs, r) fields
    (:meth:`RigidFreedoms.without_fields`), judged from R's rows at the held DOFs, the
    held directions' and the springs' DOFs only, never R at every DOF (48 bytes a DOF,
    as much again for S R): what MPI rank 0 evaluates on the whole mesh. The held DOFs'
    and directions' conditions are the same numbers; the springs' R^T S R is summed over
    their DOFs alone, equal to round-off."""
    x = np.asarray(node_points, dtype=float)
    L = float(np.sqrt(((x - center) ** 2).sum(axis=1).mean())) or 1.0
    if fields:
        R = rigid_body_modes(x, center)
        R[:, 3:] /= L

        def rows(dofs):
            return R[dofs]
    else:
        def rows(dofs):
            return _rigid_rows(x, center, L, dofs)
    N = np.eye(6)
    if fixed.size:
        A = rows(fixed)
        N = _null_space(A.T @ A, N)
    if constraint is not None and constraint.shape[0] and N.shape[1]:
        if fields:
            A = constraint @ R
        else:  # its columns renumbered to those it holds: the same sums, term by term
            C = sp.csr_matrix(constraint)
            cols = np.unique(C.indices)
            A = sp.csr_matrix((C.data, np.searchsorted(cols, C.indices), C.indptr),
                              shape=(C.shape[0], cols.size)) @ rows(cols)
        N = _null_space(A.T @ A, N)
    if springs is not None and N.shape[1]:
        if fields:
            RSR = R.T @ (springs @ R)
        else:  # the springs' rows and columns only
            S = sp.csr_matrix(springs)
            held = np.union1d(np.flatnonzero(np.diff(S.indptr)), S.indices)
            Rs = rows(held)
            RSR = Rs.T @ (S[held][:, held] @ Rs)
        G = N.T @ RSR @ N
        # twist metric: the rigid mass at the centre, rotations scaled as in R
        shift = np.eye(6)
        shift[0:3, 3:6] = skew(np.asarray(center, dtype=float))
        scale = np.diag([1.0, 1.0, 1.0, 1.0 / L, 1.0 / L, 1.0 / L])
        Mt = (np.eye(6) if rigid_mass is None
              else scale @ shift.T @ np.asarray(rigid_mass) @ shift @ scale)
        Mt = N.T @ Mt @ N
        lam, vec = sla.eigh(0.5 * (G + G.T), 0.5 * (Mt + Mt.T))
        # round-off of an exact zero: ~1e-16 of the stiffest spring's omega^2
        zero = lam <= 1e-14 * max(float(np.abs(lam).max()), 1e-300)
        free = lam <= max(omega2_floor, 0.0) if rigid_mass is not None else zero
        if (free & ~zero).any():
            log.warning("%d rigid-body motion(s) left by the held components meet springs "
                        "too soft to hold them (omega^2 below %.1e rad^2/s^2, where the "
                        "eigensolver sees 0 Hz): treated as free", int((free & ~zero).sum()),
                        omega2_floor)
        N, _ = np.linalg.qr(N @ vec[:, free | zero]) if (free | zero).any() else (N[:, :0], None)
    names, twists = [], []
    for _ in range(N.shape[1]):
        # the unit twist closest to the span (ties to round-off: the first in TWIST_NAMES)
        score = np.linalg.norm(N, axis=1)
        k = int(np.flatnonzero(score >= score.max() - 1e-6)[0])
        t = N @ N[k]
        t /= np.linalg.norm(t)
        name = TWIST_NAMES[k]
        v, w = t[:3], t[3:]
        if np.linalg.norm(w) > 1e-3 and abs(v @ w) <= 1e-6 * np.linalg.norm(w):
            # a rotation about an axis off the centre of mass (v = -w x p, v . w = 0)
            name = TWIST_NAMES[3 + int(np.argmax(np.abs(w)))]
        names.append(name if name not in names else f"{name}_{names.count(name) + 1}")
        twists.append(t)
        N = N - np.outer(t, t @ N)
        u, s, _ = np.linalg.svd(N, full_matrices=False)
        N = u[:, s > 1e-8]
    twists = np.array(twists).reshape(-1, 6)
    if not fields:
        motion = np.zeros((0, twists.shape[0]))
    else:
        motion = R @ twists.T if twists.size else np.zeros((x.size, 0))
    return RigidFreedoms(tuple(names), motion, twists, np.array(center, dtype=float), L)


def _rigid_rows(points: np.ndarray, center: np.ndarray, length: float,
                dofs: np.ndarray) -> np.ndarray:
    """(dofs.size, 6) the rows ``dofs`` (3 p + c) of the rigid-body modes at ``center``
    with the rotation columns divided by ``length`` (m), from those DOFs' points alone:
    the numbers of the whole (n_dofs, 6) array's rows."""
    dofs = np.asarray(dofs, dtype=np.int64)
    R = rigid_body_modes(points[dofs // 3], center).reshape(-1, 3, 6)
    R = R[np.arange(dofs.size), dofs % 3]
    R[:, 3:] /= length
    return R


def support_summary(fe, modes) -> list[str]:
    """Summary lines of the supports: the rigid-body modes they leave and the
    components held exactly in a local frame (:mod:`pipeline.fe.constraints`); logged as
    well."""
    lines = []
    if fe.n_rigid:
        lines.append(f"supports leave {fe.n_rigid} rigid-body mode(s) at 0 Hz: "
                     + ", ".join(fe.rigid.names))
    if fe.constraint is not None:
        lines.append(f"{fe.constraint.what}: {fe.constraint.held} free DOF(s) held exactly "
                     f"(u = T q, {fe.constraint.n_q} coordinates)")
    for line in lines:
        log.info("%s", line)
    return lines


def refuse_grounded_supports(raw_supports, path) -> None:
    """Refuse (ConfigError, one line) an Exudyn export of the file ``path`` whose stored
    config (``raw_supports``: its ``supports`` list as read) has springs, bushings or
    components held in a local frame: the export's matrices are those of the unsupported
    body with the fixed DOFs removed, which cannot carry them."""
    from pipeline._util import validate

    for i, item in enumerate(raw_supports or []):
        kinds = [k for k in ("spring", "bushing", "frame") if isinstance(item, dict) and k in item]
        if kinds:
            raise validate.fail(
                f"supports[{i}]", kinds[0],
                f"supports that fix global x, y, z components only, for an Exudyn export "
                f"(its matrices are the unsupported body's with the fixed DOFs removed; "
                f"the config stored in {path} has a {kinds[0]})")
