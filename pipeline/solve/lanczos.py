"""Block Lanczos for the largest eigenpairs of a symmetric operator.

Full re-orthogonalisation (:func:`_orthogonalise`: a local pass, then one against the
whole basis, repeated when it is not enough) and thick restarts; the operator is applied
to a block of vectors at a time (for shift-invert, one pass over the factor per block
instead of one per vector: :mod:`pipeline.solve.eigen`).
"""

from __future__ import annotations

import logging

import numpy as np

from pipeline.errors import SolverError

log = logging.getLogger(__name__)


def _orthonormal_block(W: np.ndarray, basis: np.ndarray, rng, scale: float):
    """Orthonormal rows V spanning the rows of W (k, n), already orthogonal to ``basis``.

    Returns (V, B) with W = B^T V. A well-conditioned W (smallest singular value above
    1e-6 of the largest and of ``scale``) goes through Cholesky QR twice: two (k x k) Gram matrices and two
    thin products, where an SVD of the (n x k) block costs several passes over it. Else
    the SVD: directions of W below round-off of ``scale`` are replaced by random
    vectors orthogonal to ``basis`` (rows) and to the rest (their coupling row is 0).
    """
    s2, E = np.linalg.eigh(W @ W.T)
    if s2[-1] > 0.0 and np.sqrt(max(s2[0], 0.0)) > 1e-6 * max(np.sqrt(s2[-1]), scale):
        s = np.sqrt(s2)
        V = (E.T @ W) / s[:, None]
        B = s[:, None] * E.T
        L = np.linalg.cholesky(V @ V.T)  # = I + O(cond^2 eps): one more pass fixes it
        V = np.linalg.inv(L) @ V
        return V, L.T @ B
    U, s, Vt = np.linalg.svd(W.T, full_matrices=False)  # W^T = U s Vt
    V = np.ascontiguousarray(U.T)
    B = s[:, None] * Vt
    small = s <= 1e-12 * scale
    if small.any():
        good = V[~small]
        R = rng.standard_normal((int(small.sum()), W.shape[1]))
        for _ in range(2):
            for Q in (basis, good):
                R -= (R @ Q.T) @ Q
        Ur, _, _ = np.linalg.svd(R.T, full_matrices=False)
        V[small] = Ur.T
        B[small] = 0.0
    return V, B


#: a full Gram-Schmidt pass that leaves less than this fraction of a row's norm is
#: repeated (Daniel, Gragg, Kaufman and Stewart's criterion, 1/sqrt(2))
REORTHOGONALISE_BELOW = 0.7071


def _orthogonalise(W: np.ndarray, basis: np.ndarray, H: np.ndarray, near: int, lo: int,
                   hi: int) -> None:
    """Orthogonalise the rows of W = S V (k, n) against ``basis[:hi]`` in place and add
    the projection coefficients to ``H[:hi, lo:hi]``.

    In exact arithmetic the block recurrence S V_j = V_{j-1} B_{j-1}^T + V_j A_j +
    V_{j+1} B_j couples W only to the previous block and to V_j itself (rows
    ``near:hi``; after a thick restart, to every kept Ritz vector too: ``near`` = 0).
    A first classical Gram-Schmidt pass against those rows removes the large
    components; one pass against the whole basis then removes what round-off left
    along the older rows (full re-orthogonalisation). That is two passes over the
    basis per step instead of four for CGS twice against all of it, with the same
    orthogonality: the full pass is repeated when it removes much of a row (the norm
    falls below :data:`REORTHOGONALISE_BELOW` of what it was), which is when one pass
    is not enough.
    """
    if near > 0:
        Qn = basis[near:hi]
        C = Qn @ W.T  # (hi - near, k)
        H[near:hi, lo:hi] += C
        W -= C.T @ Qn
    Q = basis[:hi]
    before = np.einsum("ij,ij->i", W, W)  # squared row norms
    for _ in range(2):
        C = Q @ W.T  # (hi, k)
        H[:hi, lo:hi] += C
        W -= C.T @ Q
        # Q has orthonormal rows: what is left of a row's squared norm is what it was
        # less the squared coefficients removed (no further pass over W)
        left = before - np.einsum("ij,ij->j", C, C)
        if np.all(left >= REORTHOGONALISE_BELOW ** 2 * before):
            break
        before = np.einsum("ij,ij->i", W, W)


