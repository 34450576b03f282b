"""How accurate a set of computed modes is, measured from K and M themselves.

For eigenpairs (omega_k^2, x_k) of K x = omega^2 M x (K, M (n x n), X (n, m)):

- the relative residual, in the Euclidean norm,

      res_k = ||K x_k - omega_k^2 M x_k||_2 / ||K x_k||_2

  (:func:`relative_residuals`). It is what a reader computes by hand, and it is NOT a
  mesh-independent measure of a mode's error: K amplifies an error component of
  eigenvalue lambda by lambda / omega_k^2, so an error of size e in the mesh-scale
  components of a mode leaves a residual of about e lambda / omega_k^2. The factor
  path's modes are exact to round-off in those components (its residual is the floor
  ~eps ||K|| ||x|| / ||K x||: 3e-8 on the cantilever at 101k DOFs); LOBPCG stops on
  the residual in the preconditioner's (energy-dual) norm, which weighs those
  components by 1 / lambda, so its modes leave a larger Euclidean residual (1.6e-3 at
  101k DOFs, 6.1e-3 at 1M) while their frequencies agree with the factor path's to
  7e-11 (101k) and their shapes to a subspace angle of 3e-8 (1M);
- the normwise backward error (Higham and Higham 1998, for the pencil (K, M)),

      eta_k = ||K x_k - omega_k^2 M x_k||_inf
              / ((||K||_inf + omega_k^2 ||M||_inf) ||x_k||_inf)

  (:func:`backward_errors`): the smallest relative perturbation of K and M of which
  the pair is exact; O(eps) for a backward-stable solve;
- the agreement of two solutions of the same pencil: the largest relative frequency
  difference (:func:`frequency_difference`) and the largest principal angle between
  the spans of their mode shapes in the M inner product (:func:`largest_subspace_angle`),
  computed from its sine, which keeps angles down to 1e-16 (an angle from the cosine
  rounds everything below ~1e-8 to zero).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp

from pipeline.solve.blas import column_norms, scaled_inf_norm, sparse_times_dense


def relative_residuals(K: sp.spmatrix, M: sp.spmatrix, X: np.ndarray,
                       omega2: np.ndarray) -> np.ndarray:
    """(m,) ||K x_k - omega2_k M x_k||_2 / ||K x_k||_2 for X (n, m), omega2 (m,) in
    rad^2/s^2 (a column with K x_k = 0, a rigid-body mode, is measured against
    ||omega2_k M x_k|| instead, and 0 when both vanish).

    >>> K, M = sp.diags([2.0, 8.0]).tocsr(), sp.identity(2, format="csr")
    >>> relative_residuals(K, M, np.eye(2), np.array([2.0, 7.2])).round(3)
    array([0. , 0.1])
    """
    _, KX, MX = _images(K, M, X, omega2)
    scale = column_norms(KX)
    scale = np.where(scale > 0, scale, column_norms(MX))
    KX -= MX
    return column_norms(KX) / np.where(scale > 0, scale, 1.0)


def _images(K, M, X, omega2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(X, K X, M X diag(omega2)), X as a C-contiguous float64 (n, m) block."""
    X = np.ascontiguousarray(X, dtype=np.float64).reshape(K.shape[0], -1)
    MX = sparse_times_dense(M, X)
    MX *= np.asarray(omega2, dtype=np.float64)
    return X, sparse_times_dense(K, X), MX


def backward_errors(K: sp.spmatrix, M: sp.spmatrix, X: np.ndarray,
                    omega2: np.ndarray) -> np.ndarray:
    """(m,) normwise backward errors of the eigenpairs (module doc): dimensionless.

    >>> K, M = sp.diags([2.0, 8.0]).tocsr(), sp.identity(2, format="csr")
    >>> backward_errors(K, M, np.eye(2), np.array([2.0, 7.2])).round(4)
    array([0.    , 0.0526])
    """
    X, R, MX = _images(K, M, X, omega2)
    R -= MX
    omega2 = np.asarray(omega2, dtype=np.float64)
    denom = ((scaled_inf_norm(K) + np.abs(omega2) * scaled_inf_norm(M))
             * np.abs(X).max(axis=0))
    return np.abs(R).max(axis=0) / np.where(denom > 0, denom, 1.0)


def frequency_difference(f: np.ndarray, f_ref: np.ndarray) -> float:
    """max_k |f_k / f_ref_k - 1| over the common modes (a zero reference frequency, a
    rigid-body mode, compares |f_k| against the largest reference frequency)."""
    n = min(len(f), len(f_ref))
    f = np.asarray(f[:n], dtype=np.float64)
    f_ref = np.asarray(f_ref[:n], dtype=np.float64)
    scale = np.where(f_ref != 0, np.abs(f_ref), np.abs(f_ref).max() or 1.0)
    return float(np.max(np.abs(f - f_ref) / scale)) if n else 0.0


def _m_orthonormal(X: np.ndarray, M: sp.spmatrix | None) -> np.ndarray:
    """A basis of span X (n, m) orthonormal in the M inner product (Cholesky of the Gram
    matrix; M None: the Euclidean one)."""
    MX = X if M is None else sparse_times_dense(M, X)
    G = X.T @ MX
    L = la.cholesky(0.5 * (G + G.T), lower=True)
    return la.solve_triangular(L, X.T, lower=True).T


def largest_subspace_angle(X: np.ndarray, Y: np.ndarray,
                           M: sp.spmatrix | None = None) -> float:
    """The largest principal angle (radians) between span X and span Y (both (n, m),
    full column rank) in the M inner product (None: Euclidean).

    sin(theta_max) = max over unit x in span X of ||x - Q Q^T M x||_M, Q an
    M-orthonormal basis of span Y: the square root of the largest eigenvalue of
    R^T M R, R = Qx - Q (Q^T M Qx).

    >>> X = np.eye(3)[:, :1]
    >>> Y = np.array([[np.cos(1e-9)], [np.sin(1e-9)], [0.0]])
    >>> round(largest_subspace_angle(X, Y) / 1e-9, 6)
    1.0
    """
    X = np.ascontiguousarray(X, dtype=np.float64)
    Y = np.ascontiguousarray(Y, dtype=np.float64)
    if X.shape != Y.shape:
        raise ValueError(f"shapes {X.shape} and {Y.shape}: expected equal (n, m)")
    Qx, Qy = _m_orthonormal(X, M), _m_orthonormal(Y, M)
    MQy = Qy if M is None else sparse_times_dense(M, Qy)
    R = Qx - Qy @ (MQy.T @ Qx)
    MR = R if M is None else sparse_times_dense(M, R)
    G = R.T @ MR
    s2 = float(np.linalg.eigvalsh(0.5 * (G + G.T))[-1])
    return float(np.arcsin(min(1.0, np.sqrt(max(s2, 0.0)))))
