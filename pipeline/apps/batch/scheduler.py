"""Running a batch: the cache check, the Dask cluster, memory-aware admission, locking,
progress, and the report at the end (:func:`run_batch`).

Execution: a local Dask cluster by default (worker processes, one per core, each with a
memory limit), or an existing cluster given by ``--scheduler tcp://host:8786``. Each
case runs as :func:`pipeline.apps.batch.worker.run_case_task`. Scheduling is memory
aware through Dask worker resources: each worker advertises ``memory`` (bytes cases may
use: ``BUDGET_FRACTION`` = 80 % of its memory limit for the local cluster; ``dask worker
--resources memory=19e9`` on your own cluster) and each case requests its estimate
(:func:`pipeline.apps.batch.cases.estimate_case_memory`), so two 10 GB cases never share
a 16 GB budget. On the local cluster the client also admits cases so that the estimates
of the running ones stay within the machine's budget (:func:`admit`). A case larger
than every worker's budget fails at once instead of waiting forever
(:func:`split_by_budget`).

Workers write the HDF5 file straight into ``cases/`` when they see the same folder as
the client (checked with a token file); otherwise they send the file's bytes back and
the client writes it. One batch run at a time holds the output folder (``.lock``,
``flock``). Partial files of an interrupted run are removed first; cases whose file is
intact are served from the cache (:mod:`pipeline.apps.batch.cache`).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import signal
import secrets
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from pipeline._util.atomic import private_folder, write_bytes, write_text
from pipeline._util.resources import environment_kept
from pipeline.apps.batch import report
from pipeline.apps.batch.cache import (
    CaseRecord,
    cached_record,
    clean_partials,
    failure,
    finish_record,
    h5_path,
    read_record,
    record_from_file,
    write_record,
)
from pipeline.apps.batch.cases import Case, portable_config
from pipeline.apps.batch.outcome import NO_RECORD, BatchResult, CaseOutcome
from pipeline.apps.batch.spec import BatchSpec, load_batch
from pipeline.apps.batch.worker import (
    EVENT_TOPIC,
    TOKEN_FILE,
    TaskResult,
    run_case_task,
)
from pipeline.errors import FileFormatError, PipelineError
from pipeline.run import available_memory_bytes

log = logging.getLogger(__name__)

__all__ = ["BUDGET_FRACTION", "admit", "plan_local_workers", "run_batch", "split_by_budget"]

# Share of a local worker's memory limit it advertises to cases (Dask pauses a worker at
# 80 % of its limit)
BUDGET_FRACTION = 0.8


@contextlib.contextmanager
def batch_lock(outdir: Path):
    """Hold an exclusive lock on the output folder (one batch run at a time)."""
    import fcntl  # POSIX only

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


class Progress:
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


# --------------------------------------------------------------------------- planning
def plan_local_workers(requested: int | None, pending: Sequence[Case]) -> int:
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


# --------------------------------------------------------------------------- cluster
def worker_info(client) -> dict[str, dict]:
    """The scheduler's description of every worker (address -> info)."""
    try:
        info = client.scheduler_info(n_workers=-1)
    except TypeError:
        info = client.scheduler_info()
    return dict(info.get("workers", {}))


def quiet_distributed_logs() -> None:
    """In a worker or nanny: log nothing more from dask (run on them when interrupted)."""
    for name in ("distributed", "tornado", "asyncio"):
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


def close_unfinished_clusters() -> None:
    """Close local clusters whose start was interrupted (their object never reached us),
    so that dask's exit hook does not print an assertion traceback closing them again."""
    from distributed.deploy.spec import SpecCluster

    logging.getLogger("distributed").setLevel(logging.CRITICAL + 1)
    # distributed has no public list of live clusters: its private registry (the one its
    # exit hook walks) where there is one, else every SpecCluster the garbage collector holds
    registry = getattr(SpecCluster, "_instances", None)
    if registry is not None and hasattr(registry, "discard"):
        clusters = list(registry)
    else:
        registry = None
        clusters = [o for o in gc.get_objects() if isinstance(o, SpecCluster)]
    for cluster in clusters:
        with contextlib.suppress(BaseException):
            cluster.close(timeout=5)
        if registry is not None:
            with contextlib.suppress(Exception):  # one cut short early may not compare
                registry.discard(cluster)


#: the worker processes' stderr (see :func:`start_forkserver_ignoring_sigint`) and how
#: much of it was relayed to the log
_WORKER_STDERR: dict = {}


