"""Batch runs: parameter sweeps of one base config, in parallel, cached, resumable.

A batch file names a base config and the cases to derive from it::

    batch:
      name: mesh_convergence              # output folder outputs/<name>/ (default: file stem)
      description: free text for the report
      base: configs/cantilever.yaml       # a config file (relative to the working directory,
                                          # else to the batch file), or an inline mapping
      set: {modes.count: 6}               # overrides applied to every case (optional)
      sweep:                              # dotted key -> list of values
        mesh.size: [0.01, 0.005, 0.0025]
        constraints.in_plane: [false, true]
      combine: product                    # product (every combination) | zip (i-th with i-th)
      cases:                              # explicit cases, after the sweep's (optional)
        - {label: steel, set: {material.E: 210e9, material.rho: 7850}}
        - {geometry.height: 0.03}         # a plain mapping of overrides also works

Overrides use the dotted paths of ``--set`` (``supports[0].fix``). Every case is resolved
and validated (:func:`pipeline.config.config_from_dict`) before anything runs; an invalid
case stops the batch with a :class:`~pipeline.errors.ConfigError` naming the batch file,
the case and the key.

Outputs, under ``outputs/<name>/`` (or ``-o DIR``)::

    cases/<key>.h5     the HDF5 file of the case (written atomically: it exists only complete)
    cases/<key>.json   a small record: status, error, DOFs, times, peak memory, frequencies
    cases/<key>.log    the pipeline's log of the run
    summary.csv, report.html, *.png   (pipeline.apps.report)

``<key>`` is a hash of the resolved config (its YAML), the pipeline version and, for a
geometry read from a file, that file's bytes. A case whose file exists and is intact is
not computed again (a re-run says so); a failed case is retried on the next run. An
interrupted batch is resumed by running it again: finished cases are kept, partial files
(``.<key>.h5.<host>.<pid>.partial.h5``) are removed and never taken for results.

Execution: a local Dask cluster by default (worker processes, one per core, each with a
memory limit), or an existing cluster given by ``--scheduler tcp://host:8786``. Each
case runs in a child process forked by the worker (Linux), so its peak memory is its own,
a crash (gmsh, MKL, the kernel's OOM killer) fails only that case, and a case that grows
beyond the worker's memory limit is stopped with a clear message. Scheduling is memory
aware through Dask worker resources: each worker advertises ``memory`` (bytes cases may
use: 80 % of its memory limit for the local cluster; ``dask worker --resources
memory=19e9`` on your own cluster) and each case requests its estimate
(:func:`estimate_case_memory`), so two 10 GB cases never share a 16 GB budget. A case
larger than every worker's budget fails at once instead of waiting forever.

Workers write the HDF5 file straight into ``cases/`` when they see the same folder as
the client (checked with a token file); otherwise they send the file's bytes back and
the client writes it.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import itertools
import json
import logging
import math
import os
import re
import secrets
import socket
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from pipeline._util.atomic import write_bytes, write_text
from pipeline.errors import ConfigError, FileFormatError, PipelineError

log = logging.getLogger(__name__)

__all__ = [
    "BatchSpec",
    "BatchResult",
    "Case",
    "load_batch",
    "case_key",
    "estimate_case_memory",
    "run_batch",
    "add_batch_parser",
    "main",
]

BATCH_KEYS = ("name", "description", "base", "set", "sweep", "combine", "cases")
CASE_KEYS = ("label", "set")
EVENT_TOPIC = "fe-reduced-body-batch"
RECORD_VERSION = 1
# Share of a local worker's memory limit it advertises to cases (Dask pauses a worker at
# 80 % of its limit); a case is stopped when its own RSS passes KILL_FRACTION of the limit.
BUDGET_FRACTION = 0.8
KILL_FRACTION = 0.95
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
_KEY_RE = re.compile(r"^[A-Za-z0-9_\-]+(\.[A-Za-z0-9_\-]+|\[\d+\])*$")


# --------------------------------------------------------------------------- batch file
@dataclass(frozen=True)
class Case:
    """One case of a batch: its overrides, the resolved config and its cache key."""

    index: int                              # 1-based position in the batch
    label: str
    overrides: tuple[tuple[str, Any], ...]  # (dotted key, value): the sweep's or the case's
    config: Any                             # pipeline.config.Config
    key: str
    memory_bytes: int | None                # estimated peak memory, None if unknown
    origin: str = "sweep"                   # sweep | case (the explicit list) | base

    @property
    def override_strings(self) -> list[str]:
        return [f"{k}={_format_value(v)}" for k, v in self.overrides]


@dataclass(frozen=True)
class BatchSpec:
    """A validated batch file."""

    name: str
    path: Path
    base: str                    # the base config file ("<inline>" for a mapping)
    description: str
    combine: str
    common: tuple[tuple[str, Any], ...]
    sweep_keys: tuple[str, ...]
    case_keys: tuple[str, ...]   # every key some case overrides (sweep first)
    cases: tuple[Case, ...]


def _format_value(value: Any) -> str:
    if isinstance(value, str):
        return value
    return json.dumps(value)


def _describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _yaml_text(value: Any) -> str:
    """``value`` as text that the config's YAML reader gives back unchanged."""
    return json.dumps(value)


def _override_items(raw: Any, where: str, file: str) -> list[tuple[str, Any]]:
    if raw is None:
        return []
    if not isinstance(raw, Mapping):
        raise ConfigError(f"batch file '{file}': key '{where}': got {_describe(raw)}, expected a "
                          "mapping of dotted config keys to values, e.g. {mesh.size: 0.005}")
    out = []
    for key, value in raw.items():
        if not isinstance(key, str) or not _KEY_RE.match(key):
            raise ConfigError(f"batch file '{file}': key '{where}.{key}': expected a dotted config "
                              "key path such as mesh.size or supports[0].fix")
        out.append((key, value))
    return out


