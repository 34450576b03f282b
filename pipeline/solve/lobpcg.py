"""Locally optimal block preconditioned conjugate gradients (LOBPCG) for K x = w M x.

Finds the ``count`` lowest eigenpairs of the symmetric pencil (K, M) from a start block
X (n, m), m >= count, given a preconditioner T ~ (K - sigma M)^-1 (``precondition(R)``
for R (n, k) returns T R (n, k)). Every sweep:

1. residuals R = K X - M X diag(w), relative residuals
   ||K x - w M x|| / max(||K x||, |sigma| ||M x||) (the measure of
   :func:`pipeline.solve.eigen.solve_modes`);
2. corrections Z = T R for the columns not yet converged (soft locking; the guard
   columns m > count stay active, they only speed up the last wanted ones);
3. W = [Z, P] (P: the previous sweep's update directions) made M-orthogonal to X
   (classical Gram-Schmidt), then an M-orthonormal basis W C of span W by SVQB: each
   column scaled to unit M-norm, G = W^T M W = E diag(g) E^T, the directions with
   g < :data:`DROP` g_max dropped (they are linear combinations of the others: the
   instability of plain LOBPCG, where a nearly singular Gram matrix turns the
   Rayleigh-Ritz step into noise). The scaling matters: the corrections of nearly
   converged columns are orders of magnitude shorter than the others', and without it
   their directions were resolved badly or dropped, so the lowest modes stalled for 2-4
   sweeps (the cantilever at 313k DOFs: 11 sweeps to 1e-6 without, 8 with; 996k DOFs:
   10 and 7);
4. Rayleigh-Ritz of (K, M) on span[X, W C] (a (m + k) x (m + k) generalized
   eigenproblem with the explicit Gram matrix), new X from the lowest m Ritz pairs and
   P = W's part. W C and its images are never formed: the Rayleigh-Ritz blocks are
   C^T (W^T K W) C etc. from W's own blocks, and P = W (C U_w), which saves a third of a
   sweep's dense flops.

Only two sparse products per sweep (K Z and M Z): K W, M W are carried along as the
same linear combinations as W. Memory: X, K X, M X and W, K W, M W, i.e. about
9 m n doubles (3M DOFs, m = 25: 5.4 GB).

The eigenvalues and residuals are computed in double precision from K and M
themselves: the preconditioner's quality sets the number of sweeps, not the accuracy.

The dense products (Gram matrices, block updates) go to MKL's dgemm where MKL is there
(:func:`pipeline.solve.blas.gram`, :func:`~pipeline.solve.blas.times_small`), not to
numpy's OpenBLAS, which does not split the long dimension of a 25 x 25 Gram product over
the cores (1M x 25: 0.037 s against 0.050-0.065 s) and whose own thread pool then runs
beside MKL's sparse products. The cantilever at 999k DOFs (Intel Xeon, 2 cores, pairs of
runs): the modes stage 36.5 and 39.7 s -> 31.5 and 30.2 s, the same 6 sweeps.

Kept over :func:`scipy.sparse.linalg.lobpcg` (``benchmarks/bench_solvers.py``, same
matrices, start block and two-grid preconditioner, the cantilever at 100k DOFs, 20
modes; 2-core Xeon, load average 10-14 from other jobs, ratios from the same run): 8
sweeps and 17 s against scipy's 17 sweeps and 39 s (2.2x), peak 558 MB against 658 MB.
scipy stops on ||r||_2 of each M-normalised x; at the loosest tolerance whose modes agree
with the factor path's at least as well as ours (1e-2 of ||K x_1||: subspace angle 1e-9
against ours' 2e-7, frequencies 1e-10 both) it still needs twice the sweeps, since that
norm falls slowly on the mesh-scale components that the preconditioned residual here
(the target's measure) weighs by 1 / lambda. On the 2 mm thin strip (207k DOFs) ours
took 17 sweeps and 146 s, scipy's did not finish in 600 s (same run, load average 16).
At 996k DOFs (the cantilever, load average 10-16) ours takes 7 sweeps, 85 s after a
40 s set-up, 5.2 GB peak with K and M (so about 4.8M DOFs would fit 24 GiB), scipy's 15
sweeps, 221 s, 5.9 GB (2.6x). The bracket (103k): 10 sweeps, 14 s against 17, 22 s; the
slender beam (127k): 10 sweeps, 15 s against 100 sweeps without converging, 92 s (load
average 1-6).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp

from pipeline.solve.blas import (HALVES_ROWS, column_dots, column_norms, gram, in_halves,
                                 sparse_times_dense, times_small)

log = logging.getLogger(__name__)

#: relative M-norm below which a new direction counts as linearly dependent (dropped)
DROP = 1e-8
#: sweeps a two-grid preconditioned solve of the cantilever takes to 1e-6 (8-9 from
#: 25k to 313k DOFs, 7 at 996k): the progress estimate before the first sweep
EXPECTED_SWEEPS = 9
#: the first sweep whose history is used to project the sweeps still needed (the first
#: sweeps from a coarse start block drop the residual faster than the later rate)
PROJECT_FROM = 4


def projected_sweeps(history, target: float, window: int = 6) -> float:
    """Sweeps in all that the rate so far needs to bring the worst residual to ``target``.

    After s sweeps (``history[0]``: the start block), with ``best`` the smallest residual
    so far: ``s + log(target / best) / log(rate)``, where rate is the slower of the mean
    rate since the start, (best / history[0])^(1/s), and the mean rate of the last
    ``window`` sweeps (a plateau after a fast start shows there); ``inf`` when nothing
    improved, ``s`` once at the target.

    >>> round(projected_sweeps([1.0, 0.1, 0.01], 1e-6), 1)  # ten times per sweep
    6.0
    >>> round(projected_sweeps([1.0, 1e-2, 1e-2, 1e-2, 1e-3], 1e-6, window=2), 1)
    10.0
    >>> projected_sweeps([1.0, 1.0], 1e-6)
    inf
    """
    s = len(history) - 1
    best = min(history)
    if best <= target:
        return float(s)
    if s < 1 or best >= history[0]:
        return float("inf")
    rate = (best / history[0]) ** (1.0 / s)
    if s > window:
        before = min(history[:s - window + 1])
        rate = max(rate, (best / before) ** (1.0 / window))
    if rate >= 1.0:
        return float("inf")
    return s + float(np.log(target / best) / np.log(rate))


@dataclass(frozen=True)
class LobpcgResult:
    """X (n, m) M-orthonormal Ritz vectors, ascending; omega2 (m,) their Ritz values;
    residuals (m,) relative residuals; sweeps done; history: the largest residual of the
    wanted columns after every sweep (history[0]: the start block); converged: whether
    every wanted residual reached the target; seconds: wall time; abandoned: stopped early
    because the rate so far projected more than the ``budget`` sweeps."""

    X: np.ndarray
    omega2: np.ndarray
    residuals: np.ndarray
    sweeps: int
    history: tuple[float, ...]
    converged: bool
    seconds: float
    abandoned: bool = False


def _rayleigh_ritz(Kr: np.ndarray, Gr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Kr, Gr = 0.5 * (Kr + Kr.T), 0.5 * (Gr + Gr.T)
    return la.eigh(Kr, Gr)


def _columns(A: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """A[:, keep] for a boolean ``keep``: A itself when every column is kept, else
    ``np.compress`` (4x faster than boolean indexing on (n, 25) blocks)."""
    return A if keep.all() else np.compress(keep, A, axis=1)


def _update(A: np.ndarray, B: np.ndarray, C: np.ndarray, alpha: float) -> None:
    """A += alpha B @ C in place, by one BLAS product into A (no (n, k) temporary;
    :func:`pipeline.solve.blas.times_small`): almost twice as fast as A -= B @ C for a
    (1M x 50) A."""
    times_small(B, C, out=A, alpha=alpha, beta=1.0)


def _plus(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """A @ B + C in one new (n, k) array (``A @ B + C`` allocates and writes two)."""
    return times_small(A, B, out=np.array(C, dtype=np.float64, order="C"), beta=1.0)


def _combine(blocks: list[np.ndarray], C: np.ndarray) -> np.ndarray:
    """[B_1, B_2, ...] @ C for column blocks B_i (n, k_i) that are never joined into
    one array (C: (sum k_i, k)); each block's rows of C in turn, accumulated in place."""
    out = times_small(blocks[0], C[:blocks[0].shape[1]])
    start = blocks[0].shape[1]
    for B in blocks[1:]:
        _update(out, B, C[start:start + B.shape[1]], 1.0)
        start += B.shape[1]
    return out