def start_forkserver_ignoring_sigint() -> None:
    """Start multiprocessing's forkserver (with dask's preloads) with SIGINT ignored, so
    that every process it forks ignores SIGINT (see :func:`start_local_cluster`), and with
    its stderr in a private temporary file: what the workers print (their shutdown when
    interrupted, a start cut short) does not reach the terminal; :func:`relay_worker_output`
    passes it to the log."""
    import multiprocessing.forkserver
    import tempfile

    from distributed.utils import get_mp_context

    get_mp_context()  # sets the forkserver's preload list
    main = threading.current_thread() is threading.main_thread()
    if not _WORKER_STDERR:
        _WORKER_STDERR.update(file=tempfile.TemporaryFile(), relayed=0)
    sys.stderr.flush()
    saved = os.dup(2)
    blocked = (signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM,
                                                         signal.SIGHUP}) if main else None)
    handler = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        os.dup2(_WORKER_STDERR["file"].fileno(), 2)
        multiprocessing.forkserver.ensure_running()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        if main:
            signal.signal(signal.SIGINT, handler)
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def relay_worker_output(interrupted: bool) -> None:
    """Log what the worker processes printed since the last call: at debug level, and
    their warnings and errors at warning level unless the batch was interrupted."""
    if not _WORKER_STDERR:
        return
    fh = _WORKER_STDERR["file"]
    fh.seek(_WORKER_STDERR["relayed"])
    text = fh.read(1 << 20).decode("utf-8", "replace")
    _WORKER_STDERR["relayed"] = fh.seek(0, os.SEEK_END)
    for line in text.splitlines():
        loud = not interrupted and (" - WARNING - " in line or " - ERROR - " in line)
        log.log(logging.WARNING if loud else logging.DEBUG, "worker: %s", line)


def start_local_cluster(n_workers: int, memory_limit: int, threads_per_case: int,
                        local_directory: Path | None = None):
    """Worker processes on 127.0.0.1, one thread each; each has ``memory_limit`` (the
    machine's available memory: a case may use it all while the others wait, the client
    admits cases by their estimates) and advertises 80 % of it as the ``memory``
    resource."""
    import dask  # deferred: dask is the batch extra
    from distributed import Client, LocalCluster

    env = {"OMP_NUM_THREADS": threads_per_case, "MKL_NUM_THREADS": threads_per_case,
           "OPENBLAS_NUM_THREADS": threads_per_case}
    # Ctrl-C reaches the whole process group: only this process may handle it (it closes
    # the cluster; workers that got it too printed tracebacks). The workers are forked by a
    # forkserver started here with SIGINT ignored: the forkserver hands that disposition to
    # every process it forks (the nannies, and the workers they start), and asyncio then
    # installs no handler in them. SIGINT is ignored here only while the forkserver is
    # spawned (milliseconds), and blocked meanwhile so a Ctrl-C then is delivered after.
    with dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"}):
        start_forkserver_ignoring_sigint()
    with contextlib.ExitStack() as restore:
        restore.enter_context(dask.config.set(
            {f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in env.items()}
            | {"distributed.worker.multiprocessing-method": "forkserver"}
            | ({} if local_directory is None else {"temporary-directory": str(local_directory)})))
        try:
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                   local_directory=None if local_directory is None
                                   else str(local_directory),
                                   memory_limit=memory_limit, host="127.0.0.1",
                                   dashboard_address=None, silence_logs=logging.WARNING,
                                   # its HTTP server (health routes) would take :8787 otherwise
                                   scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                                   resources={"memory": int(BUDGET_FRACTION * memory_limit)})
            client = Client(cluster)
        except BaseException:  # interrupted while starting: close what was started, quietly
            close_unfinished_clusters()
            raise
    return cluster, client


def execute(pending: list[Case], weights: Mapping[str, int], cases_dir: Path,
            outcomes: dict[str, CaseRecord], progress: Progress, *, workers: int | None,
            scheduler: str | None, write_here: bool | None, token: str,
            start_timeout: float) -> str:
    """Run ``pending`` (unique keys) on a cluster; fill ``outcomes[key]``. ``weights``:
    how many cases of the batch share each key. Returns a line describing the cluster."""
    from distributed import Client, wait  # deferred: dask is the batch extra
    from distributed.client import FIRST_COMPLETED

    cluster = None
    scratch_holder = contextlib.ExitStack()
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
        info = worker_info(client)
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
        n = plan_local_workers(workers, pending)
        available = available_memory_bytes()
        threads_per_case = max(1, (os.cpu_count() or 1) // n)
        # the workers' scratch folder is private and removed with the cluster (dask's
        # default, <TMPDIR>/dask-scratch-space, is shared and stays behind); dask's nannies
        # write their workers' variables (MKL_NUM_THREADS=1, ...) into this process's
        # environment: it is given back as it was when the cluster is gone
        scratch_holder.enter_context(environment_kept())
        scratch = scratch_holder.enter_context(private_folder("pipeline-dask-"))
        try:
            cluster, client = start_local_cluster(n, available, threads_per_case, scratch)
        except BaseException:
            scratch_holder.close()
            raise
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
            outcomes[case.key] = finish_record(failure("ResourceError", reason), case, None)
            write_record(cases_dir, outcomes[case.key])
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
                    record = collect(fut, case, cases_dir, outcomes, progress)
                    progress.advance(weights.get(case.key, 1), "done" if record.ok else "failed")
                submit_more()
        except BaseException:
            # an interrupt: the workers' shutdown (cancelled tasks, the scheduler gone)
            # is expected, not worth a traceback on the user's terminal
            with contextlib.suppress(Exception):
                client.run(quiet_distributed_logs)
                client.run(quiet_distributed_logs, nanny=True)
            for fut in not_done:
                fut.cancel()
            raise
        finally:
            with contextlib.suppress(Exception):
                client.unsubscribe_topic(EVENT_TOPIC)
    except BaseException:
        interrupted = True
        raise
    else:
        interrupted = False
    finally:
        with contextlib.suppress(Exception):
            client.close(timeout=10)
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=20)
            relay_worker_output(interrupted)
        scratch_holder.close()
    return where


