"""Static deflection shapes K^-1 F and the exact FE static compliance T K^-1 F.

Solves are refined iteratively and judged by their normwise backward error
(:mod:`pipeline.solve.refine`); a K that is singular to working precision (a body its
supports leave free to move) is refused with a message naming the cause. Shapes: ``K``
(n_s x n_s, N/m) on the free DOFs, ``F`` (n_s x n_u, N per unit input), ``T``
(n_y x n_s).

Under an exact constraint u = T q (``constraint``: T, n_s x n_q,
:mod:`pipeline.fe.constraints`) every solve runs on the coordinates q:
X = T (T^T K T)^-1 T^T F, and a kept ``solve`` is then that of T^T K T.
"""

from __future__ import annotations

import logging
import math
from typing import Callable

import numpy as np
import scipy.sparse as sp

from pipeline.errors import SolverError
from pipeline._util.sparse import csr_diagonal
from pipeline.solve.blas import constraint_coordinates, scaled_inf_norms
from pipeline.solve.factorization import factorize as factorize_matrix
from pipeline.solve.refine import BACKWARD_ERROR_TOL, refined_solve
from pipeline.solve.thresholds import SINGULAR_COND_EPS

log = logging.getLogger(__name__)

#: b -> K^-1 b
Solve = Callable[[np.ndarray], np.ndarray]


def _solver(K, solve: Solve | None, factorize: Callable[[object], Solve] | None) -> Solve:
    """``solve``, else ``factorize(K)``, else SuperLU's LU of K (singular: SolverError; the
    static solve judges the accuracy itself)."""
    if solve is not None:
        return solve
    if factorize is not None:
        return factorize(K)
    return factorize_matrix(K, "superlu", positive_definite=False, check=False).solve


def dense_array(X) -> np.ndarray:
    return np.asarray(X.toarray() if sp.issparse(X) else X, dtype=float)


def static_shapes(K, F, solve: Solve | None = None, factorize=None, *,
                  lowest_omega2: float | None = None, stiffness_scale: float | None = None,
                  constraint: sp.spmatrix | None = None) -> np.ndarray:
    """Static deflection shapes X = K^-1 F (n_s x n_u), in m per unit input.

    ``solve``: a ready solver b -> K^-1 b; else ``factorize(K)`` gives one (default:
    SuperLU, :mod:`pipeline.solve.backends.superlu`). The solve is refined iteratively and judged by its
    normwise backward error eta = |F - K X| / (|K| |X| + |F|) (scale-invariant; the
    relative residual |F - K X| / |F| is not: it can be cond(K) eps for a perfect solve
    of a thin or slender body), accepted up to
    :data:`pipeline.solve.refine.BACKWARD_ERROR_TOL`.

    ``lowest_omega2`` (the lowest eigenvalue of K phi = omega^2 M phi, rad^2/s^2) and
    ``stiffness_scale`` (an estimate of the largest, see
    :func:`pipeline.solve.thresholds.stiffness_scale`) give the condition number
    kappa = stiffness_scale / lowest_omega2; kappa eps above
    :data:`~pipeline.solve.thresholds.SINGULAR_COND_EPS` means K is singular to working
    precision (a rigid-body motion or mechanism the supports leave free), refused as
    such. Raises :class:`SolverError` naming the cause.

    ``constraint``: T of u = T q, or None (module docstring).
    """
    Fd = dense_array(F)
    if Fd.ndim == 1:
        Fd = Fd[:, None]
    if constraint is not None:
        T = constraint
        Xq = static_shapes((T.T @ (K @ T)).tocsr(), T.T @ Fd, solve, factorize,
                           lowest_omega2=lowest_omega2, stiffness_scale=stiffness_scale)
        return np.asarray(T @ Xq, dtype=float)
    solver = _solver(K, solve, factorize)
    d = np.sqrt(np.abs(csr_diagonal(K)))
    d = np.where(d > 0, d, 1.0)
    norm_K, norm_Ks = scaled_inf_norms(K, None, 1.0 / d)  # one pass over K for both
    X, report = refined_solve(K, solver, Fd, norm_A=norm_K)
    X = np.asarray(X, dtype=float).reshape(Fd.shape)
    eta = float(report.backward_error.max(initial=0.0))
    eps = np.finfo(float).eps
    kappa = None
    if lowest_omega2 is not None and stiffness_scale is not None:
        kappa = stiffness_scale / max(float(lowest_omega2), np.finfo(float).tiny)
    # Singular or not: a lower bound of the condition number of the diagonally scaled
    # K~ = D^-1/2 K D^-1/2 (D = diag K; Cholesky and LDL^T are insensitive to that
    # scaling, van der Sluis), from the solve itself: |X~| <= |K~^-1| |F~| gives
    # cond_inf(K~) >= |K~| |X~| / |F~| with X~ = D^1/2 X, F~ = D^-1/2 F. A backward-stable
    # solve of a singular K has a small backward error; its null-space component makes
    # this bound ~1/eps. (kappa from the modes is only reported: the diagonal ratios of
    # thin P2 elements overstate it by orders of magnitude.)
    Fs = np.abs(Fd / d[:, None]).max(initial=0.0)
    if Fs > 0 and np.all(np.isfinite(X)):
        lower = norm_Ks * float(np.abs(X * d[:, None]).max(initial=0.0)) / Fs
        if lower * eps > SINGULAR_COND_EPS:
            mode = ""
            if kappa is not None:
                f1 = math.sqrt(max(float(lowest_omega2), 0.0)) / (2 * math.pi)
                mode = f"; the lowest mode is at {f1:.3g} Hz"
            raise SolverError(
                f"static solve K^-1 F: K is singular to working precision (the condition "
                f"number of the scaled K is at least {lower:.1e}{mode}): a rigid-body "
                "motion or mechanism that the supports leave free; look at mode 1's shape "
                "and support the body so that it cannot move without deforming (or give it "
                "no supports to model it as a free body)")
    if not np.all(np.isfinite(X)) or eta > BACKWARD_ERROR_TOL:
        cond = f", estimated cond(K) {kappa:.1e}" if kappa is not None else ""
        raise SolverError(
            f"static solve K^-1 F is inaccurate: backward error {eta:.1e} (> "
            f"{BACKWARD_ERROR_TOL:g}) after {report.steps} refinement steps{cond}; the "
            "factorisation of K is unreliable with this backend: try another "
            "'modes.solver' (superlu, pardiso, cholmod)")
    if report.steps:
        log.info("static solve K^-1 F: backward error %.1e -> %.1e after %d refinement "
                 "step(s)%s", float(report.initial_backward_error.max()), eta, report.steps,
                 f" (estimated cond(K) {kappa:.1e})" if kappa is not None else "")
    return X


