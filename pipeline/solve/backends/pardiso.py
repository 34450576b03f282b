"""MKL PARDISO called directly through ``ctypes`` (MKL comes with the ``fast`` extra).

Symmetric positive-definite Cholesky (matrix type 2) of the upper triangle, or symmetric
indefinite LDL^T (type -2), prepared once: 32-bit zero-based indices (no per-call index
conversion or re-hashing, unlike ``pypardiso.spsolve``) and PARDISO's variable-block
conversion of the rows (the 3 DOFs of a node share one pattern), which makes the METIS
analysis 2-3 times faster at 1M DOFs. The exact factor size, known after the analysis,
is checked against the available memory before the factorisation allocates it. Threaded
over the cores this process may use, scoped to each call (:func:`pipeline.solve.mkl.threads`).
Multiple right-hand sides are solved in one call, and the Cholesky factor ``L`` is also
offered as separate forward (``L^-1 b``) and backward (``L^-T y``) substitutions, which
the block Lanczos eigensolver uses (:mod:`pipeline.solve.eigen`); solves made there as
extra columns (the singularity check's probe, the static loads) are remembered
(:meth:`PardisoFactorization.remember`) and returned by :meth:`~PardisoFactorization.solve`
without a pass of their own. PARDISO's phase codes and error table live in this module
only.
"""

from __future__ import annotations

import ctypes
import logging
import time

import numpy as np
import scipy.sparse as sp

from pipeline._util import progress
from pipeline._util.resources import check_factor_memory, release_free_heap
from pipeline.errors import ConfigError, SolverError
from pipeline.solve import mkl
from pipeline.solve.blas import _upper_mask, upper_triangle_csr
from pipeline.solve.factorization import Capabilities, Factorization, register_backend

log = logging.getLogger(__name__)

# PARDISO phases (MKL reference, "pardiso" phase parameter)
_ANALYSIS, _FACTORISATION, _SOLVE, _FORWARD, _BACKWARD, _RELEASE_ALL = 11, 22, 33, 331, 333, -1

# PARDISO error codes (MKL reference, "pardiso" error parameter)
_PARDISO_ERRORS = {
    -1: "input inconsistent",
    -2: "not enough memory",
    -3: "reordering problem",
    -4: "zero or negative pivot: the matrix is singular or not positive definite",
    -5: "unclassified internal error",
    -6: "reordering failed",
    -7: "diagonal matrix is singular",
    -8: "32-bit integer overflow",
    -9: "not enough memory for out-of-core",
    -10: "cannot open out-of-core files",
    -11: "out-of-core read/write error",
}
# iparm[36] < 0: PARDISO converts the CSR input to variable-size blocks, merging rows
# whose patterns agree to this percentage (the 3 DOFs of a node always do): on the
# 1M-DOF cantilever the METIS analysis is 2-3 times faster than with plain CSR input,
# the numerical factorisation as fast, and it takes less CPU than PARDISO's fixed 3x3
# BSR input (whose multi-right-hand-side solves were also slower).
VBSR_THRESHOLD = -80
# factors above this size (bytes, PARDISO's iparm[16]) are freed in a background thread
BACKGROUND_RELEASE_BYTES = 1 << 30


