"""Sparse symmetric factorisations behind the shift-invert eigensolver.

A backend factorises a symmetric matrix once and then solves many right-hand sides,
one or a block of them per call, with that one factorisation. ``auto`` picks the
fastest installed backend:

``pardiso``
    MKL PARDISO called directly through ``ctypes`` (MKL comes with the ``fast`` extra,
    through pypardiso's dependency on ``mkl``). Symmetric positive-definite Cholesky
    (matrix type 2) of the upper triangle, prepared once: 32-bit zero-based indices
    (no per-call index conversion or re-hashing, unlike ``pypardiso.spsolve``) and
    PARDISO's variable-block conversion of the rows (the 3 DOFs of a node share one
    pattern), which makes the METIS analysis 2-3 times faster at 1M DOFs. The exact
    factor size, known after the analysis, is checked against the available memory
    before the factorisation allocates it. Threaded over
    the cores this process may use (``MKL_NUM_THREADS`` overrides).
    Multiple right-hand sides are solved in one call, and the factor ``L`` is also
    offered as separate forward (``L^-1 b``) and backward (``L^-T y``) substitutions,
    which the block Lanczos eigensolver uses (:mod:`pipeline.solve.eigen`).
``superlu``
    scipy's SuperLU with the ``MMD_AT_PLUS_A`` ordering (2x faster than the default
    at 100k DOFs), always available.
``cholmod``
    SuiteSparse CHOLMOD through the ``cholespy`` wheel (the ``fast`` extra). That
    wheel bundles the reference BLAS and runs on one thread: correct, but 3x slower
    than SuperLU at 100k DOFs, so ``auto`` ranks it last; it is there as an
    independent Cholesky to cross-check the others.

``cudss``
    NVIDIA cuDSS on the GPU, through nvmath-python and CuPy (an NVIDIA GPU and the
    ``gpu`` extra). Cholesky of the upper triangle (type SPD, upper view). The
    reordering runs on the host's cores (cuDSS's OpenMP threading layer, found beside
    the library or named by ``CUDSS_MT_LIB``), the factorisation and the solves on the
    GPU, whose free memory is checked against cuDSS's own estimate before the
    factorisation. No separate forward and backward substitutions, so the eigensolver
    uses ARPACK's shift-invert mode with it. Never chosen by ``auto``:
    ``modes.solver: cudss`` asks for it. Measured on an H100 (16-core host) for the
    cantilever: 996k DOFs analysis 3.9 s, factorisation 0.67 s, one solve 9.6 ms;
    2.83M DOFs 14.5 s, 3.2 s and 37 ms, 52 GB of GPU memory (``benchmarks/bench_gpu.py``).

``mumps`` (python-mumps) is an accepted name in the config but has no usable wheel
for this Python/numpy (pip offers only the 0.0.2 wheel, built against numpy 1, which
fails to import under numpy 2; later versions are source-only), nor has
scikit-sparse (source-only); they are reported as not installed.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp

from pipeline.errors import ConfigError, ResourceError, SolverError
from pipeline._util import progress
from pipeline._util.resources import (HEADROOM, check_factor_memory, release_free_heap,
                                      usable_cores)

log = logging.getLogger(__name__)

BACKENDS = ("pardiso", "superlu", "cholmod", "mumps", "cudss")

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
_MKL_DOMAIN_PARDISO = 4
# iparm[36] < 0: PARDISO converts the CSR input to variable-size blocks, merging rows
# whose patterns agree to this percentage (the 3 DOFs of a node always do). Measured on
# the 1M-DOF cantilever: METIS analysis 5-9 s instead of 13-28 s with plain CSR input,
# numerical factorisation within noise of it (155-170 s CPU on both), and 15% less CPU
# than PARDISO's fixed 3x3 BSR input (whose multi-RHS solves were also slower).
VBSR_THRESHOLD = -80
# factors above this size (bytes, PARDISO's iparm[16]) are freed in a background thread
BACKGROUND_RELEASE_BYTES = 1 << 30


@functools.lru_cache(maxsize=1)
def _mkl_library() -> Any | None:
    """The MKL runtime library (``libmkl_rt``), or None when it is not installed."""
    from ctypes.util import find_library

    # MKL's OpenMP threads otherwise spin for 200 ms after every solve, competing with
    # the numpy (OpenBLAS) work between solves on a 2-core machine: a 10x slowdown of
    # the Rayleigh-Ritz step was measured. Read when the OpenMP runtime starts.
    os.environ.setdefault("KMP_BLOCKTIME", "0")
    candidates = []
    if os.environ.get("PYPARDISO_MKL_RT"):
        candidates.append(os.environ["PYPARDISO_MKL_RT"])
    for prefix in (sys.prefix, sys.base_prefix):
        candidates += sorted(glob.glob(os.path.join(prefix, "lib", "libmkl_rt.so*")), key=len)
        candidates += sorted(glob.glob(os.path.join(prefix, "Library", "bin", "mkl_rt*.dll")),
                             key=len)
    # find_library runs gcc on a named temporary file: an interrupt there would leave it
    from pipeline._util.atomic import signals_held

    with signals_held():
        found = find_library("mkl_rt")
    if found:
        candidates.append(found)
    for path in candidates:
        try:
            lib = ctypes.CDLL(path)
            lib.pardiso  # noqa: B018  (the symbol must exist)
        except (OSError, AttributeError):
            continue
        if "MKL_NUM_THREADS" not in os.environ:
            # MKL's own default on the 2-vCPU AMD machines is one thread, and the sparse
            # products (mkl_sparse_d_mm) follow it: measured at 1M DOFs, K (80M
            # non-zeros) times 25 vectors took 1.33 s on one thread, 0.55 s on two
            lib.MKL_Set_Num_Threads(ctypes.c_int(usable_cores()))
        P = ctypes.POINTER
        lib.pardiso.restype = None
        lib.pardiso.argtypes = [P(ctypes.c_int64)] + [P(ctypes.c_int32)] * 5 + [
            ctypes.c_void_p, P(ctypes.c_int32), P(ctypes.c_int32), P(ctypes.c_int32),
            P(ctypes.c_int32), P(ctypes.c_int32), P(ctypes.c_int32), ctypes.c_void_p,
            ctypes.c_void_p, P(ctypes.c_int32)]
        log.debug("MKL runtime: %s", path)
        return lib
    return None


@functools.lru_cache(maxsize=1)
def _cholespy() -> Any | None:
    try:
        import cholespy

        return cholespy
    except Exception:  # ImportError, or its bundled libraries failing to load
        return None


@functools.lru_cache(maxsize=1)
def _cudss_modules() -> tuple[Any, Any] | None:
    """(cupy, nvmath) where an NVIDIA GPU, CuPy and nvmath-python with a loadable cuDSS
    library are all present; else None."""
    try:
        import cupy
        import nvmath.sparse.advanced  # noqa: F401
        from nvmath.bindings import cudss

        if cupy.cuda.runtime.getDeviceCount() < 1:
            return None
        cudss.get_property(0)  # loads libcudss: a missing library fails here
        return cupy, sys.modules["nvmath"]
    except Exception:  # not installed, no driver, no device, no library
        return None


def available_backends(gpu: bool = True) -> list[str]:
    """Installed backends, fastest first (measured at 100k DOFs); ``cudss`` (the GPU)
    last, since ``auto`` never chooses it. ``gpu=False`` does not look for it (probing
    imports CuPy and loads cuDSS: a second or so that a CPU run need not pay)."""
    found = []
    if _mkl_library() is not None:
        found.append("pardiso")
    found.append("superlu")
    if _cholespy() is not None:
        found.append("cholmod")
    if gpu and _cudss_modules() is not None:
        found.append("cudss")
    return found


@dataclass
class Factorization:
    """A factorised symmetric matrix A (n x n).

    ``solve(b)``: A^-1 b for b of shape (n,) or (n, k). When the backend has a
    symmetric factor A = F F^T, ``forward(b)`` = F^-1 b and ``backward(y)`` = F^-T y
    (same shapes); otherwise they are None. ``release()`` frees the factor.
    ``info``: factor statistics (``factor_nnz``, ``factor_bytes``, ``format``...).
    """

    solve: Callable[[np.ndarray], np.ndarray]
    backend: str
    n: int
    release: Callable[[], None] = lambda: None
    forward: Callable[[np.ndarray], np.ndarray] | None = None
    backward: Callable[[np.ndarray], np.ndarray] | None = None
    info: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- inputs
def _upper_mask(indptr: np.ndarray, indices: np.ndarray, n: int):
    """Mask of the entries with column >= row, and the indptr of those entries."""
    rows = np.repeat(np.arange(n, dtype=np.int32), np.diff(indptr))
    mask = indices >= rows
    del rows
    kept = np.zeros(mask.size + 1, dtype=np.int32 if mask.size < 2**31 else np.int64)
    np.cumsum(mask, out=kept[1:])
    return mask, kept[indptr].astype(np.int64)


def upper_triangle_csr(A: sp.csr_matrix) -> sp.csr_matrix:
    """The upper triangle (diagonal included) of CSR ``A``, sorted, 32-bit indices.

    One pass over A's arrays; no COO intermediate.
    """
    A = sp.csr_matrix(A)
    if not A.has_sorted_indices:
        A = A.copy()
        A.sort_indices()
    n = A.shape[0]
    mask, indptr = _upper_mask(A.indptr, A.indices, n)
    itype = np.int32 if indptr[-1] < 2**31 else np.int64
    return sp.csr_matrix((A.data[mask], A.indices[mask].astype(itype, copy=False),
                          indptr.astype(itype, copy=False)), shape=A.shape)


# --------------------------------------------------------------------------- products
class _SparseMatrixT(ctypes.Structure):
    _fields_ = [("type", ctypes.c_int), ("mode", ctypes.c_int), ("diag", ctypes.c_int)]


def sparse_times_dense(A: sp.spmatrix, X: np.ndarray, out: np.ndarray | None = None,
                       alpha: float = 1.0, beta: float = 0.0) -> np.ndarray:
    """A @ X for CSR ``A`` (n x m, 32-bit indices) and dense X (m,) or (m, k); with
    ``out`` (n,) or (n, k), C-contiguous, of the product's precision): out = alpha A X +
    beta out in place, returned (a fused update: no temporary, no second pass).

    MKL's threaded sparse BLAS when MKL is there (``mkl_sparse_d_mm`` for several
    columns, ``mkl_sparse_d_mv`` for one: 0.044 s against scipy's single-threaded 0.096 s
    for K of 1M DOFs on 2 cores, which is what a one-column conjugate-gradient solve does
    seven times an iteration), else scipy's product; the result is the same to
    round-off, in X's shape. A float32 ``A`` with a float32 X stays in float32
    (``mkl_sparse_s_mm``: 0.38 s against 0.99 s in double for K of 1M DOFs times 25
    vectors, 2 threads), for preconditioners (:mod:`pipeline.solve.multigrid`); any
    other mix is computed in float64.

    >>> import numpy as np, scipy.sparse as sp
    >>> A = sp.csr_matrix(np.array([[2.0, 1.0], [0.0, 3.0]]))
    >>> y = np.ones(2)
    >>> sparse_times_dense(A, np.array([1.0, 1.0]), out=y, alpha=-1.0, beta=2.0)
    array([-1., -1.])
    """
    lib = _mkl_library()
    single = A.dtype == np.float32 and np.asarray(X).dtype == np.float32
    dtype = np.float32 if single else np.float64
    X = np.asarray(X, dtype=dtype)
    if out is not None and (out.dtype != dtype or not out.flags.c_contiguous
                            or out.shape != (A.shape[0],) + X.shape[1:]):
        raise ValueError(f"out: expected a C-contiguous {np.dtype(dtype).name} array of "
                         f"shape {(A.shape[0],) + X.shape[1:]}; got {out.dtype.name} "
                         f"{out.shape}")
    if (lib is None or not sp.isspmatrix_csr(A) or A.indices.dtype != np.int32
            or A.indptr.dtype != np.int32 or A.dtype != dtype or X.ndim not in (1, 2)
            or X.shape[0] != A.shape[1] or A.nnz == 0 or X.size == 0):
        return _update_out(A @ X, out, alpha, beta)
    m = A.shape[0]
    handle = ctypes.c_void_p()
    ip = A.indptr
    P = ctypes.POINTER
    create = lib.mkl_sparse_s_create_csr if single else lib.mkl_sparse_d_create_csr
    scalar = ctypes.c_float if single else ctypes.c_double
    st = create(
        ctypes.byref(handle), ctypes.c_int(0), ctypes.c_int(m), ctypes.c_int(A.shape[1]),
        ip.ctypes.data_as(P(ctypes.c_int32)),
        ctypes.c_void_p(ip.ctypes.data + 4),  # rows_end = indptr[1:]
        A.indices.ctypes.data_as(P(ctypes.c_int32)), A.data.ctypes.data_as(ctypes.c_void_p))
    if st != 0:
        return _update_out(A @ X, out, alpha, beta)
    descr = _SparseMatrixT(20, 0, 0)  # SPARSE_MATRIX_TYPE_GENERAL
    if out is None:
        beta = 0.0
    try:
        if X.ndim == 1 or X.shape[1] == 1:  # one column: the matrix-vector product
            x = np.ascontiguousarray(X.reshape(-1))
            Y = np.empty((m,) + X.shape[1:], dtype=dtype) if out is None else out
            mv = lib.mkl_sparse_s_mv if single else lib.mkl_sparse_d_mv
            mv.argtypes = [ctypes.c_int, scalar, ctypes.c_void_p, _SparseMatrixT,
                           ctypes.c_void_p, scalar, ctypes.c_void_p]
            st = mv(10, alpha, handle, descr, x.ctypes.data, beta, Y.ctypes.data)
        else:
            k = X.shape[1]
            if X.flags.f_contiguous and out is None:  # column-major in and out: no copies
                layout, ldx, ldy = 102, A.shape[1], m
                Y = np.empty((m, k), dtype=dtype, order="F")
            else:
                X = np.ascontiguousarray(X)
                layout, ldx, ldy = 101, k, k
                Y = np.empty((m, k), dtype=dtype) if out is None else out
            mm = lib.mkl_sparse_s_mm if single else lib.mkl_sparse_d_mm
            mm.argtypes = [ctypes.c_int, scalar, ctypes.c_void_p, _SparseMatrixT,
                           ctypes.c_int, ctypes.c_void_p, ctypes.c_int, ctypes.c_int,
                           scalar, ctypes.c_void_p, ctypes.c_int]
            st = mm(10, alpha, handle, descr, layout,  # non-transposed
                    X.ctypes.data, k, ldx, beta, Y.ctypes.data, ldy)
    finally:
        lib.mkl_sparse_destroy(handle)
    if st != 0:  # MKL refused before touching Y (argument checks): scipy's product
        return _update_out(A @ X, out, alpha, beta)
    return Y


def _update_out(AX: np.ndarray, out: np.ndarray | None, alpha: float, beta: float
                ) -> np.ndarray:
    """alpha AX + beta out into out (or AX itself without ``out``): the numpy fallback of
    :func:`sparse_times_dense`."""
    AX = np.asarray(AX)
    if out is None:
        return AX
    if beta == 0.0:
        np.multiply(AX.reshape(out.shape), alpha, out=out)
    else:
        out *= beta
        out += alpha * AX.reshape(out.shape)
    return out


def column_norms(A: np.ndarray) -> np.ndarray:
    """(k,) Euclidean norms of the columns of A (n, k): one pass, no (n, k) temporary
    (``np.linalg.norm(A, axis=0)`` squares A into one: 61 ms against 15 ms at 1M x 25).

    >>> column_norms(np.array([[3.0, 0.0], [4.0, 2.0]]))
    array([5., 2.])
    """
    return np.sqrt(np.einsum("ij,ij->j", A, A))


def axpby(a: float, x: np.ndarray, b: float, y: np.ndarray) -> np.ndarray:
    """y = a x + b y in place for C-contiguous arrays of one shape and precision, and y
    returned: MKL's threaded ``cblas_?axpby`` (one pass over both) when MKL is there,
    else numpy (two passes).

    >>> y = np.ones(3, dtype=np.float32)
    >>> axpby(2.0, np.arange(3, dtype=np.float32), 0.5, y)
    array([0.5, 2.5, 4.5], dtype=float32)
    """
    if x.shape != y.shape or x.dtype != y.dtype or not (x.flags.c_contiguous
                                                       and y.flags.c_contiguous):
        raise ValueError(f"axpby: x {x.dtype.name} {x.shape} and y {y.dtype.name} "
                         f"{y.shape}: expected C-contiguous arrays of one shape and dtype")
    lib = _mkl_library()
    if lib is not None and y.dtype in (np.float32, np.float64) and y.size < 2**31:
        single = y.dtype == np.float32
        f = lib.cblas_saxpby if single else lib.cblas_daxpby
        scalar = ctypes.c_float if single else ctypes.c_double
        f.argtypes = [ctypes.c_int, scalar, ctypes.c_void_p, ctypes.c_int, scalar,
                      ctypes.c_void_p, ctypes.c_int]
        f(y.size, a, x.ctypes.data, 1, b, y.ctypes.data, 1)
        return y
    if b != 1.0:
        y *= b
    y += a * x
    return y


# --------------------------------------------------------------------------- PARDISO
class _Pardiso:
    """One MKL PARDISO factorisation (matrix type 2 or -2), prepared once."""

    def __init__(self, A: sp.spmatrix, positive_definite: bool = True, single: bool = False,
                 analysis_only: bool = False):
        lib = _mkl_library()
        if lib is None:
            raise ConfigError("config key 'modes.solver': 'pardiso' needs MKL (install the "
                              "'fast' extra: pip install -e '.[fast]')")
        self.lib = lib
        self.n = A.shape[0]
        self.mtype = 2 if positive_definite else -2
        U = upper_triangle_csr(sp.csr_matrix(A))
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
        if "MKL_NUM_THREADS" not in os.environ:
            lib.MKL_Domain_Set_Num_Threads(ctypes.c_int(usable_cores()),
                                           ctypes.c_int(_MKL_DOMAIN_PARDISO))
        self._alive = True  # from the first call on, PARDISO may hold memory to release
        self.seconds = {"analysis": 0.0, "factorisation": 0.0}
        t0 = time.perf_counter()
        try:
            if analysis_only:  # in a background thread (PatternAnalysis): no progress stage
                self._call(11)
            else:
                with progress.stage("ordering (METIS)"):
                    self._call(11)  # analysis: ordering and symbolic factorisation
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
                self._call(22)  # numerical factorisation
        except BaseException:
            self.release()
            raise
        self.seconds["factorisation"] = time.perf_counter() - t1

    def _call(self, phase: int, b: np.ndarray | None = None, x: np.ndarray | None = None,
              nrhs: int = 1) -> None:
        P = ctypes.POINTER
        i32 = ctypes.c_int32
        err = i32(0)
        dummy = np.zeros(1, dtype=self.dtype)
        self.lib.pardiso(
            self.pt.ctypes.data_as(P(ctypes.c_int64)), ctypes.byref(i32(1)), ctypes.byref(i32(1)),
            ctypes.byref(i32(self.mtype)), ctypes.byref(i32(phase)), ctypes.byref(i32(self.n)),
            self.a.ctypes.data, self.ia.ctypes.data_as(P(i32)), self.ja.ctypes.data_as(P(i32)),
            None, ctypes.byref(i32(nrhs)), self.iparm.ctypes.data_as(P(i32)),
            ctypes.byref(i32(0)), (dummy if b is None else b).ctypes.data,
            (dummy if x is None else x).ctypes.data, ctypes.byref(err))
        if err.value != 0:
            what = _PARDISO_ERRORS.get(err.value, "unknown error")
            if err.value == -4 or (phase == 22 and err.value == -7):
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
        return self._apply(33, b)

    def forward(self, b: np.ndarray) -> np.ndarray:
        return self._apply(331, b)

    def backward(self, y: np.ndarray) -> np.ndarray:
        return self._apply(333, y)

    def solve_rows(self, phase: int, bt: np.ndarray) -> np.ndarray:
        """Solve for a C-ordered (k, n) block of right-hand sides (rows); no copies."""
        if not self._alive:
            raise SolverError("the PARDISO factorisation was released")
        bt = np.ascontiguousarray(bt, dtype=self.dtype)
        xt = np.empty_like(bt)
        self._call(phase, bt, xt, bt.shape[0] if bt.ndim == 2 else 1)
        return xt

    def release(self) -> None:
        """Free PARDISO's memory. A factor above 1 GB is freed in a background thread
        (0.7 s for the 9 GB factor at 1M DOFs, which then overlaps the file writing);
        the interpreter waits for that thread before it exits."""
        if not self._alive:
            return
        self._alive = False

        def free() -> None:
            try:
                self._call(-1)
            except SolverError:  # releasing must never mask the real error
                pass
            self.a = self.ia = self.ja = np.zeros(1)

        if int(self.iparm[16]) * 1024 > BACKGROUND_RELEASE_BYTES:
            import threading

            self.releasing = threading.Thread(target=free, name="pardiso-release")
            self.releasing.start()
        else:
            free()

    def info(self) -> dict:
        # iparm[16]: memory of numerical factorisation and solution (KB), iparm[17]: nnz
        # of the factor
        return {"format": "csr-upper/vbsr" + ("/float32" if self.dtype == np.float32 else ""),
                "analysis_seconds": self.seconds["analysis"],
                "numeric_seconds": self.seconds["factorisation"],
                "factor_nnz": int(self.iparm[17]),
                "factor_bytes": int(self.iparm[16]) * 1024,
                "analysis_bytes": int(self.iparm[14]) * 1024}


class PatternAnalysis:
    """PARDISO's analysis (ordering, symbolic factorisation) of a symmetric matrix's
    pattern, run in a background thread while its values are still being assembled.

    ``indptr`` (n + 1,), ``indices`` (nnz,): the full (both triangles) CSR pattern, sorted.
    :func:`factorize` takes the analysis for a matrix of exactly this pattern
    (:meth:`take`) and only factorises numerically; any other matrix gets its own
    analysis and this one is released. At 100k DOFs the analysis is 0.3 s, at 300k about
    1.5 s, beside an element loop that leaves a core idle below about 150k DOFs.
    :meth:`release` (always call it: ``with`` does) waits for the thread and frees
    PARDISO's memory if nobody took it.
    """

    def __init__(self, indptr: np.ndarray, indices: np.ndarray):
        import threading

        n = indptr.size - 1
        pattern = sp.csr_matrix((np.zeros(indices.size), indices, indptr), shape=(n, n))
        self._result: list = [None, None]  # (_Pardiso, exception)

        def analyse() -> None:
            try:
                t0 = time.perf_counter()
                self._result[0] = _Pardiso(pattern, analysis_only=True)
                lib = _mkl_library()
                if lib is not None and hasattr(lib, "mkl_thread_free_buffers"):
                    lib.mkl_thread_free_buffers()  # MKL's pool of this thread's buffers
                log.info("ordering (METIS) of %d DOFs beside the assembly: %.2f s", n,
                         time.perf_counter() - t0)
            except BaseException as exc:  # reported by take(); the main path then analyses
                self._result[1] = exc

        self._thread = threading.Thread(target=analyse, name="pardiso-analysis", daemon=True)
        self._thread.start()

    def take(self, A: sp.spmatrix) -> "_Pardiso | None":
        """The analysed PARDISO object for ``A`` (same pattern; the caller owns it and
        sets the values), else None (and this analysis is released)."""
        self._thread.join()
        fact, self._result[0] = self._result[0], None
        if fact is None:
            if self._result[1] is not None:
                log.debug("the analysis ahead failed (%s): analysing again", self._result[1])
            return None
        U = upper_triangle_csr(sp.csr_matrix(A))
        if not (np.array_equal(U.indptr, fact.ia) and np.array_equal(U.indices, fact.ja)):
            fact.release()
            release_free_heap()
            return None
        fact.a = U.data.astype(fact.dtype, copy=False)  # the analysis thread's zeros go
        del U
        release_free_heap()  # that thread's malloc arena would keep their pages
        return fact

    def release(self) -> None:
        self._thread.join()
        fact, self._result[0] = self._result[0], None
        if fact is not None:
            fact.release()
            release_free_heap()

    def __enter__(self) -> "PatternAnalysis":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _pardiso(A: sp.spmatrix, positive_definite: bool, single: bool = False,
             analysis: PatternAnalysis | None = None) -> Factorization:
    fact = None
    if analysis is not None and positive_definite and not single:
        fact = analysis.take(A)
        if fact is not None:
            fact.factorise()
    ahead = fact is not None
    if fact is None:
        fact = _Pardiso(A, positive_definite, single)
    info = fact.info()
    info["analysis_ahead"] = ahead
    info["rows"] = fact.solve_rows
    fwd = fact.forward if positive_definite else None
    bwd = fact.backward if positive_definite else None
    return Factorization(fact.solve, "pardiso", A.shape[0], fact.release, fwd, bwd, info)


def _superlu(A: sp.spmatrix, positive_definite: bool = True) -> Factorization:
    from scipy.sparse.linalg import splu

    try:
        lu = splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A",
                  options={"SymmetricMode": True, "DiagPivotThresh": 0.01})
    except RuntimeError as exc:
        raise SolverError(f"SuperLU could not factorise the {A.shape[0]}x{A.shape[0]} system "
                          f"({exc}): the matrix is singular; check the supports") from None
    if positive_definite and np.array_equal(lu.perm_r, lu.perm_c):
        # symmetric pivoting only: A = P^T L D L^T P with D = diag(U), so by Sylvester's
        # law of inertia A is positive definite iff every U_ii > 0
        negative = int((lu.U.diagonal() <= 0).sum())
        if negative:
            raise SolverError(f"the {A.shape[0]}x{A.shape[0]} stiffness system is singular or "
                              f"not positive definite ({negative} non-positive pivots): check "
                              "the supports (a body that can move as a rigid body or mechanism "
                              "needs supports) and the material (E > 0, -1 < nu < 0.5)")
    info = {"format": "csc", "factor_nnz": int(lu.L.nnz + lu.U.nnz),
            "factor_bytes": int(12 * (lu.L.nnz + lu.U.nnz))}
    return Factorization(lu.solve, "superlu", A.shape[0], lambda: None, None, None, info)


def _cholmod(A: sp.spmatrix) -> Factorization:
    cholespy = _cholespy()
    A = sp.csr_matrix(A)
    n = A.shape[0]
    try:
        solver = cholespy.CholeskySolverD(n, A.indptr.astype(np.int32),
                                          A.indices.astype(np.int32),
                                          np.ascontiguousarray(A.data, dtype=np.float64),
                                          cholespy.MatrixType.CSR)
    except (ValueError, RuntimeError) as exc:
        raise SolverError(f"CHOLMOD could not factorise the {n}x{n} system ({exc}): the "
                          "stiffness matrix is singular or not positive definite; check the "
                          "supports") from None
    holder = [solver]

    def solve(b: np.ndarray) -> np.ndarray:
        if holder[0] is None:
            raise SolverError("the CHOLMOD factorisation was released")
        b = np.ascontiguousarray(b, dtype=np.float64)
        x = np.zeros_like(b)
        holder[0].solve(b, x)
        return x

    def release() -> None:
        holder[0] = None

    return Factorization(solve, "cholmod", n, release, None, None, {"format": "csr"})


def _cudss_threading_lib() -> str | None:
    """cuDSS's OpenMP threading layer, so that its reordering uses every core (9.1 ->
    3.9 s at 1M DOFs on 16 cores): ``CUDSS_MT_LIB``, else beside the cuDSS wheel's
    library on sys.path or LD_LIBRARY_PATH; None runs it on one core."""
    named = os.environ.get("CUDSS_MT_LIB")
    if named:
        return named
    folders = [os.path.join(entry, "nvidia", cu, "lib") for entry in sys.path
               for cu in ("cu13", "cu12")]
    folders += [f for f in os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep) if f]
    for folder in folders:
        hits = sorted(glob.glob(os.path.join(folder, "libcudss_mtlayer_gomp.so*")))
        if hits:
            return hits[0]
    return None


def _gpu_free_bytes(cupy) -> float:
    """Free GPU memory (bytes), after returning what CuPy's pool and CUDA's default
    stream-ordered pool hold unused (a released factor stays reserved there)."""
    cupy.get_default_memory_pool().free_all_blocks()
    try:
        pool = cupy.cuda.runtime.deviceGetDefaultMemPool(cupy.cuda.Device().id)
        cupy.cuda.runtime.memPoolTrimTo(pool, 0)
    except Exception:  # an older CUDA or CuPy without stream-ordered pools
        pass
    return float(cupy.cuda.Device().mem_info[0])


def _cudss(A: sp.spmatrix) -> Factorization:
    """Cholesky of the symmetric positive definite ``A`` on the GPU (cuDSS)."""
    cupy, nvmath = _cudss_modules()
    import cupyx.scipy.sparse as csp
    from nvmath.bindings import cudss

    n = A.shape[0]
    quiet = logging.getLogger(__name__ + ".cudss")  # nvmath logs every phase at INFO
    quiet.setLevel(logging.WARNING)
    options = nvmath.sparse.advanced.DirectSolverOptions(
        sparse_system_type=cudss.MatrixType.SPD, sparse_system_view=cudss.MatrixViewType.UPPER,
        multithreading_lib=_cudss_threading_lib(), logger=quiet, blocking=True)
    U = upper_triangle_csr(sp.csr_matrix(A))
    rhs = cupy.zeros((n, 1), order="F")
    solver = None
    try:
        solver = nvmath.sparse.advanced.DirectSolver(csp.csr_matrix(U), rhs, options=options)
        del U
        t0 = time.perf_counter()
        with progress.stage("ordering (cuDSS)"):
            estimates = solver.plan().memory_estimates
        t1 = time.perf_counter()
        need = float(max(int(estimates.permanent_device_memory),
                         int(estimates.peak_device_memory)))
        free = _gpu_free_bytes(cupy)
        if need > HEADROOM * free:
            raise ResourceError(f"the cuDSS factorisation of the {n}-DOF system needs "
                                f"{need / 1e9:.1f} GB of GPU memory; {free / 1e9:.1f} GB are "
                                "free: use a coarser mesh.size, or modes.solver: auto (CPU)")
        with progress.stage("factorise (cuDSS)"):
            info = solver.factorize()
            cupy.cuda.Device().synchronize()
        if int(info.info) != 0:
            raise SolverError(f"cuDSS could not factorise the {n}x{n} system (zero or "
                              f"negative pivot, info {int(info.info)}): the stiffness matrix "
                              "is singular or not positive definite; check the supports")
        t2 = time.perf_counter()
    except BaseException:
        if solver is not None:
            solver.free()
        _gpu_free_bytes(cupy)
        raise
    holder = [solver]

    def solve(b: np.ndarray) -> np.ndarray:
        """A^-1 b for b (n,) or (n, k), one column at a time through the GPU (a cuDSS
        solver keeps the shape of its right-hand side)."""
        if holder[0] is None:
            raise SolverError("the cuDSS factorisation was released")
        b = np.asarray(b, dtype=np.float64)
        cols = b.reshape(n, -1)
        x = np.empty_like(cols)
        for j in range(cols.shape[1]):
            rhs.set(np.asfortranarray(cols[:, j:j + 1]))
            holder[0].reset_operands(b=rhs)
            x[:, j:j + 1] = cupy.asnumpy(holder[0].solve())
        return x.reshape(b.shape)

    def release() -> None:
        if holder[0] is not None:
            holder[0].free()
            holder[0] = None
            _gpu_free_bytes(cupy)

    info_dict = {"format": "csr-upper/cuda", "analysis_seconds": t1 - t0,
                 "numeric_seconds": t2 - t1, "factor_nnz": int(info.lu_nnz),
                 "factor_bytes": 0, "device_bytes": int(need)}
    return Factorization(solve, "cudss", n, release, None, None, info_dict)


def resolve_backend(backend: str = "auto") -> str:
    """The backend ``backend`` names (``auto``: the fastest installed one)."""
    host = available_backends(gpu=False)
    if backend == "auto":
        return host[0]
    if backend in host:
        return backend
    available = available_backends()
    if backend not in available:
        missing = ""
        if backend in ("pardiso", "cholmod"):
            missing = f" ('{backend}' comes with the 'fast' extra: pip install -e '.[fast]')"
        elif backend == "mumps":
            missing = " (python-mumps has no wheel for this Python/numpy)"
        elif backend == "cudss":
            missing = (" ('cudss' needs an NVIDIA GPU with its driver, CuPy and "
                       "nvmath-python with cuDSS: pip install -e '.[gpu]', i.e. "
                       "cupy-cuda13x and 'nvmath-python[cu13]')")
        raise ConfigError(f"config key 'modes.solver': got '{backend}', expected one of the "
                          f"installed backends: auto, {', '.join(available)}{missing}")
    return backend


def check_factorization(A: sp.spmatrix, fact: Factorization, seed: int = 7) -> float:
    """Relative error of solving A x = A z for a known random z; SolverError if large.

    A singular A (for example a body without enough supports) makes the solution
    differ from z by arbitrary null-space components, however small the residual. A
    backward-stable factor of a regular A misses z by about cond(A) eps (the rounding
    amplified along the lowest eigenvector), so the error is judged against
    :data:`SINGULAR_COND_EPS`, the bound on cond(A) eps the static solve uses: a fixed
    1e-3 refused a 500 x 50 x 0.2 mm strip, whose K is fine (f1 within 2.1% of beam
    theory) but misses z by 1.0e-3 to 2.8e-3 depending on z and on the DOF order.
    """
    z = np.random.default_rng(seed).standard_normal(A.shape[0])
    x = fact.solve(A @ z)
    error = float(np.linalg.norm(x - z) / np.linalg.norm(z))
    if not np.isfinite(error) or error > SINGULAR_COND_EPS:
        raise SolverError(
            f"the {A.shape[0]}x{A.shape[0]} stiffness system is singular to working precision "
            f"(backend {fact.backend}: solving A x = A z misses z by {error:.1e} relative); "
            "check the supports: a body that can move as a rigid body or mechanism needs "
            "supports, or must be solved as a free body (no supports at all)")
    return error


def factorize(A: sp.spmatrix, backend: str = "auto", positive_definite: bool = True,
              check: bool = True, single: bool = False,
              analysis: PatternAnalysis | None = None) -> Factorization:
    """Factorise the symmetric matrix ``A`` (n x n) once, with ``backend``.

    ``backend``: ``auto`` or one of :data:`BACKENDS`; a backend that is not installed
    is refused (ConfigError) with the list of those that are. ``single``: a float32
    PARDISO factor (iparm[27] = 1; half the memory and about half the flops; its solves
    take and return float32), for :mod:`pipeline.solve.mixed`. A singular ``A`` raises
    SolverError: from the factorisation itself, or (``check``) from
    :func:`check_factorization`. ``analysis``: a :class:`PatternAnalysis` of ``A``'s
    pattern started earlier (PARDISO then only factorises numerically); it is taken or
    released here in every case.
    """
    try:
        backend = resolve_backend(backend)
        if A.shape[0] != A.shape[1] or A.shape[0] == 0:
            raise SolverError(f"cannot factorise a {A.shape[0]}x{A.shape[1]} matrix")
        if single and backend != "pardiso":
            raise ConfigError(f"config key 'modes.precision': a single-precision factor "
                              f"needs the 'pardiso' backend, not '{backend}'",
                              key="modes.precision")
        if backend == "pardiso":
            fact = _pardiso(A, positive_definite, single, analysis)
        elif backend == "cholmod":
            with progress.stage("factorise (CHOLMOD)"):
                fact = _cholmod(A)
        elif backend == "cudss":
            fact = _cudss(A)
        else:
            with progress.stage("factorise (SuperLU)"):
                fact = _superlu(A, positive_definite)
    finally:
        if analysis is not None:
            analysis.release()  # nothing left to free when _pardiso took it
    if check:
        try:
            check_factorization(A, fact)
        except SolverError:
            fact.release()
            raise
    return fact


# --------------------------------------------------------------------------- refined solves
#: A solve is accepted when its normwise backward error (see :func:`backward_errors`) is
#: at most this: it then solved (A + dA) x = b with |dA| / |A| <= 1e-10, a perturbation
#: of the stiffness far below any modelling error. Cholesky/LDL^T solves reach 1e-16 to
#: 1e-14 (n eps at worst); iterative refinement brings a less accurate factor there too.
BACKWARD_ERROR_TOL = 1e-10
#: A matrix whose estimated condition number times eps exceeds this is singular to
#: working precision: its solutions may be wrong by 100 % in the direction of the
#: (near-)null space, however small the residual.
SINGULAR_COND_EPS = 1e-2


@dataclass(frozen=True)
class SolveReport:
    """How accurate a refined solve A X = B is.

    backward_error: (k,) normwise backward error per column after refinement;
    initial_backward_error: (k,) the same before refinement; steps: refinement steps done.
    """

    backward_error: np.ndarray
    initial_backward_error: np.ndarray
    steps: int


def scaled_inf_norm(A: sp.spmatrix, w: np.ndarray | None = None,
                    rows_per_chunk: int = 1 << 16) -> float:
    """|W |A| W|_inf = max_i w_i sum_j |A_ij| w_j for W = diag(w) (w (n,) >= 0; None:
    the identity, i.e. ||A||_inf).

    Row chunks of A's own arrays, one CSR product with |A_ij| each: no abs copy of A
    (``abs(A)`` copies its values and indices, 1 GB for K of 1M DOFs, written fresh every
    call: 0.7 s each; two sparse-times-sparse products with diag(w) took 0.9 s and three
    copies of K's values at 314k DOFs)."""
    A = A if sp.isspmatrix_csr(A) else sp.csr_matrix(A)
    n = A.shape[0]
    best = 0.0
    for r0 in range(0, n, rows_per_chunk):
        r1 = min(n, r0 + rows_per_chunk)
        lo, hi = int(A.indptr[r0]), int(A.indptr[r1])
        part = sp.csr_matrix((np.abs(A.data[lo:hi]), A.indices[lo:hi],
                              A.indptr[r0:r1 + 1] - lo), shape=(r1 - r0, A.shape[1]))
        if w is None:
            sums = np.asarray(part.sum(axis=1)).ravel()
        else:
            sums = w[r0:r1] * (part @ w)
        best = max(best, float(sums.max(initial=0.0)))
    return best


def backward_errors(A: sp.spmatrix, X: np.ndarray, B: np.ndarray, R: np.ndarray | None = None
                    ) -> np.ndarray:
    """Normwise (Rigal-Gaches) backward error of every column of X as a solution of A X = B:

        eta_j = ||b_j - A x_j||_inf / (||A||_inf ||x_j||_inf + ||b_j||_inf)

    the smallest relative perturbation of A and b of which x_j is the exact solution. Unlike
    the relative residual ||r|| / ||b|| (which can be cond(A) eps for a perfect solve) it is
    scale-invariant and independent of the conditioning. X, B: (n, k); R: B - A X if known.
    """
    if R is None:
        R = B - sparse_times_dense(A, X)
    norm_A = scaled_inf_norm(A)
    denom = norm_A * np.abs(X).max(axis=0) + np.abs(B).max(axis=0)
    return np.abs(R).max(axis=0) / np.where(denom > 0, denom, 1.0)


def refined_solve(A: sp.spmatrix, solve: Callable[[np.ndarray], np.ndarray], B: np.ndarray,
                  max_steps: int = 4) -> tuple[np.ndarray, SolveReport]:
    """X = A^-1 B (B: (n,) or (n, k)) with ``solve`` and fixed-precision iterative refinement
    x <- x + solve(b - A x) while the backward error exceeds eps-level round-off and still
    halves (at most ``max_steps`` steps). Returns X (shape of B) and a :class:`SolveReport`;
    the caller judges the backward error (see :data:`BACKWARD_ERROR_TOL`).
    """
    B = np.asarray(B, dtype=float)
    B2 = B[:, None] if B.ndim == 1 else B
    X = np.asarray(solve(np.asfortranarray(B2)), dtype=float).reshape(B2.shape)
    if not np.all(np.isfinite(X)):
        eta = np.full(B2.shape[1], np.inf)
        return X.reshape(B.shape), SolveReport(eta, eta, 0)
    R = B2 - sparse_times_dense(A, X)
    eta = backward_errors(A, X, B2, R)
    eta0, steps = eta.copy(), 0
    floor = 16 * np.finfo(float).eps
    while steps < max_steps and eta.max() > floor:
        dX = np.asarray(solve(np.asfortranarray(R)), dtype=float).reshape(B2.shape)
        X_new = X + dX
        R_new = B2 - sparse_times_dense(A, X_new)
        eta_new = backward_errors(A, X_new, B2, R_new)
        if not np.all(np.isfinite(eta_new)) or eta_new.max() > 0.5 * eta.max():
            if eta_new.max() < eta.max():
                X, R, eta = X_new, R_new, eta_new
                steps += 1
            break
        X, R, eta = X_new, R_new, eta_new
        steps += 1
    if steps:
        log.debug("iterative refinement: backward error %.2e -> %.2e in %d steps",
                  float(eta0.max()), float(eta.max()), steps)
    return X.reshape(B.shape), SolveReport(eta, eta0, steps)


def stiffness_scale(K: sp.spmatrix, M: sp.spmatrix) -> float:
    """The stiffness scale of the mesh (rad^2/s^2): the median diagonal ratio K_ii / M_ii,
    the squared frequency of a typical element (as :func:`pipeline.solve.eigen.default_shift`
    uses). Median, not max: a Cholesky/LDL^T solve is insensitive to symmetric diagonal
    scaling (van der Sluis), so a few stiff sliver elements (a 0.5 mm strip meshed at 5 mm
    has max/median ~1e2) do not make K harder to solve. With the lowest eigenvalue
    lambda_1 it estimates the condition number that governs solves with K."""
    d_k = np.abs(K.diagonal())
    d_m = np.abs(M.diagonal())
    ok = d_m > 0
    return float(np.median(d_k[ok] / d_m[ok])) if ok.any() else float(d_k.max(initial=0.0))


def rigid_omega2_threshold(scale: float) -> float:
    """omega^2 (rad^2/s^2) below which a mode of a body with stiffness scale ``scale`` (see
    :func:`stiffness_scale`) is a rigid-body mode: zero to round-off, 100 eps of the scale.
    Relative, so a soft body (E = 500 Pa, f1 = 0.007 Hz) or a 0.2 mm strip keeps its
    elastic modes elastic (a supported K that is singular was refused by the
    factorisation check already), while the eigenvalues of a free body's rigid modes
    (set to 0 by the eigensolver, round-off ~eps scale otherwise) stay below it."""
    return float(scale) * 100.0 * np.finfo(float).eps
