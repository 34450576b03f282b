"""Mixed precision for the modes stage: a float32 factor, double-precision answers.

``modes.precision: mixed`` (or ``auto`` when a double-precision factor would not fit in
memory) factorises the shifted stiffness in single precision with PARDISO
(``iparm[27] = 1``): half the factor memory and about half the flops (1.84x faster at
100k DOFs, measured). The float32 factor is used twice:

1. as the shift-invert operator of the block Lanczos method (:mod:`pipeline.solve.eigen`)
   with a loose tolerance (:data:`LANCZOS_TOLERANCE`): it finds the subspace, not the
   digits;
2. as the preconditioner T = (K - sigma M)^-1 (float32) of LOBPCG in double precision
   (:func:`refine`, :mod:`pipeline.solve.lobpcg`): residuals R = K X - M X diag(w) in
   double, corrections Z = T R, Rayleigh-Ritz with K and M on span[X, Z, P], until
   every preconditioned residual sqrt(r^T T r) / omega is below :data:`TARGET_RESIDUAL`
   (frequency error ~ its square) or stops improving: 3 sweeps at 101k DOFs, against
   4-6 when the test was the Euclidean residual ||K x - w M x|| / ||K x||, which float32
   noise in the high-frequency components keeps large (see lobpcg);
3. as the preconditioner of conjugate gradients for the static correction K^-1 F
   (:func:`static_solver`), instead of a second, double-precision factorisation.

The eigenvalues and residuals are thus computed in double precision; only the quality
of the preconditioner is single precision, and that sets the number of sweeps, not the
accuracy. Frequencies agree with the double-precision path to ~1e-10 relative on the
test meshes (``tests/test_solvers.py``; the eigenvalue error goes as the squared
residual over the gap).

The shift: unshifted, a float32 factor of the cantilever's K (cond ~ 3e7) solves with
O(1) relative error, since float32 round-off perturbs every eigenvalue of K by about
eps32 * lambda_max. With A = K - sigma M, sigma = -:data:`SHIFT_FACTOR` * eps32 *
lambda_max (lambda_max estimated from max K_ii / M_ii, which for the consistent mass is
within a small factor of it) that perturbation is a fraction 1/SHIFT_FACTOR of the
smallest eigenvalue of A, so the float32 operator has the right low eigenvectors.
Shapes: K, M (n x n) CSR; X (n, m).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp

from pipeline.config.schema import PRECISIONS
from pipeline.solve.factorization import Factorization, SolverFactorization, factorize
from pipeline.solve.lobpcg import lobpcg
from pipeline.solve.pcg import pcg

log = logging.getLogger(__name__)

__all__ = ["PRECISIONS", "factorize_single", "mixed_shift", "refine", "static_solver"]
EPS32 = float(np.finfo(np.float32).eps)
SHIFT_FACTOR = 16.0
LANCZOS_TOLERANCE = 1e-5  # float32 operator: its round-off noise is ~1e-7 of theta_max
TARGET_RESIDUAL = 1e-6  # preconditioned residual sqrt(r^T T r) / omega (see lobpcg)
MAX_SWEEPS = 12


def mixed_shift(K: sp.spmatrix, M: sp.spmatrix, sigma: float) -> float:
    """The shift for a float32 factor: at most ``sigma`` and at most
    -SHIFT_FACTOR * eps32 * max(K_ii / M_ii) (rad^2/s^2)."""
    d = K.diagonal() / M.diagonal()
    lam_max = float(np.max(d[np.isfinite(d)])) if d.size else 1.0
    return min(float(sigma), -SHIFT_FACTOR * EPS32 * lam_max)


def factorize_single(K: sp.spmatrix, M: sp.spmatrix, sigma: float) -> Factorization:
    """Float32 PARDISO factor of K - sigma M (sigma < 0 from :func:`mixed_shift`)."""
    t0 = time.perf_counter()
    fact = factorize((K - sigma * M).tocsr(), "pardiso", positive_definite=True, check=False,
                     single=True)
    log.info("float32 factor of K %+.3g M in %.2f s (%.2f GB)", -sigma,
             time.perf_counter() - t0, fact.info.get("factor_bytes", 0) / 1e9)
    return fact


def refine(K: sp.spmatrix, M: sp.spmatrix, X: np.ndarray, fact: Factorization,
           sigma: float = 0.0, target: float = TARGET_RESIDUAL,
           max_sweeps: int = MAX_SWEEPS) -> tuple[np.ndarray, dict]:
    """Refine the approximate eigenvectors X (n, m) of (K, M) in double precision with
    the float32 factor ``fact`` as the preconditioner of LOBPCG
    (:func:`pipeline.solve.lobpcg.lobpcg`), until every preconditioned residual
    sqrt(r^T T r) / omega is <= ``target`` or stops improving. ``sigma``: the
    eigensolver's own shift (< 0 for a free body), which scales rigid-body residuals.

    Returns (X refined (n, m), statistics: sweeps, preconditioned-residual history).
    """
    result = lobpcg(K, M, X, fact.solve, X.shape[1], sigma=sigma, target=target,
                    max_sweeps=max_sweeps, patience=3)
    return result.X, {"refine_sweeps": result.sweeps,
                      "refine_residuals": list(result.history),
                      "refine_residual": min(result.history),
                      "refine_seconds": result.seconds}


def static_solver(K: sp.spmatrix, fact: Factorization) -> Factorization:
    """K^-1 by conjugate gradients preconditioned with the float32 factor of
    K - sigma M (:func:`pipeline.solve.pcg.pcg`): the static correction's solver when no
    double factor of K exists. Owns ``fact`` (its ``release`` frees it)."""
    K = sp.csr_matrix(K)

    def solve(B: np.ndarray) -> np.ndarray:
        X, its = pcg(K, B, lambda R: np.asarray(fact.solve(R), dtype=np.float64))
        log.debug("static solve by PCG with the float32 factor: %d iterations", its)
        return X

    return SolverFactorization(solve, backend="pardiso-float32+pcg", n=fact.n,
                               release=fact.release, info=dict(fact.info))
