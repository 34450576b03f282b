"""Mixed precision for the modes stage: a float32 factor, double-precision answers.

``modes.precision: mixed`` (or ``auto`` when a double-precision factor would not fit in
memory) factorises the shifted stiffness in single precision with PARDISO
(``iparm[27] = 1``): half the factor memory and about half the flops (1.84x faster at
100k DOFs, measured). The float32 factor is used twice:

1. as the shift-invert operator of the block Lanczos method (:mod:`pipeline.solve.eigen`)
   with a loose tolerance (:data:`LANCZOS_TOLERANCE`): it finds the subspace, not the
   digits;
2. as the preconditioner T = (K - sigma M)^-1 (float32) of a locally optimal block
   refinement in double precision (:func:`refine`): residuals R = K X - M X diag(w) in
   double, corrections Z = T R, and a Rayleigh-Ritz step with K and M on span[X, Z, P]
   (P: the previous update directions, as in LOBPCG), until every relative residual
   ||K x - w M x|| / ||K x|| is below :data:`TARGET_RESIDUAL` or stops improving.

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
from pipeline.solve.factorize import Factorization, factorize, sparse_times_dense

log = logging.getLogger(__name__)

__all__ = ["PRECISIONS", "factorize_single", "mixed_shift", "refine"]
EPS32 = float(np.finfo(np.float32).eps)
SHIFT_FACTOR = 16.0
LANCZOS_TOLERANCE = 1e-5  # float32 operator: its round-off noise is ~1e-7 of theta_max
TARGET_RESIDUAL = 1e-7
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


def _m_orthonormal(S: np.ndarray, MS: np.ndarray, KS: np.ndarray, drop: float = 1e-10):
    """A basis C of span(S) with (S C)^T M (S C) = I, dropping directions whose
    M-norm is below ``drop`` of the largest; returns (C, reduced K, the Gram eigen-floor)."""
    G = S.T @ MS
    G = 0.5 * (G + G.T)
    g, E = np.linalg.eigh(G)
    keep = g > drop * g[-1]
    C = E[:, keep] / np.sqrt(g[keep])
    Kr = C.T @ (S.T @ KS) @ C
    return C, 0.5 * (Kr + Kr.T)


def refine(K: sp.spmatrix, M: sp.spmatrix, X: np.ndarray, fact: Factorization,
           sigma: float = 0.0, target: float = TARGET_RESIDUAL, max_sweeps: int = MAX_SWEEPS) -> tuple[np.ndarray, dict]:
    """Refine the approximate eigenvectors X (n, m) of (K, M) in double precision with
    the float32 factor ``fact`` as preconditioner (LOBPCG-type sweeps, see module doc).
    ``sigma``: the eigensolver's own shift (< 0 for a free body), which scales the
    residuals of rigid-body modes as in :func:`pipeline.solve.eigen.solve_modes`.

    Returns (X refined (n, m), statistics: sweeps, residual history).
    """
    X = np.ascontiguousarray(X, dtype=np.float64)
    m = X.shape[1]
    P = None
    best = None
    history: list[float] = []
    t0 = time.perf_counter()
    KX, MX = sparse_times_dense(K, X), sparse_times_dense(M, X)
    sweeps = 0
    while True:
        if sweeps == 0:  # Rayleigh-Ritz on span(X): exact M-orthonormality, ordered
            C, Kr = _m_orthonormal(X, MX, KX)
            w, U = np.linalg.eigh(Kr)
            B = C @ U[:, :m]
            X, KX, MX, w = X @ B, KX @ B, MX @ B, w[:m]
        R = KX - MX * w
        scale = np.maximum(np.linalg.norm(KX, axis=0), abs(sigma) * np.linalg.norm(MX, axis=0))
        res = np.linalg.norm(R, axis=0) / np.where(scale > 0, scale, 1.0)
        history.append(float(res.max()))
        if best is None or history[-1] < best[0]:
            best = (history[-1], X.copy())
        if (res.max() <= target or sweeps >= max_sweeps
                or (len(history) > 2 and history[-1] > 0.5 * history[-2])):
            X = best[1]  # the iterate with the smallest residual (round-off may stall it)
            break
        sweeps += 1
        active = res > target  # soft locking: converged modes get no new directions
        Z = np.asarray(fact.solve(np.ascontiguousarray(R[:, active])), dtype=np.float64)
        Z = Z.reshape(X.shape[0], -1)
        S = np.concatenate([X, Z] if P is None else [X, Z, P[:, active]], axis=1)
        del Z
        MZ = sparse_times_dense(M, np.ascontiguousarray(S[:, m:]))
        norms = np.sqrt(np.maximum(np.einsum("ij,ij->j", S[:, m:], MZ), 1e-300))
        S[:, m:] /= norms  # unit M-norm: the Gram matrix's scales are comparable
        MZ /= norms
        KZ = sparse_times_dense(K, np.ascontiguousarray(S[:, m:]))
        KS = np.concatenate([KX, KZ], axis=1)
        MS = np.concatenate([MX, MZ], axis=1)
        del KZ, MZ
        C, Kr = _m_orthonormal(S, MS, KS)
        w, U = np.linalg.eigh(Kr)  # the sweep's Rayleigh-Ritz on span[X, Z, P]
        w = w[:m]
        B = C @ U[:, :m]  # (cols of S, m)
        Xn = S @ B
        P = S[:, m:] @ B[m:]  # the new directions' part of the update
        KX, MX = KS @ B, MS @ B
        X = Xn
        del S, KS, MS, Xn
    return X, {"refine_sweeps": sweeps, "refine_residuals": history,
               "refine_residual": best[0],
               "refine_seconds": time.perf_counter() - t0}
