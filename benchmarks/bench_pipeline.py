"""Benchmark: the pipeline against the straightforward stack, from 20k to 1M DOFs.

``make bench`` (or ``python benchmarks/bench_pipeline.py [--large] [--write-doc]``)
runs, each case in its own subprocess so that the peak memory (ru_maxrss) is the
case's own:

- the real pipeline, :func:`pipeline.run.run_pipeline` on ``configs/cantilever.yaml``
  with ``mesh.size`` set for about 20k, 100k and 300k DOFs (and 1M with ``--large``)
  and ``modes.count`` = 20: mesh, assembly, eigensolve, reduced model, HDF5 file;
- the straightforward stack at the sizes it can finish (20k, 100k): the same gmsh
  mesh, plain scikit-fem ``form.assemble(basis)``, ``A[free][:, free]`` and
  ``scipy.sparse.linalg.eigsh(K, 20, M, sigma=0)`` with its default SuperLU.

It prints one table (DOFs, stage times, total, peak memory, speed-up over the
straightforward stack from the same run) and the time-to-accuracy line: the fewest
DOFs whose first five frequencies are within 0.1% of the finest mesh's.
``--write-doc`` also writes the table and the machine into docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "cantilever.yaml"
DOC = ROOT / "docs" / "performance.md"
# mesh.size (m) of the cantilever -> DOFs with HXT, one gmsh thread (P2)
SIZES = {"20k": 0.0085, "100k": 0.005, "300k": 0.0032, "600k": 0.0025, "1M": 0.00211,
         "3M": 0.00146, "6M": 0.00116}
LARGE = ("600k", "1M", "3M")  # opt-in: --large, or named in --sizes; once unless repeated
# only when named in --sizes: 5.5M DOFs, about 15 min and 21 GB on the 24 GB machine, and
# once; NGSolve does not run there (no maxh: its factor would need about 100 GB)
HUGE = ("6M",)
# NGSolve's maxh for about the same DOFs (P2 VectorH1, netgen 6.2.2608, measured: 0.0079
# -> 24,957; 0.00497 -> 88,008; 0.0047 -> 93,504; 0.0045 -> 98,142; 0.0044 -> 176,841;
# 0.0043 -> 175,992; 0.00339 -> 333,318; 0.00229 -> 597,972; 0.00224 ->
# 614,802; 0.00223 -> 1,214,421; 0.00222 -> 1,227,582; 0.00221 -> 1,226,895; 0.0022 ->
# 1,224,567; 0.00209 -> 1,280,949; 0.00199 -> 1,313,007; 0.00158 -> 2,323,056 DOFs).
# netgen's DOFs jump with the number of element layers across the 20 mm thickness, so no
# maxh gives 1.0M: 1M is compared at 1.21M DOFs (the nearest above; 21.5 GB, just inside
# the cap of run_watched on the 24 GB machine: on a busier host it is stopped), 3M at
# 2.32M (its factor alone needs 29 GB); 600k (621k DOFs here) at 615k, the largest below
# that jump (8.9-9.3 GB); 100k (101,406 DOFs here) at 98,142, the largest below the jump
# to 176k.
NGSOLVE_MAXH = {"20k": 0.0079, "100k": 0.0045, "300k": 0.00339, "600k": 0.00224,
                "1M": 0.00223, "3M": 0.00158}
NGSOLVE_VARIANTS = ("pardiso_spd", "sparsecholesky", "pardiso")
REFERENCE_SIZES = ("20k", "100k")  # the straightforward stack: 300k takes 6 min, 10 GB
COUNT = 20


# --------------------------------------------------------------------------- child side
def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_pipeline_case(size: float, count: int, workdir: Path, precision: str = "auto",
                      method: str = "auto", shapes: Path | None = None) -> dict:
    """One pipeline run; returns stage times, peak memory and the frequencies (and the
    accuracy of its modes, :func:`mode_accuracy`); ``shapes``: save the mode shapes
    there (.npy) for :func:`add_agreement`."""
    t_imports = time.perf_counter()
    sys.path.insert(0, str(ROOT))
    from pipeline.cli import tune_process

    tune_process()  # as the CLI's process: before numpy loads
    import pipeline.solve.stage as modes_module  # the name run_pipeline calls
    from pipeline.config import load_config
    from pipeline.run import run_pipeline

    captured: dict = {}
    solve = modes_module.solve_modes

    def spy(*args, **kwargs):  # records the eigensolver's own statistics
        result = solve(*args, **kwargs)
        captured.update(result.stats or {})
        captured["M"], captured["shapes"] = args[1], result.shapes
        # measured here, while K is alive anyway (holding K past the modes stage would keep
        # the factor tied to it alive too); its time is taken off the stage and the total
        t_acc = time.perf_counter()
        captured.update(mode_accuracy(args[0], args[1], result.shapes, result.omega2))
        captured["accuracy_s"] = time.perf_counter() - t_acc
        return result

    modes_module.solve_modes = spy
    cfg = load_config(CONFIG, [f"mesh.size={size}", f"modes.count={count}",
                               f"modes.precision={precision}", f"modes.method={method}"])
    t0 = time.perf_counter()
    result = run_pipeline(cfg, workdir / "out.hdf5", mesh_dir=workdir)
    total = time.perf_counter() - t0
    # the accuracy of the modes was measured inside the modes stage: off the stage and the
    # total (the breakdown's "modes, other" included it before), on the process's checks
    accuracy_s = captured.pop("accuracy_s")
    t = dict(result.times, modes=result.times["modes"] - accuracy_s)
    total -= accuracy_s
    t_checks = time.perf_counter()  # the bench's own checks below, with accuracy_s
    seconds = stage_seconds(t, captured, t0 - t_imports)
    import numpy as np

    from pipeline.solve.blas import sparse_times_dense

    Phi = captured.pop("shapes")
    accuracy = {key: captured.pop(key) for key in ("true_residual", "backward_error")}
    accuracy["dc_gain"] = stored_dc_gain(workdir / "out.hdf5")
    if shapes is not None:
        write_whole(shapes, lambda fh: np.save(fh, Phi))
    ortho = float(np.abs(Phi.T @ sparse_times_dense(captured.pop("M"), Phi)
                         - np.eye(Phi.shape[1])).max())
    del Phi
    checks_s = accuracy_s + time.perf_counter() - t_checks
    kind = ("pipeline" if precision == method == "auto"
            else f"pipeline ({method if method != 'auto' else precision})")
    return {"kind": kind, "n_dofs": result.n_dofs, "n_free": result.n_free,
            "mesh": t.get("mesh"), "assembly": t.get("assemble"), "eigensolve": t.get("modes"),
            "reduction": t.get("reduce"), "write": t.get("write"), "total": total,
            "peak_mb": _peak_mb(), "backend": result.backend,
            "frequencies": [float(f) for f in result.frequencies_hz],
            "factor_s": captured.get("factor_seconds", captured.get("setup_seconds")),
            "sweeps": captured.get("sweeps"),
            "lanczos_s": captured.get("eigensolver_seconds"),
            "factor_gb": (captured.get("factor_bytes") or 0) / 1e9,
            "solves": captured.get("solves"), "method": captured.get("method"),
            "m_orthonormality": ortho,
            "file_mb": (workdir / "out.hdf5").stat().st_size / 1e6, "seconds": seconds,
            "checks_s": checks_s, **accuracy}


def mode_accuracy(K, M, Phi, omega2) -> dict:
    """The accuracy of the final modes Phi (n, m), omega2 (m,) from K and M themselves
    (:mod:`pipeline.solve.accuracy`), not from the solver's own measure: the largest
    true relative residual ||K x - w^2 M x|| / ||K x|| and the largest normwise backward
    error."""
    from pipeline.solve import accuracy

    return {"true_residual": float(accuracy.relative_residuals(K, M, Phi, omega2).max()),
            "backward_error": float(accuracy.backward_errors(K, M, Phi, omega2).max())}


def stored_dc_gain(path: Path) -> list | None:
    """G(0) = D - C A^-1 B of the plant in ``path`` (None: no plant, or A singular)."""
    import numpy as np

    from pipeline.store.read import load_model

    try:
        plant = load_model(path).plant
        return None if plant is None else plant.dc_gain().tolist()
    except (np.linalg.LinAlgError, ValueError):
        return None


def stage_seconds(times: dict, stats: dict, imports_s: float) -> dict:
    """Where one run's time went (s): the pipeline's stage times (``times``), the
    eigensolver's own timers (every ``*_seconds`` of its statistics ``stats``) and the
    imports before the run (``imports_s``), for :func:`breakdown`."""
    seconds = {"imports": imports_s}
    seconds.update({f"stage:{k}": float(v) for k, v in times.items()})
    for key, value in stats.items():
        if key.endswith("_seconds") and isinstance(value, (int, float)):
            seconds[key[:-len("_seconds")]] = float(value)
    if stats.get("analysis_ahead"):  # the ordering ran beside the assembly, off the path
        seconds["analysis (beside the assembly)"] = seconds.pop("analysis", 0.0)
    return seconds


def run_reference_case(size: float, count: int, workdir: Path) -> dict:
    """The straightforward stack: plain skfem assembly, fancy indexing, eigsh/SuperLU."""
    sys.path.insert(0, str(ROOT))
    import numpy as np
    from scipy.sparse.linalg import eigsh

    from pipeline.fe.assemble import assemble_reference
    from pipeline.config import load_config
    from pipeline.fe.space import build_space
    from pipeline.fe.mesh import generate_mesh, read_mesh
    from pipeline.fe.regions import fixed_dofs, free_dofs, resolve_regions

    cfg = load_config(CONFIG, [f"mesh.size={size}", f"modes.count={count}"])
    t0 = time.perf_counter()
    path = generate_mesh(cfg.geometry, cfg.mesh, workdir / "ref.msh")
    space = build_space(read_mesh(path), cfg.mesh.order)
    regions = resolve_regions(space, cfg.regions)
    t1 = time.perf_counter()
    K, M = assemble_reference(space, cfg.material)
    free = free_dofs(space.n_dofs, fixed_dofs(space, regions, cfg.supports,
                                              cfg.constraints.in_plane))
    K = K[free][:, free]
    M = M[free][:, free]
    t2 = time.perf_counter()
    w, _ = eigsh(K, k=count, M=M, sigma=0)
    t3 = time.perf_counter()
    return {"kind": "straightforward", "n_dofs": space.n_dofs, "n_free": int(free.size),
            "mesh": t1 - t0, "assembly": t2 - t1, "eigensolve": t3 - t2, "reduction": None,
            "write": None, "total": t3 - t0, "peak_mb": _peak_mb(), "backend": "superlu",
            "frequencies": [float(f) for f in np.sort(np.sqrt(np.abs(w)) / (2 * np.pi))]}


# --------------------------------------------------------------------------- parent side
#: a case is stopped when its resident memory passes this fraction of the memory that
#: was available when it started (a case that does not fit ends in one error row
#: instead of swapping the machine or waking the OOM killer)
MEMORY_FRACTION = 0.92


@dataclass(frozen=True)
class Finished:
    """A watched child: exit code, its output, and why it was stopped (None: it ended)."""

    returncode: int | None
    stdout: str
    stderr: str
    error: str | None
    peak_rss_bytes: int


def _available_bytes() -> int:
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _rss_bytes(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


#: seconds an interrupted bench gives its running case to clean up after SIGTERM (the
#: pipeline removes its temporary files on SIGTERM) before SIGKILL
STOP_GRACE_S = 10.0


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):  # the group is gone already
        pass


def stop_case(proc: subprocess.Popen, grace_s: float) -> None:
    """Leave no process of a case started in its own session (``start_new_session``):
    a case still running gets SIGTERM for its whole process group and ``grace_s``
    seconds to end, then the group gets SIGKILL, whatever is left of it (a case that
    ended may leave children of its own)."""
    try:
        if proc.poll() is None and grace_s > 0:
            _signal_group(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                pass
    finally:
        _signal_group(proc.pid, signal.SIGKILL)
        proc.wait()


def run_watched(cmd: list[str], timeout: float, limit_bytes: int | None = None,
                poll_s: float = 0.25, cwd: Path = ROOT, env: dict | None = None) -> Finished:
    """Run ``cmd`` (in ``cwd``, default the repository; ``env``: its environment, default
    this process's) and stop it, with a one-line reason, when it runs past ``timeout``
    seconds or its resident memory passes ``limit_bytes`` (default:
    :data:`MEMORY_FRACTION` of the memory available now). The case runs in its own
    session; stopped, it gets SIGKILL at once, and when the bench itself is interrupted
    it gets SIGTERM first (:func:`stop_case`): no process of it is left either way."""
    from pipeline._util.interrupts import held

    limit = limit_bytes or int(MEMORY_FRACTION * _available_bytes())
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc, peak, error, interrupted = None, 0, None, True
        try:
            with held():  # an interrupt during the start waits until proc is known
                proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=out, stderr=err,
                                        text=True, start_new_session=True)
                t0 = time.perf_counter()
            while proc.poll() is None:
                peak = max(peak, _rss_bytes(proc.pid))
                if peak > limit:
                    error = (f"stopped at {peak / 1e9:.1f} GB resident: over the "
                             f"{limit / 1e9:.1f} GB available")
                elif time.perf_counter() - t0 > timeout:
                    error = f"timed out after {timeout:.0f} s"
                if error:
                    break
                time.sleep(poll_s)
            interrupted = False
        finally:  # ended, stopped, or the bench itself interrupted: no case left running
            if proc is not None:
                stop_case(proc, STOP_GRACE_S if interrupted else 0.0)
        out.seek(0)
        err.seek(0)
        return Finished(proc.returncode, out.read(), err.read(), error, peak)


def _run_child(kind: str, label: str, count: int, timeout: float, variant: str = "auto",
               shapes: Path | None = None) -> dict:
    """One case in its own process; ``variant``: a modes.precision (auto, double, mixed)
    or a modes.method (``multigrid``, ``factor``); ``shapes``: where the child saves its
    mode shapes."""
    precision, method = (("auto", variant) if variant in ("multigrid", "factor")
                         else (variant, "auto"))
    # the child's own name for the row (run_pipeline_case), also on a refused case's row
    name = kind if kind != "pipeline" or variant == "auto" else f"pipeline ({variant})"
    with tempfile.TemporaryDirectory(prefix=f"bench_{label}_") as tmp:
        out = Path(tmp) / "result.json"
        cmd = [sys.executable, str(Path(__file__).resolve()), "--child", kind,
               "--size", str(SIZES[label]), "--count", str(count), "--result", str(out),
               "--precision", precision, "--method", method]
        if shapes is not None and kind == "pipeline":
            cmd += ["--shapes", str(shapes)]
        t0 = time.perf_counter()
        proc = run_watched(cmd, timeout)
        wall = time.perf_counter() - t0
        if proc.error:
            return {"kind": name, "label": label, "error": proc.error}
        if proc.returncode != 0 or not out.exists():
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
            return {"kind": name, "label": label,
                    "error": f"exit {proc.returncode}: {' | '.join(tail)}"}
        row = json.loads(out.read_text())
        row.update(label=label, process_s=wall)
        return row


def _run_ngsolve(label: str, inverse: str, count: int, timeout: float) -> dict:
    """One NGSolve case (benchmarks/bench_ngsolve.py) in its own process."""
    kind = f"ngsolve ({inverse})"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_ngsolve.py"), "--maxh",
           str(NGSOLVE_MAXH[label]), "--count", str(count), "--inverse", inverse]
    t0 = time.perf_counter()
    proc = run_watched(cmd, timeout)
    if proc.error:
        return {"kind": kind, "label": label, "error": proc.error}
    lines = [x for x in proc.stdout.splitlines() if x.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-2:]
        return {"kind": kind, "label": label, "error": f"exit {proc.returncode}: "
                + " | ".join(tail)}
    row = json.loads(lines[-1])
    row.update(kind=kind, label=label, process_s=time.perf_counter() - t0, reduction=None,
               write=None)
    return row


#: the stages both stacks run: NGSolve builds no reduced model and writes no file, so the
#: like-for-like comparison is over these (its ``total`` is their sum)
SAME_WORK = ("mesh", "assembly", "eigensolve")


def same_work(row: dict) -> float | None:
    """Seconds of the work both stacks do (:data:`SAME_WORK`: mesh, assembly, eigensolve)
    in one row, or None when a stage is missing."""
    if row.get("same_work") is not None:
        return row["same_work"]
    parts = [row.get(key) for key in SAME_WORK]
    return None if any(p is None for p in parts) else float(sum(parts))


def median_row(runs: list[dict]) -> dict:
    """The run with the median whole-process time, with the medians of time (the total
    and :func:`same_work`) and peak memory over ``runs`` (errors are kept if every run
    failed)."""
    good = [r for r in runs if "error" not in r]
    if not good:
        return runs[-1]
    good = [dict(r, same_work=same_work(r)) for r in good]
    good.sort(key=lambda r: r.get("process_s", r["total"]))
    row = dict(good[len(good) // 2])
    for key in ("total", "same_work", "peak_mb", "process_s"):
        values = sorted(r[key] for r in good if r.get(key) is not None)
        if values:
            mid = len(values) // 2
            row[key] = (values[mid] if len(values) % 2 else
                        0.5 * (values[mid - 1] + values[mid]))
    probes = [r["host_speed"] for r in good if r.get("host_speed")]
    if probes:  # each figure's median over the runs
        row["host_speed"] = [sorted(p[i] for p in probes)[len(probes) // 2] for i in (0, 1)]
    row["runs"] = len(good)
    return row


#: the pipeline rows compared with NGSolve: the default path, and the factor path where
#: ``--also-factor`` ran it beside a factor-free default (NGSolve's residual class)
PEER_KINDS = ("pipeline", "pipeline (factor)")


def peer_comparison(rows: list[dict], rel: float = 0.01) -> str:
    """Per size and pipeline row (:data:`PEER_KINDS`): the pipeline against NGSolve's
    fastest variant whose first 5 frequencies agree with ours to ``rel`` (the meshes
    differ, so agreement is to discretisation).

    Two ratios: NGSolve's total over the pipeline's (which also builds the reduced model
    and writes the file, work NGSolve does not do), and the ratio over the same work,
    mesh + assembly + eigensolve on both sides (:func:`same_work`); and both stacks' true
    relative residuals (:func:`mode_accuracy`), the accuracy the ratio is at."""
    lines = ["| size | pipeline | pipeline DOFs | pipeline s | pipeline MB | "
             "NGSolve best (correct) | NGSolve DOFs | NGSolve s | NGSolve MB | "
             "NGSolve / pipeline time | pipeline mesh + assembly + eigensolve s | "
             "same work: NGSolve / pipeline | true rel. residual: pipeline, NGSolve |",
             "|" + " --- |" * 13]
    for label in dict.fromkeys(r["label"] for r in rows):
        peers = [r for r in rows if r["label"] == label and r["kind"].startswith("ngsolve")
                 and "error" not in r]
        failed = [r for r in rows if r["label"] == label and r["kind"].startswith("ngsolve")
                  and "error" in r]
        for ours in (r for r in rows if r["label"] == label and r["kind"] in PEER_KINDS
                     and "error" not in r):
            head = (f"| {label} | {ours.get('method') or ours['kind']} | {ours['n_dofs']:,} | "
                    f"{ours['total']:.1f} | {ours['peak_mb']:,.0f} |")
            if not peers and failed:
                lines.append(f"{head} {failed[0]['kind']}: did not run "
                             f"({short_error(failed[0]['error'])}) |" + " |" * 7)
                continue
            if not peers:
                continue
            ok = [r for r in peers if max(abs(f / g - 1) for f, g in zip(
                r["frequencies"][:5], ours["frequencies"][:5])) <= rel]
            if not ok:
                lines.append(f"{head} no variant agrees to {rel:.0%} |" + " |" * 7)
                continue
            best = min(ok, key=lambda r: r["total"])
            mine, theirs = same_work(ours), same_work(best)
            ratio = "-" if not (mine and theirs) else f"{theirs / mine:.2f}x"
            lines.append(f"{head} {best['kind']} | {best['n_dofs']:,} | "
                         f"{best['total']:.1f} | {best['peak_mb']:,.0f} | "
                         f"{best['total'] / ours['total']:.2f}x | {_fmt(mine, '.1f')} | "
                         f"{ratio} | {_fmt(ours.get('true_residual'), '.1e')}, "
                         f"{_fmt(best.get('true_residual'), '.1e')} |")
    if len(lines) <= 2:
        return "NGSolve: not run (pip install -e '.[bench]')"
    return "\n".join(lines) + (
        "\n\nNGSolve / pipeline time: the whole runs (the pipeline's also builds the reduced "
        "model and writes the HDF5 file, NGSolve's ends with its eigenpairs); same work: "
        "mesh + assembly + eigensolve on both sides. The pipeline column names its "
        "eigensolver: where it is the factor-free multigrid-lobpcg (from about 500k DOFs), "
        "`--also-factor` adds the factor path's row, at NGSolve's residual.")


def short_error(text: str, limit: int = 160) -> str:
    """A case's error as one short line: the exception's own message when there is one
    (``...Error: message``), else the text; past ``limit`` characters it ends at the last
    clause that fits (``; `` or ``, ``), else the last word, and says it was cut.

    >>> short_error("exit 1: x | ResourceError: needs 29 GB; a mesh.size 1.7 times "
    ...             "larger would fit", limit=30)
    'needs 29 GB (...)'
    """
    tail = text.rsplit("Error: ", 1)[-1] if "Error: " in text else text
    line = " ".join(tail.split())
    if len(line) <= limit:
        return line
    cut = line[:limit - 6]
    for mark in ("; ", ", ", " "):
        if mark in cut:
            cut = cut[:cut.rindex(mark)]
            break
    return cut + " (...)"


def _fmt(value, spec: str = ".2f") -> str:
    return "-" if value is None else format(value, spec)


def table(rows: list[dict]) -> str:
    """The results as one Markdown table."""
    ref = {r["label"]: r for r in rows if r["kind"] == "straightforward" and "error" not in r}
    head = ("| stack | DOFs | mesh s | assembly s | eigensolve s | reduction s | write s | "
            "total s | peak MB | speed-up |")
    lines = [head, "|" + " --- |" * 10]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['kind']} | {r['label']} | {short_error(r['error'])} |"
                         + " |" * 7)
            continue
        speed = "-"
        if r["kind"].startswith("pipeline") and r["label"] in ref:
            speed = f"{ref[r['label']]['total'] / r['total']:.1f}x"
        lines.append(
            f"| {r['kind']} | {r['n_dofs']:,} | {_fmt(r['mesh'])} | {_fmt(r['assembly'])} | "
            f"{_fmt(r['eigensolve'])} | {_fmt(r['reduction'])} | {_fmt(r['write'])} | "
            f"{_fmt(r['total'])} | {r['peak_mb']:,.0f} | {speed} |")
    return "\n".join(lines)


def details(rows: list[dict]) -> str:
    """Eigensolve breakdown of the pipeline rows."""
    lines = ["| stack | DOFs | method | factorisation (multigrid: set-up) s | factor GB | "
             "eigensolver s | vectors solved (LOBPCG sweeps) | true rel. residual | "
             "max abs(Phi^T M Phi - I) | HDF5 MB | process wall s |",
             "|" + " --- |" * 11]
    for r in rows:
        if not r["kind"].startswith("pipeline") or "error" in r:
            continue
        solved = (f"({r['sweeps']})" if r.get("sweeps") is not None
                  else (r.get('solves') or 0) // 2 or '-')
        lines.append(f"| {r['kind']} | {r['n_dofs']:,} | {r.get('method') or '-'} | "
                     f"{_fmt(r.get('factor_s'))} | "
                     f"{_fmt(r.get('factor_gb'))} | {_fmt(r.get('lanczos_s'))} | "
                     f"{solved} | {_fmt(r.get('true_residual'), '.1e')} | "
                     f"{_fmt(r.get('m_orthonormality'), '.1e')} | {_fmt(r.get('file_mb'), '.1f')} | "
                     f"{_fmt(r.get('process_s'))} |")
    return "\n".join(lines)


def add_agreement(pairs: list[tuple[dict, Path]]) -> None:
    """For the pipeline rows of one size (with the files their mode shapes were saved
    to): the agreement of every row with the reference path, the first row that solved
    with a factor, as ``row["agreement"]``: the reference's kind, the largest relative
    frequency difference, the largest principal angle between the spans of the mode
    shapes (Euclidean inner product, radians) and the largest DC gain difference relative
    to the largest reference gain. Rows on another mesh (other DOFs) are not compared."""
    import numpy as np

    from pipeline.solve import accuracy

    done = [(r, p) for r, p in pairs if r["kind"].startswith("pipeline") and "error" not in r]
    ref = next(((r, p) for r, p in done if r.get("method") != "multigrid-lobpcg"), None)
    if ref is None or not ref[1].exists():
        return
    ref_row, ref_shapes = ref[0], np.load(ref[1])
    for row, path in done:
        if row is ref_row or row["n_free"] != ref_row["n_free"] or not path.exists():
            continue
        agree = {"reference": ref_row["kind"],
                 "freq_diff": accuracy.frequency_difference(row["frequencies"],
                                                            ref_row["frequencies"]),
                 "angle": accuracy.largest_subspace_angle(np.load(path), ref_shapes)}
        if row.get("dc_gain") is not None and ref_row.get("dc_gain") is not None:
            g, g_ref = np.asarray(row["dc_gain"]), np.asarray(ref_row["dc_gain"])
            agree["dc_gain_diff"] = float(np.abs(g - g_ref).max() / np.abs(g_ref).max())
        row["agreement"] = agree


def accuracy_table(rows: list[dict]) -> str:
    """The accuracy of every pipeline row's modes, computed from K and M
    (:func:`mode_accuracy`), and its agreement with the reference path of the same size
    where one ran (:func:`add_agreement`); NGSolve's rows measured the same way from its
    own K and M (``bench_ngsolve.mode_accuracy``), so that the comparison's "same
    accuracy" is shown."""
    lines = ["| stack | DOFs | method | true rel. residual | "
             "backward error | reference | max rel. frequency difference | "
             "largest subspace angle (rad) | DC gain difference |", "|" + " --- |" * 9]
    for r in rows:
        if "error" in r or not (r["kind"].startswith("pipeline")
                                or r.get("true_residual") is not None):
            continue
        a = r.get("agreement") or {}
        lines.append(f"| {r['kind']} | {r['n_dofs']:,} | {r.get('method') or '-'} | "
                     f"{_fmt(r.get('true_residual'), '.1e')} | "
                     f"{_fmt(r.get('backward_error'), '.1e')} | {a.get('reference', '-')} | "
                     f"{_fmt(a.get('freq_diff'), '.1e')} | {_fmt(a.get('angle'), '.1e')} | "
                     f"{_fmt(a.get('dc_gain_diff'), '.1e')} |")
    return ("Accuracy of the modes, from K and M: the true relative residual is "
            "max_k norm(K x_k - w_k^2 M x_k) / norm(K x_k) (2-norms), the backward error "
            "the smallest relative change of K and M that makes the pairs exact "
            "(pipeline.solve.accuracy). The residual weighs an error component of "
            "eigenvalue lambda by lambda / w^2: LOBPCG stops on the energy-norm residual, "
            "so its modes show 1e-3 here while agreeing with the factor path's to the "
            "angle and frequency difference in its row (where a factor path ran at the "
            "same size: --also-factor). NGSolve's rows: its own K and M on its free "
            "DOFs, each complex Arnoldi vector made real by the phase of its largest "
            "entry.\n\n" + "\n".join(lines))


#: the columns of :func:`breakdown`: (heading, keys of a row's "seconds" summed); the
#: modes stage is split into its solver's own timers, the rest of it is "modes, other"
BREAKDOWN = (("imports", ("imports",)), ("mesh (gmsh, space)", ("stage:mesh",)),
             ("assembly", ("stage:assemble",)), ("ordering", ("analysis",)),
             ("waiting for the ordering", ("analysis_wait",)),
             ("factorisation (multigrid: set-up)", ("numeric", "setup")),
             ("passes over the factor", ("solve",)), ("mass products", ("mass",)),
             ("orthogonalisation", ("orthogonalisation",)), ("refinement", ("refine",)),
             ("Rayleigh-Ritz", ("rayleigh_ritz",)))
MODES_PARTS = ("analysis", "analysis_wait", "numeric", "setup", "solve", "mass",
               "orthogonalisation", "refine", "rayleigh_ritz")


def breakdown(rows: list[dict]) -> str:
    """Where the whole process's time goes, per pipeline case (s): imports, the stages,
    the eigensolver's own timers (ordering, factorisation, passes over the factor, ...;
    for multigrid the set-up, the rest is "modes, other": LOBPCG's sweeps), and what is
    left of the process's wall time: the bench's own checks of the result (the modes'
    residuals and backward errors from K and M, their M-orthonormality, the file's DC
    gain: they grow with N) and the interpreter's start and exit (a row of an earlier
    JSON without ``checks_s`` keeps its checks in the last); then the host's speed before
    the case (:func:`host_speed`, medians over the case's runs)."""
    heads = [h for h, _ in BREAKDOWN] + ["modes, other", "reduce", "write",
                                         "bench's checks", "start, exit", "process",
                                         "host GB/s", "host GFlop/s"]
    lines = ["| stack | DOFs | " + " | ".join(heads) + " |", "|" + " --- |" * (len(heads) + 2)]
    for r in rows:
        sec = r.get("seconds")
        if not r["kind"].startswith("pipeline") or "error" in r or not sec:
            continue
        cells = [sum(sec.get(k, 0.0) for k in keys) if any(k in sec for k in keys)
                 else None for _, keys in BREAKDOWN]
        if sec.get("analysis (beside the assembly)") is not None:
            cells[3] = None  # off the critical path
        modes_other = sec.get("stage:modes", 0.0) - sum(sec.get(k, 0.0) for k in MODES_PARTS)
        accounted = sec.get("imports", 0.0) + r["total"]
        checks = r.get("checks_s")
        rest = (r["process_s"] - accounted - (checks or 0.0)
                if r.get("process_s") is not None else None)
        speed = r.get("host_speed") or (None, None)
        cells += [modes_other, sec.get("stage:reduce"), sec.get("stage:write"), checks, rest,
                  r.get("process_s"), speed[0], speed[1]]
        ordering = _fmt(cells[3]) if sec.get("analysis (beside the assembly)") is None else (
            f"({sec['analysis (beside the assembly)']:.2f} beside)")
        text = [_fmt(c) for c in cells[:-2]] + [_fmt(c, ".1f") for c in cells[-2:-1]] + [
            _fmt(c, ".0f") for c in cells[-1:]]
        text[3] = ordering
        lines.append(f"| {r['kind']} | {r['n_dofs']:,} | " + " | ".join(text) + " |")
    return "\n".join(lines) if len(lines) > 2 else "breakdown: no pipeline case"


def time_to_accuracy(rows: list[dict], n_freq: int = 5, rel: float = 1e-3) -> str:
    runs = sorted((r for r in rows if r["kind"] == "pipeline" and "error" not in r),
                  key=lambda r: r["n_dofs"])
    if len(runs) < 2:
        return "time to accuracy: needs at least two pipeline sizes"
    finest = runs[-1]
    f_ref = finest["frequencies"][:n_freq]
    parts = []
    first = None
    for r in runs[:-1]:
        err = max(abs(f / g - 1.0) for f, g in zip(r["frequencies"][:n_freq], f_ref))
        parts.append(f"{r['n_dofs']:,} DOFs: {100 * err:.3f}%")
        if first is None and err <= rel:
            first = r
    verdict = (f"{first['n_dofs']:,} DOFs ({first['total']:.1f} s) suffice"
               if first else "no coarser mesh is close enough")
    return (f"time to accuracy: first {n_freq} frequencies within {100 * rel:g}% of the finest "
            f"mesh's ({finest['n_dofs']:,} DOFs): {verdict}; worst deviation "
            + ", ".join(parts))


def _touch_line(touch) -> str:
    if not touch:
        return "Fresh memory: not measured."
    return (f"Fresh memory (measured before the cases, 1 GiB in a child process): "
            f"{touch[0]:.2f} s/GiB on first touch, {touch[1]:.2f} s/GiB written again; "
            "every case pays the first figure for each GiB of its peak, which bounds the "
            "large cases from below.")


def report(rows: list[dict], meta: dict) -> str:
    return "\n\n".join([
        f"Machine: {meta['machine']}.",
        f"Run {meta.get('date', '')}; load average (1 min) {meta['load_before']:.1f} before and "
        f"{meta['load_after']:.1f} after (the machine is shared); {meta['count']} modes per "
        "case; times in seconds, wall clock; peak MB is the case's ru_maxrss.",
        _touch_line(meta.get("first_touch_s_per_gib")), _speed_line(rows),
        table(rows), details(rows), accuracy_table(rows),
        "Where the time goes (s):\n\n" + breakdown(rows), peer_comparison(rows),
        time_to_accuracy(rows)])


def _ngsolve_installed() -> bool:
    import importlib.util

    return importlib.util.find_spec("ngsolve") is not None


def first_touch_seconds_per_gb(gib: float = 1.0) -> tuple[float, float] | None:
    """(s/GiB the first time, s/GiB again at once) to write fresh memory, in a child process.

    On the VMs this bench runs on, memory the guest has not touched lately is backed by the
    host on first touch, at seconds per GiB (more than ten times the cost of writing it again),
    and memory freed for more than a few seconds is handed back and costs that again. Every
    case pays it for its peak memory, so the bench prints it beside the machine."""
    code = ("import numpy as np, time\n"
            f"a = np.empty(int({gib} * 2**30) // 8)\n"
            "t = time.perf_counter(); a.fill(1.0); t1 = time.perf_counter(); a.fill(2.0)\n"
            "print(t1 - t, time.perf_counter() - t1)\n")
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=120, check=True).stdout.split()
        return float(out[0]) / gib, float(out[1]) / gib
    except (subprocess.SubprocessError, OSError, ValueError, IndexError):
        return None


