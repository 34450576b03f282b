"""The factor-free eigen solve on MPI ranks: LOBPCG preconditioned by the two-grid cycle.

The serial factor-free path (:mod:`pipeline.solve.multigrid`, :mod:`pipeline.solve.lobpcg`)
on distributed rows, with PETSc's objects for what crosses ranks:

- **The prolongation P** from the embedded linear (P1) space, a PETSc MPIAIJ matrix
  (n_free x n_coarse). Each rank makes its own rows (:func:`prolongation_rows`): a
  vertex DOF is its coarse DOF (1), an edge midpoint's DOF the mean of its edge's two
  vertex DOFs (1/2 each; a held vertex contributes nothing), exactly
  :func:`pipeline.fe.coarse.p1_prolongation`'s matrix, the coarse DOFs numbered in
  PETSc's row order (the free vertex DOFs a rank owns are its coarse rows).
- **The two-grid cycle** is the serial one (:class:`RankTwoGrid`, a
  :class:`~pipeline.solve.multigrid.TwoGrid` in double precision) on A = K - sigma M:
  Chebyshev-Jacobi smoothing, the Galerkin coarse matrix A_c = P^T A P (PETSc's PtAP)
  factorised by MUMPS, lambda_max(D^-1 A) by the same power steps; every product with
  A, P or P^T is one PETSc MatMatMult of a whole block of columns
  (:class:`BlockProduct`) and the coarse solve one MatMatSolve. PETSc's own two-level
  PCMG with the same smoother applies a preconditioner one column at a time: on the
  cantilever at 100k DOFs (2 ranks) LOBPCG took 19.6 s with it, 8.1 s with the block
  cycle (K times 25 columns: 0.39 s column by column, 0.094 s as one block).
- **The start block**: the coarse pencil's own modes (P^T K P, P^T M P, shift-invert
  Krylov-Schur on MUMPS' factor of the coarse matrix, to
  :data:`~pipeline.solve.eigen.MULTIGRID_START_TOLERANCE`), prolongated by P.
- **LOBPCG** is :func:`pipeline.solve.lobpcg.lobpcg` on this rank's rows: its products
  with K and M are PETSc's, its Gram matrices sums over the ranks.

The static correction's K^-1 F uses the same cycle under PETSc's conjugate gradients
(:data:`pipeline.solve.multigrid.PCG_RTOL`; the cycle as a Python PC), as the serial
path uses it under its own.

Measured (the cantilever at mesh.size 0.005, 100,695 free DOFs, 20 modes, 2 ranks on the
2-core Intel Xeon): 8 LOBPCG sweeps as on one process, the modes stage 9.8 s (serial
factor-free 3.8 s with two MKL threads and the float32 cycle); conjugate gradients on
GAMG inside Krylov-Schur's shift-invert, the path before, took 5 min 03 s.

Options: PETSc's options with the prefix ``pipeline_mg_`` reach the static solves' CG,
``pipeline_mg_coarse_`` the coarse factor (``-pipeline_mg_coarse_mat_mumps_icntl_14
50``), ``pipeline_mg_start_`` the start block's eigen solve, which uses the same coarse
factor (one factorisation: at 1M DOFs on 2 ranks the coarse problem has 136k DOFs).
Every call is collective.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp

from pipeline.distributed.mpi import allreduce_sum
from pipeline.distributed.operators import BlockProduct
from pipeline.fe.space import TET_EDGES
from pipeline.solve import lobpcg as lobpcg_module
from pipeline.errors import SolverError
from pipeline.solve.eigen import MULTIGRID_ACCEPT
from pipeline.solve.multigrid import PCG_RTOL, POWER_STEPS, TwoGrid

log = logging.getLogger(__name__)

#: the options prefixes of the static solves' CG (its PC is the cycle), of the coarse
#: factor (MUMPS' options: ``-pipeline_mg_coarse_mat_mumps_icntl_14 50``) and of the
#: start block's coarse eigen solve (``-pipeline_mg_start_eps_*``), which shares the
#: coarse factor
PREFIX = "pipeline_mg_"
COARSE_PREFIX = "pipeline_mg_coarse_"
START_PREFIX = "pipeline_mg_start_"
#: SLEPc's purification of the start block's eigenvectors (one more single-column solve
#: with the coarse factor for each converged vector, x <- (A_c - sigma M_c)^-1 M_c x),
#: off unless the user sets this option: the block only starts LOBPCG, to
#: :data:`~pipeline.solve.eigen.MULTIGRID_START_TOLERANCE`, and the serial start block
#: has no such step (with it: 1.0 s of the start block's 2.8 s at 618,582 free DOFs,
#: 86,010 coarse, on 2 ranks).
START_PURIFY_OPTION = START_PREFIX + "eps_purify"


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


def _midpoint_ends(mesh, dofs: np.ndarray, n_vertices: int):
    """(at (q,): the local rows of ``dofs`` (a rank's rows' DOFs) at edge midpoints,
    (q, 2) the PETSc rows of the same component at the edge's two vertices, -1 where
    held)."""
    nodes, comps = dofs // 3, dofs % 3
    at = np.flatnonzero(nodes >= n_vertices)
    if not at.size:
        return at, np.zeros((0, 2), dtype=np.int64)
    local = mesh.local_nodes(nodes[at])
    ends = midpoint_vertices(mesh.space.element_nodes, mesh.space.node_points.shape[0])
    if np.any(ends[local] < 0):
        raise AssertionError("a midpoint node without its element on this rank")
    return at, np.stack([mesh.dof_rows[3 * ends[local, side] + comps[at]]
                         for side in (0, 1)], axis=1)


def prolongation_rows(mesh, dofs: np.ndarray, coarse, n_vertices: int,
                      n_coarse: int) -> sp.csr_matrix:
    """This rank's rows ``mesh.lo:mesh.hi`` of P (module doc) as CSR
    (hi - lo, n_coarse) with the global coarse column numbers.

    mesh: the rank's :class:`~pipeline.distributed.submesh.RankMesh`; dofs (hi - lo,):
    the free DOF (3 node + component) of each of its rows; coarse: the coarse DOF of
    PETSc rows, ``coarse[rows]`` (:func:`coarse_numbering` of every row, or a
    :class:`CoarseRows`); n_vertices: the whole mesh's vertex count (global nodes
    below it are vertices); n_coarse: the coarse DOFs."""
    lo, hi = mesh.lo, mesh.hi
    dofs = np.asarray(dofs, dtype=np.int64)
    rows, cols, vals = [], [], []
    at = np.flatnonzero(dofs // 3 < n_vertices)
    rows.append(at)
    cols.append(coarse[lo + at])
    vals.append(np.ones(at.size))
    at, end_rows = _midpoint_ends(mesh, dofs, n_vertices)
    for side in (0, 1):
        held = end_rows[:, side] < 0
        rows.append(at[~held])
        cols.append(coarse[end_rows[~held, side]])
        vals.append(np.full(int((~held).sum()), 0.5))
    P = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(hi - lo, n_coarse))
    P.sum_duplicates()
    return P


class CoarseRows:
    """The coarse DOF (:func:`coarse_numbering` of every row) of this rank's rows
    ``lo:hi`` (``own``) and of the few other rows its prolongation rows read
    (``others``, ascending, and their ``others_coarse``); ``self[rows]`` for any of
    them. n_coarse: the coarse DOFs over all ranks."""

    def __init__(self, lo: int, own: np.ndarray, others: np.ndarray,
                 others_coarse: np.ndarray, n_coarse: int):
        self.lo, self.own, self.n_coarse = lo, own, n_coarse
        self.others, self.others_coarse = others, others_coarse

    def __getitem__(self, rows) -> np.ndarray:
        rows = np.asarray(rows, dtype=np.int64)
        mine = (rows >= self.lo) & (rows < self.lo + self.own.size)
        out = np.empty(rows.shape, dtype=np.int64)
        out[mine] = self.own[rows[mine] - self.lo]
        out[~mine] = self.others_coarse[np.searchsorted(self.others, rows[~mine])]
        return out


def coarse_rows(comm, part, mesh, n_vertices: int) -> CoarseRows:
    """The :class:`CoarseRows` of this rank (collective): its own rows' coarse DOFs from
    the vertex rows' counts of the ranks before it, the other rows' (the vertex ends of
    its midpoint rows, owned by its neighbours) asked of their owners (MPI_Alltoall):
    no rank holds every row's."""
    lo, hi = part.rows(comm.rank)
    dofs = part.owned_dofs(comm.rank)
    vertex = dofs // 3 < n_vertices
    counts = comm.allgather(int(np.count_nonzero(vertex)))
    own = np.where(vertex, sum(counts[:comm.rank]) + np.cumsum(vertex) - 1, -1)
    ends = _midpoint_ends(mesh, dofs, n_vertices)[1].ravel()
    others = np.unique(ends[(ends >= 0) & ((ends < lo) | (ends >= hi))])
    owner = np.searchsorted(part.starts, others, side="right") - 1
    asked = comm.alltoall([others[owner == r] for r in range(comm.size)])
    told = comm.alltoall([own[rows - lo] for rows in asked])
    others_coarse = np.empty(others.size, dtype=np.int64)
    for r in range(comm.size):
        others_coarse[owner == r] = told[r]
    return CoarseRows(lo, own, others, others_coarse, int(sum(counts)))


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