def _gram(left: list[np.ndarray], right: list[np.ndarray],
          symmetric: bool = False) -> np.ndarray:
    """[L_1, L_2, ...]^T [R_1, R_2, ...] from the column blocks, block by block.

    ``symmetric``: the result is symmetric (W^T K W, W^T M W with R_i = A L_i for a
    symmetric A): the blocks below the diagonal are the transposes of those above,
    which saves a quarter of the products for two blocks."""
    rows = np.cumsum([0] + [a.shape[1] for a in left])
    cols = np.cumsum([0] + [b.shape[1] for b in right])
    G = np.empty((rows[-1], cols[-1]))
    for i, a in enumerate(left):
        for j, b in enumerate(right):
            if symmetric and j < i:
                G[rows[i]:rows[i + 1], cols[j]:cols[j + 1]] = \
                    G[cols[j]:cols[j + 1], rows[i]:rows[i + 1]].T
            else:
                G[rows[i]:rows[i + 1], cols[j]:cols[j + 1]] = gram(a, b)
    return G


def _one_process(partial: np.ndarray) -> np.ndarray:
    """The sum over ranks of a per-rank partial product, on one process: the product."""
    return partial


def _times(A, X: np.ndarray) -> np.ndarray:
    """A X for a sparse A, or ``A(X)`` for an operator given as a function."""
    return A(X) if callable(A) else sparse_times_dense(A, X)