def block_lanczos(op, n: int, count: int, b: int, tol: float, max_basis: int,
                  seed: int = 12345, max_restarts: int = 50, with_images: bool = False,
                  converge: int | None = None):
    """The ``count`` largest eigenpairs of the symmetric operator ``op`` (n x n).

    ``op(Y)`` applies the operator to the rows of Y (k, n). Block Lanczos with full
    re-orthogonalisation (:func:`_orthogonalise`); the projected matrix is built from the
    projection coefficients themselves, which makes thick restarts (keep the best Ritz vectors,
    continue from the residual block) exact. The basis lives in one preallocated
    (max_basis + b, n) array, so each projection is one matrix product.
    Returns (Y (count, n) orthonormal Ritz vectors, theta (count,), steps, restarts).

    ``with_images``: ``op`` returns (S Y, Z) where Z (k, n) is some linear image of the
    rows of Y (for the shift-invert operator: F^-T Y); the same combinations of the
    images as of the basis are returned as a fifth item (count, n).

    ``converge``: how many of the leading pairs must meet ``tol`` (None: all ``count``);
    the others are returned as the basis has them (a start block's guard columns, which
    only need to point the right way).
    """
    rng = np.random.default_rng(seed)
    cap = max_basis + b
    basis = np.empty((cap, n))  # pages are touched only as rows are filled
    images = np.empty((cap, n)) if with_images else None
    V, _ = _orthonormal_block(rng.standard_normal((b, n)), basis[:0], rng, 1.0)
    size = 0  # rows in basis
    near = 0  # first row of the previous block (0 on the first step and after a restart)
    H = np.zeros((cap, cap))
    steps = restarts = 0
    scale = 0.0
    while True:
        lo, hi = size, size + V.shape[0]
        near = min(near, lo)  # first row of the blocks S V is coupled to (see _orthogonalise)
        basis[lo:hi] = V
        size = hi
        out = op(V)
        if with_images:
            W, images[lo:hi] = out
        else:
            W = out
        W = np.array(W, dtype=np.float64)  # own copy: modified in place below
        del out
        steps += 1
        scale = max(scale, float(np.sqrt(np.einsum("ij,ij->i", W, W).max())))  # no temporary
        Q = basis[:hi]
        _orthogonalise(W, basis, H, near, lo, hi)
        Hs = np.triu(H[:hi, :hi])
        Hs = Hs + np.triu(Hs, 1).T
        theta, U = np.linalg.eigh(Hs)
        theta, U = theta[::-1], U[:, ::-1]  # largest first
        V, B = _orthonormal_block(W, Q, rng, scale)
        del W
        want = min(count, hi)
        resid = np.linalg.norm(B @ U[lo:hi, :want], axis=0)
        need = count if converge is None else min(converge, count)
        converged = want == count and bool(
            np.all(resid[:need] <= tol * np.abs(theta[:need])))
        if converged or hi >= n - b:
            if want < count:
                raise SolverError(f"block Lanczos: the Krylov space of this {n}-DOF problem "
                                  f"holds only {want} of the {count} modes asked for")
            Ut = np.ascontiguousarray(U[:, :count].T)
            Y = Ut @ Q
            if with_images:
                return Y, theta[:count], steps, restarts, Ut @ images[:hi]
            return Y, theta[:count], steps, restarts
        near = lo
        if hi + V.shape[0] > max_basis:
            if restarts >= max_restarts:
                worst = float(np.max(resid[:need] / np.abs(theta[:need])))
                raise SolverError(f"block Lanczos did not converge for {count} modes in "
                                  f"{steps} steps (worst relative residual {worst:.1e}, "
                                  f"tolerance {tol:.1e}); try a smaller modes.count or a "
                                  "larger modes.tolerance")
            keep = min(hi - V.shape[0], max(count + V.shape[0], max_basis // 2))
            Ut = np.ascontiguousarray(U[:, :keep].T)
            basis[:keep] = Ut @ Q
            if with_images:
                images[:keep] = Ut @ images[:hi]
            H[:] = 0.0
            H[np.arange(keep), np.arange(keep)] = theta[:keep]
            # H[:keep, keep:] (the coupling B U_last of V to the kept vectors) is found
            # again by the next step's projections
            size = keep
            near = 0  # the residual block is coupled to every kept Ritz vector
            restarts += 1
            log.debug("block Lanczos: restart %d after %d steps, kept %d", restarts, steps,
                      keep)
