"""The factor-free eigen solve on MPI ranks: LOBPCG preconditioned by the two-grid cycle.

The serial factor-free path (:mod:`pipeline.solve.multigrid`, :mod:`pipeline.solve.lobpcg`)
on distributed rows, with PETSc's objects for what crosses ranks:

- **The prolongation P** from the embedded linear (P1) space, a PETSc MPIAIJ matrix
  (n_free x n_coarse). Each rank makes its own rows (:func:`prolongation_rows`): a
  vertex DOF is its coarse DOF (1), an edge midpoint's DOF the mean of its edge's two
  vertex DOFs (1/2 each; a held vertex contributes nothing), exactly
  :func:`pipeline.fe.coarse.p1_prolongation`'s matrix, the coarse DOFs numbered in
  PETSc's row order (the free vertex DOFs a rank owns are its coarse rows).
- **The two-grid cycle** is PETSc's PCMG on A = K - sigma M with two levels, Galerkin
  coarse matrix A_c = P^T A P (PtAP), factorised by MUMPS (Cholesky), and Chebyshev
  smoothing on Jacobi's D^-1 A of degree :data:`pipeline.solve.multigrid.DEGREE` over
  [:data:`~pipeline.solve.multigrid.LOWER`, 1.1] times PETSc's estimate of
  lambda_max(D^-1 A): the serial cycle's choices (PETSc estimates lambda_max by a
  Krylov method, the serial path by power steps, so the two cycles differ slightly and
  so do the iterates; both converge to the same modes).
- **The start block**: the coarse pencil's own modes (P^T K P, P^T M P, shift-invert
  Krylov-Schur on MUMPS' factor of the coarse matrix, to
  :data:`~pipeline.solve.eigen.MULTIGRID_START_TOLERANCE`), prolongated by P.
- **LOBPCG** is :func:`pipeline.solve.lobpcg.lobpcg` on this rank's rows: its products
  with K and M are PETSc's, its Gram matrices sums over the ranks.

The static correction's K^-1 F uses the same cycle under PETSc's conjugate gradients
(:data:`pipeline.solve.multigrid.PCG_RTOL`), as the serial path uses it under its own.

Measured (the cantilever at mesh.size 0.005, 100,695 free DOFs, 20 modes, 2 ranks on the
2-core Intel Xeon): conjugate gradients on GAMG inside Krylov-Schur's shift-invert took
5 min 03 s for the modes; this path takes the seconds in docs/distributed.md.

Options: PETSc's options with the prefix ``pipeline_mg_`` reach the cycle (for example
``-pipeline_mg_mg_levels_ksp_max_it 4``); ``pipeline_mg_coarse_`` the start block's
eigen solve. Every call is collective.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp

from pipeline.distributed.mpi import allreduce_sum
from pipeline.fe.space import TET_EDGES
from pipeline.solve import lobpcg as lobpcg_module
from pipeline.solve.multigrid import DEGREE, LOWER, PCG_RTOL

log = logging.getLogger(__name__)

#: the options prefix of the two-grid cycle's KSP (CG for static solves; its PC is the
#: cycle) and of the start block's coarse eigen solve
PREFIX = "pipeline_mg_"
COARSE_PREFIX = "pipeline_mg_coarse_"


def coarse_numbering(is_vertex_row: np.ndarray) -> np.ndarray:
    """(n_free,) the coarse DOF of each PETSc row that is a free vertex DOF, in row
    order (-1 elsewhere): a rank's coarse rows are then those of its own vertex rows.

    >>> coarse_numbering(np.array([True, False, True, True])).tolist()
    [0, -1, 1, 2]
    """
    coarse = np.cumsum(is_vertex_row, dtype=np.int64) - 1
    return np.where(is_vertex_row, coarse, -1)


def midpoint_vertices(element_nodes: np.ndarray, n_nodes: int) -> np.ndarray:
    """(n_nodes, 2) the two vertices of each edge-midpoint node of quadratic tetrahedra
    (meshio's tetra10 order: corners, then the midpoints of edges 01, 12, 02, 03, 13,
    23), -1 for a vertex; local node numbers."""
    ends = np.full((n_nodes, 2), -1, dtype=np.int64)
    elements = np.asarray(element_nodes, dtype=np.int64)
    for k, (a, b) in enumerate(TET_EDGES):
        ends[elements[:, 4 + k], 0] = elements[:, a]
        ends[elements[:, 4 + k], 1] = elements[:, b]
    return ends


def prolongation_rows(mesh, free_of_row: np.ndarray, coarse_of_row: np.ndarray,
                      n_vertices: int) -> sp.csr_matrix:
    """This rank's rows ``mesh.lo:mesh.hi`` of P (module doc) as CSR
    (hi - lo, n_coarse) with the global coarse column numbers.

    mesh: the rank's :class:`~pipeline.distributed.submesh.RankMesh`; free_of_row
    (n_free,): the free DOF (3 node + component) of each PETSc row; coarse_of_row:
    :func:`coarse_numbering`; n_vertices: the whole mesh's vertex count (global nodes
    below it are vertices)."""
    lo, hi = mesh.lo, mesh.hi
    dofs = np.asarray(free_of_row[lo:hi], dtype=np.int64)
    nodes, comps = dofs // 3, dofs % 3
    n_coarse = int(coarse_of_row.max(initial=-1)) + 1
    rows, cols, vals = [], [], []
    vertex = nodes < n_vertices
    at = np.flatnonzero(vertex)
    rows.append(at)
    cols.append(coarse_of_row[lo + at])
    vals.append(np.ones(at.size))
    at = np.flatnonzero(~vertex)
    if at.size:
        local = mesh.local_nodes(nodes[at])
        ends = midpoint_vertices(mesh.space.element_nodes, mesh.space.node_points.shape[0])
        if np.any(ends[local] < 0):
            raise AssertionError("a midpoint node without its element on this rank")
        for side in (0, 1):
            end_rows = mesh.dof_rows[3 * ends[local, side] + comps[at]]
            held = end_rows < 0
            rows.append(at[~held])
            cols.append(coarse_of_row[end_rows[~held]])
            vals.append(np.full(int((~held).sum()), 0.5))
    P = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(hi - lo, n_coarse))
    P.sum_duplicates()
    return P


def petsc_prolongation(PETSc, rows: sp.csr_matrix, coarse_rows: int):
    """The MPIAIJ P from every rank's rows (``coarse_rows``: this rank's coarse rows)."""
    n_loc, n_coarse = rows.shape
    rows = rows.tocsr()
    P = PETSc.Mat().createAIJ(
        size=((n_loc, PETSc.DETERMINE), (coarse_rows, n_coarse)),
        csr=(rows.indptr.astype(PETSc.IntType), rows.indices.astype(PETSc.IntType),
             rows.data), comm=PETSc.COMM_WORLD)
    P.assemble()
    return P


def prolongation(PETSc, space, free: np.ndarray, part, rank: int):
    """The MPIAIJ P (module doc) of the distributed quadratic ``space``
    (:class:`~pipeline.distributed.submesh.DistributedSpace`) with sorted ``free`` DOFs
    and the row partition ``part``; collective."""
    free_of_row = np.asarray(free, dtype=np.int64)[part.order]
    coarse_of_row = coarse_numbering(free_of_row < 3 * space.body.n_vertices)
    lo, hi = part.rows(rank)
    rows = prolongation_rows(space.local, free_of_row, coarse_of_row,
                             space.body.n_vertices)
    return petsc_prolongation(PETSc, rows, int(np.count_nonzero(coarse_of_row[lo:hi] >= 0)))


def two_grid_solver(PETSc, A, P):
    """A KSP (conjugate gradients to :data:`~pipeline.solve.multigrid.PCG_RTOL`) whose
    PC is the two-grid cycle on A (module doc), set up; the caller destroys it. PETSc
    options with the prefix :data:`PREFIX` override the choices."""
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setOptionsPrefix(PREFIX)
    ksp.setOperators(A)
    ksp.setType(PETSc.KSP.Type.CG)
    ksp.setTolerances(rtol=PCG_RTOL, atol=0.0, max_it=500)
    pc = ksp.getPC()
    pc.setType(PETSc.PC.Type.MG)
    pc.setMGLevels(2)
    pc.setMGType(PETSc.PC.MGType.MULTIPLICATIVE)
    pc.setMGCycleType(PETSc.PC.MGCycleType.V)
    pc.setMGInterpolation(1, P)
    options = PETSc.Options()
    defaults = {
        "pc_mg_galerkin": "both",
        "mg_levels_ksp_type": "chebyshev",
        "mg_levels_pc_type": "jacobi",
        "mg_levels_ksp_max_it": str(DEGREE),
        "mg_levels_ksp_chebyshev_esteig": f"0,{LOWER},0,1.1",
        "mg_coarse_ksp_type": "preonly",
        "mg_coarse_pc_type": "cholesky",
        "mg_coarse_pc_factor_mat_solver_type": "mumps",
        "mg_coarse_mat_mumps_icntl_15": "0",  # see eigen.MUMPS_BLOCK_ANALYSIS_OPTION
    }
    mine = [name for name in defaults if not options.hasName(PREFIX + name)]
    for name in mine:
        options.setValue(PREFIX + name, defaults[name])
    try:
        ksp.setFromOptions()
        ksp.setUp()
    finally:
        for name in mine:
            options.delValue(PREFIX + name)
    return ksp


def _by_columns(apply, A):
    """X (n_loc, k) -> (n_loc, k): ``apply(x, y)`` (a PETSc product or the cycle) on each
    column of this rank's rows; the work vectors, which the caller destroys."""
    x, y = A.createVecs()

    def op(X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64).reshape(X.shape[0], -1)
        out = np.empty_like(X)
        for c in range(X.shape[1]):
            x.getArray()[:] = X[:, c]
            apply(x, y)
            out[:, c] = y.getArray()
        return out
    return op, (x, y)


