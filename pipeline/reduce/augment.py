"""The augmented basis of ``static_correction: augment``: the Ritz basis of span[Phi, X].

Phi (n_s x n_m) are the retained M-orthonormal modes and X = K^-1 F (n_s x n_u) the
static shapes. Each static shape is M-orthogonalised against Phi and the shapes kept
before it (classical Gram-Schmidt, applied twice for round-off); a shape left with less
than :data:`AUGMENT_DROP_TOL` of its M-norm is dependent and dropped with a warning. The
basis V = [Phi, kept] (n_s x n_b) then gives the projected pencil K_r = V^T K V,
M_r = V^T M V (n_b x n_b), K_r Z = M_r Z diag(omega^2), and the Ritz basis Psi = V Z
(M-orthonormal, ascending omega^2 in rad^2/s^2), each column signed so that its largest
coefficient in Z is positive.

The steps are written once for any block of columns that offers ``gram`` (B^T C, the
same on every process), ``times`` (B Q for a small Q), ``like`` (a block of the same
rows) and ``local`` (its rows here, (n_rows, k)): :class:`Columns` wraps a whole numpy
array (one process), :class:`pipeline.distributed.blocks.RowBlock` holds one rank's rows
(the same basis on N ranks). ``apply_K`` / ``apply_M`` map a block to its image.

>>> import scipy.sparse as sp
>>> K, M = sp.diags([1.0, 4.0, 9.0]).tocsr(), sp.identity(3, format="csr")
>>> Phi = Columns(np.eye(3)[:, :1])          # the lowest mode, omega^2 = 1
>>> X = Columns(np.array([[1.0], [0.25], [0.0]]))  # K^-1 of a load on DOFs 1 and 2
>>> w2, Psi, n_kept = augmented_basis(lambda B: B.like(K @ B.local),
...                                   lambda B: B.like(M @ B.local), Phi, X, ["f"])
>>> n_kept, w2.round(6).tolist()
(1, [1.0, 4.0])
"""

from __future__ import annotations

import logging
import math
from typing import Callable, Sequence

import numpy as np
import scipy.linalg as sla

from pipeline.errors import SolverError

log = logging.getLogger(__name__)

#: A static shape whose M-norm falls below this fraction of its initial M-norm after
#: M-orthogonalisation against the basis is numerically dependent and dropped.
AUGMENT_DROP_TOL = 1e-8


class Columns:
    """A whole (n, k) numpy block with the interface :func:`augmented_basis` uses."""

    def __init__(self, local: np.ndarray):
        self.local = np.asarray(local, dtype=np.float64)

    @property
    def shape(self) -> tuple[int, int]:
        return self.local.shape

    def like(self, local: np.ndarray) -> "Columns":
        return Columns(local)

    def times(self, Q: np.ndarray) -> "Columns":
        return Columns(self.local @ np.asarray(Q, dtype=np.float64))

    def gram(self, other: "Columns") -> np.ndarray:
        return self.local.T @ other.local


def augmented_basis(apply_K: Callable, apply_M: Callable, Phi, X,
                    input_names: Sequence[str]):
    """(omega2 (n_b,), Psi (block, n_s x n_b, M-orthonormal), number of static shapes
    kept) for the blocks ``Phi`` (n_s x n_m) and ``X`` (n_s x n_u) (module doc);
    SolverError when the projected eigenproblem fails."""
    kept = []
    for j in range(X.shape[1]):
        x = X.like(X.local[:, j:j + 1].copy())
        norm0 = math.sqrt(max(float(x.gram(apply_M(x))[0, 0]), 0.0))
        if norm0 == 0.0:
            log.warning("static correction augment: input %r produces no static deflection; "
                        "its static shape is not added", input_names[j])
            continue
        for _ in range(2):
            x = x.like(x.local - Phi.times(Phi.gram(apply_M(x))).local)
            for q in kept:
                x = x.like(x.local - q.local * float(q.gram(apply_M(x))[0, 0]))
        norm = math.sqrt(max(float(x.gram(apply_M(x))[0, 0]), 0.0))
        if norm <= AUGMENT_DROP_TOL * norm0:
            log.warning("static correction augment: the static shape of input %r is "
                        "numerically dependent on the basis (%.2e of its M-norm left); "
                        "dropped", input_names[j], norm / norm0)
            continue
        kept.append(x.like(x.local / norm))
    V = Phi.like(np.hstack([Phi.local] + [q.local for q in kept])) if kept else Phi
    Kr, Mr = V.gram(apply_K(V)), V.gram(apply_M(V))
    try:
        w2, Z = sla.eigh(0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T))
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise SolverError(f"projected eigenproblem of the augmented basis failed: {exc}") from exc
    # each column's sign fixed by its largest coefficient (eigh's is arbitrary, and would
    # flip with round-off): a retained mode keeps its own sign, and N ranks give the
    # serial basis
    largest = Z[np.argmax(np.abs(Z), axis=0), np.arange(Z.shape[1])]
    Z = Z * np.where(largest < 0, -1.0, 1.0)
    return w2, V.times(Z), len(kept)


def augment(apply_K: Callable, apply_M: Callable, Phi, X, input_names: Sequence[str],
            omega2_retained: np.ndarray):
    """:func:`augmented_basis` and what it did, logged: (omega2 (n_b,), Psi (block)).
    ``omega2_retained`` (n_m,): Phi's own omega^2; a Ritz value of the augmented basis
    more than 1e-6 below its mode's means the modes were not converged (a warning)."""
    w2, Psi, n_kept = augmented_basis(apply_K, apply_M, Phi, X, input_names)
    n_modes = len(omega2_retained)
    w2_r = np.asarray(omega2_retained, dtype=float)
    if np.any(np.abs(w2[:n_modes] - w2_r) > 1e-6 * np.abs(w2_r)):
        log.warning("augmented basis moved a retained frequency by more than 1e-6 "
                    "relative (max %.3g); are the modes converged?",
                    float(np.max(np.abs(w2[:n_modes] / w2_r - 1))))
    extra_hz = np.sqrt(np.maximum(w2[n_modes:], 0.0)) / (2 * math.pi)
    log.info("augmented basis: %d modes + %d static shapes; extra Ritz frequencies %s Hz",
             n_modes, n_kept, np.array2string(extra_hz, precision=1))
    return w2, Psi