def prolongation(PETSc, space, part, comm):
    """The MPIAIJ P (module doc) of the distributed quadratic ``space``
    (:class:`~pipeline.distributed.submesh.DistributedSpace`) on the row partition
    ``part`` (this rank's own rows' suffice: :func:`coarse_rows`); collective."""
    n_vertices = space.body.n_vertices
    coarse = coarse_rows(comm, part, space.local, n_vertices)
    rows = prolongation_rows(space.local, part.owned_dofs(comm.rank), coarse, n_vertices,
                             coarse.n_coarse)
    return petsc_prolongation(PETSc, rows, int(np.count_nonzero(coarse.own >= 0)))


class CoarseFactor:
    """MUMPS' Cholesky factor of the distributed coarse matrix A_c; ``solve(B)`` for this
    rank's coarse rows B (n_c_loc, k) solves all k columns at once (MatMatSolve)."""

    def __init__(self, PETSc, Ac):
        from pipeline.distributed.eigen import mumps_cholesky

        self.PETSc, self.Ac = PETSc, Ac
        try:
            self.ksp = mumps_cholesky(PETSc, Ac, COARSE_PREFIX, "the coarse matrix P^T A P")
        except BaseException:
            Ac.destroy()
            raise
        self.factor = self.ksp.getPC().getFactorMatrix()

    def solve(self, B: np.ndarray) -> np.ndarray:
        PETSc = self.PETSc
        B = np.asfortranarray(B, dtype=np.float64).reshape(B.shape[0], -1)
        comm = self.Ac.getComm()
        size = ((B.shape[0], PETSc.DETERMINE), (PETSc.DECIDE, B.shape[1]))
        Bd = PETSc.Mat().createDense(size=size, array=B, comm=comm)
        Xd = PETSc.Mat().createDense(size=size, comm=comm)
        Xd.setUp()
        Xd.assemble()
        self.factor.matSolve(Bd, Xd)
        X = np.array(Xd.getDenseArray(), dtype=np.float64, order="C")
        Bd.destroy()
        Xd.destroy()
        return X

    def refactor(self, A, P) -> None:
        """A_c = P^T A P for an A of the same nonzero pattern, into the same matrix
        (PETSc's PtAP reusing its symbolic product), factorised numerically on MUMPS'
        analysis of the first (PCSetUp of a matrix whose values changed)."""
        A.PtAP(P, result=self.Ac)
        self.ksp.setOperators(self.Ac)
        self.ksp.setUp()
        self.factor = self.ksp.getPC().getFactorMatrix()

    def release(self) -> None:
        if self.ksp is not None:
            self.ksp.destroy()
            self.Ac.destroy()
        self.ksp = self.factor = None


