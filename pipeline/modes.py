"""Modes stage: the lowest eigenpairs of K phi = omega^2 M phi.

scipy's ``eigsh`` in shift-invert mode, with the shifted matrix factorised once by
:mod:`pipeline.solvers`. The Ritz vectors are then re-orthonormalised by a small
dense Rayleigh-Ritz step, so that Phi^T M Phi = I and Phi^T K Phi = diag(omega^2)
hold to round-off even for repeated frequencies.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .errors import SolverError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ModeSet:
    """Modes of the constrained body.

    omega2: (n_m,) rad^2/s^2, ascending (rigid modes clipped to >= 0).
    frequencies_hz: (n_m,) Hz.
    shapes: (n_free, n_m) M-orthonormal mode shapes on the free DOFs.
    residuals: (n_m,) ||K phi - omega^2 M phi|| / ||K phi|| (rigid: / ||M phi|| |shift|).
    n_rigid: number of zero-frequency (rigid-body) modes found.
    backend: the factorisation used; shift: the eigsh shift sigma (rad^2/s^2).
    """

    omega2: np.ndarray
    frequencies_hz: np.ndarray
    shapes: np.ndarray
    residuals: np.ndarray
    n_rigid: int
    backend: str
    shift: float
    seconds: float


def default_shift(K: sp.spmatrix, M: sp.spmatrix, supported: bool) -> float:
    """eigsh shift: 0 for a supported body, a small negative value for a free one.

    For a free body K is singular; K - sigma M with sigma < 0 is positive definite.
    |sigma| is 1e-7 of the median diagonal ratio K_ii / M_ii (a stiffness scale of
    the finest element), far below any elastic eigenvalue of the meshes we solve and far
    above round-off of the rigid-body modes.
    """
    if supported:
        return 0.0
    ratio = np.median(K.diagonal() / M.diagonal())
    return -1e-7 * float(ratio)


def solve_modes(K: sp.spmatrix, M: sp.spmatrix, count: int, *, supported: bool = True,
                backend: str = "auto", tolerance: float = 0.0, shift: float | None = None,
                progress=None) -> ModeSet:
    """The ``count`` lowest modes of (K, M), both (n x n) on the free DOFs.

    ``supported``: False for a free body (then the shift is negative, see
    :func:`default_shift`). ``progress``, if given, is called once per operator solve.
    """
    from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, eigsh

    from .solvers import factorize

    t0 = time.perf_counter()
    n = K.shape[0]
    if count >= n - 1:
        raise SolverError(f"config key 'modes.count': got {count}, expected fewer than the "
                          f"{n - 1} free degrees of freedom of this mesh (refine the mesh)")
    sigma = default_shift(K, M, supported) if shift is None else float(shift)
    shifted = K - sigma * M if sigma != 0.0 else K
    fact = factorize(shifted, backend, positive_definite=True)
    del shifted
    log.info("factorised %d DOFs with %s in %.2f s (shift %.3g)", n, fact.backend,
             time.perf_counter() - t0, sigma)

    def apply(b):
        if progress is not None:
            progress(1)
        return fact.solve(b)

    op = LinearOperator((n, n), matvec=apply, dtype=np.float64)
    ncv = min(n, max(2 * count + 1, count + 20))
    rng = np.random.default_rng(12345)
    v0 = rng.standard_normal(n)
    try:
        w, v = eigsh(K, k=count, M=M, sigma=sigma, which="LM", OPinv=op, tol=tolerance, ncv=ncv,
                     v0=v0, maxiter=max(1000, 10 * n // ncv))
    except ArpackNoConvergence as exc:
        raise SolverError(f"eigsh did not converge for {count} modes (converged: "
                          f"{len(exc.eigenvalues)}); try a smaller modes.count or a finer "
                          "modes.tolerance") from None
    finally:
        fact.release()
    # Rayleigh-Ritz: exact M-orthonormality and diagonal K in the computed subspace
    Kv, Mv = K @ v, M @ v
    Kr, Mr = v.T @ Kv, v.T @ Mv
    Kr, Mr = 0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T)
    from scipy.linalg import eigh

    w, Q = eigh(Kr, Mr)
    v = v @ Q
    Kv, Mv = Kv @ Q, Mv @ Q
    order = np.argsort(w)
    w, v, Kv, Mv = w[order], v[:, order], Kv[:, order], Mv[:, order]
    # sign convention: the largest-magnitude entry of every mode is positive
    idx = np.abs(v).argmax(axis=0)
    signs = np.sign(v[idx, np.arange(v.shape[1])])
    v, Kv, Mv = v * signs, Kv * signs, Mv * signs
    scale = np.maximum(np.linalg.norm(Kv, axis=0), abs(sigma) * np.linalg.norm(Mv, axis=0))
    residuals = np.linalg.norm(Kv - Mv * w, axis=0) / np.where(scale > 0, scale, 1.0)
    rigid = np.zeros(w.size, dtype=bool)
    if not supported:
        rigid = np.abs(w) < 1e-6 * abs(sigma)
    w = np.where(rigid, 0.0, w)
    if (w < 0).any():
        raise SolverError(f"negative eigenvalue {w.min():.3e} rad^2/s^2: the stiffness matrix is "
                          "indefinite; check the material (E > 0, -1 < nu < 0.5)")
    seconds = time.perf_counter() - t0
    return ModeSet(omega2=w, frequencies_hz=np.sqrt(w) / (2 * np.pi), shapes=v,
                   residuals=residuals, n_rigid=int(rigid.sum()), backend=fact.backend,
                   shift=sigma, seconds=seconds)