def collect(fut, case: Case, cases_dir: Path, outcomes: dict[str, CaseRecord],
            progress: Progress) -> CaseRecord:
    """Store the result of one finished future: file (if sent back), record, log."""
    h5 = h5_path(cases_dir, case.key)
    try:
        result: TaskResult = fut.result()
    except Exception as exc:  # KilledWorker, a worker without the pipeline, a lost scheduler
        name = type(exc).__name__
        hint = (" (the worker process died more than the allowed number of times while "
                "running it)" if name == "KilledWorker" else "")
        result = TaskResult(failure(name, f"{name}: {exc}{hint}"))
    record = result.record
    if record.ok:
        try:
            if result.h5_bytes is not None:
                write_bytes(h5, result.h5_bytes)
            record = record_from_file(h5, case, verify=result.h5_bytes is not None).updated(record)
        except (OSError, FileFormatError) as exc:
            record = record.replace(status="failed", error_type=type(exc).__name__,
                                    error=f"the case ran but its file is not usable: {exc}")
    if result.log:
        with contextlib.suppress(OSError):
            write_text(cases_dir / f"{case.key}.log", result.log)
    record = finish_record(record, case, h5 if record.ok else None)
    write_record(cases_dir, record)
    outcomes[case.key] = record
    progress.running.discard(case.key)
    if record.ok:
        peak = record.peak_memory_mb if record.peak_memory_mb is not None else float("nan")
        progress.line(f"case {case.index} ({case.label}): done in {record.wall_s or 0.0:.1f} s, "
                      f"{record.get('n_dofs', '?')} DOFs, peak {peak:.0f} MB")
    else:
        progress.line(f"case {case.index} ({case.label}): FAILED: {record.error}")
    return record


# --------------------------------------------------------------------------- the batch
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
    t0 = time.perf_counter()
    spec = batch if isinstance(batch, BatchSpec) else load_batch(batch)
    outdir = Path(output) if output else Path("outputs") / spec.name
    cases_dir = outdir / "cases"
    cases_dir.mkdir(parents=True, exist_ok=True)
    where = "nothing to run"
    with batch_lock(outdir):
        removed = clean_partials(cases_dir)
        if removed:
            log.info("removed %d partial file(s) of an interrupted run", removed)
        token = secrets.token_hex(16)
        write_text(cases_dir / TOKEN_FILE, token)
        outcomes: dict[str, CaseRecord] = {}
        cached: set[str] = set()
        unique = list({c.key: c for c in spec.cases}.values())
        for case in unique:
            record = cached_record(cases_dir, case, verify)
            if record is not None:
                outcomes[case.key] = record
                cached.add(case.key)
        pending = [c for c in unique if c.key not in outcomes]
        n_cached = sum(c.key in cached for c in spec.cases)
        bar = Progress(len(spec.cases), spec.name, progress, echo)
        try:
            bar.line(f"batch '{spec.name}' ({spec.path}): {len(spec.cases)} cases, {n_cached} "
                     f"already computed (cached, skipped), {len(pending)} to run")
            bar.advance(n_cached, "cached")
            if pending and compute:
                weights: dict[str, int] = {}
                for case in spec.cases:
                    weights[case.key] = weights.get(case.key, 0) + 1
                where = execute(pending, weights, cases_dir, outcomes, bar, workers=workers,
                                scheduler=scheduler, write_here=write_here, token=token,
                                start_timeout=start_timeout)
        finally:
            bar.close()
            with contextlib.suppress(OSError):
                (cases_dir / TOKEN_FILE).unlink()
        result_outcomes = []
        for case in spec.cases:
            record = outcomes.get(case.key)
            if record is None:
                status = "not run"
                record = read_record(cases_dir, case.key) or NO_RECORD
                if record.ok:  # a finished record whose file is gone: nothing known
                    record = NO_RECORD
            elif case.key in cached:
                status = "cached"
            else:
                status = "done" if record.ok else "failed"
            h5 = h5_path(cases_dir, case.key)
            result_outcomes.append(CaseOutcome(case, status, record,
                                               h5 if status in ("done", "cached") else None))
        result = BatchResult(spec, outdir, result_outcomes, time.perf_counter() - t0, where)
        result.files = report.write_outputs(result)
        result.wall_s = time.perf_counter() - t0
    return result
