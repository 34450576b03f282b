"""NVIDIA cuDSS on the GPU, through nvmath-python and CuPy (an NVIDIA GPU and the ``gpu``
extra).

Cholesky of the upper triangle (type SPD, upper view). The reordering runs on the host's
cores (cuDSS's OpenMP threading layer, found beside the library or named by
``CUDSS_MT_LIB``), the factorisation and the solves on the GPU, whose free memory is
checked against cuDSS's own estimate before the factorisation. No separate forward and
backward substitutions, so the eigensolver uses ARPACK's shift-invert mode with it.
Never chosen by ``auto``: ``modes.solver: cudss`` asks for it. Figures measured on an
H100 are in ``docs/performance.md`` (``benchmarks/bench_gpu.py`` reproduces them).
"""

from __future__ import annotations

import functools
import glob
import logging
import os
import sys
import time
from typing import Any

import numpy as np
import scipy.sparse as sp

from pipeline._util import progress
from pipeline._util.resources import HEADROOM, beyond_usable
from pipeline.errors import ResourceError, SolverError
from pipeline.solve.blas import upper_triangle_csr
from pipeline.solve.factorization import Capabilities, Factorization, register_backend


@functools.lru_cache(maxsize=1)
def cudss_modules() -> tuple[Any, Any] | None:
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


def _threading_lib() -> str | None:
    """cuDSS's OpenMP threading layer, so that its reordering uses every core (2.3 times
    faster at 1M DOFs on 16 cores): ``CUDSS_MT_LIB``, else beside the cuDSS wheel's
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


def factor(A: sp.spmatrix, *, positive_definite: bool = True, single: bool = False,
           analysis=None) -> "CudssFactorization":
    """Cholesky of the symmetric positive definite ``A`` on the GPU (cuDSS)."""
    cupy, nvmath = cudss_modules()
    import cupyx.scipy.sparse as csp
    from nvmath.bindings import cudss

    n = A.shape[0]
    quiet = logging.getLogger(__name__ + ".cudss")  # nvmath logs every phase at INFO
    quiet.setLevel(logging.WARNING)
    options = nvmath.sparse.advanced.DirectSolverOptions(
        sparse_system_type=cudss.MatrixType.SPD, sparse_system_view=cudss.MatrixViewType.UPPER,
        multithreading_lib=_threading_lib(), logger=quiet, blocking=True)
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
                                f"{need / 1e9:.1f} GB of GPU memory, "
                                f"{beyond_usable(need, free, 'free')}: use a coarser "
                                "mesh.size, or modes.solver: auto (CPU)")
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
    return CudssFactorization(
        solver, rhs, cupy, n,
        info={"format": "csr-upper/cuda", "analysis_seconds": t1 - t0,
              "numeric_seconds": t2 - t1, "factor_nnz": int(info.lu_nnz),
              "factor_bytes": 0, "device_bytes": int(need)})


class CudssFactorization(Factorization):
    """A cuDSS Cholesky factor on the GPU (made by :func:`factor`)."""

    backend = "cudss"
    capabilities = Capabilities(gpu=True)

    def __init__(self, solver, rhs, cupy, n: int, *, info: dict):
        super().__init__(n, info=info)
        self._solver, self._rhs, self._cupy = solver, rhs, cupy

    def solve(self, b: np.ndarray) -> np.ndarray:
        """A^-1 b for b (n,) or (n, k), one column at a time through the GPU (a cuDSS
        solver keeps the shape of its right-hand side)."""
        if self._solver is None:
            raise SolverError("the cuDSS factorisation was released")
        b = np.asarray(b, dtype=np.float64)
        cols = b.reshape(self.n, -1)
        x = np.empty_like(cols)
        for j in range(cols.shape[1]):
            self._rhs.set(np.asfortranarray(cols[:, j:j + 1]))
            self._solver.reset_operands(b=self._rhs)
            x[:, j:j + 1] = self._cupy.asnumpy(self._solver.solve())
        return x.reshape(b.shape)

    def release(self) -> None:
        if self._solver is not None:
            self._solver.free()
            self._solver = None
            _gpu_free_bytes(self._cupy)


register_backend("cudss", factor, installed=lambda: cudss_modules() is not None,
                 capabilities=CudssFactorization.capabilities,
                 install_hint="'cudss' needs an NVIDIA GPU with its driver, CuPy and "
                              "nvmath-python with cuDSS: pip install -e '.[gpu]', i.e. "
                              "cupy-cuda13x and 'nvmath-python[cu13]'")
