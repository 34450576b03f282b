"""Result records of a simulation: runs, summary rows, per-scenario and overall results.

A :class:`Run` holds one time integration (times t (n_t,) in s, signals (n_t,) by name
with their SI units, measured and predicted values); a :class:`Row` is one line of the
printed summary, a measured value beside its analytic prediction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.apps.simulate.scenarios import Scenario

__all__ = ["Run", "Row", "ScenarioResult", "SimulationResults"]


@dataclass
class Run:
    """One time integration: a model (FE or lumped) in one scenario (one mass)."""

    model: str
    key: str
    t: np.ndarray
    signals: dict[str, np.ndarray]
    units: dict[str, str]
    measured: dict[str, float]
    predicted: dict[str, float]
    info: dict[str, Any] = field(default_factory=dict)
    mass: float | None = None


@dataclass(frozen=True)
class Row:
    """One line of the summary: a measured value beside its analytic prediction."""

    scenario: str
    model: str
    quantity: str
    measured: float
    predicted: float
    units: str
    note: str = ""

    @property
    def rel_error(self) -> float:
        if not (math.isfinite(self.measured) and math.isfinite(self.predicted)) \
                or self.predicted == 0:
            return math.nan
        return self.measured / self.predicted - 1.0


@dataclass
class ScenarioResult:
    scenario: Scenario
    runs: list[Run]
    rows: list[Row]
    notes: list[str] = field(default_factory=list)
    fits: dict[str, dict[str, Any]] = field(default_factory=dict)

    def run(self, key: str = "fe", mass: float | None = None) -> Run:
        for r in self.runs:
            if r.key == key and (mass is None or (r.mass is not None
                                                  and math.isclose(r.mass, mass))):
                return r
        raise KeyError(f"no run {key!r}" + ("" if mass is None else f" with mass {mass:g}"))

    def row(self, quantity: str, model_key: str = "fe") -> Row:
        prefix = "lumped" if model_key == "lumped" else "FE"
        for r in self.rows:
            if r.quantity == quantity and r.model.startswith(prefix):
                return r
        raise KeyError(f"no row {quantity!r} for {model_key}")


@dataclass
class SimulationResults:
    model_path: Path
    scenarios: list[ScenarioResult]
    output: Path | None = None
    files: list[Path] = field(default_factory=list)
    wall_s: float = 0.0

    def __getitem__(self, name: str) -> ScenarioResult:
        for s in self.scenarios:
            if s.scenario.name == name:
                return s
        raise KeyError(name)

    @property
    def rows(self) -> list[Row]:
        return [r for s in self.scenarios for r in s.rows]

    def table(self) -> str:
        """The printed summary: measured beside predicted, one line per quantity."""
        head = (f"{'scenario':<14}{'model':<36}{'quantity':<38}{'measured':>14}"
                f"{'predicted':>14}{'error':>10}  units")
        lines = [head, "-" * len(head)]
        for r in self.rows:
            err = f"{r.rel_error:+.2e}" if math.isfinite(r.rel_error) else "-"
            fmt = lambda v: f"{v:.6g}" if math.isfinite(v) else "-"  # noqa: E731
            lines.append(f"{r.scenario:<14.14}{r.model:<36.36}{r.quantity:<38.38}"
                         f"{fmt(r.measured):>14}{fmt(r.predicted):>14}{err:>10}  {r.units}"
                         + (f"  ({r.note})" if r.note else ""))
        for s in self.scenarios:
            for n in s.notes:
                lines.append(f"note [{s.scenario.name}]: {n}")
        return "\n".join(lines)

