"""The case records of a batch folder: what happened to a case, and whether its file is
still good enough to skip computing it again.

Files of a case, under ``<batch folder>/cases/``::

    <key>.h5     the HDF5 result (written atomically: it exists only complete)
    <key>.json   its :class:`CaseRecord` (status, error, DOFs, times, memory, frequencies)
    <key>.log    the pipeline's log of the run

A :class:`CaseRecord` is a frozen dataclass; :meth:`CaseRecord.to_json` and
:meth:`CaseRecord.from_json` are the one place it becomes JSON and back (a field that is
None is left out of the file). Records are written through :mod:`pipeline._util.atomic`.
A cached case is served when its record says ``ok`` and the file's size and mtime are
those recorded (``verify=True``: its checksum is checked too); otherwise the record is
rebuilt from the verified file, or the case is computed again.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from pipeline._version import __version__
from pipeline._util.atomic import write_text
from pipeline.apps.batch.cases import RECORD_VERSION, Case, portable_config
from pipeline.config import config_to_yaml
from pipeline.errors import FileFormatError
from pipeline.store.summary import read_summary

log = logging.getLogger(__name__)

__all__ = [
    "CaseRecord",
    "cached_record",
    "clean_partials",
    "finish_record",
    "h5_path",
    "read_record",
    "record_from_file",
    "write_record",
]


@dataclass(frozen=True)
class CaseRecord:
    """What is known about one case; None: not known (left out of the JSON file).

    Read access by field name as well (``record["n_dofs"]``, ``record.get("error")``),
    as the JSON file reads.
    """

    status: str                                     # ok | failed
    key: str | None = None
    error: str | None = None
    error_type: str | None = None
    traceback: str | None = None
    n_dofs: int | None = None
    n_free_dofs: int | None = None
    n_elements: int | None = None
    frequencies_hz: tuple[float, ...] | None = None  # Hz, (n_modes,)
    mode_labels: tuple[str, ...] | None = None
    mass_kg: float | None = None
    times_s: dict[str, float] | None = None          # stage -> seconds
    peak_memory_mb: float | None = None              # peak RSS of the case process, MB
    solver: str | None = None
    compute_s: float | None = None
    rebuilt_from_file: bool | None = None
    worker: str | None = None
    written_by_worker: bool | None = None
    started_utc: str | None = None
    finished_utc: str | None = None
    started_unix: float | None = None
    finished_unix: float | None = None
    wall_s: float | None = None
    record_version: int | None = None
    pipeline_version: str | None = None
    label: str | None = None
    overrides: tuple[str, ...] | None = None
    memory_estimate_mb: float | None = None
    file: str | None = None
    file_size: int | None = None
    file_mtime_ns: int | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def __getitem__(self, name: str) -> Any:
        value = getattr(self, name, None) if name in FIELD_NAMES else None
        if value is None:
            raise KeyError(name)
        return value

    def get(self, name: str, default: Any = None) -> Any:
        value = getattr(self, name) if name in FIELD_NAMES else None
        return default if value is None else value

    def updated(self, other: CaseRecord) -> CaseRecord:
        """This record with every field ``other`` knows (not None) taken from ``other``."""
        return dataclasses.replace(self, **{f.name: getattr(other, f.name) for f in fields(other)
                                            if getattr(other, f.name) is not None})

    def replace(self, **changes: Any) -> CaseRecord:
        return dataclasses.replace(self, **changes)

    def to_json(self) -> str:
        data = {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) is not None}
        return json.dumps(data, indent=1, sort_keys=True) + "\n"

    @classmethod
    def from_json(cls, text: str) -> CaseRecord:
        """The record of a JSON text (unknown keys are ignored); ValueError if it is not one."""
        data = json.loads(text)
        if not isinstance(data, dict) or not isinstance(data.get("status"), str):
            raise ValueError("not a case record")
        data = {k: v for k, v in data.items() if k in FIELD_NAMES}
        for name in ("frequencies_hz", "mode_labels", "overrides"):
            if isinstance(data.get(name), list):
                data[name] = tuple(data[name])
        return cls(**data)


FIELD_NAMES = frozenset(f.name for f in fields(CaseRecord))


def failure(error_type: str, error: str) -> CaseRecord:
    """The record of a case that failed with ``error`` (one line)."""
    return CaseRecord(status="failed", error_type=error_type, error=error)


def h5_path(cases_dir: Path, key: str) -> Path:
    return cases_dir / f"{key}.h5"


def write_record(cases_dir: Path, record: CaseRecord) -> None:
    write_text(cases_dir / f"{record.key}.json", record.to_json())


def read_record(cases_dir: Path, key: str) -> CaseRecord | None:
    """The record of ``key`` if there is a readable one, else None."""
    try:
        record = CaseRecord.from_json((cases_dir / f"{key}.json").read_text(encoding="utf-8"))
    except (OSError, ValueError, TypeError):
        return None
    return record if record.key == key else None


def record_from_file(path: Path, case: Case, verify: bool = True) -> CaseRecord:
    """A case record rebuilt from its HDF5 file (verified); FileFormatError if unusable
    (not ours, corrupt, another config or version, a dataset missing)."""
    s = read_summary(path, verify_checksum=verify)
    if s.config_yaml is not None and s.config_yaml != config_to_yaml(portable_config(case.config)):
        raise FileFormatError(f"file '{path}': its config differs from case {case.index}'s",
                              key=str(path))
    if s.pipeline_version != __version__:
        raise FileFormatError(f"file '{path}': written by pipeline "
                              f"{s.pipeline_version}, not {__version__}", key=str(path))
    mesh, modes = s.mesh, s.modes
    missing = [name for name, ok in (
        ("mesh", mesh is not None and mesh.cells is not None and mesh.n_dofs is not None
         and mesh.n_free_dofs is not None),
        ("modes", modes is not None and modes.labels is not None),
        ("body", s.body is not None)) if not ok]
    if missing:
        raise FileFormatError(f"file '{path}': not a case result of this pipeline (no "
                              f"complete {', '.join(missing)})", key=str(path))
    run = s.run
    return CaseRecord(
        status="ok", n_dofs=mesh.n_dofs, n_free_dofs=mesh.n_free_dofs,
        n_elements=sum(mesh.cells.values()),
        frequencies_hz=tuple(float(f) for f in modes.frequencies_hz),
        mode_labels=modes.labels, mass_kg=s.body.mass,
        times_s=dict(run.times_s) if run is not None else {},
        peak_memory_mb=(run.peak_memory_mb if run is not None
                        and run.peak_memory_mb is not None else math.nan),
        solver=(run.solver or "") if run is not None else "",
        rebuilt_from_file=True)


def finish_record(record: CaseRecord, case: Case, h5: Path | None) -> CaseRecord:
    """``record`` with the case's identity and, when ``h5`` exists, its size and mtime."""
    record = record.replace(key=case.key, record_version=RECORD_VERSION,
                            pipeline_version=__version__, label=case.label,
                            overrides=tuple(case.override_strings),
                            memory_estimate_mb=None if case.memory_bytes is None
                            else case.memory_bytes / 1e6)
    if h5 is not None and h5.exists():
        st = h5.stat()
        return record.replace(file=h5.name, file_size=st.st_size, file_mtime_ns=st.st_mtime_ns)
    return record.replace(file=None)


