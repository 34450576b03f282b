"""Running one case on a worker: the Dask task :func:`run_case_task`.

On Linux each case runs in a child process forked by the worker (the heavy modules are
imported once before, :func:`pipeline.run.preload_stage_modules`), so its peak memory is
its own (``wait4``'s ``ru_maxrss``), a crash (gmsh, MKL, the kernel's OOM killer) fails
only that case, and a case whose resident memory passes ``KILL_FRACTION`` of the worker's
memory limit is stopped with a clear message. The child dies with the worker thread that
forked it (``PR_SET_PDEATHSIG``). Elsewhere the case runs in the worker's own process.

The child writes its :class:`~pipeline.apps.batch.cache.CaseRecord` to ``result.json``
and its log (stdout, stderr and Python logging, C libraries included) to ``run.log`` in a
temporary folder. The task returns a :class:`TaskResult`: the record, the log and, when
the worker does not see the client's folder, the HDF5 file's bytes.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline._util.atomic import write_text
from pipeline.apps.batch.cache import CaseRecord, failure
from pipeline.config import Config
from pipeline.errors import PipelineError
from pipeline.run import preload_stage_modules, run_pipeline

log = logging.getLogger(__name__)

__all__ = ["EVENT_TOPIC", "KILL_FRACTION", "TOKEN_FILE", "TaskResult", "run_case_task"]

EVENT_TOPIC = "fe-reduced-body-batch"
# a case is stopped when its own RSS passes this share of the worker's memory limit
KILL_FRACTION = 0.95
TOKEN_FILE = ".batch-token"
POLL_S = 0.1
_PRELOADED = False


@dataclass(frozen=True)
class TaskResult:
    """What the task of one case sends back to the client.

    ``record``: what happened; ``log``: the case's log text; ``h5_bytes``: the HDF5 file
    when the worker could not write it into the client's folder, else None. Read access by
    name as well (``result["status"]``: the record's fields, ``"log"``, ``"h5_bytes"``).
    """

    record: CaseRecord
    log: str = ""
    h5_bytes: bytes | None = None

    def __getitem__(self, name: str) -> Any:
        if name in ("log", "h5_bytes"):
            return getattr(self, name)
        return self.record[name]


def utc_text(t: float) -> str:
    """Unix time ``t`` as ISO 8601 UTC text (seconds)."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))


def preload_once() -> None:
    """Import the heavy modules once in the worker, so forked cases start at once."""
    global _PRELOADED
    if not _PRELOADED:
        preload_stage_modules()
        _PRELOADED = True


def set_parent_death_signal() -> None:
    """Linux: SIGKILL this process when the thread that forked it dies."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except Exception:
        pass


def run_here(cfg: Config, target: Path, workdir: Path) -> CaseRecord:
    """Run one case in this process; the record of what happened (never raises)."""
    t0 = time.perf_counter()
    try:
        result = run_pipeline(cfg, target)  # the mesh stays private to the run
        record = CaseRecord(
            status="ok",
            n_dofs=int(result.n_dofs),
            n_free_dofs=int(result.n_free),
            n_elements=int(result.n_elements),
            frequencies_hz=tuple(float(f) for f in result.frequencies_hz),
            mode_labels=tuple(str(s) for s in result.labels),
            mass_kg=float(result.mass),
            times_s={k: float(x) for k, x in result.times.items()},
            peak_memory_mb=float(result.peak_memory_mb),
            solver=str(result.backend))
    except PipelineError as exc:
        record = failure(type(exc).__name__, str(exc))
    except MemoryError:
        record = failure("MemoryError", "out of memory (MemoryError)")
    except Exception as exc:  # a bug: keep the traceback in the record and the log
        log.exception("case failed with an unexpected error")
        record = failure(type(exc).__name__, f"{type(exc).__name__}: {exc}").replace(
            traceback=traceback.format_exc())
    return record.replace(compute_s=time.perf_counter() - t0)


def child_main(cfg: Config, target: Path, workdir: Path) -> None:
    """The body of a forked case process: stdout, stderr and the log go to run.log (C
    libraries print there too); run; write result.json."""
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
        write_text(workdir / "result.json", run_here(cfg, target, workdir).to_json())
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()


def died_record(code: int) -> CaseRecord:
    """The record of a case process that ended (exit code ``code``) without a result."""
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = str(-code)
        hint = " (out of memory? the kernel's OOM killer sends SIGKILL)" if code == -9 else ""
        return failure("CaseProcessDied", f"the case process was killed by signal {name}{hint}")
    return failure("CaseProcessDied",
                   f"the case process exited with code {code} without a result")


def run_forked(cfg: Config, target: Path, workdir: Path, memory_limit: int | None
               ) -> CaseRecord:
    """Run one case in a forked child; watch its memory; the record (never raises)."""
    parent = os.getpid()
    pid = os.fork()
    if pid == 0:  # the child: never return into the worker's code
        code = 1
        try:
            set_parent_death_signal()
            if os.getppid() == parent:
                child_main(cfg, target, workdir)
                code = 0
        except BaseException:
            pass
        finally:
            os._exit(code)

    kill_at = KILL_FRACTION * memory_limit if memory_limit else None
    killed_for_memory = 0
    try:
        import psutil  # optional: without it the memory watch is off

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
            time.sleep(POLL_S)
    except BaseException:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        raise
    code = os.waitstatus_to_exitcode(status)
    result_file = workdir / "result.json"
    if killed_for_memory:
        record = failure("ResourceError",
                         f"stopped at {killed_for_memory / 1e9:.1f} GB, beyond "
                         f"{KILL_FRACTION:.0%} of the worker's memory limit "
                         f"({memory_limit / 1e9:.1f} GB); the estimate was too low: run it "
                         "with fewer workers or a coarser mesh")
    elif result_file.exists():
        try:
            record = CaseRecord.from_json(result_file.read_text(encoding="utf-8"))
        except (OSError, ValueError, TypeError):
            record = died_record(code)
    else:
        record = died_record(code)
    # the child's own peak RSS (wait4), MB
    return record.replace(peak_memory_mb=usage.ru_maxrss / 1024.0)


def sees_client_folder(cases_dir: str, token: str) -> bool:
    """Whether this worker sees the client's ``cases_dir`` (its token file holds ``token``)."""
    try:
        return (Path(cases_dir) / TOKEN_FILE).read_text(encoding="utf-8").strip() == token
    except OSError:
        return False


def run_case_task(cfg: Config, key: str, cases_dir: str, token: str,
                  write_here: bool | None) -> TaskResult:
    """The Dask task of one case (runs on a worker). Never raises for a case failure.

    ``write_here``: True writes ``<cases_dir>/<key>.h5`` from the worker, False sends the
    file's bytes back, None decides by checking the token file in ``cases_dir``.
    """
    started = time.time()
    memory_limit = None
    worker_name = socket.gethostname()
    try:
        from distributed import get_worker  # deferred: dask is the batch extra

        worker = get_worker()
        worker_name = str(worker.address)
        memory_limit = getattr(getattr(worker, "memory_manager", None), "memory_limit", None)
        worker.log_event(EVENT_TOPIC, {"token": token, "key": key, "event": "started"})
    except Exception:  # not on a Dask worker (tests, a plain call)
        pass
    shared = sees_client_folder(cases_dir, token) if write_here is None else write_here
    h5_bytes = None
    with tempfile.TemporaryDirectory(prefix=f"fe-batch-{key}-") as tmp:
        workdir = Path(tmp)
        target = Path(cases_dir) / f"{key}.h5" if shared else workdir / f"{key}.h5"
        if sys.platform.startswith("linux") and hasattr(os, "fork"):
            preload_once()
            record = run_forked(cfg, target, workdir, memory_limit)
        else:
            record = run_here(cfg, target, workdir)
        log_file = workdir / "run.log"
        log_text = log_file.read_text(encoding="utf-8", errors="replace") \
            if log_file.exists() else ""
        if record.ok and not shared:
            h5_bytes = target.read_bytes()
    finished = time.time()
    record = record.replace(key=key, worker=worker_name, written_by_worker=bool(shared),
                            started_utc=utc_text(started), finished_utc=utc_text(finished),
                            started_unix=started, finished_unix=finished,
                            wall_s=finished - started)
    return TaskResult(record, log_text, h5_bytes)
