"""Craig-Bampton data (:mod:`pipeline.reduce.craig_bampton`, ``/craig_bampton``) on MPI
ranks, for the interfaces of a connection model whose rigid parent region the supports
clamp (:mod:`pipeline.distributed.connection`).

Serially, s = T [z; q] (q = [q_P; q_C...], the interfaces in config order) on the
unsupported K, M; the fixed-interface modes Phi solve (K_zz, M_zz), the constraint
modes are z = X q with K_zz X = -K_zq, and B = [[X, Phi], [I, 0]] reduces
K_t = T^T K T, M_t = T^T M T. On the ranks only the run's supported K_ff, M_ff (the
free DOFs f; the parent region's DOFs x are held) exist. With R_P the rigid-body modes
about P (K R_P = 0 for the unsupported K) and E_P = R_P on the x rows, 0 elsewhere:

- T_z (the z columns) has no x row: (K_zz, M_zz) = T_z^T (K_ff, M_ff) T_z, a
  :class:`~pipeline.distributed.constraints.DistributedConstraint` (PETSc's PtAP), its
  modes by SLEPc on MUMPS and the constraint modes by the same factor of K_zz;
- every basis vector b = s_f + E_P c (c its q_P coefficients, s_f its free rows) is
  lifted to b~ = b - R_P c, zero on the x rows: K b = K b~ exactly, so every K product
  is the supported K's, and K_zq = T_z^T K_ff E~ with E~ = [-R_P,f, E_C] (the child
  interfaces' rigid motions on their region rows): b~ = T_z X + E~;
- M products take the rows of M R_P that couple to the held points (W = (M R_P)_f,
  :func:`~pipeline.distributed.assemble.rigid_mass_rows`) and D_P = R_P^T M R_P:

      a^T M b = a~^T M_ff b~ + a~^T W c_b + c_a^T W^T b~ + c_a^T D_P c_b.

When the parent is not what the run holds (a distributing parent, other supports,
added masses: :mod:`pipeline.distributed.unsupported`), K and M are the unsupported
pair on every DOF: nothing is lifted (c = 0), E_P = R_P on the parent region's rows,
and the products are the pair's own.

The basis on every point (``/craig_bampton/shapes``) is b~ + R_P c on the free points
(each rank's own) and R_P c on the held ones (rank 0, which has their coordinates),
written block by block. The floating-frame invariants of the basis without the
parent's static modes (zero on the held points) are
:func:`pipeline.distributed.ffrf.modes_invariants`'.
"""

from __future__ import annotations

import logging

import numpy as np

from pipeline.config import Config
from pipeline.distributed.assemble import rigid_mass_rows
from pipeline.distributed.blocks import PointBlocks, RowBlock
from pipeline.distributed.constraints import DistributedConstraint, from_entries
from pipeline.distributed.eigen import solve_eigen
from pipeline.distributed.mpi import petsc
from pipeline.distributed.operators import KspSolve, RowMatrix
from pipeline.distributed.reduce import rayleigh_ritz_rows
from pipeline.errors import ConfigError
from pipeline.fe.body import rigid_body_modes
from pipeline.reduce.craig_bampton import CraigBamptonModel, coordinate_labels

log = logging.getLogger(__name__)

__all__ = ["clamped_solve", "interface_rows", "craig_bampton_on_ranks"]


def clamped_solve(cfg: Config, con: DistributedConstraint, count: int):
    """(omega2 (count,) rad^2/s^2, the clamped modes on the coordinates q of ``con`` (a
    RowBlock on q's partition, M_c-orthonormal), residuals (count,), SLEPc's solver,
    whose KSP solves with K_c: the caller destroys it) of (K_c, M_c) = (T_c^T K T_c,
    T_c^T M T_c) made by ``con.project``: SLEPc's shift-invert on MUMPS, then the
    Rayleigh-Ritz step and sign convention of the modes stage."""
    PETSc, SLEPc = petsc()
    Kc, Mc = con.K, con.M
    if count >= con.n_q:
        raise ConfigError(f"modes.count: {count} clamped modes of a body with {con.n_q} "
                          f"coordinates; expected fewer than {con.n_q}", key="modes.count",
                          value=count, expected=f"< {con.n_q}")
    omega2, local, stats = solve_eigen(PETSc, SLEPc, Kc.petsc, Mc.petsc, count,
                                       cfg.modes.tolerance or 1e-10)
    return (*rayleigh_ritz_rows(Kc, Mc, RowBlock(con.comm, Kc.part, local), 0.0),
            stats.pop("eps"))