def _resolve_base(base: Any, batch_path: Path) -> tuple[Any, str, str]:
    """(raw mapping, source path for relative geometry paths, display name) of ``base``."""
    from pipeline._util.yamlio import parse_yaml as _parse_yaml

    file = str(batch_path)
    if isinstance(base, Mapping):
        return dict(base), str(batch_path), "<inline>"
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(f"batch file '{file}': key 'batch.base': got {_describe(base)}, expected "
                          "a config file path or an inline config mapping")
    candidates = [Path(base)] if Path(base).is_absolute() else [Path(base),
                                                                 batch_path.parent / base]
    for cand in candidates:
        if cand.is_file():
            try:
                text = cand.read_text(encoding="utf-8")
            except (OSError, UnicodeDecodeError) as exc:
                raise ConfigError(f"batch file '{file}': key 'batch.base': config file '{cand}' "
                                  f"cannot be read ({exc})") from None
            raw = _parse_yaml(text, f"batch file '{file}': base config file '{cand}'")
            if not isinstance(raw, Mapping):
                raise ConfigError(f"batch file '{file}': key 'batch.base': config file '{cand}' "
                                  "does not hold a mapping of config keys")
            return dict(raw), str(cand), str(cand)
    looked = " or ".join(f"'{c}'" for c in dict.fromkeys(str(c) for c in candidates))
    raise ConfigError(f"batch file '{file}': key 'batch.base': config file '{base}' not found "
                      f"(looked for {looked})")


def _sweep_points(sweep: Any, combine: str, file: str) -> tuple[list[str], list[list]]:
    if sweep is None:
        return [], []
    if not isinstance(sweep, Mapping) or not sweep:
        raise ConfigError(f"batch file '{file}': key 'batch.sweep': got {_describe(sweep)}, "
                          "expected a mapping of dotted config keys to lists of values")
    keys, lists = [], []
    for key, values in _override_items(sweep, "batch.sweep", file):
        if not isinstance(values, list) or not values:
            raise ConfigError(f"batch file '{file}': key 'batch.sweep.{key}': got "
                              f"{_describe(values)}, expected a non-empty list of values")
        keys.append(key)
        lists.append(values)
    if combine == "zip":
        lengths = {k: len(v) for k, v in zip(keys, lists)}
        if len(set(lengths.values())) > 1:
            detail = ", ".join(f"{k}: {n}" for k, n in lengths.items())
            raise ConfigError(f"batch file '{file}': key 'batch.sweep': combine 'zip' needs lists "
                              f"of equal length, got {detail}")
        points = [list(p) for p in zip(*lists)]
    else:
        points = [list(p) for p in itertools.product(*lists)]
    return keys, points


def load_batch(path: str | Path) -> BatchSpec:
    """Read and validate a batch file: every case is resolved and checked here.

    Raises ConfigError naming the batch file, the case (number and overrides) and the
    config key for every invalid case (all of them, not just the first).
    """
    from pipeline._util.yamlio import parse_yaml as _parse_yaml
    from pipeline.config import apply_overrides, config_from_dict

    path = Path(path)
    file = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"batch file '{file}': not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"batch file '{file}': cannot be read ({exc})") from None
    doc = _parse_yaml(text, f"batch file '{file}'")
    if not isinstance(doc, Mapping) or set(doc) != {"batch"}:
        raise ConfigError(f"batch file '{file}': expected one top-level key 'batch' (got "
                          f"{_describe(sorted(doc) if isinstance(doc, Mapping) else doc)})")
    raw = doc["batch"]
    if not isinstance(raw, Mapping):
        raise ConfigError(f"batch file '{file}': key 'batch': got {_describe(raw)}, expected a "
                          "mapping with base, sweep, combine, cases, ...")
    for key in raw:
        if key not in BATCH_KEYS:
            raise ConfigError(f"batch file '{file}': key 'batch.{key}' is not known; expected one "
                              f"of: {', '.join(BATCH_KEYS)}")
    if "base" not in raw:
        raise ConfigError(f"batch file '{file}': key 'batch.base' is missing; it is required "
                          "(a config file or an inline config)")
    name = raw.get("name", path.stem)
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ConfigError(f"batch file '{file}': key 'batch.name': got {_describe(name)}, expected "
                          "a name of 1-64 letters, digits, '_', '-' or '.'")
    description = raw.get("description", "") or ""
    if not isinstance(description, str):
        raise ConfigError(f"batch file '{file}': key 'batch.description': expected text")
    combine = raw.get("combine", "product")
    if combine not in ("product", "zip"):
        raise ConfigError(f"batch file '{file}': key 'batch.combine': got {_describe(combine)}, "
                          "expected product or zip")
    base_raw, source, base_name = _resolve_base(raw["base"], path)
    common = _override_items(raw.get("set"), "batch.set", file)
    sweep_keys, points = _sweep_points(raw.get("sweep"), combine, file)

    entries: list[tuple[str | None, list[tuple[str, Any]], str]] = [
        (None, list(zip(sweep_keys, point)), "sweep") for point in points]
    explicit = raw.get("cases")
    if explicit is not None and not isinstance(explicit, list):
        raise ConfigError(f"batch file '{file}': key 'batch.cases': got {_describe(explicit)}, "
                          "expected a list of cases ({label: ..., set: {key: value}})")
    for i, item in enumerate(explicit or []):
        where = f"batch.cases[{i}]"
        if isinstance(item, Mapping) and item and set(item) <= set(CASE_KEYS):
            label = item.get("label")
            if label is not None and not isinstance(label, str):
                raise ConfigError(f"batch file '{file}': key '{where}.label': expected text")
            entries.append((label, _override_items(item.get("set") or {}, f"{where}.set", file),
                            "case"))
        elif isinstance(item, Mapping):
            entries.append((None, _override_items(item, where, file), "case"))
        else:
            raise ConfigError(f"batch file '{file}': key '{where}': got {_describe(item)}, "
                              "expected {label: ..., set: {key: value}} or a mapping of overrides")
    if not entries:
        entries = [("base", [], "base")]

    cases, errors = [], []
    for index, (label, items, origin) in enumerate(entries, 1):
        label = label or (", ".join(f"{k}={_format_value(v)}" for k, v in items) or "base")
        texts = [f"{k}={_yaml_text(v)}" for k, v in common + items]
        try:
            merged = apply_overrides(base_raw, texts)
            cfg = config_from_dict(merged, source=source)
        except ConfigError as exc:
            errors.append(f"case {index} ({label}): {exc}")
            continue
        cases.append(Case(index=index, label=label, overrides=tuple(items), config=cfg,
                          key=case_key(cfg), memory_bytes=estimate_case_memory(cfg),
                          origin=origin))
    if errors:
        head = (f"batch file '{file}': {len(errors)} of {len(entries)} cases are invalid; "
                "nothing was run")
        raise ConfigError(head + ":\n  " + "\n  ".join(errors))
    case_keys = list(sweep_keys)
    for _, items, _ in entries:
        case_keys += [k for k, _ in items if k not in case_keys]
    return BatchSpec(name=name, path=path, base=base_name, description=description,
                     combine=combine, common=tuple(common), sweep_keys=tuple(sweep_keys),
                     case_keys=tuple(case_keys), cases=tuple(cases))


