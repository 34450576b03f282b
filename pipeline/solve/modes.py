"""The modes stage's record: the eigenpairs of K phi = omega^2 M phi and what goes with them.

:class:`Modes` is what :func:`pipeline.solve.eigen.solve_modes` returns and what
:func:`pipeline.solve.stage.compute_modes` completes (mode shapes on every mesh point,
labels). For a supported body it may also carry the factorisation of K that the
shift-invert solve made (shift 0: the factor of K itself), handed on explicitly to the
reduce stage, whose static correction K^-1 F needs the same factor (a second
factorisation doubles that time at 1M DOFs).

Lifetime of the kept factor: whoever receives a :class:`Modes` with a factorisation owns
it and frees it with :meth:`Modes.release_factorization` (idempotent). The pipeline
(:func:`pipeline.run.run_pipeline`) ties that release to the lifetime of K, so the factor
is freed when the reduce stage drops K -- before the connection models factorise the
unsupported K -- and releases it once more, explicitly, after the reduce stage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.solve.factorization import Factorization


@dataclass(frozen=True)
class Modes:
    """Modes of the constrained body.

    omega2: (n_m,) rad^2/s^2, ascending (rigid modes clipped to >= 0).
    frequencies_hz: (n_m,) Hz.
    shapes: (n_free, n_m) M-orthonormal mode shapes on the free DOFs (kg^-1/2).
    residuals: (n_m,) ||K phi - omega^2 M phi|| / ||K phi|| (rigid: / ||M phi|| |shift|).
    n_rigid: number of zero-frequency (rigid-body) modes found.
    backend: the factorisation used; shift: the shift sigma (rad^2/s^2).
    seconds: wall time of the whole solve; stats: what the solver did (method, solves,
    steps, factor size...).
    labels: dominant motion of every mode (empty until labelled).
    shapes_full: (n_points, 3, n_m) the shapes on every mesh point (zero on the fixed
    DOFs), or None.
    factorization: the kept factorisation of K (shift 0 only), or None; of T^T K T when
    ``constraint`` is set.
    constraint: (n_free, n_q) T of the exact constraint u = T q the modes were solved
    under (:mod:`pipeline.fe.constraints`; ``shapes`` are T psi already), or None; on
    MPI ranks its distributed twin
    (:class:`pipeline.distributed.constraints.DistributedConstraint`).
    """

    omega2: np.ndarray
    frequencies_hz: np.ndarray
    shapes: np.ndarray
    residuals: np.ndarray
    n_rigid: int
    backend: str
    shift: float
    seconds: float
    stats: dict | None = None
    labels: tuple[str, ...] = ()
    shapes_full: np.ndarray | None = None
    factorization: Factorization | None = None
    constraint: object | None = None

    @property
    def solve(self):
        """b -> K^-1 b with the kept factorisation of K (of T^T K T under a
        ``constraint``: b and the result are then (n_q,)), or None when none is kept."""
        return None if self.factorization is None else self.factorization.solve

    def release_factorization(self) -> None:
        """Free the kept factor now (a no-op when none is kept or it was freed)."""
        if self.factorization is not None:
            self.factorization.release()