#: the host-speed probe: a Gram product of two (n, 25) float64 blocks (memory-bound, the
#: kind of product LOBPCG's dense work and the sparse products are made of) and a square
#: dgemm (arithmetic-bound, the kind PARDISO's factorisation runs), on MKL where the
#: pipeline uses it, in a child process that the pipeline's own command-line tuning runs in
PROBE_ROWS, PROBE_COLUMNS, PROBE_SQUARE, PROBE_REPEAT = 2_000_000, 25, 2000, 5
PROBE_CODE = f"""
import sys, time
sys.path.insert(0, {str(ROOT)!r})
from pipeline.cli import tune_process
tune_process()
import numpy as np
from pipeline.solve.blas import gram
rng = np.random.default_rng(0)
def median(fn, *args):
    fn(*args)
    times = []
    for _ in range({PROBE_REPEAT}):
        t = time.perf_counter(); fn(*args); times.append(time.perf_counter() - t)
    return sorted(times)[len(times) // 2]
A = rng.standard_normal(({PROBE_ROWS}, {PROBE_COLUMNS})); B = A + 1.0
gbs = 2 * A.nbytes / median(gram, A, B) / 1e9
del A, B
C = rng.standard_normal(({PROBE_SQUARE}, {PROBE_SQUARE}))
gflops = 2 * {PROBE_SQUARE} ** 3 / median(gram, C, C) / 1e9
print(gbs, gflops)
"""


