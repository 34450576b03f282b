"""LOBPCG in batches of modes, for bodies whose full LOBPCG block does not fit in memory.

LOBPCG (:mod:`pipeline.solve.lobpcg`) holds about LOBPCG_BLOCKS blocks of (n x m)
doubles for a block of m = count + guard columns (X, K X, M X, the search directions W
and their images, the new P and its images, the best iterate, the preconditioner's
work): at 5.5M DOFs and m = 23 that is 13 GB, more than what is left beside K, M and the
coarse factor on a 24 GB machine. Solved in batches of b modes (plus g guard columns),
batch j finds the lowest b modes of (K, M) restricted to the M-orthogonal complement of
the Y (n x c) modes found before it:

    Z = (I - Y (M Y)^T) T R          every correction the preconditioner T returns,

and its start block is made M-orthogonal to Y the same way. Every search direction of
LOBPCG is then M-orthogonal to Y (the update directions are linear combinations of
earlier corrections, and the Rayleigh-Ritz step combines X and those), so its Ritz
pairs are the eigenpairs of the pencil on that complement: the modes c+1, ... of the
whole pencil, to the accuracy of Y. An error e in a converged Y changes the next modes
by O(e^2) of the eigenvalue gap (a Rayleigh quotient), far below the tolerance.

Memory: LOBPCG_BLOCKS * 8 n (b + g) bytes of LOBPCG and 2 * 8 n c of Y and M Y (the
last batch has c = count - b). Time: each batch sweeps about as often as one wide
block (the guard columns keep the gap to the next mode), so the sparse products cost
about the same per mode, plus the projection (two (n x c) by (n x k) products a sweep).
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np
import scipy.sparse as sp

from pipeline.solve import lobpcg
from pipeline.solve.blas import sparse_times_dense

log = logging.getLogger(__name__)


def _deflate(Z: np.ndarray, found: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Z - Y (M Y)^T Z in place for every (Y, M Y) of ``found`` (Z (n, k), Y (n, c)):
    M-orthogonal to the modes found so far."""
    for Y, MY in found:
        lobpcg._update(Z, Y, MY.T @ Z, -1.0)
    return Z


def _worst(histories: list[tuple[float, ...]]) -> tuple[float, ...]:
    """The largest residual over the batches after every sweep (a batch that stopped
    earlier counts with its last value)."""
    length = max(len(h) for h in histories)
    return tuple(max(h[min(i, len(h) - 1)] for h in histories) for i in range(length))


def batched_lobpcg(K: sp.spmatrix, M: sp.spmatrix, start: Callable[[int, int], np.ndarray],
                   precondition: Callable[[np.ndarray], np.ndarray], count: int, batch: int,
                   guard: int, **options) -> lobpcg.LobpcgResult:
    """The ``count`` lowest eigenpairs of (K, M) by :func:`pipeline.solve.lobpcg.lobpcg`
    in batches of ``batch`` modes with ``guard`` guard columns each (module doc).

    ``start(i, j)``: the start block (n, j - i) for modes i..j-1 (columns of the coarse
    modes, prolonged). ``options``: passed to each LOBPCG call (``sigma``, ``target``,
    ``max_sweeps``, ``on_sweep``, ``budget``). Returns one result: X (n, count) the modes
    of all batches, their Ritz values and residuals, the sweeps summed, the history the
    worst batch's after every sweep (:func:`_worst`), converged when every batch
    converged, abandoned (and only the batches so far) when one was.
    """
    if batch >= count:
        return lobpcg.lobpcg(K, M, start(0, count + guard), precondition, count, **options)
    found: list[tuple[np.ndarray, np.ndarray]] = []
    omega2, residuals, histories = [], [], []
    sweeps, seconds, converged, abandoned = 0, 0.0, True, False
    for first in range(0, count, batch):
        wanted = min(batch, count - first)
        X0 = _deflate(np.ascontiguousarray(start(first, first + wanted + guard)), found)

        def deflated(R: np.ndarray) -> np.ndarray:
            Z = np.asarray(precondition(R), dtype=np.float64).reshape(R.shape[0], -1)
            return _deflate(np.ascontiguousarray(Z), found)

        result = lobpcg.lobpcg(K, M, X0, deflated, wanted, **options)
        del X0
        log.info("LOBPCG batch of modes %d-%d: %d sweeps, %.1f s", first + 1, first + wanted,
                 result.sweeps, result.seconds)
        sweeps += result.sweeps
        seconds += result.seconds
        histories.append(result.history)
        converged = converged and result.converged
        abandoned = abandoned or result.abandoned
        Y = np.ascontiguousarray(result.X[:, :wanted])
        omega2.append(result.omega2[:wanted])
        residuals.append(result.residuals[:wanted])
        del result
        found.append((Y, sparse_times_dense(M, Y)))
        del Y
        if abandoned:
            break
    X = np.hstack([Y for Y, _ in found])
    found.clear()
    return lobpcg.LobpcgResult(X=X, omega2=np.concatenate(omega2),
                               residuals=np.concatenate(residuals), sweeps=sweeps,
                               history=_worst(histories), converged=converged,
                               seconds=seconds, abandoned=abandoned)