def cached_record(cases_dir: Path, case: Case, verify: bool) -> CaseRecord | None:
    """The record of a finished case whose file is intact, else None (compute it)."""
    h5 = h5_path(cases_dir, case.key)
    if not h5.exists():
        return None
    record = read_record(cases_dir, case.key)
    st = h5.stat()
    if (not verify and record is not None and record.ok
            and record.file_size == st.st_size and record.file_mtime_ns == st.st_mtime_ns):
        return record
    try:
        rebuilt = record_from_file(h5, case)
    except FileFormatError as exc:
        log.warning("case %d: %s; computing it again", case.index, exc)
        return None
    if record is not None and record.ok:
        rebuilt = rebuilt.updated(record.replace(rebuilt_from_file=None))
    rebuilt = finish_record(rebuilt, case, h5)
    write_record(cases_dir, rebuilt)
    return rebuilt


def partial_files(cases_dir: Path) -> Iterator[Path]:
    """Temporary files an interrupted writer left (never taken for results)."""
    return cases_dir.glob(".*.partial*")


def clean_partials(cases_dir: Path) -> int:
    """Remove the partial files of an interrupted run; how many there were."""
    n = 0
    for p in partial_files(cases_dir):
        with contextlib.suppress(OSError):
            p.unlink()
            n += 1
    return n
