"""Preconditioned conjugate gradients for K X = B with several right-hand sides at once.

Used where a solve with K is needed but no double-precision factor of K exists: the
static correction K^-1 F under the factor-free multigrid solver (T = the two-grid cycle,
:mod:`pipeline.solve.multigrid`) and under mixed precision (T = the float32 factor of
K - sigma M, :mod:`pipeline.solve.mixed`). Each column runs its own CG recurrence
(alpha and beta per column) on shared (n, k) blocks, so every iteration is one sparse
product with k columns and one application of T to them. A column stops at
||B - K X|| <= rtol ||B|| (the recursive residual; the caller's iterative refinement
measures the true one), or as soon as its normwise backward error on the recursive
residual, ||r||_inf / (||K||_inf ||x||_inf + ||b||_inf), is at most eps: past that
round-off floor the true residual no longer falls (the recursive one keeps falling
away from it), so further iterations cannot improve x. Measured on the cantilever at
313k DOFs with the two-grid cycle: the true backward error stops at 2e-16 after 14
iterations, while rtol = 1e-12 took 21-23 (a third of the static solve).

beta is Polak-Ribiere's, z_new^T (r_new - r_old) / z_old^T r_old (flexible CG, Golub and
Ye 1999; Notay 2000): equal to Fletcher-Reeves' z_new^T r_new / z_old^T r_old for a
fixed symmetric T, and it keeps the convergence when T varies slightly from one
application to the next, as a float32 cycle or a float32 factor does (rounding at
1e-7 makes T neither exactly linear nor exactly symmetric). Since r_new - r_old is
-alpha K p, it costs one more dot product an iteration, and K p is kept until then.

Kept over :func:`scipy.sparse.linalg.cg` (``benchmarks/bench_solvers.py``: four body-load
columns to 1e-10 with the two-grid cycle; 2-core Xeon under a load average of 10-16 from
other jobs, ratios from the same run): the cantilever at 100k DOFs, 16 iterations and 13 s
against scipy's 20 and 72 s; the 2 mm strip at 207k, 29 and 73 s against 41 and 164 s;
at a load average of 1-6, the bracket (103k) 17 and 5.2 s against 18 and 8.7 s, the
slender beam (127k) 16 and 2.7 s against 25 and 7.6 s.
scipy's CG takes one right-hand side at a time (a sparse product and a cycle per column
and iteration), and its Fletcher-Reeves beta assumes a fixed T, which the float32 cycle
is only to rounding (a likely cause of its extra iterations).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp

from pipeline.errors import SolverError
from pipeline.solve.blas import column_norms, scaled_inf_norm, sparse_times_dense

RTOL = 1e-12
MAX_ITER = 500


class Pcg:
    """The recurrence of :func:`pcg` as a state that advances one iteration per
    application of T, for a caller that applies T to a larger block anyway: the
    factor-free eigensolver rides the static solves' columns along in LOBPCG's cycles
    (:meth:`pipeline.solve.multigrid.TwoGrid.ride`) and finishes them later.

    ``residual`` is the (n, k) block to precondition next (the recursive residual R),
    ``advance(Z)`` takes Z = T R and makes the next iteration; ``finished`` once every
    column has stopped (module doc), ``solution()`` is then X (the shape of B).
    :func:`pcg` is ``Pcg(A, B, rtol).run(precondition, max_iter)``, with the same
    arithmetic in the same order. ``norm_A``: ||A||_inf (the round-off floor of the stop
    test) where the caller knows it already; one pass over A otherwise.
    """

    def __init__(self, A: sp.spmatrix, B: np.ndarray, rtol: float = RTOL,
                 max_iter: int = MAX_ITER, norm_A: float | None = None):
        B = np.asarray(B, dtype=np.float64)
        self.vector = B.ndim == 1
        self.A, self.rtol, self.max_iter = A, rtol, max_iter
        B = np.ascontiguousarray(B.reshape(B.shape[0], -1))
        self.X = np.zeros_like(B)
        bnorm = column_norms(B)
        self.goal = rtol * np.where(bnorm > 0, bnorm, 1.0)
        self.norm_A = scaled_inf_norm(A) if norm_A is None else float(norm_A)
        self.b_inf = np.abs(B).max(axis=0)
        self.residual = B.copy()
        self.iterations = 0
        self.finished = False
        self._P = self._AP = self._rz = self._alpha = None

    def _done(self) -> np.ndarray:
        R, eps = self.residual, np.finfo(np.float64).eps
        floor = np.abs(R).max(axis=0) <= eps * (self.norm_A * np.abs(self.X).max(axis=0)
                                                + self.b_inf)
        return (column_norms(R) <= self.goal) | floor

    def advance(self, Z: np.ndarray) -> None:
        """Take Z = T R (n, k) and make the next iteration (or set ``finished``);
        SolverError after ``max_iter`` iterations."""
        R = self.residual
        Z = np.asarray(Z, dtype=np.float64).reshape(R.shape)
        if self._P is None:  # Z = T B: the first search directions
            self._P = Z.copy()
            self._rz = np.einsum("ij,ij->j", R, Z)
        else:
            rz_new = np.einsum("ij,ij->j", R, Z)
            z_dr = -self._alpha * np.einsum("ij,ij->j", Z, self._AP)  # z_new^T (r_new - r_old)
            self._AP = None
            rz = self._rz
            beta = np.where(rz != 0, z_dr / np.where(rz != 0, rz, 1.0), 0.0)
            self._P *= beta
            self._P += Z
            self._rz = rz_new
        del Z
        done = self._done()
        if np.all(done):
            self.finished = True
            return
        if self.iterations >= self.max_iter:
            rnorm = column_norms(R)
            raise SolverError(f"conjugate gradients did not reach a relative residual of "
                              f"{self.rtol:g} in {self.max_iter} iterations (now "
                              f"{float((rnorm / self.goal).max() * self.rtol):.1e}): K is "
                              "singular or nearly so (a rigid-body motion or mechanism the "
                              "supports leave free?)")
        self.iterations += 1
        P = self._P
        AP = sparse_times_dense(self.A, P)
        pap = np.einsum("ij,ij->j", P, AP)
        alpha = np.where(~done & (pap > 0), self._rz / np.where(pap > 0, pap, 1.0), 0.0)
        self.X += P * alpha
        R -= AP * alpha
        self._AP, self._alpha = AP, alpha

    def solution(self) -> np.ndarray:
        return self.X[:, 0] if self.vector else self.X

    def run(self, precondition: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, int]:
        """Iterate to the end: (X, iterations)."""
        while not self.finished:
            self.advance(precondition(self.residual))
        return self.solution(), self.iterations


def pcg(A: sp.spmatrix, B: np.ndarray, precondition: Callable[[np.ndarray], np.ndarray],
        rtol: float = RTOL, max_iter: int = MAX_ITER) -> tuple[np.ndarray, int]:
    """(X, iterations) with A X = B for symmetric positive definite A (n x n), B (n,) or
    (n, k); ``precondition(R)`` returns T R for R (n, k). Each column stops at rtol or at
    the round-off floor (module doc); SolverError after ``max_iter``.

    >>> import numpy as np, scipy.sparse as sp
    >>> A = sp.diags([4.0, 3.0, 2.0]).tocsr()
    >>> X, its = pcg(A, np.ones(3), lambda R: R / A.diagonal()[:, None])
    >>> np.allclose(X, [0.25, 1 / 3, 0.5]), its
    (True, 1)
    """
    return Pcg(A, B, rtol, max_iter).run(precondition)
