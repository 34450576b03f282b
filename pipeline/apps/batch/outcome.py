"""What a batch run produced: the outcome of every case and of the whole batch.

Built by :func:`pipeline.apps.batch.scheduler.run_batch`, read by the report
(:mod:`pipeline.apps.batch.report`) and the command line.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pipeline.apps.batch.cache import CaseRecord
from pipeline.apps.batch.cases import Case
from pipeline.apps.batch.spec import BatchSpec

__all__ = ["NO_RECORD", "STATUSES", "BatchResult", "CaseOutcome"]

#: outcome of a case in one run
STATUSES = ("done", "cached", "failed", "not run")
#: the record of a case nothing is known about (not run, no earlier failure)
NO_RECORD = CaseRecord(status="none")


@dataclass(frozen=True)
class CaseOutcome:
    """What happened to one case in this run."""

    case: Case
    status: str                      # done | cached | failed | not run
    record: CaseRecord = NO_RECORD
    h5: Path | None = None           # the case's HDF5 file when done or cached

    @property
    def error(self) -> str:
        return self.record.error or ""


@dataclass
class BatchResult:
    """The outcome of a batch run; ``files``: what the report wrote (name -> path)."""

    spec: BatchSpec
    outdir: Path
    outcomes: list[CaseOutcome]
    wall_s: float
    workers: str                     # where the cases ran, in words
    files: dict[str, Path] = field(default_factory=dict)

    def count(self, status: str) -> int:
        return sum(o.status == status for o in self.outcomes)

    @property
    def failed(self) -> list[CaseOutcome]:
        return [o for o in self.outcomes if o.status == "failed"]