class PardisoFactorization(Factorization):
    """One MKL PARDISO factorisation (matrix type 2 or -2), prepared once.

    ``analysis_only``: stop after the analysis (:class:`PatternAnalysis`); the values
    are then set in :attr:`a` and :meth:`factorise` called. ``upper``: A is already the
    upper triangle (sorted, 32-bit indices), taken as it is."""

    backend = "pardiso"
    capabilities = Capabilities(indefinite=True, half_solves=True, single_precision=True,
                                pattern_analysis=True)

    def __init__(self, A: sp.spmatrix, positive_definite: bool = True, single: bool = False,
                 analysis_only: bool = False, upper: bool = False):
        lib = mkl.mkl_library()
        if lib is None:
            raise ConfigError("config key 'modes.solver': 'pardiso' needs MKL (install the "
                              "'fast' extra: pip install -e '.[fast]')")
        super().__init__(A.shape[0])
        if not positive_definite:  # LDL^T with Bunch-Kaufman pivots: no F F^T halves
            self.capabilities = Capabilities(indefinite=True, single_precision=True,
                                             pattern_analysis=True)
        self.lib = lib
        self.analysis_ahead = False
        self.mtype = 2 if positive_definite else -2
        U = A if upper else upper_triangle_csr(sp.csr_matrix(A))
        if U.indptr.dtype != np.int32:
            raise SolverError(f"the {self.n}x{self.n} system has {U.nnz} non-zeros in its "
                              "upper triangle: more than 32-bit PARDISO indices hold")
        # single: PARDISO factorises and solves in float32 (iparm[27] = 1; a, b, x float32)
        self.dtype = np.float32 if single else np.float64
        self.a, self.ia, self.ja = U.data.astype(self.dtype, copy=False), U.indptr, U.indices
        del U
        self.pt = np.zeros(64, dtype=np.int64)
        self.iparm = np.zeros(64, dtype=np.int32)
        ip = self.iparm
        ip[0] = 1  # supply all values
        ip[1] = 3  # METIS nested dissection, OpenMP version (same fill, analysis 30% faster)
        ip[9] = 8  # pivot perturbation 1e-8 (indefinite type only)
        ip[17] = -1  # report the factor's non-zeros
        ip[20] = 1  # Bunch-Kaufman pivoting (indefinite type only)
        ip[23] = 1  # two-level parallel factorisation
        ip[27] = 1 if single else 0  # single-precision factor (pipeline.solve.mixed)
        ip[34] = 1  # zero-based indices: scipy's arrays are passed as they are
        ip[36] = VBSR_THRESHOLD  # rows with (nearly) equal patterns -> variable blocks
        self._alive = True  # from the first call on, PARDISO may hold memory to release
        self._known: list[tuple[np.ndarray, np.ndarray]] = []  # (b, A^-1 b): remember()
        # analysis_wait: how long take() waited for an analysis run ahead (PatternAnalysis)
        self.seconds = {"analysis": 0.0, "factorisation": 0.0, "analysis_wait": 0.0}
        t0 = time.perf_counter()
        try:
            if analysis_only:  # in a background thread (PatternAnalysis): no progress stage
                self._call(_ANALYSIS)
            else:
                with progress.stage("ordering (METIS)"):
                    self._call(_ANALYSIS)  # ordering and symbolic factorisation
        except BaseException:
            self.release()
            raise
        self.seconds["analysis"] = time.perf_counter() - t0
        if not analysis_only:
            self.factorise()

    def factorise(self) -> None:
        """Numerical factorisation (phase 22) of the analysed pattern with the values in
        ``self.a`` (the upper triangle's data in the analysed order). PARDISO's analysis
        reads the pattern only: analysed on zero values and given the values before this
        call (:meth:`PatternAnalysis.take`), the factor solves bitwise like one analysed
        with them (measured)."""
        t1 = time.perf_counter()
        try:
            # the exact factor size is known now, before the factorisation allocates it
            check_factor_memory(float(self.iparm[16]) * 1024, self.n)
            with progress.stage("factorise (PARDISO)") as watch:
                watch.expect_work(progress.cholesky_flops(float(self.iparm[17]), self.n))
                self._call(_FACTORISATION)
        except BaseException:
            self.release()
            raise
        self.seconds["factorisation"] = time.perf_counter() - t1
        self.info = self.statistics()

    def _call(self, phase: int, b: np.ndarray | None = None, x: np.ndarray | None = None,
              nrhs: int = 1) -> None:
        P = ctypes.POINTER
        i32 = ctypes.c_int32
        err = i32(0)
        dummy = np.zeros(1, dtype=self.dtype)
        with mkl.threads():
            self.lib.pardiso(
                self.pt.ctypes.data_as(P(ctypes.c_int64)), ctypes.byref(i32(1)),
                ctypes.byref(i32(1)), ctypes.byref(i32(self.mtype)), ctypes.byref(i32(phase)),
                ctypes.byref(i32(self.n)), self.a.ctypes.data,
                self.ia.ctypes.data_as(P(i32)), self.ja.ctypes.data_as(P(i32)), None,
                ctypes.byref(i32(nrhs)), self.iparm.ctypes.data_as(P(i32)),
                ctypes.byref(i32(0)), (dummy if b is None else b).ctypes.data,
                (dummy if x is None else x).ctypes.data, ctypes.byref(err))
        if err.value != 0:
            what = _PARDISO_ERRORS.get(err.value, "unknown error")
            if err.value == -4 or (phase == _FACTORISATION and err.value == -7):
                where = int(self.iparm[29])
                at = f"; first bad pivot at equation {where}" if where > 0 else ""
                raise SolverError(
                    f"PARDISO could not factorise the {self.n}x{self.n} system ({what}{at}): "
                    "the stiffness matrix is singular or not "
                    "positive definite; check the supports (an unsupported body must be "
                    "solved as a free body, with no supports) and the material")
            if err.value in (-2, -9):
                raise SolverError(f"PARDISO ran out of memory factorising the {self.n}x{self.n} "
                                  f"system (error {err.value}); use a coarser mesh.size")
            raise SolverError(f"PARDISO failed in phase {phase} on the {self.n}x{self.n} system: "
                              f"error {err.value} ({what})")

    def _apply(self, phase: int, b: np.ndarray) -> np.ndarray:
        if not self._alive:
            raise SolverError("the PARDISO factorisation was released")
        b = np.asarray(b, dtype=self.dtype)
        if b.shape[0] != self.n:
            raise ValueError(f"right-hand side has {b.shape[0]} rows, expected {self.n}")
        if b.ndim == 1:
            b = np.ascontiguousarray(b)
            x = np.empty_like(b)
            self._call(phase, b, x, 1)
            return x
        # PARDISO wants column-major (n, k): a C-ordered (k, n) array, i.e. b.T
        bt = np.ascontiguousarray(b.T)
        xt = np.empty_like(bt)
        self._call(phase, bt, xt, bt.shape[0])
        return xt.T

    def solve(self, b: np.ndarray) -> np.ndarray:
        known = self._recall(b)
        return self._apply(_SOLVE, b) if known is None else known

    def remember(self, B: np.ndarray, X: np.ndarray) -> None:
        """Keep X = A^-1 B (both (n, k)), solved already (the probe of
        :func:`~pipeline.solve.factorization.check_factorization` and the static loads
        ride along in the eigensolver's first passes over the factor,
        :func:`pipeline.solve.eigen._lanczos_modes`): :meth:`solve` of exactly those
        columns returns them without a pass of its own."""
        self._known += [(np.array(B[:, j]), np.array(X[:, j])) for j in range(B.shape[1])]

    def _recall(self, b: np.ndarray) -> np.ndarray | None:
        """A^-1 b from :meth:`remember` when every column of b (n,) or (n, k) is known."""
        if not self._known or not self._alive or np.shape(b)[0] != self.n:
            return None
        columns = np.asarray(b).reshape(self.n, -1).T
        found = [next((x for known, x in self._known if np.array_equal(c, known)), None)
                 for c in columns]
        if any(x is None for x in found):
            return None
        return (found[0].copy() if np.ndim(b) == 1
                else np.column_stack(found).astype(self.dtype, copy=False))

    def forward(self, b: np.ndarray) -> np.ndarray:
        self._check_halves()
        return self._apply(_FORWARD, b)

    def backward(self, y: np.ndarray) -> np.ndarray:
        self._check_halves()
        return self._apply(_BACKWARD, y)

    def solve_rows(self, bt: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        return self._rows(_SOLVE, bt, out)

    def forward_rows(self, bt: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        self._check_halves()
        return self._rows(_FORWARD, bt, out)

    def backward_rows(self, yt: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        self._check_halves()
        return self._rows(_BACKWARD, yt, out)

    def _check_halves(self) -> None:
        if not self.capabilities.half_solves:
            raise SolverError("an indefinite PARDISO factor (LDL^T with pivoting) has no "
                              "separate forward and backward substitutions")

    def _rows(self, phase: int, bt: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Solve for a C-ordered (k, n) block of right-hand sides (rows), into ``out``
        when given (C-ordered, the factor's precision, bt's shape); no copies."""
        if not self._alive:
            raise SolverError("the PARDISO factorisation was released")
        bt = np.ascontiguousarray(bt, dtype=self.dtype)
        xt = np.empty_like(bt) if out is None else out
        if xt.shape != bt.shape or xt.dtype != self.dtype or not xt.flags.c_contiguous:
            raise ValueError(f"out: expected a C-ordered {np.dtype(self.dtype).name} array "
                             f"of shape {bt.shape}, got {xt.dtype.name} {xt.shape}")
        self._call(phase, bt, xt, bt.shape[0] if bt.ndim == 2 else 1)
        return xt

    def release(self) -> None:
        """Free PARDISO's memory. A factor above 1 GB is freed in a background thread
        (freeing the 9 GB factor of 1M DOFs takes most of a second, which then overlaps
        the file writing); the interpreter waits for that thread before it exits."""
        if not self._alive:
            return
        self._alive = False
        self._known = []

        def free() -> None:
            try:
                self._call(_RELEASE_ALL)
            except SolverError:  # releasing must never mask the real error
                pass
            self.a = self.ia = self.ja = np.zeros(1)

        if int(self.iparm[16]) * 1024 > BACKGROUND_RELEASE_BYTES:
            import threading

            self.releasing = threading.Thread(target=free, name="pardiso-release")
            self.releasing.start()
        else:
            free()

    def statistics(self) -> dict:
        """The factor's statistics, for :attr:`info` (iparm[16]: memory of the numerical
        factorisation and solution in KB, iparm[17]: non-zeros of the factor)."""
        return {"format": "csr-upper/vbsr" + ("/float32" if self.dtype == np.float32 else ""),
                "analysis_seconds": self.seconds["analysis"],
                "analysis_wait_seconds": self.seconds["analysis_wait"],
                "numeric_seconds": self.seconds["factorisation"],
                "factor_nnz": int(self.iparm[17]),
                "factor_bytes": int(self.iparm[16]) * 1024,
                "analysis_bytes": int(self.iparm[14]) * 1024,
                "analysis_ahead": self.analysis_ahead}


def _sorted_rows(indptr: np.ndarray, indices: np.ndarray) -> bool:
    """Whether every CSR row's column indices increase (scipy's check, no temporaries);
    True where that private kernel is not there (the caller's word is taken)."""
    try:
        from scipy.sparse._sparsetools import csr_has_sorted_indices

        return bool(csr_has_sorted_indices(indptr.size - 1, indptr, indices))
    except (ImportError, TypeError, ValueError):
        return True


class PatternAnalysis:
    """PARDISO's analysis (ordering, symbolic factorisation) of a symmetric matrix's
    pattern, run in a background thread while its values are still being assembled.

    ``indptr`` (n + 1,), ``indices`` (nnz,): the full (both triangles) CSR pattern, sorted.
    :func:`factorize` takes the analysis for a matrix of exactly this pattern
    (:meth:`take`) and only factorises numerically; any other matrix gets its own
    analysis and this one is released. At 100k DOFs the analysis is 0.3 s, at 300k about
    1.5 s, beside an element loop that leaves a core idle below about 150k DOFs. The
    thread also marks the entries of the upper triangle in the full pattern, so that
    :meth:`take` gathers the values (10 ms at 100k DOFs) instead of extracting the
    triangle of the assembled matrix (80 ms).
    :meth:`release` (always call it: ``with`` does) waits for the thread and frees
    PARDISO's memory if nobody took it.
    """

    def __init__(self, indptr: np.ndarray, indices: np.ndarray):
        import threading

        n = indptr.size - 1
        self._result: list = [None, None]  # (PardisoFactorization, exception)
        self._pattern = (indptr, indices)
        self._upper: np.ndarray | None = None  # (nnz,) bool: column >= row

        def analyse() -> None:
            try:
                t0 = time.perf_counter()
                if not _sorted_rows(indptr, indices):  # PARDISO reads sorted rows only
                    raise ValueError("the pattern's rows are not sorted")
                # the upper triangle's pattern straight from the mask, with zeros PARDISO's
                # analysis does not read (no full-pattern values to allocate and gather)
                self._upper, upper_indptr = _upper_mask(indptr, indices, n)
                itype = np.int32 if upper_indptr[-1] < 2**31 else np.int64
                pattern = sp.csr_matrix(
                    (np.zeros(int(upper_indptr[-1])), indices[self._upper].astype(itype),
                     upper_indptr.astype(itype)), shape=(n, n))
                self._result[0] = PardisoFactorization(pattern, analysis_only=True,
                                                       upper=True)
                del pattern
                lib = mkl.mkl_library()
                if lib is not None and hasattr(lib, "mkl_thread_free_buffers"):
                    lib.mkl_thread_free_buffers()  # MKL's pool of this thread's buffers
                log.info("ordering (METIS) of %d DOFs ahead of the values: %.2f s", n,
                         time.perf_counter() - t0)
            except BaseException as exc:  # reported by take(); the main path then analyses
                self._result[1] = exc

        self._thread = threading.Thread(target=analyse, name="pardiso-analysis", daemon=True)
        self._thread.start()

    def take(self, A: sp.spmatrix) -> "PardisoFactorization | None":
        """The analysed PARDISO object for ``A`` (same pattern; the caller owns it and
        sets the values), else None (and this analysis is released)."""
        t0 = time.perf_counter()
        self._thread.join()
        fact, self._result[0] = self._result[0], None
        if fact is not None:
            fact.seconds["analysis_wait"] = time.perf_counter() - t0
        if fact is None:
            if self._result[1] is not None:
                log.debug("the analysis ahead failed (%s): analysing again", self._result[1])
            return None
        A = sp.csr_matrix(A)
        if not all(mine is theirs or np.array_equal(mine, theirs)
                   for mine, theirs in zip((A.indptr, A.indices), self._pattern)):
            fact.release()
            release_free_heap()
            return None
        # the upper triangle's values in CSR order: what upper_triangle_csr(A) would give
        fact.a = A.data[self._upper].astype(fact.dtype, copy=False)  # the zeros go
        self._upper = None
        release_free_heap()  # that thread's malloc arena would keep their pages
        return fact

    def release(self) -> None:
        self._thread.join()
        self._upper = None
        fact, self._result[0] = self._result[0], None
        if fact is not None:
            fact.release()
            release_free_heap()

    def __enter__(self) -> "PatternAnalysis":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def factor(A: sp.spmatrix, *, positive_definite: bool = True, single: bool = False,
           analysis: PatternAnalysis | None = None) -> PardisoFactorization:
    """PARDISO factor of ``A`` (see :func:`pipeline.solve.factorization.factorize`); with
    ``analysis`` of ``A``'s pattern, only the numerical factorisation runs here."""
    fact = None
    if analysis is not None and positive_definite and not single:
        fact = analysis.take(A)
        if fact is not None:
            fact.analysis_ahead = True
            fact.factorise()
    if fact is None:
        fact = PardisoFactorization(A, positive_definite, single)
    return fact


register_backend("pardiso", factor, installed=lambda: mkl.mkl_library() is not None,
                 capabilities=PardisoFactorization.capabilities,
                 install_hint="'pardiso' comes with the 'fast' extra: pip install -e '.[fast]'")