class RankTwoGrid(TwoGrid):
    """The serial two-grid cycle in double precision (:meth:`TwoGrid.apply`, the same
    Chebyshev-Jacobi smoothing and exact coarse correction) on this rank's rows: its
    products with A, P and P^T are :class:`BlockProduct`, its coarse solve MUMPS'
    (:class:`CoarseFactor`), lambda_max(D^-1 A) from the same power steps with the norms
    summed over the ranks. (PETSc has no float32 build here, so there is no float32
    cycle.) A: the PETSc matrix K - sigma M; P: the prolongation; collective."""

    def __init__(self, PETSc, A, P):  # noqa: D107 (not TwoGrid's: nothing is whole here)
        t0 = time.perf_counter()
        self.PETSc, self.comm = PETSc, A.getComm().tompi4py()
        self._P = P
        self.P = BlockProduct(PETSc, P)
        self.PT = BlockProduct(PETSc, P, transpose=True)
        self._smoother(A)
        self.coarse_n = int(P.getSize()[1])
        self.coarse = CoarseFactor(PETSc, A.PtAP(P))
        self._single = self._ptd = self._p32 = self._riding = None  # serial-only caches
        self._a_norm = None  # ||A||_inf, made on first use (TwoGrid._norm_inf)
        self.lambda_max = self._lambda_max()
        self.seconds = time.perf_counter() - t0

    def _smoother(self, A) -> None:
        """A's products and Jacobi's D^-1 (a non-positive diagonal entry: SolverError)."""
        self.A = BlockProduct(self.PETSc, A)
        d = A.getDiagonal()
        diagonal = d.getArray().copy()
        d.destroy()
        if float(allreduce_sum(self.comm, np.array([diagonal.min(initial=np.inf)]),
                               "MIN")[0]) <= 0:
            raise SolverError("multigrid: the stiffness matrix has a non-positive diagonal "
                              "entry; expected a positive definite K")
        self.dinv = 1.0 / diagonal

    def refresh(self, A) -> None:
        """The cycle of a new A with the nonzero pattern of the one it was made for (a
        rotation sweep's K(Omega) at the next speed): P is kept (the mesh's, not A's);
        what depends on A's values is made again: the smoother's D^-1 and lambda_max,
        the Galerkin A_c = P^T A P (PtAP into the same matrix) and its MUMPS factor,
        numerically only (the analysis of the first A is kept)."""
        t0 = time.perf_counter()
        self._smoother(A)
        self._a_norm = None  # A's values changed
        self.coarse.refactor(A, self._P)
        self.lambda_max = self._lambda_max()
        self.seconds = time.perf_counter() - t0

    @staticmethod
    def _product(A, X: np.ndarray) -> np.ndarray:
        return A(X)

    def _lambda_max(self) -> float:
        x = np.random.default_rng(3 + self.comm.rank).standard_normal((self.dinv.size, 1))
        lam = 1.0
        for _ in range(POWER_STEPS):
            y = self.dinv[:, None] * self.A(x)
            norms = np.sqrt(allreduce_sum(self.comm, np.array([(y * y).sum(), (x * x).sum()])))
            lam = float(norms[0] / norms[1])
            x = y / norms[0]
        return 1.1 * lam

    def apply_double(self, R: np.ndarray) -> np.ndarray:
        """T R for this rank's rows R (n_loc, k): the double-precision cycle."""
        return self.apply(R, single=False)

    def release(self) -> None:
        self.coarse.release()


