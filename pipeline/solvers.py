"""Sparse symmetric factorisations behind eigsh's shift-invert operator.

A backend factorises a symmetric matrix once and then solves many right-hand sides
with that one factorisation. ``auto`` picks the fastest installed backend:
MKL PARDISO (through pypardiso's library handle, symmetric positive-definite or
symmetric indefinite type, upper triangle only), else SuperLU with the
``MMD_AT_PLUS_A`` ordering.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp

from .errors import ConfigError, SolverError

log = logging.getLogger(__name__)

BACKENDS = ("pardiso", "superlu")


def available_backends() -> list[str]:
    """Installed backends, fastest first."""
    found = []
    try:
        import pypardiso  # noqa: F401

        found.append("pardiso")
    except Exception:  # ImportError, or MKL failing to load
        pass
    found.append("superlu")
    return found


@dataclass
class Factorization:
    """A factorised symmetric matrix: ``solve(b)`` with b (n,) or (n, k)."""

    solve: Callable[[np.ndarray], np.ndarray]
    backend: str
    n: int
    release: Callable[[], None] = lambda: None


def _pardiso(A: sp.csr_matrix, positive_definite: bool) -> Factorization:
    import pypardiso

    upper = sp.triu(A, format="csr")
    upper.sort_indices()
    solver = pypardiso.PyPardisoSolver(mtype=2 if positive_definite else -2)
    solver.set_iparm(1, 1)  # use the iparm values below, not the defaults
    solver.set_iparm(2, 3)  # parallel nested-dissection ordering
    solver.set_iparm(10, 8)  # pivot perturbation 1e-8
    solver.set_iparm(11, 0)  # no scaling (symmetric)
    solver.set_iparm(13, 0)  # no weighted matching (symmetric)
    solver.set_iparm(21, 1)  # Bunch-Kaufman pivoting for indefinite
    solver.set_iparm(24, 1)  # two-level parallel factorisation
    solver.set_iparm(27, 1)  # check the matrix structure
    try:
        solver.factorize(upper)
    except pypardiso.pardiso_wrapper.PyPardisoError as exc:
        raise SolverError(f"PARDISO could not factorise the {A.shape[0]}x{A.shape[0]} system "
                          f"({exc}); the stiffness matrix is singular or not positive definite: "
                          "check the supports (a free body needs no support) and the material")

    def solve(b: np.ndarray) -> np.ndarray:
        solver.set_phase(33)
        return solver._call_pardiso(upper, np.asarray(b, dtype=np.float64))

    def release() -> None:
        solver.free_memory(everything=True)

    return Factorization(solve, "pardiso", A.shape[0], release)


def _superlu(A: sp.csr_matrix) -> Factorization:
    from scipy.sparse.linalg import splu

    try:
        lu = splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A",
                  options={"SymmetricMode": True, "DiagPivotThresh": 0.01})
    except RuntimeError as exc:
        raise SolverError(f"SuperLU could not factorise the {A.shape[0]}x{A.shape[0]} system "
                          f"({exc}): the matrix is singular; check the supports") from None
    return Factorization(lu.solve, "superlu", A.shape[0])


def factorize(A: sp.spmatrix, backend: str = "auto", positive_definite: bool = True
              ) -> Factorization:
    """Factorise the symmetric matrix ``A`` (n x n) once, with ``backend``.

    ``backend``: ``auto`` or one of :data:`BACKENDS`; a backend that is not installed
    is refused with the list of those that are.
    """
    available = available_backends()
    if backend == "auto":
        backend = available[0]
    elif backend not in available:
        raise ConfigError(f"config key 'modes.solver': got '{backend}', expected one of the "
                          f"installed backends: auto, {', '.join(available)}")
    A = sp.csr_matrix(A)
    if backend == "pardiso":
        fact = _pardiso(A, positive_definite)
    else:
        fact = _superlu(A)
    check = np.ones(A.shape[0])
    x = fact.solve(check)
    residual = np.linalg.norm(A @ x - check) / np.linalg.norm(check)
    if not np.isfinite(x).all() or residual > 1e-6:
        raise SolverError(f"the {A.shape[0]}x{A.shape[0]} system is singular to working precision "
                          f"(backend {backend}, relative residual {residual:.2e}); check the "
                          "supports: an unsupported body must be solved as a free body")
    return fact