def interface_rows(mesh, rows: RowBlock, iface, every: bool = False
                   ) -> np.ndarray:
    """(hi - lo, 6) this rank's rows (PETSc order) of the rigid-body modes about the
    interface point, on the rows of the interface's region (``every``: on every row)."""
    dofs = rows.dofs()
    nodes = dofs // 3
    points = mesh.space.node_points[mesh.local_nodes(nodes)]
    R = rigid_body_modes(points, iface.point)[3 * np.arange(dofs.size) + dofs % 3]
    return R if every else R * np.isin(nodes, iface.nodes)[:, None]


def craig_bampton_on_ranks(cfg, space, K: RowMatrix, M: RowMatrix,
                           entries, n_z: int, D_P: np.ndarray | None
                           ) -> tuple[CraigBamptonModel, RowBlock]:
    """The :class:`CraigBamptonModel` with ``cfg.craig_bampton_modes`` fixed-interface
    modes (module; collective); its ``shapes`` are a PointBlocks dataset (n_points, 3,
    n_b + N) written by rank 0. ``entries``: this rank's entries of T_c's rows
    (:func:`~pipeline.distributed.connection.clamped_entries`, the z columns are the
    first ``n_z`` keys); ``D_P`` (6, 6) the rigid mass at the parent point, whose
    region the run holds, or None: ``K``, ``M`` are the unsupported pair on every DOF
    (:mod:`pipeline.distributed.unsupported`), the parent's rows among them, and no
    vector is lifted (b~ = b, E_P = R_P on the parent region's rows). Also returns the
    lifted basis b~ (n_free, n_b + N) on the ranks."""
    held = D_P is not None
    PETSc, _ = petsc()
    comm = K.comm
    interfaces = space.connections
    parent, children = interfaces[0], interfaces[1:]
    rows, keys, values, anchored = entries
    z = keys < n_z
    con = from_entries(comm, (rows[z], keys[z], values[z], anchored[anchored < n_z]),
                       K.part, "clamped interfaces")
    con.project(PETSc, K, M)
    eps = None
    try:
        omega2, phi_z, residuals, eps = clamped_solve(cfg, con, cfg.craig_bampton_modes)
        u = RowBlock(comm, K.part, np.zeros((K.hi - K.lo, 0)))  # u's rows
        E_P = (-interface_rows(space.local, u, parent, every=True) if held
               else interface_rows(space.local, u, parent))
        E = u.like(np.hstack([E_P] + [interface_rows(space.local, u, c)
                                      for c in children]))
        rhs = con.to_q(K.apply(E))
        X = rhs.like(-KspSolve(eps.getST().getKSP(), con.K).solve_rows(rhs.local))
        static = con.from_q(X)
        B = u.like(np.hstack([static.local + E.local, con.from_q(phi_z).local]))
    finally:
        if eps is not None:
            eps.destroy()
        con.destroy()
    nb, n = 6 * len(interfaces), omega2.size
    c = np.zeros((6, nb + n))  # the parent coefficients of the lifted vectors
    Kr, Mr = B.gram(K.apply(B)), B.gram(M.apply(B))
    if held:
        c[:, :6] = np.eye(6)
        BW = B.gram(B.like(rigid_mass_rows(space.local, parent.point))) @ c
        Mr = Mr + BW + BW.T + c.T @ D_P @ c
    names, units = coordinate_labels(interfaces, n)
    log.info("Craig-Bampton: %d interface(s), %d boundary + %d modal coordinates on %d "
             "rank(s)", len(interfaces), nb, n, comm.size)
    return CraigBamptonModel(interfaces, 0.5 * (Mr + Mr.T), 0.5 * (Kr + Kr.T), names,
                             units, _shapes(space, B, c, parent, held), omega2,
                             residuals), B


def _shapes(space, B: RowBlock, c: np.ndarray, parent, held: bool) -> PointBlocks:
    """The basis on every point: b~ + R_P c on each rank's free points, R_P c on the
    held points (rank 0; ``held`` False: B holds every point)."""
    full = B.like(B.local + interface_rows(space.local, B, parent, every=True) @ c)
    points, values = full.on_points()
    if held and B.comm.rank == 0:
        held = parent.nodes
        R = rigid_body_modes(space.node_points[held], parent.point) @ c
        points = np.concatenate([points, held])
        values = np.concatenate([values, R.reshape(held.size, 3, -1)])
        order = np.argsort(points, kind="stable")
        points, values = points[order], values[order]
    return PointBlocks(B.comm, space.n_nodes, points, values)