class _CyclePC:
    """petsc4py's Python PC context: the cycle on one column (conjugate gradients)."""

    def __init__(self, cycle: RankTwoGrid):
        self.cycle = cycle

    def apply(self, pc, x, y) -> None:
        y.getArray()[:] = self.cycle.apply(x.getArray().reshape(-1, 1), single=False)[:, 0]


def two_grid_solver(PETSc, A, cycle: RankTwoGrid):
    """A KSP: conjugate gradients on A to :data:`~pipeline.solve.multigrid.PCG_RTOL`,
    preconditioned by ``cycle`` (the static solves); the caller destroys it. PETSc
    options with the prefix :data:`PREFIX` override the choices."""
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setOptionsPrefix(PREFIX)
    ksp.setOperators(A)
    ksp.setType(PETSc.KSP.Type.CG)
    ksp.setTolerances(rtol=PCG_RTOL, atol=0.0, max_it=500)
    pc = ksp.getPC()
    pc.setType(PETSc.PC.Type.PYTHON)
    pc.setPythonContext(_CyclePC(cycle))
    ksp.setFromOptions()
    ksp.setUp()
    return ksp


def lobpcg_modes(PETSc, SLEPc, K, M, P, count: int, width: int, shift: float,
                 target: float, start_tolerance: float, max_sweeps: int,
                 accept: float = MULTIGRID_ACCEPT):
    """(omega2 (count,), this rank's rows (n_loc, count) of the M-orthonormal modes,
    stats, ksp): two-grid preconditioned LOBPCG on the PETSc pair (K, M) with the
    prolongation P (module doc); ``width`` >= count columns (the rest guard columns),
    ``shift`` sigma (0, or below zero for a body free to move), ``target`` LOBPCG's
    preconditioned residual; a LOBPCG that stops above ``accept`` is refused
    (SolverError, as on one process). ``ksp``: conjugate gradients on the cycle for
    A = K - sigma M (the static correction's solver when sigma = 0); the caller destroys
    it and ``stats["keep"]``."""
    t0 = time.perf_counter()
    if shift != 0.0:
        A = K.copy()
        A.axpy(-shift, M, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
    else:
        A = K
    cycle = RankTwoGrid(PETSc, A, P)
    ksp = two_grid_solver(PETSc, A, cycle)
    Mc = M.PtAP(P)
    width = min(width, cycle.coarse_n // 2)
    try:
        X = _start_block(PETSc, SLEPc, cycle, Mc, width, start_tolerance)
    finally:
        Mc.destroy()
    t1 = time.perf_counter()
    # PETSc's objects the caller destroys, on every rank at the same point (MUMPS'
    # termination is collective: never left to the garbage collector)
    keep = [cycle.coarse.ksp, cycle.coarse.Ac] + ([A] if A is not K else [])
    try:
        result = _lobpcg(PETSc, K, M, X, cycle, count, shift, target, max_sweeps, accept)
    except BaseException:
        for obj in (ksp, *keep):
            obj.destroy()
        raise
    return (result.omega2[:count], result.X[:, :count],
            {**_stats(cycle, result, width, target, t1 - t0), "keep": keep}, ksp)


def _start_block(PETSc, SLEPc, cycle: RankTwoGrid, Mc, width: int, tolerance: float):
    """This rank's rows of the prolongated lowest ``width`` modes of the coarse pencil
    (A_c, M_c = P^T M P) by shift-invert on the cycle's own coarse factor, without
    SLEPc's purification of the eigenvectors (:data:`START_PURIFY_OPTION`)."""
    from pipeline.distributed.eigen import _option_unless_set, solve_eigen

    with _option_unless_set(PETSc.Options(), START_PURIFY_OPTION, 0):
        _, coarse_rows, cstats = solve_eigen(PETSc, SLEPc, cycle.coarse.Ac, Mc, width,
                                             tolerance, prefix=START_PREFIX,
                                             ksp=cycle.coarse.ksp)
    cstats.pop("eps").destroy()
    return cycle.P(coarse_rows)


def _lobpcg(PETSc, K, M, X, cycle: RankTwoGrid, count: int, shift: float, target: float,
            max_sweeps: int, accept: float):
    """LOBPCG from the start block X on this rank's rows, the serial path's acceptance
    (the same history on every rank: its sums are)."""
    comm = PETSc.COMM_WORLD.tompi4py()
    result = lobpcg_module.lobpcg(
        BlockProduct(PETSc, K), BlockProduct(PETSc, M), X, cycle.apply_double, count,
        sigma=shift, target=target, max_sweeps=max_sweeps,
        total=lambda a: allreduce_sum(comm, a))
    if not result.converged and min(result.history) > accept:
        raise SolverError(
            f"multigrid eigensolver did not converge for {count} modes in "
            f"{result.sweeps} sweeps (worst preconditioned residual "
            f"{min(result.history):.1e}, tolerance {target:.1e}); try modes.method: "
            "factor, or a coarser mesh.size", key="modes.method", value="multigrid",
            expected="a body the two-grid cycle converges on")
    if not result.converged and comm.rank == 0:
        log.warning("multigrid eigensolver stopped at a preconditioned residual of %.1e "
                    "(tolerance %.1e): round-off floor", min(result.history), target)
    return result


def _stats(cycle: RankTwoGrid, result, width: int, target: float, setup: float) -> dict:
    """The stats of a two-grid LOBPCG solve (logged at INFO)."""
    log.info("two-grid LOBPCG on %d ranks: %d sweeps of %d vectors in %.1f s (set-up "
             "%.2f s, of it the cycle %.2f s; coarse %d DOFs), preconditioned residual "
             "%.1e", cycle.comm.size, result.sweeps, width, result.seconds, setup,
             cycle.seconds, cycle.coarse_n, min(result.history))
    return {"method": "slepc-lobpcg-two-grid", "coarse_dofs": int(cycle.coarse_n),
            "setup_seconds": setup, "cycle_seconds": cycle.seconds, "sweeps": result.sweeps,
            "history": list(result.history), "tolerance": target, "block": width,
            "converged": bool(result.converged)}


class TwoGridSweep:
    """Two-grid LOBPCG for a family of operators A of one nonzero pattern with the same
    M and P (a rotation sweep's K(Omega) = K + Omega^2 S, speed after speed): the cycle
    is made for the first A and refreshed for the next (:meth:`RankTwoGrid.refresh`: P,
    the coarse mass M_c = P^T M P and MUMPS' coarse analysis kept; the smoother, A_c and
    its numeric factor made again), then the coarse start block and LOBPCG as
    :func:`lobpcg_modes`; no conjugate-gradient solver (the sweep solves no static
    problem). Collective; :meth:`release` frees it."""

    def __init__(self, PETSc, SLEPc, M, P):
        self.PETSc, self.SLEPc, self.M, self.P = PETSc, SLEPc, M, P
        self.cycle: RankTwoGrid | None = None
        self.Mc = None

    def solve(self, A, count: int, width: int, target: float, start_tolerance: float,
              max_sweeps: int, accept: float = MULTIGRID_ACCEPT):
        """(omega2 (count,), this rank's rows (n_loc, count), stats) of (A, M) at shift 0."""
        t0 = time.perf_counter()
        if self.cycle is None:
            self.cycle = RankTwoGrid(self.PETSc, A, self.P)
            self.Mc = self.M.PtAP(self.P)
        else:
            self.cycle.refresh(A)
        width = min(width, self.cycle.coarse_n // 2)
        X = _start_block(self.PETSc, self.SLEPc, self.cycle, self.Mc, width, start_tolerance)
        t1 = time.perf_counter()
        result = _lobpcg(self.PETSc, A, self.M, X, self.cycle, count, 0.0, target,
                         max_sweeps, accept)
        return (result.omega2[:count], result.X[:, :count],
                _stats(self.cycle, result, width, target, t1 - t0))

    def release(self) -> None:
        """Free the cycle and the coarse mass (collective)."""
        if self.cycle is not None:
            self.cycle.release()
            self.Mc.destroy()
        self.cycle = self.Mc = None
