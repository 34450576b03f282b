"""Factor-free solves for meshes whose sparse factor does not fit: a two-grid method.

A quadratic (P2) tetrahedral mesh contains its own linear (P1) space: the vertices, with
every edge midpoint interpolated halfway between its two vertices. That embedding is a
prolongation P (n x n_c, :func:`pipeline.fe.coarse.p1_prolongation`) onto about 1/7 of
the DOFs, and the Galerkin coarse matrix A_c = P^T A P (A = K - sigma M) is factorised
directly: a 3M-DOF P2 problem (a ~40 GB double factor) has a ~0.4M-DOF P1 coarse
problem (a ~1-2 GB factor). The preconditioner T ~ A^-1 is one symmetric two-grid cycle:

    z  = S_pre(r)                      Chebyshev-Jacobi smoothing, degree DEGREE
    z += P A_c^-1 P^T (r - A z)        exact coarse correction
    z  = S_post(r, z)                  the same smoothing again (T stays symmetric)

The smoother is the Chebyshev polynomial in D^-1 A (D = diag A) that damps the interval
[LOWER, 1.1] * lambda_max(D^-1 A) (lambda_max by a few power steps): the components the
coarse P1 space cannot represent. On the cantilever (P2, 101k DOFs) conjugate gradients
with this T reach 1e-8 in 13-17 iterations (degree 2-4), independent of the mesh size
because the coarse problem is solved exactly.

For LOBPCG the cycle runs in float32 (``apply(R, single=True)``): a float32 copy of
D^-1 A (4 bytes per non-zero; the index arrays are shared with A) and float32 smoothing
on Rh = D^-1 R, where each Chebyshev step is one threaded axpby, one sparse product
accumulated into the step (MKL's beta = 1) and one axpy (12% off the cycle at 1M
DOFs); the restriction by P^T D and the prolongation run in float32 too (P's entries
1 and 1/2 are exact, and the residual they carry is float32 already), and only the coarse
solve is in double (at 1M DOFs and 25 vectors: 1.37 s a cycle instead of 1.65-1.8 s, the
(n, k) float64 conversions it no longer makes). A preconditioner only chooses search
directions, and the eigenvalues and residuals stay in double, so this changes neither
the accuracy nor (measured) the sweep count; it halves the memory traffic of the
sparse products, which are most of a sweep (K times 25 vectors at 1M DOFs is 2.5
times faster). PCG (static solves) takes the float32 cycle too: its Polak-Ribiere beta
(flexible CG, :mod:`pipeline.solve.pcg`) does not assume a fixed linear T, and X and its
residual stay in double, so it reaches the same round-off floor; each column is scaled
to unit max before the cast, so a residual near that floor does not underflow.

Used by :mod:`pipeline.solve.eigen` as the preconditioner of :func:`pipeline.solve.lobpcg.lobpcg`
(``modes.method: multigrid``) and, through :meth:`TwoGrid.factorization`, as the solver
K^-1 F of the static correction (preconditioned conjugate gradients to a relative
residual of :data:`PCG_RTOL`). The static correction's loads are known before the modes (the
input ports), so its conjugate gradients start with LOBPCG (:meth:`TwoGrid.ride`): each
sweep's cycle takes their residual as k more columns and makes one PCG iteration
(:class:`pipeline.solve.pcg.Pcg`, the same recurrence), and the solve the reduce stage
asks for later continues from there. A one-column PCG iteration of its own streams K
seven times for one vector; riding, it costs about a tenth of that. The cantilever at
999k DOFs (one tip load, Intel Xeon 2 cores, alternating runs): the static solve 6.8-8.7 s ->
3.1-4.0 s, 7 of its iterations in LOBPCG's 6 sweeps. Shapes: A (n x n) CSR, P
(n x n_c) CSR, blocks (n, k).

Kept over the library: PyAMG's smoothed aggregation (``smoothed_aggregation_solver``
with the six rigid-body modes as near-null space, K's held DOFs as unit rows so that
the hierarchy sees 3 x 3 node blocks; ``benchmarks/bench_solvers.py``) measured on the
same matrices, the cantilever at 100k DOFs, 20 modes, same LOBPCG and start block
(2-core Xeon, load average 10-14 from other jobs; ratios from the same run): the
two-grid cycle takes 8 sweeps and 17 s, SA 19 sweeps and 503 s (29x; 2.4x the sweeps,
the rest from one V-cycle per column in double against one float32 cycle for the whole
block), peak 558 MB against 785 MB. Under PCG (static solves, four columns to 1e-10):
25k DOFs 18 iterations against 42, 0.7 s against 10.9 s; 996k DOFs 17 against 70,
25 s against 514 s (21x; set-up 6 s against 41 s), peak 2.6 GB against 3.6 GB.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp

from pipeline._util.resources import retained_heap
from pipeline.errors import SolverError
from pipeline._util.sparse import csr_diagonal
from pipeline.solve.blas import (axpby, by_rows, galerkin_product, scaled_inf_norm,
                                 sparse_times_dense)
from pipeline.solve.factorization import (Factorization, SolverFactorization, factorize,
                                          resolve_backend)
from pipeline.solve.pcg import Pcg

log = logging.getLogger(__name__)

# Chebyshev smoothing steps before and after the coarse correction. 4 against 3 (same
# runs, Intel Xeon 2 cores): the cantilever at 999k DOFs 6 LOBPCG sweeps instead of 7,
# modes and static solve 43 s instead of 45 s (medians of 3); 312k 7 sweeps instead of
# 8, -8%; the bracket (103k) and the slender beam (127k) 9 instead of 10, -9% and -20%;
# the 2 mm strip (207k) 16 instead of 17 but 14% slower (each cycle does 8 sparse
# products instead of 6)
DEGREE = 4
LOWER = 0.05  # lower end of the smoothed interval, as a fraction of lambda_max(D^-1 A)
POWER_STEPS = 12
PCG_BLOCKS = 8  # (n x k) blocks a PCG iteration allocates (residual, search direction, cycle)
RIDER_BLOCKS = 6  # (n x k) blocks a riding PCG holds through the sweeps (TwoGrid.ride)
PCG_RTOL = 1e-12  # static solves: ||F - K X|| <= PCG_RTOL ||F|| per column
PCG_MAX_ITER = 500


def _csr32(A: sp.spmatrix) -> sp.csr_matrix:
    A = sp.csr_matrix(A)
    if A.nnz < 2**31 and A.shape[0] < 2**31:
        A.indices = A.indices.astype(np.int32, copy=False)
        A.indptr = A.indptr.astype(np.int32, copy=False)
    return A


def coarse_matrix(tg: "TwoGrid", M: sp.spmatrix) -> sp.csr_matrix:
    """P^T M P (n_c x n_c) on the coarse space of ``tg`` (the P1 mass of a P2 mesh)."""
    return _csr32(galerkin_product(tg.PT, _csr32(M), tg.P))


def _analysis_ahead(coarse: sp.csr_matrix, backend: str):
    """PARDISO's analysis of the coarse matrix's pattern started in a background thread
    (:class:`~pipeline.solve.backends.pardiso.PatternAnalysis`) when PARDISO will
    factorise it, else None (the backend analyses as it factorises)."""
    if resolve_backend(backend) != "pardiso":
        return None
    from pipeline.solve.backends.pardiso import PatternAnalysis

    coarse.sort_indices()  # in place: the analysis reads sorted rows (scipy's product's are not)
    return PatternAnalysis(coarse.indptr, coarse.indices)


class TwoGrid:
    """The two-grid preconditioner of the module doc for A (n x n) and P (n x n_c).

    ``backend``: the factorisation backend of the coarse matrix. ``apply(R)`` returns
    T R for R (n,) or (n, k); ``release()`` frees the coarse factor.
    """

    def __init__(self, A: sp.spmatrix, P: sp.spmatrix, backend: str = "auto"):
        t0 = time.perf_counter()
        self.A = _csr32(A)
        self.P = _csr32(P)
        self.PT = _csr32(self.P.T)
        if self.P.shape[0] != self.A.shape[0]:
            raise ValueError(f"prolongation P has {self.P.shape[0]} rows; expected "
                             f"{self.A.shape[0]} (the rows of A)")
        coarse = _csr32(galerkin_product(self.PT, self.A, self.P))
        self.coarse_n = coarse.shape[0]
        # the coarse matrix's ordering runs beside the smoother's set-up (D^-1, the
        # float32 D^-1 A and lambda_max's power steps), its numerical factor after them
        ahead = _analysis_ahead(coarse, backend)
        try:
            d = csr_diagonal(self.A)
            if not np.all(d > 0):
                raise SolverError("multigrid: the stiffness matrix has a non-positive "
                                  "diagonal entry; expected a positive definite K")
            self.dinv = 1.0 / d
            self._single: tuple[sp.csr_matrix, np.ndarray] | None = None
            self._ptd: sp.csr_matrix | None = None
            self._p32: sp.csr_matrix | None = None
            self._riding: tuple[np.ndarray, Pcg] | None = None
            self._a_norm: float | None = None
            self.lambda_max = self._lambda_max()
        except BaseException:
            if ahead is not None:
                ahead.release()
            raise
        self.coarse = factorize(coarse, backend, positive_definite=True, check=False,
                                analysis=ahead)
        del coarse
        self.seconds = time.perf_counter() - t0
        log.info("two-grid preconditioner: %d -> %d coarse DOFs, coarse factor %.2f GB, "
                 "lambda_max(D^-1 A) %.3g, set up in %.1f s", self.A.shape[0], self.coarse_n,
                 self.coarse.info.get("factor_bytes", 0) / 1e9, self.lambda_max, self.seconds)

    def _lambda_max(self) -> float:
        """1.1 times the power-step estimate of lambda_max(D^-1 A), on the float32 D^-1 A
        the cycle uses anyway (half the memory traffic of A and D^-1 in double: 1M DOFs,
        12 steps, 0.75 -> 0.3 s; the estimate only sets the smoothed interval)."""
        B, _ = self._operator(True)
        x = np.random.default_rng(3).standard_normal(self.A.shape[0]).astype(np.float32)
        lam = 1.0
        for _ in range(POWER_STEPS):
            y = sparse_times_dense(B, x)
            norm_y = float(np.linalg.norm(y))
            lam = norm_y / float(np.linalg.norm(x))
            x = y / np.float32(norm_y)
        return 1.1 * lam  # power steps approach lambda_max from below

    def _operator(self, single: bool) -> tuple[sp.csr_matrix, np.ndarray]:
        """(A, D^-1) in float64; with ``single``, the float32 cycle's operators
        (D^-1 A, D^-1): the float32 rows of A scaled by D^-1 (made on first use; indices
        shared with A, 4 bytes a non-zero)."""
        if not single:
            return self.A, self.dinv
        if self._single is None:
            A = self.A
            data = np.empty(A.nnz, dtype=np.float32)
            dinv32 = self.dinv.astype(np.float32)

            def fill(part: slice) -> None:  # cast, then scale in float32, chunk by chunk
                rows = 1 << 16  # row chunks: no nnz-long temporary
                for start in range(part.start or 0, part.stop, rows):
                    stop = min(start + rows, part.stop)
                    lo, hi = A.indptr[start], A.indptr[stop]
                    np.copyto(data[lo:hi], A.data[lo:hi], casting="unsafe")
                    data[lo:hi] *= np.repeat(dinv32[start:stop],
                                             np.diff(A.indptr[start:stop + 1]))

            by_rows(fill, A.shape[0])  # row halves on two threads: the same values
            self._single = (sp.csr_matrix((data, A.indices, A.indptr), shape=A.shape), dinv32)
        return self._single

    def _restriction_scaled(self) -> sp.csr_matrix:
        """P^T D (n_c x n) in float32: the restriction of a residual given as
        D^-1 (R - A Z) (itself float32 in the cycle)."""
        if self._ptd is None:
            PT = self.PT
            self._ptd = sp.csr_matrix(((PT.data * (1.0 / self.dinv)[PT.indices])
                                       .astype(np.float32), PT.indices, PT.indptr),
                                      shape=PT.shape)
        return self._ptd

    def _prolongation_single(self) -> sp.csr_matrix:
        """P in float32 (its entries 1 and 1/2 are exact; indices shared with P)."""
        if self._p32 is None:
            P = self.P
            self._p32 = sp.csr_matrix((P.data.astype(np.float32), P.indices, P.indptr),
                                      shape=P.shape)
        return self._p32

    def _chebyshev(self) -> tuple[float, float, float]:
        """(theta, delta, sigma) of the smoothed interval [LOWER, 1] * lambda_max(D^-1 A):
        its centre, half-width and their ratio."""
        hi = self.lambda_max
        lo = LOWER * hi
        theta, delta = 0.5 * (hi + lo), 0.5 * (hi - lo)
        return theta, delta, theta / delta

    def _smooth_single(self, Rh: np.ndarray, Z: np.ndarray | None) -> np.ndarray:
        """The float32 form of :meth:`_smooth` for Rh = D^-1 R, with B = D^-1 A: every
        step is D = c1 D + c2 (Rh - B Z), Z += D, i.e. one axpby, one sparse product
        accumulated into D (beta = 1) and one axpy, threaded and without temporaries
        (numpy's form makes six passes over (n, k) blocks on one thread: a third of a
        step for K of 1M DOFs times 25 vectors)."""
        B, _ = self._operator(True)
        theta, delta, sigma = self._chebyshev()
        rho = 1.0 / sigma
        D = _scaled(Rh, np.float32(1.0 / theta))
        if Z is None:
            Z = _copied(D)
        else:
            sparse_times_dense(B, Z, out=D, alpha=-1.0 / theta, beta=1.0)
            axpby(1.0, D, 1.0, Z)
        for _ in range(DEGREE - 1):
            rho_new = 1.0 / (2.0 * sigma - rho)
            c2 = 2.0 * rho_new / delta
            axpby(c2, Rh, rho_new * rho, D)
            sparse_times_dense(B, Z, out=D, alpha=-c2, beta=1.0)
            axpby(1.0, D, 1.0, Z)
            rho = rho_new
        return Z

    def _smooth(self, R: np.ndarray, Z: np.ndarray | None) -> np.ndarray:
        """Z + the Chebyshev correction of degree DEGREE for A Z = R (Z None: from 0),
        in double precision. In-place updates: each step is one sparse product and four
        passes over (n, k)."""
        A, dinv = self._operator(False)
        theta, delta, sigma = self._chebyshev()
        rho = 1.0 / sigma
        dinv = dinv[:, None]
        D = self._residual(R, Z, A)
        D *= dinv
        D *= 1.0 / theta
        if Z is None:
            Z = D.copy()
        else:
            Z += D
        for _ in range(DEGREE - 1):
            res = self._residual(R, Z, A)
            res *= dinv
            rho_new = 1.0 / (2.0 * sigma - rho)
            D *= rho_new * rho
            res *= 2.0 * rho_new / delta
            D += res
            del res
            Z += D
            rho = rho_new
        return Z

    def _residual(self, R: np.ndarray, Z: np.ndarray | None, A) -> np.ndarray:
        """R - A Z in a new array (R itself copied when Z is None)."""
        if Z is None:
            return R.copy()
        AZ = self._product(A, Z)
        np.subtract(R, AZ, out=AZ)
        return AZ

    @staticmethod
    def _product(A, X: np.ndarray) -> np.ndarray:
        """A X for the cycle's double-precision operators (A, P^T, P); a subclass whose
        operators are distributed (:mod:`pipeline.distributed.multigrid`) overrides it."""
        return sparse_times_dense(A, X)

    def apply(self, R: np.ndarray, single: bool = False) -> np.ndarray:
        """T R (float64) for R (n,) or (n, k); ``single``: the float32 cycle of the
        module doc."""
        R = np.asarray(R, dtype=np.float64)
        vector = R.ndim == 1
        R = R.reshape(R.shape[0], -1)
        if single:
            return self._apply_single(R, vector)
        R = np.ascontiguousarray(R)
        Z = self._smooth(R, None)
        res = self._residual(R, Z, self.A)
        rc = np.ascontiguousarray(self._product(self.PT, res))
        del res
        zc = np.asarray(self.coarse.solve(rc)).reshape(rc.shape)
        Z += self._product(self.P, np.ascontiguousarray(zc))
        Z = self._smooth(R, Z)
        return Z[:, 0] if vector else Z

    def _apply_single(self, R: np.ndarray | list[np.ndarray], vector: bool = False
                      ) -> np.ndarray | list[np.ndarray]:
        """The float32 cycle of :meth:`apply` for R (n, k) float64, or for a list of such
        blocks as one cycle, returning a list of blocks (C-contiguous each; no joined
        copy of the inputs). Each column is scaled to unit max before the cast (T is
        linear), so a small residual (PCG near its floor) neither underflows nor goes
        subnormal; the scale stays in double (it may lie outside float32's range). The
        restriction and prolongation run in float32 too (P's entries 1 and 1/2 are
        exact; the residual they carry is float32 already), so only the coarse solve
        (n_c, k) is in double: at 1M DOFs and 25 columns that spares four (n, k)
        conversions, a fifth of the cycle."""
        blocks = R if isinstance(R, list) else [R]
        B, dinv32 = self._operator(True)
        n = B.shape[0]
        edges = np.cumsum([0] + [b.shape[1] for b in blocks])
        Rh = np.empty((n, int(edges[-1])), dtype=np.float32)
        scale = np.empty(Rh.shape[1])
        for b, lo, hi in zip(blocks, edges[:-1], edges[1:]):
            parts = by_rows(lambda s, b=b: (b[s].max(axis=0), b[s].min(axis=0)), n)
            s = np.maximum(np.max([p[0] for p in parts], axis=0),
                           -np.min([p[1] for p in parts], axis=0))
            scale[lo:hi] = np.where(np.isfinite(s) & (s > 0), s, 1.0)

        def cast(rows: slice) -> None:  # Rh = D^-1 R / scale, row half by row half
            for b, lo, hi in zip(blocks, edges[:-1], edges[1:]):
                np.multiply(b[rows], 1.0 / scale[lo:hi], out=Rh[rows, lo:hi],
                            casting="unsafe")
            Rh[rows] *= dinv32[rows, None]

        by_rows(cast, n)
        Z = self._smooth_single(Rh, None)
        res = _copied(Rh)  # D^-1 (R - A Z); its restriction is (P^T D) res
        sparse_times_dense(B, Z, out=res, alpha=-1.0, beta=1.0)
        rc = self._product(self._restriction_scaled(), res)
        del res
        rc = np.ascontiguousarray(rc, dtype=np.float64)
        zc = np.asarray(self.coarse.solve(rc)).reshape(rc.shape)
        self._prolong_into(np.ascontiguousarray(zc, dtype=np.float32), Z)
        Z = self._smooth_single(Rh, Z)
        out = [np.empty((n, hi - lo)) for lo, hi in zip(edges[:-1], edges[1:])]

        def unscale(rows: slice) -> None:
            for o, lo, hi in zip(out, edges[:-1], edges[1:]):
                np.multiply(Z[rows, lo:hi], scale[lo:hi], out=o[rows])

        by_rows(unscale, n)
        if isinstance(R, list):
            return out
        return out[0][:, 0] if vector else out[0]

    def _prolong_into(self, zc: np.ndarray, Z: np.ndarray) -> None:
        """Z += P zc in float32, accumulated into Z (one product, no (n, k) temporary)."""
        sparse_times_dense(self._prolongation_single(), zc, out=Z, beta=1.0)

    def apply_single(self, R: np.ndarray) -> np.ndarray:
        """``apply(R, single=True)``: the float32 cycle (LOBPCG's preconditioner)."""
        return self.apply(R, single=True)

    def ride(self, B: np.ndarray, rtol: float = PCG_RTOL) -> None:
        """Start the conjugate gradients of A X = B (n, k) that :meth:`precondition`
        advances one iteration per LOBPCG sweep and :meth:`solve` finishes when asked
        for exactly this B (the static correction's loads, announced by the modes
        stage): their columns ride in the sweep's own cycle (module doc)."""
        self._riding = (np.array(B, dtype=np.float64),
                        Pcg(self.A, B, rtol, PCG_MAX_ITER, self._norm_inf()))

    def precondition(self, R: np.ndarray) -> np.ndarray:
        """LOBPCG's preconditioner: the float32 cycle on R (n, k), with the riding
        conjugate gradients' residual as extra columns of the same cycle while they
        run (:meth:`ride`)."""
        riding = None if self._riding is None else self._riding[1]
        if riding is None or riding.finished:
            return self.apply_single(R)
        Z, Zs = self._apply_single([np.ascontiguousarray(R, dtype=np.float64),
                                    riding.residual])
        riding.advance(Zs)
        return Z

    def solve(self, B: np.ndarray, rtol: float = PCG_RTOL,
              max_iter: int = PCG_MAX_ITER) -> np.ndarray:
        """A^-1 B by preconditioned conjugate gradients (:func:`pipeline.solve.pcg.pcg`),
        all columns of B (n,) or (n, k) at once, each to ||B - A X|| <= rtol ||B||; the
        riding solve of :meth:`ride` continued where B is its right-hand side."""
        width = 1 if np.ndim(B) == 1 else np.shape(B)[1]
        with retained_heap(PCG_BLOCKS * 8.0 * self.A.shape[0] * width):
            run = self._take_riding(B, rtol, max_iter)
            rode = 0 if run is None else run.iterations
            if run is None:
                run = Pcg(self.A, B, rtol, max_iter, self._norm_inf())
            X, self.iterations = run.run(self.apply_single)
        log.debug("multigrid PCG: %d iterations (%d of them in LOBPCG's sweeps)",
                  self.iterations, rode)
        return X

    def _take_riding(self, B: np.ndarray, rtol: float, max_iter: int) -> Pcg | None:
        """The riding solve if B (and rtol, max_iter) are its own, else None; it is
        handed out once."""
        if self._riding is None:
            return None
        loads, run = self._riding
        B = np.asarray(B)
        if (run.rtol != rtol or run.max_iter != max_iter or B.shape[0] != loads.shape[0]
                or B.reshape(B.shape[0], -1).shape != loads.reshape(loads.shape[0], -1).shape
                or not np.array_equal(B.reshape(loads.shape), loads)):
            return None
        self._riding = None
        run.vector = B.ndim == 1
        return run

    def _norm_inf(self) -> float:
        """||A||_inf, the floor of every PCG's stop test: one pass over A, made once."""
        if self._a_norm is None:
            self._a_norm = scaled_inf_norm(self.A)
        return self._a_norm

    def release(self) -> None:
        self.coarse.release()
        self._single = self._ptd = self._p32 = self._riding = None

    def factorization(self) -> Factorization:
        """This solver as a :class:`Factorization` of A (``solve`` by PCG), which the
        static correction uses like a direct factor; ``release()`` frees the coarse
        factor."""
        return SolverFactorization(self.solve, backend="multigrid", n=self.A.shape[0],
                                   release=self.release,
                                   info={"coarse_dofs": self.coarse_n,
                                         "factor_bytes": self.coarse.memory_bytes})


def _scaled(X: np.ndarray, c) -> np.ndarray:
    """c X in a new array, by row halves on two threads for tall X (element-wise: the
    same result however the rows are split)."""
    out = np.empty_like(X)
    by_rows(lambda s: np.multiply(X[s], c, out=out[s]), X.shape[0])
    return out


def _copied(X: np.ndarray) -> np.ndarray:
    """A copy of X, by row halves on two threads for tall X."""
    out = np.empty_like(X)
    by_rows(lambda s: np.copyto(out[s], X[s]), X.shape[0])
    return out
