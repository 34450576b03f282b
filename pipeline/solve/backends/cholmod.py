"""SuiteSparse CHOLMOD through the ``cholespy`` wheel (the ``fast`` extra).

That wheel bundles the reference BLAS and runs on one thread: correct, but 3 times
slower than SuperLU at 100k DOFs, so ``auto`` ranks it after SuperLU; it is there as an
independent Cholesky to cross-check the others.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import scipy.sparse as sp

from pipeline._util import progress
from pipeline.errors import SolverError
from pipeline.solve.factorization import Capabilities, Factorization, register_backend


@functools.lru_cache(maxsize=1)
def cholespy_module() -> Any | None:
    """The ``cholespy`` module, or None when it is missing or its libraries fail to load."""
    try:
        import cholespy

        return cholespy
    except Exception:  # ImportError, or its bundled libraries failing to load
        return None


class CholmodFactorization(Factorization):
    """Cholesky of a symmetric positive definite matrix by CHOLMOD."""

    backend = "cholmod"
    capabilities = Capabilities()

    def __init__(self, A: sp.spmatrix):
        cholespy = cholespy_module()
        A = sp.csr_matrix(A)
        n = A.shape[0]
        try:
            solver = cholespy.CholeskySolverD(n, A.indptr.astype(np.int32),
                                              A.indices.astype(np.int32),
                                              np.ascontiguousarray(A.data, dtype=np.float64),
                                              cholespy.MatrixType.CSR)
        except (ValueError, RuntimeError) as exc:
            raise SolverError(f"CHOLMOD could not factorise the {n}x{n} system ({exc}): the "
                              "stiffness matrix is singular or not positive definite; check "
                              "the supports") from None
        super().__init__(n, info={"format": "csr"})
        self._solver = solver

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._solver is None:
            raise SolverError("the CHOLMOD factorisation was released")
        b = np.ascontiguousarray(b, dtype=np.float64)
        x = np.zeros_like(b)
        self._solver.solve(b, x)
        return x

    def release(self) -> None:
        self._solver = None


def factor(A: sp.spmatrix, *, positive_definite: bool = True, single: bool = False,
           analysis=None) -> CholmodFactorization:
    """CHOLMOD factor of ``A`` (see :func:`pipeline.solve.factorization.factorize`)."""
    with progress.stage("factorise (CHOLMOD)"):
        return CholmodFactorization(A)


register_backend("cholmod", factor, installed=lambda: cholespy_module() is not None,
                 capabilities=CholmodFactorization.capabilities,
                 install_hint="'cholmod' comes with the 'fast' extra: pip install -e '.[fast]'")
