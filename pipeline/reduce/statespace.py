"""The one state-space type every module speaks: :class:`StateSpace`.

A continuous-time LTI model (SI units)::

    x' = A x + B u,    y = C x + D u

A (n_x, n_x), B (n_x, n_u), C (n_y, n_x), D (n_y, n_u): real, finite, read-only float64
arrays, checked in the constructor, which names the matrix and the shape it expected
(as python-control's ``StateSpace`` does). Names label the columns of B (inputs), the
rows of C (outputs) and the rows of A (states); units, when known, are per name.

Structural models name their outputs ``<port>/position``, ``<port>/velocity`` and
``<port>/acceleration`` and, when modal, their states ``eta_k`` and ``eta_dot_k``
(theory.md §3). Every model the pipeline builds or reads (the modal plant and its
filtered twin, the lumped chain, the connection-point model, the systems a simulation
steps) is a StateSpace; the DC gain and the frequency response are computed here, once.

>>> import numpy as np
>>> ss = StateSpace([[0, 1], [-4, -0.4]], [[0], [1]], [[1, 0]], [[0]],
...                 input_names=["f"], output_names=["tip/position"])
>>> ss.dc_gain()
array([[0.25]])
>>> ss.ports
('tip',)
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

QUANTITIES = ("position", "velocity", "acceleration")


def _matrix(name: str, value, shape: tuple[int | None, int | None]) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)  # a copy: the caller's array stays theirs
    except (TypeError, ValueError):
        raise ValueError(f"StateSpace.{name}: expected a real matrix, got "
                         f"{type(value).__name__}") from None
    if a.ndim == 0 and a.size == 1 and shape != (None, None):
        a = a.reshape(1, 1)
    if a.ndim == 1:
        a = a.reshape(-1, 1) if name == "B" else a.reshape(1, -1)
    if a.ndim != 2:
        raise ValueError(f"StateSpace.{name} has {a.ndim} dimensions, expected a 2-D matrix")
    for got, want in zip(a.shape, shape):
        if want is not None and got != want:
            raise ValueError(f"StateSpace.{name} has shape {a.shape}, expected "
                             f"{tuple('*' if w is None else w for w in shape)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"StateSpace.{name} holds non-finite values (NaN or inf)")
    a.setflags(write=False)
    return a


def _names(kind: str, given: Sequence[str] | None, n: int, default: str) -> tuple[str, ...]:
    if given is None or len(given) == 0:
        return tuple(f"{default}{i + 1}" for i in range(n))
    names = tuple(str(s) for s in given)
    if len(names) != n:
        raise ValueError(f"StateSpace: {len(names)} {kind} names for {n} {kind}s")
    return names


@dataclass(frozen=True, eq=False)
class StateSpace:
    """x' = A x + B u, y = C x + D u (see the module docstring).

    Parameters
    ----------
    A, B, C, D : array_like, shapes (n_x, n_x), (n_x, n_u), (n_y, n_x), (n_y, n_u).
    input_names, output_names, state_names : labels (default ``u1..``, ``y1..``, ``x1..``).
    input_units, output_units : one SI unit string per input / output, or empty.
    label : what the model is (``"plant"``, ``"filtered"``, ``"lumped"``, ...).
    filter_kind, cutoff_hz : an output filter in series (``"none"`` for a plant).
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    input_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    state_names: tuple[str, ...] = ()
    input_units: tuple[str, ...] = ()
    output_units: tuple[str, ...] = ()
    label: str = ""
    filter_kind: str = "none"
    cutoff_hz: float | None = None
    attrs: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        A = _matrix("A", self.A, (None, None))
        n = A.shape[0]
        if A.shape[1] != n:
            raise ValueError(f"StateSpace.A has shape {A.shape}, expected a square matrix")
        B = _matrix("B", self.B, (n, None))
        C = _matrix("C", self.C, (None, n))
        D = _matrix("D", self.D, (C.shape[0], B.shape[1]))
        for k, v in zip("ABCD", (A, B, C, D)):
            object.__setattr__(self, k, v)
        n_u, n_y = B.shape[1], C.shape[0]
        object.__setattr__(self, "input_names", _names("input", self.input_names, n_u, "u"))
        object.__setattr__(self, "output_names", _names("output", self.output_names, n_y, "y"))
        object.__setattr__(self, "state_names", _names("state", self.state_names, n, "x"))
        for kind, n_k in (("input", n_u), ("output", n_y)):
            units = tuple(str(u) for u in getattr(self, f"{kind}_units") or ())
            if units and len(units) != n_k:
                raise ValueError(f"StateSpace: {len(units)} {kind} units for {n_k} {kind}s")
            object.__setattr__(self, f"{kind}_units", units)

    def __iter__(self):
        """Unpacks as the four matrices: ``A, B, C, D = ss``."""
        return iter((self.A, self.B, self.C, self.D))

    # ------------------------------------------------------------------ sizes, names
    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    @property
    def n_inputs(self) -> int:
        return self.B.shape[1]

    @property
    def n_outputs(self) -> int:
        return self.C.shape[0]

    @property
    def ports(self) -> tuple[str, ...]:
        """Output ports: the names of the ``<port>/position`` outputs, in order."""
        return tuple(n.rsplit("/", 1)[0] for n in self.output_names if n.endswith("/position"))

    def rows(self, port: str) -> tuple[int, int, int]:
        """Output rows of ``port``'s position, velocity and acceleration.

        Raises KeyError naming the port when one of them is missing."""
        index = {n: i for i, n in enumerate(self.output_names)}
        try:
            return tuple(index[f"{port}/{q}"] for q in QUANTITIES)  # type: ignore[return-value]
        except KeyError:
            raise KeyError(f"{self.label or 'model'}: output port '{port}' lacks one of "
                           "position/velocity/acceleration") from None

    def col(self, name: str) -> int:
        """Column of input ``name`` (ValueError when unknown)."""
        return list(self.input_names).index(name)

    def modal_indices(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Indices (eta, eta_dot) of the modal states when the model has the modal form
        x = [eta; eta'] with A = [[0, I], [-Omega2, -2 Gamma]] (diagonal blocks); else None."""
        pos = {n: i for i, n in enumerate(self.state_names)}
        eta, dot, k = [], [], 1
        while f"eta_{k}" in pos and f"eta_dot_{k}" in pos:
            eta.append(pos[f"eta_{k}"])
            dot.append(pos[f"eta_dot_{k}"])
            k += 1
        if not eta:
            return None
        e, d = np.array(eta), np.array(dot)
        A = self.A
        scale = max(float(np.abs(A).max()), 1.0)

        def off(X):
            return X - np.diag(np.diag(X))

        ok = (np.allclose(A[np.ix_(e, d)], np.eye(e.size), atol=1e-12 * scale)
              and np.abs(off(A[np.ix_(d, e)])).max(initial=0.0) <= 1e-12 * scale
              and np.abs(off(A[np.ix_(d, d)])).max(initial=0.0) <= 1e-12 * scale
              and np.abs(A[np.ix_(e, e)]).max(initial=0.0) <= 1e-12 * scale)
        return (e, d) if ok else None

    # ------------------------------------------------------------------ responses
    def frequency_response(self, s: complex) -> np.ndarray:
        """G(s) = C (s I - A)^-1 B + D, (n_y, n_u), complex."""
        n = self.n_states
        return self.C @ np.linalg.solve(s * np.eye(n) - self.A, self.B) + self.D

    def dc_gain(self) -> np.ndarray:
        """G(0) = D - C A^-1 B, (n_y, n_u). Raises numpy's LinAlgError when A is singular
        (a free body: rigid-body modes have no static gain)."""
        return self.D - self.C @ np.linalg.solve(self.A, self.B)

    def poles(self) -> np.ndarray:
        """Eigenvalues of A, rad/s (complex)."""
        return np.linalg.eigvals(self.A)

    # ------------------------------------------------------------------ conversions
    def with_(self, **changes) -> "StateSpace":
        """A copy with some fields replaced (validated again)."""
        return replace(self, **changes)

    def to_control(self):
        """The python-control ``StateSpace`` with the same matrices and names."""
        import control

        return control.ss(self.A, self.B, self.C, self.D, inputs=list(self.input_names),
                          outputs=list(self.output_names), states=list(self.state_names))
