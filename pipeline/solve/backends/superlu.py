"""scipy's SuperLU: always available.

The ``MMD_AT_PLUS_A`` column ordering with symmetric mode is used because it was twice
as fast as scipy's default ordering at 100k DOFs. An LU, so it also factorises symmetric
indefinite matrices; it offers no separate forward and backward substitutions, so the
eigensolver uses ARPACK's shift-invert mode with it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from pipeline._util import progress
from pipeline.errors import SolverError
from pipeline.solve.factorization import Capabilities, Factorization, register_backend


class SuperLUFactorization(Factorization):
    """LU of a symmetric matrix by SuperLU (``scipy.sparse.linalg.splu``)."""

    backend = "superlu"
    capabilities = Capabilities(indefinite=True)

    def __init__(self, A: sp.spmatrix, positive_definite: bool = True):
        from scipy.sparse.linalg import splu

        n = A.shape[0]
        try:
            lu = splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A",
                      options={"SymmetricMode": True, "DiagPivotThresh": 0.01})
        except RuntimeError as exc:
            raise SolverError(f"SuperLU could not factorise the {n}x{n} system ({exc}): the "
                              "matrix is singular; check the supports") from None
        if positive_definite and np.array_equal(lu.perm_r, lu.perm_c):
            # symmetric pivoting only: A = P^T L D L^T P with D = diag(U), so by
            # Sylvester's law of inertia A is positive definite iff every U_ii > 0
            negative = int((lu.U.diagonal() <= 0).sum())
            if negative:
                raise SolverError(f"the {n}x{n} stiffness system is singular or not positive "
                                  f"definite ({negative} non-positive pivots): check the "
                                  "supports (a body that can move as a rigid body or "
                                  "mechanism needs supports) and the material (E > 0, "
                                  "-1 < nu < 0.5)")
        nnz = int(lu.L.nnz + lu.U.nnz)
        super().__init__(n, info={"format": "csc", "factor_nnz": nnz,
                                  "factor_bytes": 12 * nnz})
        self._lu = lu

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._lu is None:
            raise SolverError("the SuperLU factorisation was released")
        return self._lu.solve(b)

    def release(self) -> None:
        self._lu = None


def factor(A: sp.spmatrix, *, positive_definite: bool = True, single: bool = False,
           analysis=None) -> SuperLUFactorization:
    """SuperLU factor of ``A`` (see :func:`pipeline.solve.factorization.factorize`)."""
    with progress.stage("factorise (SuperLU)"):
        return SuperLUFactorization(A, positive_definite)


register_backend("superlu", factor, installed=lambda: True,
                 capabilities=SuperLUFactorization.capabilities)
