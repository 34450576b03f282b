"""The factorisation protocol and the registry of backends.

A backend factorises a symmetric matrix A (n x n) once and then solves many right-hand
sides with that one factor, one or a block of them per call. Every backend is one module
under :mod:`pipeline.solve.backends` that implements :class:`Factorization` and ends in a
:func:`register_backend` line; :func:`factorize` then reaches it by name, and ``auto``
picks the first installed one in registration order (fastest first, measured at 100k
DOFs). A new backend is one new module and one import line in
``pipeline/solve/backends/__init__.py``.

The protocol, after scikit-sparse's ``Factor`` and scipy's ``LinearOperator``:

- ``solve(b)``: A^-1 b for b (n,) or (n, k); ``solve_rows(bt)``: the same for a
  C-ordered (k, n) block of right-hand sides, returned as (k, n) (no transposed copies
  where the backend takes row blocks);
- ``forward(b)`` = F^-1 b and ``backward(y)`` = F^-T y for a symmetric factor A = F F^T,
  and their row-block forms, where :attr:`Capabilities.half_solves` says so (the block
  Lanczos eigensolver needs them: :mod:`pipeline.solve.eigen`);
- ``memory_bytes`` and ``flops``: the factor's size and an estimate of the work it took;
- ``info``: plain statistics (``format``, ``factor_nnz``, ``factor_bytes``, seconds...);
- ``release()``: frees the factor (also on leaving a ``with`` block).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.sparse as sp

from pipeline._util import progress
from pipeline.errors import ConfigError, SolverError
from pipeline.solve.thresholds import SINGULAR_COND_EPS


@dataclass(frozen=True)
class Capabilities:
    """What a backend offers.

    positive_definite: factorises symmetric positive definite matrices (Cholesky);
    indefinite: also symmetric indefinite ones (``positive_definite=False``);
    half_solves: separate forward F^-1 b and backward F^-T y substitutions (A = F F^T);
    single_precision: a float32 factor (``single=True``; solves take float32);
    pattern_analysis: takes a pattern analysis started ahead (``analysis=``);
    gpu: the factor lives on a GPU (never chosen by ``auto``; probing it costs seconds).
    """

    positive_definite: bool = True
    indefinite: bool = False
    half_solves: bool = False
    single_precision: bool = False
    pattern_analysis: bool = False
    gpu: bool = False


class Factorization(abc.ABC):
    """A factorised symmetric matrix A (n x n); see the module doc for the protocol.

    Subclasses set :attr:`backend` and :attr:`capabilities` and implement :meth:`solve`;
    the other methods have defaults built on it.
    """

    backend: str = ""
    capabilities: Capabilities = Capabilities()

    def __init__(self, n: int, *, info: dict | None = None):
        self.n = int(n)
        self.info: dict = dict(info or {})

    @abc.abstractmethod
    def solve(self, b: np.ndarray) -> np.ndarray:
        """A^-1 b for b (n,) or (n, k), in b's shape."""

    def solve_rows(self, bt: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """A^-1 for the rows of a C-ordered (k, n) block: (k, n), written into ``out``
        ((k, n), C-ordered) when given (in place where the backend can) and returned."""
        return _into(np.asarray(self.solve(np.asarray(bt).T)).T, out)

    def forward(self, b: np.ndarray) -> np.ndarray:
        """F^-1 b for A = F F^T (b (n,) or (n, k)); only with ``half_solves``."""
        raise SolverError(f"backend '{self.backend}' has no separate forward and backward "
                          "substitutions")

    def backward(self, y: np.ndarray) -> np.ndarray:
        """F^-T y for A = F F^T (y (n,) or (n, k)); only with ``half_solves``."""
        raise SolverError(f"backend '{self.backend}' has no separate forward and backward "
                          "substitutions")

    def forward_rows(self, bt: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """:meth:`forward` of the rows of a C-ordered (k, n) block: (k, n) (``out``: as
        in :meth:`solve_rows`)."""
        return _into(self.forward(np.asarray(bt).T).T, out)

    def backward_rows(self, yt: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """:meth:`backward` of the rows of a C-ordered (k, n) block: (k, n) (``out``: as
        in :meth:`solve_rows`)."""
        return _into(self.backward(np.asarray(yt).T).T, out)

    @property
    def memory_bytes(self) -> int:
        """Bytes the factor holds (0 when the backend does not say)."""
        return int(self.info.get("factor_bytes", 0))

    @property
    def flops(self) -> float:
        """Estimated flops of the factorisation from the factor's non-zeros (0 when the
        backend does not report them): :func:`pipeline._util.progress.cholesky_flops`."""
        nnz = self.info.get("factor_nnz")
        return progress.cholesky_flops(float(nnz), self.n) if nnz else 0.0

    def release(self) -> None:
        """Free the factor; solving afterwards raises SolverError where it would fail."""

    def __enter__(self) -> "Factorization":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _into(X: np.ndarray, out: np.ndarray | None) -> np.ndarray:
    """X as a C-ordered array, or copied into ``out`` (same shape) and ``out`` returned."""
    if out is None:
        return np.ascontiguousarray(X)
    if out.shape != X.shape:
        raise ValueError(f"out: expected shape {X.shape}, got {out.shape}")
    out[...] = X
    return out


class SolverFactorization(Factorization):
    """A solve function presented as a :class:`Factorization` (for example conjugate
    gradients preconditioned by a factor, :mod:`pipeline.solve.mixed`), so that the
    static correction uses it like a direct factor."""

    def __init__(self, solve: Callable[[np.ndarray], np.ndarray], *, backend: str, n: int,
                 release: Callable[[], None] | None = None, info: dict | None = None):
        super().__init__(n, info=info)
        self.backend = backend
        self._solve = solve
        self._release = release

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._solve(b)

    def release(self) -> None:
        if self._release is not None:
            self._release()


# --------------------------------------------------------------------------- registry
#: factor(A, *, positive_definite, single, analysis) -> Factorization
FactorFunction = Callable[..., Factorization]


@dataclass(frozen=True)
class Backend:
    """A registered backend: ``factor`` makes a :class:`Factorization`; ``installed``
    says (cheaply, cached by the backend) whether it can run here; ``install_hint`` is
    the one line that tells a user how to get it."""

    name: str
    factor: FactorFunction
    installed: Callable[[], bool]
    capabilities: Capabilities = field(default_factory=Capabilities)
    install_hint: str = ""


_REGISTRY: dict[str, Backend] = {}


def register_backend(name: str, factor: FactorFunction, *, installed: Callable[[], bool],
                     capabilities: Capabilities = Capabilities(),
                     install_hint: str = "") -> None:
    """Register the backend ``name`` (the ``modes.solver`` value that selects it); ``auto``
    tries the backends in registration order. Registering a name again replaces it."""
    _REGISTRY[name] = Backend(name=name, factor=factor, installed=installed,
                              capabilities=capabilities, install_hint=install_hint)


def _registry() -> dict[str, Backend]:
    # the built-in backends register themselves when pipeline.solve is imported (its
    # __init__ imports pipeline.solve.backends), which Python does before this module
    return _REGISTRY


def backend_capabilities(name: str) -> Capabilities:
    """What the registered backend ``name`` offers."""
    return _registry()[name].capabilities


def available_backends(gpu: bool = True) -> list[str]:
    """Installed backends in registration order (fastest first); GPU backends last, since
    ``auto`` never chooses them. ``gpu=False`` does not look for them (probing imports
    CuPy and loads its libraries: a second or so that a CPU run need not pay)."""
    entries = _registry().values()
    host = [b.name for b in entries if not b.capabilities.gpu and b.installed()]
    if not gpu:
        return host
    return host + [b.name for b in entries if b.capabilities.gpu and b.installed()]


def resolve_backend(backend: str = "auto") -> str:
    """The backend ``backend`` names (``auto``: the fastest installed one); ConfigError
    naming the installed ones (and how to get the one asked for) otherwise."""
    host = available_backends(gpu=False)
    if backend == "auto":
        return host[0]
    if backend in host:
        return backend
    available = available_backends()
    if backend not in available:
        entry = _registry().get(backend)
        hint = f" ({entry.install_hint})" if entry is not None and entry.install_hint else ""
        raise ConfigError(f"config key 'modes.solver': got '{backend}', expected one of the "
                          f"installed backends: auto, {', '.join(available)}{hint}")
    return backend


def check_factorization(A: sp.spmatrix, fact: Factorization, seed: int = 7) -> float:
    """Relative error of solving A x = A z for a known random z; SolverError if large.

    A singular A (for example a body without enough supports) makes the solution
    differ from z by arbitrary null-space components, however small the residual. A
    backward-stable factor of a regular A misses z by about cond(A) eps (the rounding
    amplified along the lowest eigenvector), so the error is judged against
    :data:`~pipeline.solve.thresholds.SINGULAR_COND_EPS`, the bound on cond(A) eps the
    static solve uses: a fixed 1e-3 refused a 500 x 50 x 0.2 mm strip, whose K is fine
    (f1 within 2.1% of beam theory) but misses z by 1.0e-3 to 2.8e-3 depending on z and
    on the DOF order.
    """
    z = np.random.default_rng(seed).standard_normal(A.shape[0])
    x = fact.solve(A @ z)
    error = float(np.linalg.norm(x - z) / np.linalg.norm(z))
    if not np.isfinite(error) or error > SINGULAR_COND_EPS:
        raise SolverError(
            f"the {A.shape[0]}x{A.shape[0]} stiffness system is singular to working precision "
            f"(backend {fact.backend}: solving A x = A z misses z by {error:.1e} relative); "
            "check the supports: a body that can move as a rigid body or mechanism needs "
            "supports, or must be solved as a free body (no supports at all)")
    return error


def factorize(A: sp.spmatrix, backend: str = "auto", *, positive_definite: bool = True,
              check: bool = True, single: bool = False, analysis=None) -> Factorization:
    """Factorise the symmetric matrix ``A`` (n x n) once, with ``backend``.

    ``backend``: ``auto`` or a registered name; one that is not installed is refused
    (ConfigError) with the list of those that are. ``positive_definite``: False asks for
    a symmetric indefinite factor. ``single``: a float32 factor (half the memory and
    about half the flops; its solves take and return float32), for
    :mod:`pipeline.solve.mixed`, from a backend that offers it. A singular ``A`` raises
    SolverError: from the factorisation itself, or (``check``) from
    :func:`check_factorization`. ``analysis``: a pattern analysis of ``A`` started
    earlier (:class:`pipeline.solve.backends.pardiso.PatternAnalysis`), used by a backend
    that takes one; it is taken or released here in every case.
    """
    try:
        name = resolve_backend(backend)
        if A.shape[0] != A.shape[1] or A.shape[0] == 0:
            raise SolverError(f"cannot factorise a {A.shape[0]}x{A.shape[1]} matrix")
        entry = _registry()[name]
        if single and not entry.capabilities.single_precision:
            able = [b.name for b in _registry().values() if b.capabilities.single_precision]
            raise ConfigError(f"config key 'modes.precision': a single-precision factor "
                              f"needs the {' or '.join(repr(b) for b in able)} backend, not "
                              f"'{name}'", key="modes.precision")
        fact = entry.factor(A, positive_definite=positive_definite, single=single,
                            analysis=analysis if entry.capabilities.pattern_analysis
                            else None)
    finally:
        if analysis is not None:
            analysis.release()  # nothing left to free when the backend took it
    if check:
        try:
            check_factorization(A, fact)
        except SolverError:
            fact.release()
            raise
    return fact
