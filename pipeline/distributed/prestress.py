"""Rotating and preloaded bodies on MPI ranks: the ``/rotation`` group from distributed K, M.

The serial stage (:mod:`pipeline.reduce.rotation`, physics in :mod:`pipeline.fe.prestress`)
works with the whole prestress matrices on the free DOFs (n_s). Here rank r holds the
PETSc rows ``lo:hi`` it owns and its part of the mesh (its elements and the one element
layer around them, :class:`~pipeline.distributed.submesh.RankMesh`), and evaluates every
term with the serial kernels on that part:

- the scalar node mass m (kg) of its part's elements; its rows at the nodes it owns are
  the whole mesh's (every element touching such a node is in the part);
- the centrifugal loads f_ij = (m (x) A_ij) r per unit W_ij (its rows) and the preload
  loads F_k of the force and moment inputs (rank 0's port matrices, its rows);
- the static shapes u = K^-1 [f, F] by the eigen solve's solver of K (MUMPS' factor,
  or, with ``modes.method: multigrid``, CG on its two-grid cycle;
  :func:`pipeline.distributed.reduce.static_rows`, refined as the static correction);
- the geometric stiffness K_G(sigma(u)) of its part's elements: sigma needs u on every
  node of its elements, its own rows and the halo the other ranks own
  (:class:`Halo`: each rank sends the rows its neighbours ask for, nothing else);
- every product A X with A = K_G,ij, M_ij = m (x) A_ij or m (x) [e_k x] of a row block X:
  X on the part's nodes (the halo), A X on the part, the owned rows kept. Its
  projections V^T A V = sum_r V_r^T (A V)_r are summed over the ranks (MPI_Allreduce);
- the reduced basis V = [Phi, u_c, K^-1 (K_G1 - M_perp) phi_k] M-orthonormalised with
  the distributed M (:func:`reduced_basis_rows`, the serial Gram-Schmidt);
- the full FE sweep: K(Omega) = K + Omega^2 (K_G1 - M_perp) as a PETSc matrix (K's plus
  Omega^2 times the spin term's rows, MatAXPY), its lowest n_m modes by SLEPc
  (:func:`pipeline.distributed.eigen.solve_eigen`, shift-invert at 0 on MUMPS, one
  solver and one analysis for every speed, :class:`SpeedFactor`; with
  ``modes.method: multigrid`` LOBPCG on the two-grid cycle of K(Omega) made from the
  modes stage's prolongation, kept from speed to speed with only what depends on
  K(Omega)'s values made again, :class:`~pipeline.distributed.multigrid.TwoGridSweep`)
  and the
  exact Rayleigh-Ritz step; a negative eigenvalue (MUMPS' LDL^T factors an indefinite
  K(Omega) where the serial Cholesky fails) names the unstable speed as the serial path.

Under an exact constraint u = T q (supports in a local frame,
:class:`~pipeline.distributed.constraints.DistributedConstraint`) the terms above stay
on u; the static shapes are X = T K_q^-1 T^T F (the modes stage's solver of
K_q = T^T K T), so the basis satisfies the constraint, and the full FE sweep runs on q:
T^T K(Omega) T = K_q + Omega^2 T^T (K_G1 - M_perp) T (PETSc's PtAP) with M_q, as the
serial stage does.

No rank holds the whole K, M, K_G or the whole basis: the tall blocks are
:class:`~pipeline.distributed.blocks.RowBlock` s, the small (n_b, n_b) terms are the same
on every rank. Rigid masses tied by distributing couplings add their point-mass terms
(:func:`pipeline.fe.prestress.point_mass_prestress`) through their six motions
q = G u, summed over the ranks' rows of the coupled region.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import scipy.sparse as sp

from pipeline.config import Config, Ports
from pipeline.distributed.assemble import with_int32_indices
from pipeline.distributed.blocks import RowBlock, dof_rows
from pipeline.distributed.constraints import Unconstrained
from pipeline.distributed.eigen import petsc_matrix, solve_eigen, solve_eigen_again
from pipeline.distributed.multigrid import TwoGridSweep
from pipeline._util.resources import lobpcg_guard
from pipeline.solve.eigen import (MULTIGRID_MAX_SWEEPS, MULTIGRID_START_TOLERANCE,
                                  MULTIGRID_TOLERANCE)
from pipeline.distributed.mpi import allreduce_sum, petsc
from pipeline.distributed.operators import RowMatrix
from pipeline.distributed.reduce import rayleigh_ritz_rows, static_rows
from pipeline.distributed.submesh import petsc_numbering
from pipeline.errors import SolverError
from pipeline.fe.prestress import (TENSOR_ENTRIES, centrifugal_loads, entry_matrix,
                                   geometric_stiffness, node_mass_matrix,
                                   rigid_centrifugal_load, rigid_geometric_stiffness,
                                   rigid_mass_of, tensor_mass, tensor_weights)
from pipeline.fe.space import FESpace, build_space
from pipeline.reduce.rotation import _check_point, _check_stress, _density, _weighted
from pipeline.reduce.spin import RotationModel, reduced_frequencies, unit, unstable

log = logging.getLogger(__name__)


def preload_ports(cfg: Config) -> Ports:
    """The force and moment inputs of ``cfg``: the preloads of a rotating body."""
    return Ports(inputs=tuple(p for p in cfg.ports.inputs if p.kind in ("force", "moment")))


def rotation_masses(cfg: Config, space, regions) -> tuple | None:
    """Rank 0, on the whole mesh: (the scalar node mass of the area masses (n_nodes x
    n_nodes CSR, kg) or None, the distributing point masses' (dofs, G, M6, P)) of a
    rotating body (:mod:`pipeline.fe.added_mass`), or None without rotation or masses.
    Both live on the masses' surface regions only (every rank gets them)."""
    if cfg.rotation is None or not cfg.masses:
        return None
    from pipeline.fe.added_mass import area_node_mass, distributing_point_masses

    area = area_node_mass(space, regions, cfg.masses)  # sent as its entries only
    return (None if area is None else sp.coo_matrix(area),
            tuple(distributing_point_masses(space, regions, cfg.masses)))


def on_part(A: sp.coo_matrix, points: np.ndarray) -> sp.csr_matrix:
    """(n_loc, n_loc) CSR: the entries of the (n_nodes, n_nodes) ``A`` between the part's
    nodes ``points`` (global numbers, ascending), in local numbers."""
    n = points.size
    rows, cols = (np.minimum(np.searchsorted(points, g), n - 1) for g in (A.row, A.col))
    keep = (points[rows] == A.row) & (points[cols] == A.col)
    return sp.csr_matrix((A.data[keep], (rows[keep], cols[keep])), shape=(n, n))


class RankPointMasses:
    """The rigid masses tied by distributing couplings on one rank: their six motions
    q = G u summed over the ranks' rows of the coupled region, and every term
    G^T B G of :func:`pipeline.fe.prestress.point_mass_prestress` as this rank's rows.

    ``point_masses``: (dofs, G (6, 3 n_r), M6, P) each; ``dof_rows`` (n_dofs,) the PETSc
    row of every DOF (-1: held; None without masses); ``point`` (3,) m the spin axis'
    point."""

    def __init__(self, comm, point_masses, point, dof_rows: np.ndarray | None, lo: int,
                 hi: int):
        self.comm, self.lo, self.hi = comm, lo, hi
        self.items = []
        for dofs, G, M6, P in point_masses:
            rows = dof_rows[np.asarray(dofs)]
            mine, held = (rows >= lo) & (rows < hi), rows < 0
            self.items.append((rows[mine] - lo, G[:, mine], rows[~held], G[:, ~held],
                               np.asarray(M6, float), np.asarray(P, float) - point))

    def motions(self, X: RowBlock) -> list[np.ndarray]:
        """(6, k) q = G X of each mass, the same on every rank."""
        if not self.items:
            return []
        local = np.stack([G @ X.local[rows] for rows, G, *_ in self.items])
        return list(allreduce_sum(self.comm, local))

    def blocks(self, per_entry) -> list[list[np.ndarray]]:
        """Each mass's six (6, 6) blocks per_entry(M6, A_ij) in TENSOR_ENTRIES order."""
        return [[per_entry(item[4], entry_matrix(i, j)) for i, j in TENSOR_ENTRIES]
                for item in self.items]

    def loads(self) -> np.ndarray:
        """(hi - lo, 6) this rank's rows of the masses' centrifugal loads per unit W_ij."""
        out = np.zeros((self.hi - self.lo, len(TENSOR_ENTRIES)))
        for rows, G, _, _, M6, offset in self.items:
            for col, (i, j) in enumerate(TENSOR_ENTRIES):
                out[rows, col] += G.T @ rigid_centrifugal_load(M6, offset, entry_matrix(i, j))
        return out

    def apply(self, blocks: list[np.ndarray], q: list[np.ndarray], k: int) -> np.ndarray:
        """(hi - lo, k) this rank's rows of sum G^T B G X (``blocks``: each mass's B,
        ``q``: its motions G X)."""
        out = np.zeros((self.hi - self.lo, k))
        for (rows, G, *_), B, qm in zip(self.items, blocks, q):
            out[rows] += G.T @ (B @ qm)
        return out

    def csr_rows(self, blocks: list[np.ndarray], n_free: int) -> sp.csr_matrix:
        """(hi - lo, n_free) CSR: this rank's rows of sum G^T B G, PETSc's columns."""
        out = sp.csr_matrix((self.hi - self.lo, n_free))
        for (rows, G, cols, G_free, *_), B in zip(self.items, blocks):
            block = G.T @ B @ G_free
            r, c = np.meshgrid(rows, cols, indexing="ij")
            out = out + sp.csr_matrix((block.ravel(), (r.ravel(), c.ravel())),
                                      shape=out.shape)
        return out

    def inertia(self, q: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(euler (3, n_b), coriolis (3, n_b, n_b)) of the masses' motions q = G V."""
        n_b = q[0].shape[1]
        euler, coriolis = np.zeros((3, n_b)), np.zeros((3, n_b, n_b))
        for (*_, M6, offset), qm in zip(self.items, q):
            for k, e in enumerate(np.eye(3)):
                euler[k] += qm.T @ (M6 @ np.concatenate([np.cross(e, offset), e]))
                coriolis[k] += qm.T @ rigid_mass_of(M6, np.cross(e, np.eye(3)).T) @ qm
        return euler, coriolis


class Halo:
    """A rank's view of row blocks on the DOFs of its part of the mesh.

    ``mesh.dof_rows`` (3 n_loc,) is the PETSc row of each local DOF (-1: held). The rows
    in ``lo:hi`` are this rank's; the others (the halo) are asked once of their owners.
    Collective: every rank builds it and calls :meth:`to_local` in the same order."""

    def __init__(self, comm, mesh, part):
        self.comm, self.part = comm, part
        self.lo, self.hi = part.rows(comm.rank)
        rows = np.asarray(mesh.dof_rows, dtype=np.int64)
        self.rows, self.n_loc = rows, rows.size
        self.n_free = part.n_free
        owned = (rows >= self.lo) & (rows < self.hi)
        self.owned = np.flatnonzero(owned)  # local DOFs of the owned rows
        self.halo = np.flatnonzero((rows >= 0) & ~owned)
        need = rows[self.halo]
        owner = np.searchsorted(part.starts, need, side="right") - 1
        asks = [need[owner == r] for r in range(comm.size)]
        self.where = [self.halo[owner == r] for r in range(comm.size)]
        # the rows each rank asks of this one, as offsets into this rank's rows
        self.sends = [np.asarray(a) - self.lo for a in comm.alltoall(asks)]

    def to_local(self, X: RowBlock) -> np.ndarray:
        """(3 n_loc, k): X on the part's DOFs (its own rows and the halo), 0 where held."""
        out = np.zeros((self.n_loc, X.local.shape[1]))
        out[self.owned] = X.local[self.rows[self.owned] - self.lo]
        got = self.comm.alltoall([X.local[s] for s in self.sends])
        for r, values in enumerate(got):
            out[self.where[r]] = values
        return out

    def owned_rows(self, Y: np.ndarray) -> np.ndarray:
        """(hi - lo, k) this rank's rows (PETSc order) of a (3 n_loc, k) field Y."""
        Y = np.asarray(Y, dtype=float).reshape(self.n_loc, -1)
        out = np.zeros((self.hi - self.lo, Y.shape[1]))
        out[self.rows[self.owned] - self.lo] = Y[self.owned]
        return out

    def block(self, Y: np.ndarray) -> RowBlock:
        """The RowBlock of this rank's rows of a (3 n_loc, k) field Y."""
        return RowBlock(self.comm, self.part, self.owned_rows(Y))

    def csr_rows(self, A: sp.spmatrix) -> sp.csr_matrix:
        """(hi - lo, n_free) CSR, PETSc's rows and columns, of a (3 n_loc, 3 n_loc) matrix
        of the part whose owned rows are complete; held columns dropped, int32 indices."""
        B = sp.csr_matrix(A)[self.owned].tocoo()
        cols = self.rows[B.col]
        keep = cols >= 0
        return with_int32_indices(sp.csr_matrix(
            (B.data[keep], (self.rows[self.owned][B.row[keep]] - self.lo, cols[keep])),
            shape=(self.hi - self.lo, self.n_free)))

    def apply(self, A: sp.spmatrix, X: RowBlock, X_local: np.ndarray | None = None
              ) -> RowBlock:
        """A X (rows stay) for a matrix of the part (its owned rows complete);
        ``X_local``: X on the part when already at hand."""
        return self.block(A @ (self.to_local(X) if X_local is None else X_local))


def reduced_basis_rows(shapes: RowBlock, M: RowMatrix, extra: RowBlock | None) -> RowBlock:
    """The distributed twin of :func:`pipeline.reduce.rotation.reduced_basis`: ``shapes``
    (M-orthonormal), then each column of ``extra`` M-orthonormalised against them (twice,
    for round-off) and each other; a column already spanned (relative M-norm below 1e-8)
    is dropped."""
    if extra is None or extra.local.shape[1] == 0:
        return shapes
    V = shapes
    for c in range(extra.local.shape[1]):
        col = extra.columns(slice(c, c + 1))
        x = col
        for _ in range(2):
            x = x.like(x.local - V.times(V.gram(M.apply(x))).local)
        norm = float(np.sqrt(x.gram(M.apply(x))[0, 0]))
        if norm > 1e-8 * float(np.sqrt(col.gram(M.apply(col))[0, 0])):
            V = V.like(np.hstack([V.local, x.local / norm]))
    return V


def rotation_model(cfg: Config, space, regions, free, K: RowMatrix, M: RowMatrix,
                   modes) -> RotationModel:
    """The distributed twin of :func:`pipeline.reduce.rotation.rotation_model` (module):
    the same :class:`~pipeline.reduce.spin.RotationModel` on every rank, from the
    distributed K, M (:class:`RowMatrix`, PETSc matrices attached), the modes' row block
    and MUMPS factor, this rank's part of the mesh (``space.local``) and the added masses
    rank 0 evaluated (``space.rotation_masses``)."""
    rotation = cfg.rotation
    comm = K.comm
    if modes.factorization is None or modes.factorization.ksp is None or modes.n_rigid:
        raise SolverError("rotation with modes.solver: slepc: the body is not held "
                          f"({modes.n_rigid} rigid-body mode(s)): the centrifugal static "
                          "solve needs a supported body; expected supports that hold it",
                          key="rotation", value="unsupported body",
                          expected="a held body")
    mesh = space.local
    part_space = kernel_space(mesh.space)
    halo = Halo(comm, mesh, K.part)
    axis = unit(rotation.axis)
    point = np.asarray(rotation.point, dtype=float)
    material = mesh.materials
    if comm.rank == 0:
        _check_point(point, space.node_points)
    _check_stress_once(comm, rotation, axis, mesh, material)
    area, point_masses = space.rotation_masses or (None, ())
    node_mass = node_mass_matrix(part_space, _density(material))  # the part's m, kg
    if area is not None:  # the area masses' rows of its nodes (their triangles' nodes)
        node_mass = (node_mass + on_part(area, mesh.points)).tocsr()
    masses = RankPointMasses(comm, point_masses, point, petsc_numbering(
        space.n_dofs, K.part.whole(comm)) if point_masses else None, halo.lo, halo.hi)
    loads = halo.block(centrifugal_loads(part_space, node_mass, point))  # (n_s, 6) rows
    loads = loads.like(loads.local + masses.loads())
    names = tuple(p.name for p in preload_ports(cfg).inputs)
    rhs = loads
    if names:
        cols = [space.ports.input_names.index(n) for n in names]
        F = dof_rows(sp.csc_matrix(space.ports.F)[:, cols], loads.dofs())
        rhs = loads.like(np.hstack([loads.local, F.toarray()]))
    factor = modes.factorization
    # u = T q: the static solves run on the coordinates, X = T K_q^-1 T^T F
    on = Unconstrained(K, M) if modes.constraint is None else modes.constraint

    def solve_static(F: RowBlock) -> RowBlock:
        """K^-1 F (n_s, k) on the body's constraint, rows stay."""
        return on.from_q(static_rows(on.K, factor, on.to_q(F)))

    U = solve_static(rhs)  # (n_s, 6 + n_in) static shapes, rows stay
    geometric = geometric_stiffness(part_space, material, halo.to_local(U))
    softening = [tensor_mass(node_mass, entry_matrix(i, j)) for i, j in TENSOR_ENTRIES]
    k = len(TENSOR_ENTRIES)
    weights = tensor_weights(axis)
    spin = (_weighted(geometric[:k], weights) - _weighted(softening, weights)).tocsr()
    pm_geo = masses.blocks(rigid_geometric_stiffness)
    pm_soft = masses.blocks(rigid_mass_of)
    pm_spin = [sum(w * (g - m) for w, g, m in zip(weights, geo, soft))
               for geo, soft in zip(pm_geo, pm_soft)]

    def apply_spin(X: RowBlock) -> RowBlock:
        """(K_G1 - M_perp) X, rows stay."""
        Y = halo.apply(spin, X)
        return Y.like(Y.local + masses.apply(pm_spin, masses.motions(X), X.local.shape[1]))

    Phi: RowBlock = modes.shapes
    n_m = Phi.local.shape[1]
    static = U.columns(slice(0, k)).times(weights[:, None]) if rotation.static_shape else None
    corrections = None
    if rotation.correction_shapes:
        n_c = min(rotation.correction_shapes, n_m)
        corrections = solve_static(apply_spin(Phi.columns(slice(0, n_c))))
    with_static = reduced_basis_rows(Phi, M, static)  # a shape the modes span is dropped
    V = reduced_basis_rows(with_static, M, corrections)
    plain = V.local.shape[1] == n_m
    V_local, q = halo.to_local(V), masses.motions(V)

    def project(matrices, blocks=None) -> np.ndarray:
        """(len(matrices), n_b, n_b) V^T A V, plus the masses' q^T B q per entry."""
        n_b = V.local.shape[1]
        out = np.array([V.gram(halo.apply(A, V, V_local)) for A in matrices]
                       ).reshape(-1, n_b, n_b)
        for per_entry, qm in zip(blocks or (), q):
            out += np.array([qm.T @ B @ qm for B in per_entry])
        return out

    omega2 = np.asarray(modes.omega2, dtype=float)
    centrifugal, euler, coriolis = inertia_loads_rows(halo, node_mass, mesh.space.node_points
                                                      - point, loads, V, V_local)
    if masses.items:
        pm_euler, pm_coriolis = masses.inertia(q)
        euler, coriolis = euler + pm_euler, coriolis + pm_coriolis
    model = RotationModel(
        axis=axis, point=point, speeds_rad_s=np.asarray(rotation.speeds_rad_s, float),
        frequencies_hz=np.zeros((0, n_m)),
        frequencies_reduced_hz=np.zeros((0, V.local.shape[1])),
        stiffness=np.diag(omega2).astype(float) if plain else V.gram(K.apply(V)),
        mass=np.eye(n_m) if plain else V.gram(M.apply(V)),
        geometric=project(geometric[:k], pm_geo), softening=project(softening, pm_soft),
        preload=project(geometric[k:]), input_names=names, n_modes=n_m,
        static_shape=with_static.local.shape[1] > n_m,
        centrifugal_load=centrifugal, euler_load=euler, coriolis=coriolis)
    reduced = reduced_frequencies(model)  # cheap: an unstable speed is named before the sweep
    spin_rows = halo.csr_rows(spin) + masses.csr_rows(pm_spin, halo.n_free)
    prolongation = getattr(modes.factorization, "prolongation", None)
    full = full_frequencies_rows(K, M, with_int32_indices(spin_rows), model.speeds_rad_s,
                                 n_m, cfg.modes.tolerance or
                                 (MULTIGRID_TOLERANCE if prolongation is not None else 1e-10),
                                 rest_hz=np.sqrt(np.maximum(omega2, 0.0)) / (2 * np.pi),
                                 prolongation=prolongation, constraint=modes.constraint)
    return dataclasses.replace(model, frequencies_hz=full, frequencies_reduced_hz=reduced)


def kernel_space(space: FESpace) -> FESpace:
    """The part's space with the scikit-fem mesh the prestress kernels assemble on
    (:func:`pipeline.fe.space.sub_space` has none). Its nodes are the part's: vertices
    ascending, then the edge midpoints ascending by the whole mesh's edge number, which
    is lexicographic in the vertex numbers, as scikit-fem numbers a mesh's edges; the
    element nodes are checked to be the part's."""
    built = build_space(space.body, space.order)
    if not np.array_equal(built.element_nodes, space.element_nodes):
        raise RuntimeError("rotation: a rank's part of the mesh is numbered unlike "
                           "scikit-fem's basis of it")
    return built


def _check_stress_once(comm, rotation, axis, mesh, material) -> None:
    """The serial stress warning (:func:`pipeline.reduce.rotation._check_stress`) on rank
    0, with the whole body's largest distance from the axis and densest, softest law
    (each rank's part measured, the extremes taken over the ranks)."""
    r = mesh.space.node_points - np.asarray(rotation.point, dtype=float)
    radius = np.max(np.linalg.norm(r - np.outer(r @ axis, axis), axis=1), initial=0.0)
    rho = float(np.max(material.rho, initial=0.0))
    used = np.zeros(material.D.shape[0])  # the laws some element of the body takes
    used[np.unique(material.index)] = 1.0
    top = allreduce_sum(comm, np.concatenate([[radius, rho], used]), "MAX")
    if comm.rank != 0:
        return
    # the radius at the point farthest from the axis: a stand-in point at that distance
    far = np.asarray(rotation.point, float) + top[0] * _normal(axis)
    law = material.uniform if material.uniform is not None else dataclasses.replace(
        material, index=np.flatnonzero(top[2:]), rho=np.array([top[1]]))
    _check_stress(rotation, axis, far[None, :], law)


def _normal(axis: np.ndarray) -> np.ndarray:
    """A unit vector normal to the unit ``axis``."""
    trial = np.eye(3)[int(np.argmin(np.abs(axis)))]
    n = trial - (trial @ axis) * axis
    return n / np.linalg.norm(n)


def inertia_loads_rows(halo: Halo, node_mass: sp.spmatrix, offsets: np.ndarray,
                       loads: RowBlock, V: RowBlock, V_local: np.ndarray):
    """The distributed twin of :func:`pipeline.reduce.rotation.inertia_loads`:
    (centrifugal (6, n_b), euler (3, n_b), coriolis (3, n_b, n_b)) from the part's node
    mass (n_loc x n_loc, kg), its nodes' offsets x - p (n_loc, 3) m, the load rows f
    (n_s, 6) and the basis V (rows, and ``V_local`` on the part)."""
    n_loc, n_b = node_mass.shape[0], V.local.shape[1]
    nodal = V_local.reshape(n_loc, 3, n_b)
    euler = np.empty((3, n_b))
    coriolis = np.empty((3, n_b, n_b))
    for k, e in enumerate(np.eye(3)):
        arm = np.cross(e, offsets)  # (n_loc, 3)
        euler[k] = V.gram(halo.block((node_mass @ arm).reshape(-1, 1)))[:, 0]
        turned = np.cross(e[None, :, None], nodal, axis=1)  # e_k x each column's vectors
        coriolis[k] = V.gram(halo.block(
            (node_mass @ turned.reshape(n_loc, -1)).reshape(3 * n_loc, n_b)))
    return V.gram(loads).T, euler, coriolis


def full_frequencies_rows(K: RowMatrix, M: RowMatrix, spin_rows: sp.csr_matrix, speeds,
                          count: int, tolerance: float, rest_hz: np.ndarray,
                          prolongation=None, constraint=None) -> np.ndarray:
    """(n_speeds, count) Hz: the lowest prestressed frequencies of the full FE model at
    each speed (rad/s), K(Omega) = K + Omega^2 S (``spin_rows``: this rank's rows of
    S = K_G1 - M_perp, PETSc's numbering), by SLEPc at shift 0 (module); ``rest_hz``
    (count,): the frequencies at rest (a speed 0 is not solved again). With the
    factor-free path's ``prolongation`` P: LOBPCG on the two-grid cycle of K(Omega), as
    the modes at rest, the cycle refreshed per speed
    (:class:`~pipeline.distributed.multigrid.TwoGridSweep`), ``tolerance`` its
    preconditioned residual; else shift-invert on
    MUMPS' factor. ``constraint``: the
    :class:`~pipeline.distributed.constraints.DistributedConstraint` u = T q or None; the
    sweep then runs on q, T^T K(Omega) T = K_q + Omega^2 T^T S T (PETSc's PtAP) with M_q,
    and ``prolongation`` is already q's (T^T P, the modes stage's)."""
    PETSc, SLEPc = petsc()
    S = petsc_matrix(PETSc, spin_rows, K.shape[0])
    if constraint is not None:
        S_u, S = S, S.ptap(constraint.T)
        S_u.destroy()
        K, M = constraint.K, constraint.M
    out = np.empty((len(speeds), count))
    A = None  # K(Omega), made once with K's and S's pattern: its values change per speed
    sweep = SpeedFactor() if prolongation is None else \
        TwoGridSweep(PETSc, SLEPc, M.petsc, prolongation)
    try:
        for i, speed in enumerate(speeds):
            if speed == 0:
                out[i] = rest_hz[:count]
                continue
            t0 = time.perf_counter()
            A = spin_matrix(PETSc, K.petsc, S, speed, A)
            At = RowMatrix(K.comm, None, K.part)
            At.petsc = A
            try:
                if prolongation is not None:
                    omega2, rows, _ = sweep.solve(
                        A, count, count + lobpcg_guard(count), tolerance,
                        MULTIGRID_START_TOLERANCE, MULTIGRID_MAX_SWEEPS)
                else:
                    omega2, rows = sweep.solve(PETSc, SLEPc, A, M.petsc, count, tolerance)
            except SolverError:
                raise unstable(speed, "the full FE model") from None
            if np.min(omega2) <= 0.0:  # LDL^T factored an indefinite K(Omega)
                raise unstable(speed, "the full FE model")
            omega2 = rayleigh_ritz_rows(At, M, RowBlock(K.comm, K.part, rows), 0.0)[0]
            if omega2[0] <= 0.0:
                raise unstable(speed, "the full FE model")
            out[i] = np.sqrt(omega2[:count]) / (2 * np.pi)
            log.info("rotation: %g rad/s: f = %s Hz (%.2f s)", speed,
                     ", ".join(f"{f:.4g}" for f in out[i, :4]), time.perf_counter() - t0)
    finally:
        sweep.release()
        if A is not None:
            A.destroy()
        S.destroy()
    return out


def spin_matrix(PETSc, K, S, speed: float, A=None):
    """K(Omega) = K + Omega^2 S (PETSc matrices; ``speed`` Omega rad/s), marked
    symmetric. ``A``: the previous speed's K(Omega), refilled in place (MatZeroEntries,
    then MatAXPY of K and Omega^2 S into its pattern, the same arithmetic as a copy of K
    plus Omega^2 S): its nonzero pattern, and with it MUMPS' analysis of it, stays; None:
    made as K's copy plus Omega^2 S (MatAXPY, the union of the two patterns)."""
    if A is None:
        A = K.copy()
        A.axpy(speed ** 2, S, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        return A
    A.zeroEntries()
    A.axpy(1.0, K, structure=PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
    A.axpy(speed ** 2, S, structure=PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
    return A


class SpeedFactor:
    """The factor path's solves of a rotation sweep, one SLEPc solver for every speed:
    the first speed's Krylov-Schur makes MUMPS' analysis (PORD's ordering, the symbolic
    factor) and factor of K(Omega); the next ones solve again with that solver on the
    same matrix, refilled (:func:`spin_matrix`): SLEPc keeps its KSP and PETSc's PC
    refactorises numerically only (:func:`~pipeline.distributed.eigen.solve_eigen_again`;
    5 speeds of the cantilever at 100k DOFs on 2 ranks: 6 symbolic factorisations -> 2,
    4.8 -> 1.5 s; the numeric factorisation is 9-10 of the 11-12 s a speed takes, so the
    time per speed does not move measurably).
    The pattern is the one a fresh factor per speed had, so the ordering is the same; a
    refactorisation that fails (MUMPS short of workspace after other pivots) is made
    again from scratch, as the first speed's."""

    def __init__(self):
        self.eps = None

    def solve(self, PETSc, SLEPc, A, M, count: int, tolerance: float):
        """(omega2 (count,), this rank's rows (n_loc, count)): SLEPc on (A, M) at
        shift 0 (:func:`~pipeline.distributed.eigen.solve_eigen`)."""
        if self.eps is not None:
            try:
                return solve_eigen_again(PETSc, self.eps, A, M, count)
            except SolverError:
                self.release()
        omega2, rows, stats = solve_eigen(PETSc, SLEPc, A, M, count, tolerance)
        self.eps = stats.pop("eps")  # its KSP holds MUMPS' analysis and factor
        return omega2, rows

    def release(self) -> None:
        """Free the kept solver (collective)."""
        if self.eps is not None:
            self.eps.destroy()
        self.eps = None