def static_compliance(K, F, T, solve: Solve | None = None, factorize=None) -> np.ndarray:
    """Exact FE static compliance T K^-1 F (n_y x n_u), e.g. m/N for force -> displacement.

    This is the DC gain every reduced position output should reproduce.
    """
    return np.asarray(T @ static_shapes(K, F, solve, factorize), dtype=float)


#: relief iteration: stop when a step changes X by less than this (relative)
RELIEF_TOL = 1e-13
RELIEF_MAX_STEPS = 60


def relief_shapes(K, M, F, rigid: np.ndarray, shift: float, factorize=None,
                  constraint: sp.spmatrix | None = None) -> np.ndarray:
    """Inertia-relief static shapes X (n_s x n_u) of a body that keeps the rigid-body
    modes ``rigid`` (n_s x r, M-orthonormal, K rigid = 0): the load less what accelerates
    the body as a rigid one (d'Alembert), P^T F = F - M R R^T F, deflects it by

        K X = P^T F,   R^T M X = 0 (no rigid motion in X).

    K is singular; A = K - shift M (``shift`` < 0 rad^2/s^2) is positive definite and is
    factorised once (``factorize(A)`` -> b -> A^-1 b; default SuperLU). The fixed point
    X <- A^-1 (P^T F - shift M X) (A X = K X - shift M X), projected onto R^T M X = 0 after every step, shrinks
    the error of every elastic component by |shift| / (omega^2 - shift) per step (1e-3
    with shift = -1e-3 omega_1^2); stops at :data:`RELIEF_TOL`. ``constraint``: T of
    u = T q, or None (module docstring; ``rigid`` satisfies it)."""
    R = np.asarray(rigid, dtype=float)
    Fd = dense_array(F)
    if Fd.ndim == 1:
        Fd = Fd[:, None]
    if constraint is not None:
        T = constraint
        Xq = relief_shapes((T.T @ (K @ T)).tocsr(), (T.T @ (M @ T)).tocsr(), T.T @ Fd,
                           constraint_coordinates(T, R), shift, factorize)
        return np.asarray(T @ Xq, dtype=float)
    Fe = Fd - M @ (R @ (R.T @ Fd))
    solve = _solver(sp.csr_matrix(K - shift * M), None, factorize)
    return relief_fixed_point(Fe, solve, lambda X: M @ X,
                              lambda X: X - R @ (R.T @ (M @ X)), np.linalg.norm, shift)


def relief_fixed_point(Fe: np.ndarray, solve, mass, project, norm, shift: float
                       ) -> np.ndarray:
    """The fixed point X <- project(A^-1 (Fe - shift M X)) of :func:`relief_shapes`,
    from X = 0, stopped at a relative change norm(X_new - X) / norm(X_new) <=
    :data:`RELIEF_TOL` (SolverError after :data:`RELIEF_MAX_STEPS`). ``Fe`` (n x n_u):
    the load less its rigid part; ``solve``: b -> A^-1 b, A = K - shift M; ``mass``:
    X -> M X; ``project``: X -> X - R R^T M X; ``norm``: the Frobenius norm of such an
    array (on MPI ranks each holds its rows of every array and sums the norm's squares)."""
    X = np.zeros_like(Fe)
    change = np.inf
    for _ in range(RELIEF_MAX_STEPS):
        Xn = project(np.asarray(solve(Fe - shift * mass(X)), dtype=float).reshape(Fe.shape))
        change = norm(Xn - X) / max(norm(Xn), np.finfo(float).tiny)
        X = Xn
        if change <= RELIEF_TOL:
            return X
    raise SolverError(f"inertia-relief static solve did not converge ({change:.1e} after "
                      f"{RELIEF_MAX_STEPS} steps, shift {shift:.3g} rad^2/s^2)")