# --------------------------------------------------------------------------- keys, memory
def _file_digest(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def case_key(cfg) -> str:
    """Cache key of a resolved config: 16 hex digits of a SHA-256 over its YAML, the
    pipeline version and the bytes of a geometry file, if any."""
    from pipeline import __version__
    from pipeline.config import config_to_yaml

    digest = hashlib.sha256()
    digest.update(f"fe-reduced-body batch case v{RECORD_VERSION}\n".encode())
    digest.update(f"pipeline {__version__}\n".encode())
    digest.update(config_to_yaml(cfg).encode())
    geo_path = getattr(cfg.geometry, "path", "")
    if geo_path:
        try:
            digest.update(f"geometry file {_file_digest(geo_path)}\n".encode())
        except OSError:
            digest.update(f"geometry file {geo_path} unreadable\n".encode())
    return digest.hexdigest()[:16]


def portable_config(cfg):
    """``cfg`` with a relative geometry file path made absolute, as sent to workers (whose
    working folder may differ). The cache key is computed before, from ``cfg`` itself."""
    import dataclasses

    path = getattr(cfg.geometry, "path", "")
    if path and not os.path.isabs(path):
        return dataclasses.replace(cfg, geometry=dataclasses.replace(
            cfg.geometry, path=os.path.abspath(path)))
    return cfg


def predict_mesh_size(cfg) -> tuple[int, int] | None:
    """(nodes, tetrahedra) a gmsh mesh of ``cfg`` will have, before meshing; None if unknown.

    For the box: n_tet = V / h^3 (4.0 + 1.6 x + 0.25 x^2) with x = A h / V (surface A,
    volume V, size h) and P2 nodes = n_tet (1.35 + 0.5 x), P1 nodes = n_tet (0.17 + 0.12 x):
    fitted to gmsh HXT meshes of two boxes at h = 0.02 ... 0.0025 m, within +10..+30 %
    (conservative).
    """
    g = cfg.geometry
    if g.kind != "box":
        return None
    L, H, D = g.length, g.height, g.depth
    volume = L * H * D
    area = 2.0 * (L * H + L * D + H * D)
    h = cfg.mesh.size
    x = area * h / volume
    n_tet = volume / h ** 3 * (4.0 + 1.6 * x + 0.25 * x * x)
    per_tet = (1.35 + 0.5 * x) if cfg.mesh.order == 2 else (0.17 + 0.12 * x)
    return int(math.ceil(n_tet * per_tet)), int(math.ceil(n_tet))


def estimate_case_memory(cfg) -> int | None:
    """Peak bytes a case will need (pipeline.fe.resources), or None when the mesh size
    cannot be predicted without meshing (geometry from a file)."""
    from pipeline.fe.resources import estimate_memory_bytes

    pred = predict_mesh_size(cfg)
    if pred is None:
        return None
    n_nodes, n_tet = pred
    return int(estimate_memory_bytes(n_nodes, n_tet, cfg.mesh.order, cfg.modes.count))


# --------------------------------------------------------------------------- on the worker
_WARM = False


def _warm_imports() -> None:
    """Import the heavy modules once in the worker, so forked cases start at once."""
    global _WARM
    if _WARM:
        return
    import importlib

    for name in ("numpy", "scipy.sparse", "scipy.sparse.linalg", "scipy.linalg", "h5py",
                 "meshio", "skfem", "yaml", "gmsh", "pipeline.run", "pipeline.fe.mesh",
                 "pipeline.fe.space", "pipeline.fe.assemble", "pipeline.fe.body", "pipeline.solve.eigen",
                 "pipeline.fe.regions", "pipeline.fe.resources", "pipeline.store.h5file",
                 "pipeline.solve.factorize", "pipeline.reduce.build"):
        try:
            importlib.import_module(name)
        except Exception:  # an optional module; the case itself will report real problems
            pass
    _WARM = True


def _set_parent_death_signal() -> None:
    """Linux: SIGKILL this process when the thread that forked it dies."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except Exception:
        pass


def _run_here(cfg, target: Path, workdir: Path) -> dict:
    """Run one case in this process; the record of what happened (never raises)."""
    from pipeline.run import run_pipeline

    t0 = time.perf_counter()
    out: dict[str, Any] = {"status": "failed"}
    try:
        result = run_pipeline(cfg, target, mesh_dir=workdir / "mesh")
        out = {
            "status": "ok",
            "n_dofs": int(result.n_dofs),
            "n_free_dofs": int(result.n_free),
            "n_elements": int(result.n_elements),
            "frequencies_hz": [float(f) for f in result.frequencies_hz],
            "mode_labels": [str(s) for s in result.labels],
            "mass_kg": float(result.mass),
            "times_s": {k: float(v) for k, v in result.times.items()},
            "peak_memory_mb": float(result.peak_memory_mb),
            "solver": str(result.backend),
        }
    except PipelineError as exc:
        out.update(error=str(exc), error_type=type(exc).__name__)
    except MemoryError:
        out.update(error="out of memory (MemoryError)", error_type="MemoryError")
    except Exception as exc:  # a bug: keep the traceback in the record and the log
        log.exception("case failed with an unexpected error")
        out.update(error=f"{type(exc).__name__}: {exc}", error_type=type(exc).__name__,
                   traceback=traceback.format_exc())
    out["compute_s"] = time.perf_counter() - t0
    return out


def _child(cfg, target: Path, workdir: Path) -> None:
    """The body of a forked case process: stdout, stderr and the log go to run.log (C
    libraries print there too); run; write result.json."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the batch, not one case
    fd = os.open(workdir / "run.log", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    # Python-level streams may be replaced (pytest's capture, a worker's log redirect)
    sys.stdout = open(1, "w", buffering=1, encoding="utf-8", errors="replace", closefd=False)
    sys.stderr = open(2, "w", buffering=1, encoding="utf-8", errors="replace", closefd=False)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                                           "%H:%M:%S"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.INFO)
    for name in ("distributed", "tornado", "asyncio"):
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        out = _run_here(cfg, target, workdir)
        write_text(workdir / "result.json", json.dumps(out))
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()


def _run_forked(cfg, target: Path, workdir: Path, memory_limit: int | None) -> dict:
    """Run one case in a forked child; watch its memory; the record (never raises)."""
    import signal

    parent = os.getpid()
    pid = os.fork()
    if pid == 0:  # the child: never return into the worker's code
        code = 1
        try:
            _set_parent_death_signal()
            if os.getppid() == parent:
                _child(cfg, target, workdir)
                code = 0
        except BaseException:
            pass
        finally:
            os._exit(code)

    kill_at = KILL_FRACTION * memory_limit if memory_limit else None
    killed_for_memory = 0
    try:
        import psutil

        proc = psutil.Process(pid)
    except Exception:
        proc = None
    try:
        while True:
            got, status, usage = os.wait4(pid, os.WNOHANG)
            if got == pid:
                break
            if kill_at and proc is not None:
                try:
                    rss = proc.memory_info().rss
                except Exception:
                    rss = 0
                if rss > kill_at:
                    killed_for_memory = rss
                    os.kill(pid, signal.SIGKILL)
                    _, status, usage = os.wait4(pid, 0)
                    break
            time.sleep(0.1)
    except BaseException:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        raise
    code = os.waitstatus_to_exitcode(status)
    peak_mb = usage.ru_maxrss / 1024.0
    result_file = workdir / "result.json"
    if killed_for_memory:
        out = {"status": "failed", "error_type": "ResourceError",
               "error": f"stopped at {killed_for_memory / 1e9:.1f} GB, beyond {KILL_FRACTION:.0%} "
                        f"of the worker's memory limit ({memory_limit / 1e9:.1f} GB); the "
                        "estimate was too low: run it with fewer workers or a coarser mesh"}
    elif result_file.exists():
        out = json.loads(result_file.read_text(encoding="utf-8"))
    elif code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = str(-code)
        hint = " (out of memory? the kernel's OOM killer sends SIGKILL)" if code == -9 else ""
        out = {"status": "failed", "error_type": "CaseProcessDied",
               "error": f"the case process was killed by signal {name}{hint}"}
    else:
        out = {"status": "failed", "error_type": "CaseProcessDied",
               "error": f"the case process exited with code {code} without a result"}
    out["peak_memory_mb"] = peak_mb  # the child's own peak RSS (wait4), MB
    return out


def _shared_folder(cases_dir: str, token: str) -> bool:
    try:
        return (Path(cases_dir) / ".batch-token").read_text(encoding="utf-8").strip() == token
    except OSError:
        return False


def run_case_task(cfg, key: str, cases_dir: str, token: str, write_here: bool | None) -> dict:
    """The Dask task of one case (runs on a worker). Never raises for a case failure.

    ``write_here``: True writes ``<cases_dir>/<key>.h5`` from the worker, False sends the
    file's bytes back, None decides by checking the token file in ``cases_dir``.
    """
    started = time.time()
    memory_limit = None
    worker_name = socket.gethostname()
    try:
        from distributed import get_worker

        worker = get_worker()
        worker_name = str(worker.address)
        memory_limit = getattr(getattr(worker, "memory_manager", None), "memory_limit", None)
        worker.log_event(EVENT_TOPIC, {"token": token, "key": key, "event": "started"})
    except Exception:  # not on a Dask worker (tests, a plain call)
        pass
    shared = _shared_folder(cases_dir, token) if write_here is None else write_here
    with tempfile.TemporaryDirectory(prefix=f"fe-batch-{key}-") as tmp:
        workdir = Path(tmp)
        target = Path(cases_dir) / f"{key}.h5" if shared else workdir / f"{key}.h5"
        if sys.platform.startswith("linux") and hasattr(os, "fork"):
            _warm_imports()
            out = _run_forked(cfg, target, workdir, memory_limit)
        else:
            out = _run_here(cfg, target, workdir)
        log_file = workdir / "run.log"
        out["log"] = log_file.read_text(encoding="utf-8", errors="replace") \
            if log_file.exists() else ""
        if out.get("status") == "ok" and not shared:
            out["h5_bytes"] = target.read_bytes()
    finished = time.time()
    out.update(key=key, worker=worker_name, written_by_worker=bool(shared),
               started_utc=_utc(started), finished_utc=_utc(finished), started_unix=started,
               finished_unix=finished, wall_s=finished - started)
    return out


# --------------------------------------------------------------------------- records, cache
def _utc(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))



