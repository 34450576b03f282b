"""Refined solves with a factorisation and the backward errors that judge them.

The normwise (Rigal-Gaches) backward error of a solve is the smallest relative
perturbation of A and b of which the computed x is the exact solution; fixed-precision
iterative refinement brings it to round-off with a less accurate factor too.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp

from pipeline.solve.blas import scaled_inf_norm, sparse_times_dense

log = logging.getLogger(__name__)

#: A solve is accepted when its normwise backward error (see :func:`backward_errors`) is
#: at most this: it then solved (A + dA) x = b with |dA| / |A| <= 1e-10, a perturbation
#: of the stiffness far below any modelling error. Cholesky/LDL^T solves reach 1e-16 to
#: 1e-14 (n eps at worst); iterative refinement brings a less accurate factor there too.
BACKWARD_ERROR_TOL = 1e-10


@dataclass(frozen=True)
class SolveReport:
    """How accurate a refined solve A X = B is.

    backward_error: (k,) normwise backward error per column after refinement;
    initial_backward_error: (k,) the same before refinement; steps: refinement steps done.
    """

    backward_error: np.ndarray
    initial_backward_error: np.ndarray
    steps: int


def backward_errors(A: sp.spmatrix, X: np.ndarray, B: np.ndarray, R: np.ndarray | None = None,
                    norm_A: float | None = None) -> np.ndarray:
    """Normwise (Rigal-Gaches) backward error of every column of X as a solution of A X = B:

        eta_j = ||b_j - A x_j||_inf / (||A||_inf ||x_j||_inf + ||b_j||_inf)

    the smallest relative perturbation of A and b of which x_j is the exact solution. Unlike
    the relative residual ||r|| / ||b|| (which can be cond(A) eps for a perfect solve) it is
    scale-invariant and independent of the conditioning. X, B: (n, k); R: B - A X if known;
    ``norm_A``: ||A||_inf if known (a pass over A otherwise).
    """
    if R is None:
        R = B - sparse_times_dense(A, X)
    norm_A = scaled_inf_norm(A) if norm_A is None else float(norm_A)
    denom = norm_A * np.abs(X).max(axis=0) + np.abs(B).max(axis=0)
    return np.abs(R).max(axis=0) / np.where(denom > 0, denom, 1.0)


def refined_solve(A: sp.spmatrix, solve: Callable[[np.ndarray], np.ndarray], B: np.ndarray,
                  max_steps: int = 4, norm_A: float | None = None
                  ) -> tuple[np.ndarray, SolveReport]:
    """X = A^-1 B (B: (n,) or (n, k)) with ``solve`` and fixed-precision iterative refinement
    x <- x + solve(b - A x) while the backward error exceeds eps-level round-off and still
    halves (at most ``max_steps`` steps). Returns X (shape of B) and a :class:`SolveReport`;
    the caller judges the backward error (see :data:`BACKWARD_ERROR_TOL`). ``norm_A``:
    ||A||_inf if the caller knows it (it is computed once otherwise).
    """
    B = np.asarray(B, dtype=float)
    B2 = B[:, None] if B.ndim == 1 else B
    X = np.asarray(solve(np.asfortranarray(B2)), dtype=float).reshape(B2.shape)
    if not np.all(np.isfinite(X)):
        eta = np.full(B2.shape[1], np.inf)
        return X.reshape(B.shape), SolveReport(eta, eta, 0)
    R = B2 - sparse_times_dense(A, X)
    norm_A = scaled_inf_norm(A) if norm_A is None else float(norm_A)
    eta = backward_errors(A, X, B2, R, norm_A)
    eta0, steps = eta.copy(), 0
    floor = 16 * np.finfo(float).eps
    while steps < max_steps and eta.max() > floor:
        dX = np.asarray(solve(np.asfortranarray(R)), dtype=float).reshape(B2.shape)
        X_new = X + dX
        R_new = B2 - sparse_times_dense(A, X_new)
        eta_new = backward_errors(A, X_new, B2, R_new, norm_A)
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