def _residuals(KX, MX, w, sigma, total=_one_process):
    """R = K X - M X diag(w) (n, m) and the relative residuals (m,); ``total`` sums the
    ranks' partial column sums (rows on several ranks)."""
    R = np.empty_like(MX)

    def fill(rows: slice) -> None:  # elementwise: the same values in halves or at once
        np.multiply(MX[rows], -w, out=R[rows])
        R[rows] += KX[rows]

    if R.shape[0] >= HALVES_ROWS:
        in_halves(fill, R.shape[0])
    else:
        fill(slice(None))

    def norms(A):
        return column_norms(A) if total is _one_process else \
            np.sqrt(total(column_dots(A, A)))
    scale = np.maximum(norms(KX), abs(sigma) * norms(MX))
    return R, norms(R) / np.where(scale > 0, scale, 1.0)


def lobpcg(K: sp.spmatrix, M: sp.spmatrix, X: np.ndarray,
           precondition: Callable[[np.ndarray], np.ndarray], count: int, *,
           sigma: float = 0.0, target: float = 1e-6, max_sweeps: int = 100,
           patience: int = 8, on_sweep: Callable[[int, float], None] | None = None,
           budget: float | None = None,
           total: Callable[[np.ndarray], np.ndarray] = _one_process) -> LobpcgResult:
    """The ``count`` lowest eigenpairs of (K, M) from the start block X (n, m >= count).

    Stops when every wanted relative residual is <= ``target``, after ``max_sweeps``, or
    when the largest wanted residual has not improved by 10% within ``patience`` sweeps
    (round-off floor); the best iterate is returned with ``converged`` False unless the
    target was met. ``sigma``: the eigensolver's shift (< 0 for a free body), which
    scales rigid-body residuals. ``on_sweep(sweep, worst_residual)`` is called after
    every sweep. ``budget``: from sweep :data:`PROJECT_FROM` on, give up (``abandoned``)
    as soon as :func:`projected_sweeps` exceeds it (a caller with a faster alternative
    for a slowly converging problem; None: no projection).

    Rows on several MPI ranks (:mod:`pipeline.distributed.eigen`): X and every block
    hold this rank's rows, K and M are functions X -> K X of such blocks, and ``total``
    sums a small array over the ranks (MPI_Allreduce): every Gram matrix and column sum
    is a per-rank partial product summed by it, so every rank computes the same small
    Rayleigh-Ritz problems and takes the same steps.
    """
    t0 = time.perf_counter()
    X = np.ascontiguousarray(X, dtype=np.float64)
    n, m = X.shape
    if not 0 < count <= m:
        raise ValueError(f"count {count}: expected 1..{m} (the columns of the start block)")
    KX, MX = _times(K, X), _times(M, X)
    # Rayleigh-Ritz on span(X): ordered, exactly M-orthonormal
    w, B = _rayleigh_ritz(total(gram(X, KX)), total(gram(X, MX)))
    X, KX, MX = times_small(X, B), times_small(KX, B), times_small(MX, B)
    P = KP = MP = None
    history: list[float] = []
    best: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None
    rho = np.full(m, np.inf)
    floor = max(abs(sigma), np.finfo(float).tiny)
    sweeps = 0
    while True:
        R, res = _residuals(KX, MX, w, sigma, total)
        active = rho > target  # soft locking: converged columns get no new directions
        active[count:] = True  # guard columns keep helping the last wanted ones
        R = _columns(R, active)
        Z = np.asarray(precondition(R), dtype=np.float64).reshape(n, -1)
        rho[active] = np.sqrt(np.abs(total(column_dots(R, Z)))
                              / np.maximum(np.abs(w[active]), floor))
        del R
        worst = float(rho[:count].max())
        history.append(worst)
        log.debug("sweep %d: worst rho %.1e, residuals %s", sweeps, worst,
                  " ".join(f"{r:.0e}" for r in res[:count]))
        if best is None or worst < best[0]:
            # X, w and res are rebound to new arrays every sweep, never written in place:
            # the best iterate is kept by reference (a copy of X cost 0.1 s a sweep at 1M)
            best = (worst, X, w, res)
        if on_sweep is not None and sweeps:
            on_sweep(sweeps, worst)
        stalled = (len(history) > patience
                   and min(history[-patience:]) > 0.9 * min(history[:-patience]))
        abandoned = (budget is not None and sweeps >= PROJECT_FROM and worst > target
                     and projected_sweeps(history, target) > budget)
        if worst <= target or sweeps >= max_sweeps or stalled or abandoned:
            break
        sweeps += 1
        again = rho[active] > target
        again[np.flatnonzero(active) >= count] = True
        Z = _columns(Z, again)
        active[np.flatnonzero(active)[~again]] = False
        KZ, MZ = _times(K, Z), _times(M, Z)
        # W = [Z, P] and its images, kept as column blocks (joining them would write
        # three (n, 2m) arrays a sweep, a seventh of the sweep's time at 1M DOFs)
        if P is not None:
            W = [Z, _columns(P, active)]
            KW = [KZ, _columns(KP, active)]
            MW = [MZ, _columns(MP, active)]
        else:
            W, KW, MW = [Z], [KZ], [MZ]
        del Z, KZ, MZ, P, KP, MP
        # W -= X (X^T M W): M-orthogonal to X, the images alike (one classical
        # Gram-Schmidt pass; what it leaves is handled by the explicit Gram matrix below)
        for Wb, KWb, MWb in zip(W, KW, MW):
            C = total(gram(MX, Wb))
            _update(Wb, X, C, -1.0)
            _update(KWb, KX, C, -1.0)
            _update(MWb, MX, C, -1.0)
        del Wb, KWb, MWb
        # the M-orthonormal basis W C of span W (C from W's Gram matrix, SVQB), never
        # formed: its Rayleigh-Ritz blocks are C^T (W^T K W) C etc., from products of
        # W's own blocks (forming W C and its images cost a third of a sweep's flops)
        G = total(_gram(W, MW, symmetric=True))
        G = 0.5 * (G + G.T)
        scale = 1.0 / np.sqrt(np.maximum(np.diag(G), np.finfo(float).tiny))
        g, E = np.linalg.eigh(G * scale[:, None] * scale[None, :])
        keep = g > DROP * max(g[-1], np.finfo(float).tiny)
        C = scale[:, None] * E[:, keep] / np.sqrt(g[keep])
        k = C.shape[1]
        Kr = np.empty((m + k, m + k))
        Gr = np.empty((m + k, m + k))
        # computed, not taken as diag(w) and I from the last Rayleigh-Ritz step: that
        # step's round-off is eps times the largest Ritz value of [X, W C] (W's
        # unconverged directions), and carried from sweep to sweep it grew to 2e-10 in
        # the lowest eigenvalue after 400 Jacobi-preconditioned sweeps of a 1D pencil
        # (8e-12 computed)
        Kr[:m, :m], Gr[:m, :m] = total(gram(X, KX)), total(gram(X, MX))
        Kr[:m, m:] = total(_gram([X], KW)) @ C
        Gr[:m, m:] = total(_gram([X], MW)) @ C
        Kr[m:, m:] = C.T @ total(_gram(W, KW, symmetric=True)) @ C
        Gr[m:, m:] = C.T @ G @ C
        Kr[m:, :m], Gr[m:, :m] = Kr[:m, m:].T, Gr[:m, m:].T
        w, U = _rayleigh_ritz(Kr, Gr)
        w, Bx, Bw = w[:m], U[:m, :m], C @ U[m:, :m]
        P, KP, MP = _combine(W, Bw), _combine(KW, Bw), _combine(MW, Bw)
        del W, KW, MW
        X, KX, MX = _plus(X, Bx, P), _plus(KX, Bx, KP), _plus(MX, Bx, MP)
    _, X, w, res = best
    return LobpcgResult(X=X, omega2=w, residuals=res, sweeps=sweeps, history=tuple(history),
                        converged=bool(history and min(history) <= target),
                        seconds=time.perf_counter() - t0, abandoned=abandoned)