def host_speed() -> tuple[float, float] | None:
    """(GB/s of a tall-skinny Gram product, GFlop/s of a square dgemm) right now, in a child
    process (:data:`PROBE_CODE`; about 3 s), or None if it fails.

    The shared VMs this bench runs on change speed by 25-35 % within the hour (the host's
    other tenants), far more than most changes measured here. The probe before every case
    puts each case's times beside the host's speed at the time, so that two bench runs of
    different hours can be compared (a case's time divided by the probe's time is
    steadier than either), and a reader sees which phase a figure comes from."""
    try:
        out = subprocess.run([sys.executable, "-c", PROBE_CODE], capture_output=True,
                             text=True, timeout=120, check=True).stdout.split()
        return float(out[0]), float(out[1])
    except (subprocess.SubprocessError, OSError, ValueError, IndexError):
        return None


def _speed_line(rows: list[dict]) -> str:
    probes = [r["host_speed"] for r in rows if r.get("host_speed")]
    if not probes:
        return "Host speed: not measured."
    gbs, gflops = sorted(p[0] for p in probes), sorted(p[1] for p in probes)
    return (f"Host speed (probed in a child process before every case; the VM's speed "
            f"moves with its host's other tenants): a Gram product of two "
            f"({PROBE_ROWS:,} x {PROBE_COLUMNS}) blocks {gbs[0]:.1f}-{gbs[-1]:.1f} GB/s, a "
            f"{PROBE_SQUARE}^3 dgemm {gflops[0]:.0f}-{gflops[-1]:.0f} GFlop/s (each "
            "case's median in the breakdown's last columns).")


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    import numpy
    import scipy

    try:
        from importlib.metadata import version

        mkl = version("mkl")
    except Exception:
        mkl = "not installed"
    return (f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GiB RAM, {platform.system()} "
            f"{platform.release()}; Python {platform.python_version()}, numpy "
            f"{numpy.__version__}, scipy {scipy.__version__}, MKL {mkl}")