def _write_record(cases_dir: Path, record: dict) -> None:
    write_bytes(cases_dir / f"{record['key']}.json",
                  (json.dumps(record, indent=1, sort_keys=True) + "\n").encode())


def _read_record(cases_dir: Path, key: str) -> dict | None:
    try:
        record = json.loads((cases_dir / f"{key}.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("key") == key else None


def _record_from_file(path: Path, case: Case, verify: bool = True) -> dict:
    """A case record rebuilt from its HDF5 file (verified); FileFormatError if unusable."""
    import numpy as np

    from pipeline import __version__
    from pipeline.config import config_to_yaml
    from pipeline.store.h5file import open_verified, read_strings

    with open_verified(path, verify_checksum=verify) as h5:
        stored = h5.attrs.get("config_yaml")
        if stored is not None and str(stored) != config_to_yaml(portable_config(case.config)):
            raise FileFormatError(f"file '{path}': its config differs from case {case.index}'s")
        if str(h5.attrs.get("pipeline_version")) != __version__:
            raise FileFormatError(f"file '{path}': written by pipeline "
                                  f"{h5.attrs.get('pipeline_version')}, not {__version__}")
        mesh = h5["mesh"].attrs
        run = dict(h5["run"].attrs) if "run" in h5 else {}
        cells = sum(len(h5["mesh/cells"][k]) for k in h5["mesh/cells"])
        record = {
            "status": "ok",
            "n_dofs": int(mesh["n_dofs"]),
            "n_free_dofs": int(mesh["n_free_dofs"]),
            "n_elements": int(cells),
            "frequencies_hz": [float(f) for f in np.atleast_1d(h5["modes/frequencies_hz"][()])],
            "mode_labels": read_strings(h5["modes/labels"]),
            "mass_kg": float(h5["body/mass"][()]),
            "times_s": {k[:-2]: float(v) for k, v in run.items() if k.endswith("_s")},
            "peak_memory_mb": float(run.get("peak_memory_mb", float("nan"))),
            "solver": str(run.get("solver", "")),
            "rebuilt_from_file": True,
        }
    return record


def _finish_record(record: dict, case: Case, h5: Path | None) -> dict:
    from pipeline import __version__

    record = {k: v for k, v in record.items() if k not in ("h5_bytes", "log")}
    record.update(key=case.key, record_version=RECORD_VERSION, pipeline_version=__version__,
                  label=case.label, overrides=case.override_strings,
                  memory_estimate_mb=None if case.memory_bytes is None
                  else case.memory_bytes / 1e6)
    if h5 is not None and h5.exists():
        st = h5.stat()
        record.update(file=h5.name, file_size=st.st_size, file_mtime_ns=st.st_mtime_ns)
    else:
        record.pop("file", None)
    return record


def _cached_record(cases_dir: Path, case: Case, verify: bool) -> dict | None:
    """The record of a finished case whose file is intact, else None (compute it)."""
    h5 = cases_dir / f"{case.key}.h5"
    if not h5.exists():
        return None
    record = _read_record(cases_dir, case.key)
    st = h5.stat()
    if (not verify and record and record.get("status") == "ok"
            and record.get("file_size") == st.st_size
            and record.get("file_mtime_ns") == st.st_mtime_ns):
        return record
    try:
        rebuilt = _record_from_file(h5, case)
    except FileFormatError as exc:
        log.warning("case %d: %s; computing it again", case.index, exc)
        return None
    if record and record.get("status") == "ok":
        rebuilt = {**rebuilt, **{k: v for k, v in record.items() if k != "rebuilt_from_file"}}
    rebuilt = _finish_record(rebuilt, case, h5)
    _write_record(cases_dir, rebuilt)
    return rebuilt


# --------------------------------------------------------------------------- execution
@dataclass
class CaseOutcome:
    """What happened to one case in this run."""

    case: Case
    status: str                      # done | cached | failed | not run
    record: dict = field(default_factory=dict)
    h5: Path | None = None

    @property
    def error(self) -> str:
        return str(self.record.get("error", ""))


@dataclass
class BatchResult:
    spec: BatchSpec
    outdir: Path
    outcomes: list[CaseOutcome]
    wall_s: float
    workers: str
    files: dict[str, Path] = field(default_factory=dict)

    def count(self, status: str) -> int:
        return sum(o.status == status for o in self.outcomes)

    @property
    def failed(self) -> list[CaseOutcome]:
        return [o for o in self.outcomes if o.status == "failed"]


@contextlib.contextmanager
def _batch_lock(outdir: Path):
    """Hold an exclusive lock on the output folder (one batch run at a time)."""
    import fcntl

    path = outdir / ".lock"
    fh = open(path, "a+")
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.seek(0)
            holder = fh.read().strip() or "?"
            raise PipelineError(f"batch output folder '{outdir}' is in use by another batch run "
                                f"(pid {holder}); wait for it to finish or choose another -o") \
                from None
        fh.seek(0)
        fh.truncate()
        fh.write(str(os.getpid()))
        fh.flush()
        yield
    finally:
        fh.close()


def _clean_partials(cases_dir: Path) -> int:
    n = 0
    for p in cases_dir.glob(".*.partial*"):
        with contextlib.suppress(OSError):
            p.unlink()
            n += 1
    return n


class _Progress:
    """A tqdm bar over cases (done / running / failed / cached) plus one line per case."""

    def __init__(self, total: int, name: str, enabled: bool | None, echo: Callable[[str], None]):
        from tqdm import tqdm

        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.bar = tqdm(total=total, desc=name, unit="case", disable=not self.enabled,
                        dynamic_ncols=True, file=sys.stderr,
                        bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} "
                                   "[{elapsed}<{remaining}]{postfix}")
        self.echo = echo
        self.done = self.failed = self.cached = 0
        self.running: set[str] = set()

    def line(self, text: str) -> None:
        if self.enabled:
            self.bar.write(text, file=sys.stderr)
        else:
            self.echo(text)

    def refresh(self) -> None:
        self.bar.set_postfix_str(f"done {self.done}, running {len(self.running)}, failed "
                                 f"{self.failed}, cached {self.cached}", refresh=True)

    def advance(self, n: int, status: str) -> None:
        setattr(self, status, getattr(self, status) + n)
        self.bar.update(n)
        self.refresh()

    def close(self) -> None:
        self.refresh()
        self.bar.close()


def _worker_budgets(client) -> dict[str, dict]:
    try:
        info = client.scheduler_info(n_workers=-1)
    except TypeError:
        info = client.scheduler_info()
    return dict(info.get("workers", {}))


def _start_local_cluster(n_workers: int, memory_limit: int, threads_per_case: int):
    """Worker processes on 127.0.0.1, one thread each; each has ``memory_limit`` (the
    machine's available memory: a case may use it all while the others wait, the client
    admits cases by their estimates) and advertises 80 % of it as the ``memory``
    resource."""
    import dask
    from distributed import Client, LocalCluster

    env = {"OMP_NUM_THREADS": threads_per_case, "MKL_NUM_THREADS": threads_per_case,
           "OPENBLAS_NUM_THREADS": threads_per_case}
    with dask.config.set({f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in env.items()}):
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                               memory_limit=memory_limit, host="127.0.0.1",
                               dashboard_address=None, silence_logs=logging.WARNING,
                               # its HTTP server (health routes) would take :8787 otherwise
                               scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                               resources={"memory": int(BUDGET_FRACTION * memory_limit)})
        client = Client(cluster)
    return cluster, client