def lobpcg_modes(PETSc, SLEPc, K, M, P, count: int, width: int, shift: float,
                 target: float, start_tolerance: float, max_sweeps: int):
    """(omega2 (count,), this rank's rows (n_loc, count) of the M-orthonormal modes,
    stats, ksp): two-grid preconditioned LOBPCG on the PETSc pair (K, M) with the
    prolongation P (module doc); ``width`` >= count columns (the rest guard columns),
    ``shift`` sigma (0, or below zero for a body free to move), ``target`` LOBPCG's
    preconditioned residual. ``ksp``: conjugate gradients on the cycle for A = K - sigma
    M (the static correction's solver when sigma = 0); the caller destroys it and
    ``stats["keep"]``."""
    from pipeline.distributed.eigen import solve_eigen

    comm = PETSc.COMM_WORLD.tompi4py()
    t0 = time.perf_counter()
    if shift != 0.0:
        A = K.copy()
        A.axpy(-shift, M, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
    else:
        A = K
    ksp = two_grid_solver(PETSc, A, P)
    n_coarse = P.getSize()[1]
    Kc, Mc = A.PtAP(P), M.PtAP(P)
    width = min(width, n_coarse // 2)
    _, coarse_rows, cstats = solve_eigen(PETSc, SLEPc, Kc, Mc, width, start_tolerance,
                                         "factor", None, 0.0, prefix=COARSE_PREFIX)
    cstats.pop("eps").destroy()
    Kc.destroy()
    Mc.destroy()
    xc, xf = P.createVecs()
    X = np.empty((xf.getLocalSize(), width))
    for c in range(width):
        xc.getArray()[:] = coarse_rows[:, c]
        P.mult(xc, xf)
        X[:, c] = xf.getArray()
    xc.destroy()
    xf.destroy()
    del coarse_rows
    t1 = time.perf_counter()
    times_K, kv = _by_columns(K.mult, K)
    times_M, mv = _by_columns(M.mult, M)
    precondition, pv = _by_columns(ksp.getPC().apply, A)
    try:
        result = lobpcg_module.lobpcg(
            times_K, times_M, X, precondition, count, sigma=shift, target=target,
            max_sweeps=max_sweeps, total=lambda a: allreduce_sum(comm, a))
    finally:
        for v in (*kv, *mv, *pv):
            v.destroy()
    stats = {"method": "slepc-lobpcg-two-grid", "coarse_dofs": int(n_coarse),
             "setup_seconds": t1 - t0, "sweeps": result.sweeps,
             "history": list(result.history), "tolerance": target, "block": width,
             "converged": bool(result.converged),
             "keep": [A] if A is not K else []}
    log.info("two-grid LOBPCG on %d ranks: %d sweeps of %d vectors in %.1f s (set-up "
             "%.1f s, coarse %d DOFs), preconditioned residual %.1e", comm.size,
             result.sweeps, width, result.seconds, t1 - t0, n_coarse,
             min(result.history))
    return result.omega2[:count], result.X[:, :count], stats, ksp