def check_json_option(ap: argparse.ArgumentParser, path: str | None) -> None:
    """Refuse, before any case runs, a ``--json`` path that does not end in ``.json``:
    the bench writes its rows there, and a config, a script or a page given by mistake
    would be replaced."""
    if path and Path(path).suffix.lower() != ".json":
        ap.error(f"--json {path}: expected a file name ending in .json (the bench writes "
                 "its rows there)")


def write_whole(path: str | Path, content) -> None:
    """Write ``path`` whole or not at all, through the package's atomic writer (a
    temporary name renamed over ``path``), so that an interrupted bench leaves no partial
    JSON, page or array for a later case to read. ``content``: a text, or a function
    that writes the file to the binary file object it is given (``np.save``)."""
    from pipeline._util.atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        if callable(content):
            content(fh)
        else:
            fh.write(content.encode())


def write_doc(text: str) -> None:
    marker_start, marker_end = "<!-- bench:start -->", "<!-- bench:end -->"
    block = f"{marker_start}\n{text}\n{marker_end}"
    if DOC.exists() and marker_start in DOC.read_text():
        doc = DOC.read_text()
        head, rest = doc.split(marker_start, 1)
        tail = rest.split(marker_end, 1)[1] if marker_end in rest else ""
        write_whole(DOC, head + block + tail)
    else:
        write_whole(DOC, "# Performance\n\n" + block + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--large", action="store_true",
                    help="add the 600k-, 1M- and 3M-DOF cases")
    ap.add_argument("--repeat", type=int, default=1,
                    help="runs per case; the table shows medians (time, peak memory)")
    ap.add_argument("--repeat-large", action="store_true",
                    help="repeat the 600k, 1M and 3M cases too (by default they run once)")
    ap.add_argument("--precision", default="auto", choices=["auto", "double", "mixed"],
                    help="modes.precision of the pipeline cases")
    ap.add_argument("--method", default="auto", choices=["auto", "factor", "multigrid"],
                    help="modes.method of the pipeline rows (default auto)")
    ap.add_argument("--also-multigrid", action="store_true",
                    help="also run the factor-free solver (modes.method: multigrid)")
    ap.add_argument("--also-factor", action="store_true",
                    help="also run the factor path (modes.method: factor) at the sizes of "
                         "--large, where auto takes the factor-free one")
    ap.add_argument("--also-mixed", action="store_true",
                    help="also run the pipeline with modes.precision=mixed")
    ap.add_argument("--ngsolve", choices=["auto", "yes", "no"], default="auto",
                    help="run NGSolve's variants beside ours (auto: when installed)")
    ap.add_argument("--ngsolve-variants", default=",".join(NGSOLVE_VARIANTS),
                    help="NGSolve inverses to try (comma-separated; from 600k only "
                         "the first)")
    ap.add_argument("--sizes", default=None,
                    help="comma-separated subset of " + ",".join(SIZES))
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the straightforward stack")
    ap.add_argument("--count", type=int, default=COUNT, help="modes per case")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per case")
    ap.add_argument("--no-probe", dest="probe", action="store_false",
                    help="skip the host-speed probe before every case (about 3 s each)")
    ap.add_argument("--write-doc", action="store_true", help="update docs/performance.md")
    ap.add_argument("--json", default=None, help="also write all rows to this file")
    ap.add_argument("--render", default=None, metavar="JSON",
                    help="print (and with --write-doc, write) the report of an earlier --json")
    ap.add_argument("--child", choices=["pipeline", "straightforward"], help=argparse.SUPPRESS)
    ap.add_argument("--size", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--result", help=argparse.SUPPRESS)
    ap.add_argument("--shapes", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    check_json_option(ap, args.json)
    from pipeline._util.interrupts import handle_signals

    handle_signals()  # SIGTERM and SIGHUP stop the running case too (run_watched)

    if args.child:
        with tempfile.TemporaryDirectory(prefix="bench_case_") as tmp:
            if args.child == "pipeline":
                row = run_pipeline_case(args.size, args.count, Path(tmp), args.precision,
                                        args.method, Path(args.shapes) if args.shapes else None)
            else:
                row = run_reference_case(args.size, args.count, Path(tmp))
        write_whole(args.result, json.dumps(row))
        return 0

    if args.render:
        saved = json.loads(Path(args.render).read_text())
        text = report(saved["rows"], saved["meta"])
        print(text)
        if args.write_doc:
            write_doc(text)
        return 0

    labels = args.sizes.split(",") if args.sizes else ["20k", "100k", "300k"]
    if args.large:
        labels += [x for x in LARGE if x not in labels]
    unknown = [x for x in labels if x not in SIZES]
    if unknown:
        ap.error(f"unknown size(s) {unknown}; expected some of {list(SIZES)}")
    ngsolve = args.ngsolve == "yes" or (args.ngsolve == "auto" and _ngsolve_installed())
    rows, raw = [], []
    shapes_tmp = tempfile.TemporaryDirectory(prefix="bench_shapes_")
    shapes_dir = Path(shapes_tmp.name)
    touch = first_touch_seconds_per_gb()
    load_before = os.getloadavg()
    for label in labels:
        jobs = [("straightforward", None)] if not args.no_reference and (
            label in REFERENCE_SIZES) else []
        jobs.append(("pipeline", "multigrid" if args.method == "multigrid"
                     else args.precision))
        if args.also_mixed and args.precision != "mixed":
            jobs.append(("pipeline", "mixed"))
        if args.also_multigrid and args.method != "multigrid":
            jobs.append(("pipeline", "multigrid"))
        if args.also_factor and args.method != "factor" and label in LARGE:
            jobs.append(("pipeline", "factor"))
        if ngsolve and label in NGSOLVE_MAXH:  # from 600k: the first variant only
            variants = args.ngsolve_variants.split(",")
            jobs += [("ngsolve", inverse) for inverse in
                     (variants[:1] if label in LARGE else variants)]
        runs: dict = {job: [] for job in jobs}
        rounds = max(1, args.repeat) if (label not in LARGE + HUGE or args.repeat_large) else 1
        for _ in range(rounds):  # interleaved: every job once per round
            for kind, variant in jobs:
                print(f"running {kind} {variant or ''} {label} ...", flush=True)
                speed = host_speed() if args.probe else None
                if kind == "ngsolve":
                    one = _run_ngsolve(label, variant, args.count, args.timeout)
                else:
                    one = _run_child(kind, label, args.count, args.timeout, variant or "auto",
                                     shapes_dir / f"{label}-{variant}.npy")
                one["host_speed"] = speed
                runs[(kind, variant)].append(one)
                if args.json:  # every run as it finishes: a long bench keeps what it did
                    raw.append(one)
                    write_whole(Path(args.json).with_suffix(".runs.json"), json.dumps(raw))
        label_rows = []
        for job in jobs:
            row = median_row(runs[job])
            rows.append(row)
            label_rows.append((row, shapes_dir / f"{label}-{job[1]}.npy"))
            if "error" in row:
                print(f"  {row['error']}", flush=True)
            else:
                print(f"  {row['n_dofs']:,} DOFs in {row['total']:.1f} s, peak "
                      f"{row['peak_mb']:,.0f} MB", flush=True)
        add_agreement(label_rows)
    shapes_tmp.cleanup()
    load_after = os.getloadavg()
    meta = {"machine": machine(), "load_before": load_before[0], "load_after": load_after[0],
            "count": args.count, "date": time.strftime("%Y-%m-%d %H:%M"),
            "first_touch_s_per_gib": touch}
    text = report(rows, meta)
    print()
    print(text)
    if args.json:
        write_whole(args.json, json.dumps({"meta": meta, "rows": rows}, indent=1))
    if args.write_doc:
        write_doc(text)
        print(f"\nwrote {DOC.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