def _plan_local_workers(requested: int | None, pending: Sequence[Case]) -> int:
    """Local worker processes: as requested, else one per core (no more than cases)."""
    if requested:
        return requested
    return max(1, min(os.cpu_count() or 1, len(pending)))


def admit(queue: Sequence[Case], running_bytes: int, free_slots: int,
          budget: float | None) -> list[Case]:
    """Cases of ``queue`` to start now, in order, skipping ahead past a case that does not
    fit: at most ``free_slots``, and the running cases' estimates plus theirs within
    ``budget`` (no limit when None). A case starts alone whatever its estimate when
    nothing runs (one that exceeds the budget is refused before, by split_by_budget)."""
    chosen: list[Case] = []
    for case in queue:
        if len(chosen) >= free_slots:
            break
        need = case.memory_bytes or 0
        if budget is None or (running_bytes == 0 and not chosen) \
                or running_bytes + need <= budget:
            chosen.append(case)
            running_bytes += need
    return chosen


def split_by_budget(pending: Sequence[Case], budgets: Sequence[float]
                    ) -> tuple[list[Case], list[tuple[Case, str]]]:
    """Cases that fit some worker's advertised ``memory`` and those that fit none (with
    the reason). With no budgets (no worker advertises memory) every case runs."""
    if not budgets:
        return list(pending), []
    largest = max(budgets)
    fits, refused = [], []
    for case in pending:
        if case.memory_bytes is not None and case.memory_bytes > largest:
            refused.append((case, f"needs about {case.memory_bytes / 1e9:.1f} GB (estimate), more "
                                  f"than the {largest / 1e9:.1f} GB cases may use on any worker "
                                  "(80 % of the memory available to a local cluster, or a "
                                  "worker's 'memory' resource); free memory, use a larger "
                                  "worker or a coarser mesh"))
        else:
            fits.append(case)
    return fits, refused


def _execute(pending: list[Case], weights: Mapping[str, int], cases_dir: Path,
             outcomes: dict[str, dict], progress: _Progress, *, workers: int | None,
             scheduler: str | None, write_here: bool | None, token: str,
             start_timeout: float) -> str:
    """Run ``pending`` (unique keys) on a cluster; fill ``outcomes[key]``. ``weights``:
    how many cases of the batch share each key. Returns a line describing the cluster."""
    from distributed import Client, wait
    from distributed.client import FIRST_COMPLETED

    from pipeline.fe.resources import available_memory_bytes

    cluster = None
    machine_budget: float | None = None  # local: the estimates of running cases share it
    slots = 1 << 30                      # local: one case per worker process at a time
    if scheduler:
        client = Client(scheduler, timeout=start_timeout)
        try:
            client.wait_for_workers(1, timeout=start_timeout)
        except Exception:
            client.close()
            raise PipelineError(f"scheduler {scheduler}: no worker joined within "
                                f"{start_timeout:g} s") from None
        info = _worker_budgets(client)
        budgets = [float(w["resources"]["memory"]) for w in info.values()
                   if "memory" in (w.get("resources") or {})]
        threads = sum(int(w.get("nthreads", 1)) for w in info.values())
        where = (f"scheduler {scheduler} ({len(info)} workers, {threads} threads"
                 + (f", memory resource up to {max(budgets) / 1e9:.1f} GB)" if budgets else
                    "; no worker advertises a 'memory' resource: scheduling without memory "
                    "estimates; start workers with --resources memory=BYTES)"))
        if workers:
            log.warning("--workers is ignored with --scheduler")
    else:
        n = _plan_local_workers(workers, pending)
        available = available_memory_bytes()
        threads_per_case = max(1, (os.cpu_count() or 1) // n)
        cluster, client = _start_local_cluster(n, available, threads_per_case)
        budgets = [BUDGET_FRACTION * available] * n
        machine_budget = BUDGET_FRACTION * available
        slots = n
        where = (f"local cluster ({n} worker process{'es' if n > 1 else ''}, "
                 f"{threads_per_case} thread{'s' if threads_per_case > 1 else ''} per case; "
                 f"cases share {machine_budget / 1e9:.1f} GB by their estimates)")
    progress.line(f"running {len(pending)} case(s) on {where}")
    try:
        runnable, refused = split_by_budget(pending, budgets)
        for case, reason in refused:
            outcomes[case.key] = {"status": "failed", "error_type": "ResourceError",
                                  "error": reason}
            _write_record(cases_dir, _finish_record(outcomes[case.key], case, None))
            progress.line(f"case {case.index} ({case.label}): FAILED: {reason}")
            progress.advance(weights.get(case.key, 1), "failed")
        by_key = {c.key: c for c in pending}

        def on_event(event):
            msg = event[1] if isinstance(event, tuple) else event
            if isinstance(msg, Mapping) and msg.get("token") == token \
                    and msg.get("event") == "started" and msg.get("key") in by_key \
                    and msg["key"] not in outcomes:
                progress.running.add(msg["key"])

        with contextlib.suppress(Exception):
            client.subscribe_topic(EVENT_TOPIC, on_event)
        futures: dict[Any, Case] = {}
        queue = list(runnable)
        not_done: set = set()

        def submit_more() -> None:
            running = sum(futures[f].memory_bytes or 0 for f in not_done)
            for case in admit(queue, running, slots - len(not_done), machine_budget):
                queue.remove(case)
                kwargs = {}
                if budgets and case.memory_bytes is not None:
                    kwargs["resources"] = {"memory": case.memory_bytes}
                fut = client.submit(run_case_task, portable_config(case.config), case.key,
                                    str(cases_dir.resolve()), token, write_here,
                                    key=f"fe-case-{case.key}-{token[:8]}", pure=False,
                                    retries=0, **kwargs)
                futures[fut] = case
                not_done.add(fut)

        try:
            submit_more()
            while not_done:
                try:
                    done, rest = wait(not_done, timeout=0.5, return_when=FIRST_COMPLETED)
                except TimeoutError:  # (dask.distributed.TimeoutError is the builtin one)
                    progress.refresh()
                    continue
                not_done.clear()
                not_done.update(rest)
                for fut in done:
                    case = futures[fut]
                    record = _collect(fut, case, cases_dir, outcomes, progress)
                    progress.advance(weights.get(case.key, 1),
                                     "done" if record["status"] == "ok" else "failed")
                submit_more()
        except BaseException:
            for fut in not_done:
                fut.cancel()
            raise
        finally:
            with contextlib.suppress(Exception):
                client.unsubscribe_topic(EVENT_TOPIC)
    finally:
        with contextlib.suppress(Exception):
            client.close(timeout=10)
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=20)
    return where


def _collect(fut, case: Case, cases_dir: Path, outcomes: dict[str, dict],
             progress: _Progress) -> dict:
    """Store the result of one finished future: file (if sent back), record, log."""
    h5 = cases_dir / f"{case.key}.h5"
    try:
        result = fut.result()
    except Exception as exc:  # KilledWorker, a worker without the pipeline, a lost scheduler
        name = type(exc).__name__
        hint = (" (the worker process died more than the allowed number of times while "
                "running it)" if name == "KilledWorker" else "")
        result = {"status": "failed", "error_type": name, "error": f"{name}: {exc}{hint}"}
    log_text = result.pop("log", "")
    data = result.pop("h5_bytes", None)
    if result.get("status") == "ok":
        try:
            if data is not None:
                write_bytes(h5, data)
            result = {**_record_from_file(h5, case, verify=data is not None), **result}
        except (OSError, FileFormatError) as exc:
            result = {**result, "status": "failed", "error_type": type(exc).__name__,
                      "error": f"the case ran but its file is not usable: {exc}"}
    if log_text:
        with contextlib.suppress(OSError):
            write_bytes(cases_dir / f"{case.key}.log", log_text.encode())
    record = _finish_record(result, case, h5 if result.get("status") == "ok" else None)
    _write_record(cases_dir, record)
    outcomes[case.key] = record
    progress.running.discard(case.key)
    if record["status"] == "ok":
        t = record.get("wall_s", 0.0)
        progress.line(f"case {case.index} ({case.label}): done in {t:.1f} s, "
                      f"{record.get('n_dofs', '?')} DOFs, peak "
                      f"{record.get('peak_memory_mb', float('nan')):.0f} MB")
    else:
        progress.line(f"case {case.index} ({case.label}): FAILED: {record.get('error')}")
    return record


def run_batch(batch: str | Path | BatchSpec, output: str | Path | None = None, *,
              workers: int | None = None, scheduler: str | None = None, verify: bool = False,
              compute: bool = True, progress: bool | None = None, write_here: bool | None = None,
              start_timeout: float = 60.0, echo: Callable[[str], None] = print) -> BatchResult:
    """Run a batch: validate it, skip cached cases, compute the rest, write the report.

    ``output``: the batch folder (default ``outputs/<name>``). ``workers``: local worker
    processes (default one per core, fewer for memory). ``scheduler``: address of an
    existing Dask scheduler instead of a local cluster. ``verify``: check the checksum of
    every cached file, not only its size and time. ``compute=False``: only (re)write the
    summary and report from what is there. Case failures do not raise: see
    :attr:`BatchResult.failed`.
    """
    from pipeline.apps import report

    t0 = time.perf_counter()
    spec = batch if isinstance(batch, BatchSpec) else load_batch(batch)
    outdir = Path(output) if output else Path("outputs") / spec.name
    cases_dir = outdir / "cases"
    cases_dir.mkdir(parents=True, exist_ok=True)
    where = "nothing to run"
    with _batch_lock(outdir):
        removed = _clean_partials(cases_dir)
        if removed:
            log.info("removed %d partial file(s) of an interrupted run", removed)
        token = secrets.token_hex(16)
        (cases_dir / ".batch-token").write_text(token, encoding="utf-8")
        outcomes: dict[str, dict] = {}
        status: dict[str, str] = {}
        unique = list({c.key: c for c in spec.cases}.values())
        for case in unique:
            record = _cached_record(cases_dir, case, verify)
            if record is not None:
                outcomes[case.key] = record
                status[case.key] = "cached"
        pending = [c for c in unique if c.key not in outcomes]
        n_cached = sum(status.get(c.key) == "cached" for c in spec.cases)
        bar = _Progress(len(spec.cases), spec.name, progress, echo)
        try:
            bar.line(f"batch '{spec.name}' ({spec.path}): {len(spec.cases)} cases, {n_cached} "
                     f"already computed (cached, skipped), {len(pending)} to run")
            bar.advance(n_cached, "cached")
            if pending and compute:
                weights: dict[str, int] = {}
                for case in spec.cases:
                    weights[case.key] = weights.get(case.key, 0) + 1
                where = _execute(pending, weights, cases_dir, outcomes, bar, workers=workers,
                                 scheduler=scheduler, write_here=write_here, token=token,
                                 start_timeout=start_timeout)
        finally:
            bar.close()
            with contextlib.suppress(OSError):
                (cases_dir / ".batch-token").unlink()
        result_outcomes = []
        for case in spec.cases:
            record = outcomes.get(case.key)
            if record is None:
                st = "not run"
                record = _read_record(cases_dir, case.key) or {}
                if record.get("status") == "ok":
                    record = {}
            elif status.get(case.key) == "cached":
                st = "cached"
            else:
                st = "done" if record.get("status") == "ok" else "failed"
            h5 = cases_dir / f"{case.key}.h5"
            result_outcomes.append(CaseOutcome(case, st, record,
                                               h5 if st in ("done", "cached") else None))
        result = BatchResult(spec, outdir, result_outcomes, time.perf_counter() - t0, where)
        result.files = report.write_outputs(result)
        result.wall_s = time.perf_counter() - t0
    return result


# --------------------------------------------------------------------------- command line
def _print_result(result: BatchResult) -> None:
    n = len(result.outcomes)
    print(f"batch '{result.spec.name}': {n} cases: {result.count('done')} computed, "
          f"{result.count('cached')} cached, {len(result.failed)} failed"
          + (f", {result.count('not run')} not run" if result.count("not run") else "")
          + f" in {result.wall_s:.1f} s")
    for name in ("summary", "report"):
        if name in result.files:
            print(f"  {name}: {result.files[name]}")
    if result.failed:
        print(f"failed cases ({len(result.failed)}):")
        for o in result.failed:
            print(f"  case {o.case.index} ({o.case.label}) [{o.case.key}]: {o.error}")


def cmd_batch(args: argparse.Namespace) -> int:
    """``python -m pipeline batch FILE.yaml``: exit 0 when every case finished, 1 if any
    failed (they are listed), 2 for an invalid batch file (nothing runs)."""
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: got {args.workers}, expected at least 1")
    if getattr(args, "dry_run", False):
        spec = load_batch(args.file)
        print(f"batch '{spec.name}' ({spec.path}): {len(spec.cases)} valid cases, base "
              f"{spec.base}")
        for c in spec.cases:
            est = "?" if c.memory_bytes is None else f"{c.memory_bytes / 1e9:.2f} GB"
            print(f"  case {c.index:3d} [{c.key}] memory ~{est}: {c.label}")
        return 0
    if logging.getLogger().level > logging.DEBUG:
        import distributed  # noqa: F401  (it configures its loggers when imported)

        for name in ("distributed", "tornado", "bokeh"):
            logging.getLogger(name).setLevel(logging.WARNING)
    try:
        result = run_batch(args.file, args.output, workers=args.workers,
                           scheduler=args.scheduler, verify=args.verify,
                           compute=not args.report_only)
    except KeyboardInterrupt:
        print("error: batch interrupted; finished cases are kept: run the same command again "
              "to resume", file=sys.stderr)
        return 130
    _print_result(result)
    if result.failed:
        return 1
    return 0


def add_batch_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``batch`` on the CLI's subparsers (``python -m pipeline batch ...``)."""
    p = subparsers.add_parser(
        "batch", help="run a YAML batch of cases (sweep / explicit) in parallel, cached",
        description="Run every case of a batch file on a local Dask cluster (default) or an "
                    "existing one, skip cases already computed, and write summary.csv and "
                    "report.html. Exits 1 if any case failed (listed at the end).")
    p.add_argument("file", help="batch YAML file (batch: {base, sweep, combine, cases, ...})")
    p.add_argument("--workers", type=int, metavar="N",
                   help="local worker processes (default: one per core, fewer if memory needs)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="use an existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("-o", "--output", metavar="OUTDIR",
                   help="batch output folder (default outputs/<batch name>)")
    p.add_argument("--verify", action="store_true",
                   help="verify the checksum of every cached file (slower), not only size/time")
    p.add_argument("--dry-run", action="store_true",
                   help="validate the batch and list its cases, keys and memory estimates")
    p.add_argument("--report-only", action="store_true",
                   help="compute nothing; rewrite summary.csv and report.html from the records")
    p.set_defaults(func=cmd_batch)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m pipeline.apps.batch FILE ...``: the same as ``python -m pipeline batch FILE ...``
    (one CLI, one error handling: :func:`pipeline.cli.main`)."""
    from pipeline.cli.main import main as cli_main

    argv = list(sys.argv[1:] if argv is None else argv)
    return cli_main(argv if argv[:1] == ["batch"] else ["batch", *argv])


if __name__ == "__main__":  # pragma: no cover
    from pipeline.apps.batch import main as _main  # the module's own name, for pickling

    sys.exit(_main())
