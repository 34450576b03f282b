"""The pipeline's command line against the same command at an earlier revision, run by
run in one window: the speed-up of a change as a ratio of runs seconds apart.

The shared VMs this bench runs on change speed by 25-40 % within the hour (the host's
other tenants; the 1M-DOF run follows the host's memory bandwidth, which the probe of
``bench_pipeline.py`` reads), so two figures from different hours cannot show a change
of that size. Here every round runs both trees back to back, in alternating order, and
the ratio of each round is kept:

    python benchmarks/bench_baseline.py --baseline 6f9150d --sizes 1M --repeat 3

Each run is a cold ``python -m pipeline run configs/cantilever.yaml --set mesh.size=S
--set modes.count=N`` (the same interpreter and installed packages for both trees; the
tree's own ``pipeline`` package first on the path), timed from outside and watched for
its peak resident memory (sampled every 0.25 s). The baseline is a detached git
worktree of the revision in a temporary folder, removed at the end. The table gives the
medians of both, the median and range of the round-by-round ratios (baseline / current),
and the largest relative difference of the frequencies the two runs print (4 decimals:
a check that both solved the same problem, to about 1e-6 at the first mode).

An unknown revision is refused in one line (exit 2) before any run. SIGINT, SIGTERM
and SIGHUP stop the running case (SIGTERM to its process group, then SIGKILL:
``bench_pipeline.run_watched``) and remove the worktree (exit 130).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import (COUNT, ROOT, SIZES, check_json_option, host_speed,  # noqa: E402
                            machine, run_watched, write_whole)

from pipeline._util.atomic import private_folder, signals_held  # noqa: E402
from pipeline._util.interrupts import handle_signals  # noqa: E402

CONFIG = "configs/cantilever.yaml"
_MODE_LINE = re.compile(r"^\s+(\d+)\s+(\d+\.\d+)\s+\S+\s*$")
_DOFS_LINE = re.compile(r"^\S+: (\d+) DOFs")


class BenchError(Exception):
    """A bad argument or a tree that cannot run: one line, exit code 2."""


def printed_frequencies(text: str) -> list[float]:
    """The frequencies (Hz) of the mode table ``python -m pipeline run`` prints, in order.

    >>> printed_frequencies("x: 12 DOFs\\n  mode  f [Hz]  label\\n     1   65.6080  bending_z_1\\n")
    [65.608]
    """
    return [float(m.group(2)) for m in map(_MODE_LINE.match, text.splitlines()) if m]


def printed_dofs(text: str) -> int | None:
    """The DOF count of the summary's first line (``name: N DOFs (...)``), or None."""
    for line in text.splitlines():
        m = _DOFS_LINE.match(line)
        if m:
            return int(m.group(1))
    return None


def frequency_difference(a: list[float], b: list[float]) -> float | None:
    """max |a_k - b_k| / |b_k| over the modes both list (None if either lists none).

    >>> frequency_difference([100.0, 200.0], [100.0, 201.0, 300.0])
    0.004975124378109453
    """
    pairs = list(zip(a, b))
    if not pairs:
        return None
    return max(abs(x - y) / abs(y) for x, y in pairs)


def summarize(label: str, rounds: list[dict]) -> dict:
    """One row from the rounds of a size: each round holds ``current`` and ``baseline``
    runs (``seconds``, ``peak_bytes``, ``frequencies``, ``dofs``) and the host probe
    (``host_speed``: GB/s, GFlop/s, or None). ``speedup``: the median of the rounds'
    baseline / current; ``speedups``: all of them."""
    done = [r for r in rounds if "error" not in r["current"] and "error" not in r["baseline"]]
    row = {"label": label, "rounds": len(rounds), "complete": len(done)}
    errors = [r[side]["error"] for r in rounds for side in ("baseline", "current")
              if "error" in r[side]]
    if errors:
        row["error"] = errors[0]
    if not done:
        return row
    ratios = [r["baseline"]["seconds"] / r["current"]["seconds"] for r in done]
    diffs = [frequency_difference(r["current"]["frequencies"], r["baseline"]["frequencies"])
             for r in done]
    probes = [r["host_speed"] for r in done if r.get("host_speed")]
    row.update(
        dofs=done[-1]["current"]["dofs"], baseline_dofs=done[-1]["baseline"]["dofs"],
        current_s=statistics.median(r["current"]["seconds"] for r in done),
        baseline_s=statistics.median(r["baseline"]["seconds"] for r in done),
        current_peak_gb=max(r["current"]["peak_bytes"] for r in done) / 1e9,
        baseline_peak_gb=max(r["baseline"]["peak_bytes"] for r in done) / 1e9,
        speedup=statistics.median(ratios), speedups=ratios,
        frequency_difference=max((d for d in diffs if d is not None), default=None),
        host_gbs=[p[0] for p in probes])
    return row


def table(rows: list[dict], baseline: str, commit: str) -> str:
    """The markdown table of :func:`summarize`'s rows."""
    out = [f"| size | DOFs | current s | baseline {baseline} s | speed-up (rounds) | "
           "peak GB, current / baseline | max rel. frequency difference | host GB/s |",
           "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if "speedup" not in r:
            out.append(f"| {r['label']} | - | - | - | {r.get('error', 'not run')} | - | - | - |")
            continue
        spread = ", ".join(f"{x:.2f}" for x in r["speedups"])
        diff = "-" if r["frequency_difference"] is None else f"{r['frequency_difference']:.1e}"
        gbs = (f"{min(r['host_gbs']):.1f}-{max(r['host_gbs']):.1f}" if r["host_gbs"]
               else "-")
        dofs = f"{r['dofs']:,}" if r["dofs"] == r["baseline_dofs"] else \
            f"{r['dofs']:,} (baseline {r['baseline_dofs']:,})"
        out.append(f"| {r['label']} | {dofs} | {r['current_s']:.1f} | {r['baseline_s']:.1f} | "
                   f"{r['speedup']:.2f}x ({spread}) | {r['current_peak_gb']:.1f} / "
                   f"{r['baseline_peak_gb']:.1f} | {diff} | {gbs} |")
    out.append("")
    out.append(f"Baseline: {baseline} = commit {commit}. Medians of the rounds; each round "
               "ran both trees back to back (the order alternating), and its ratio is "
               "baseline / current.")
    return "\n".join(out)


def resolve_revision(rev: str) -> str:
    """The full commit id of ``rev`` in this repository (BenchError if it names none)."""
    proc = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"],
                          cwd=ROOT, capture_output=True, text=True)
    if proc.returncode != 0 or not proc.stdout.strip():
        raise BenchError(f"--baseline {rev!r}: not a commit of the repository at {ROOT}; "
                         "expected a commit id, tag or branch (git rev-parse)")
    return proc.stdout.strip()


@contextlib.contextmanager
def worktree(commit: str) -> Iterator[Path]:
    """A detached git worktree of ``commit`` in a private temporary folder, removed on
    exit (an interrupt included: the folder goes, and git forgets the tree)."""
    with private_folder("bench_baseline_") as tmp:
        path = tmp / "tree"
        try:
            proc = subprocess.run(["git", "worktree", "add", "--detach", "--quiet",
                                   str(path), commit], cwd=ROOT, capture_output=True, text=True)
            if proc.returncode != 0:
                why = " | ".join((proc.stderr or proc.stdout).strip().splitlines()[-1:])
                raise BenchError(f"git worktree add {commit[:12]}: {why or 'failed'}; expected "
                                 "a worktree of the revision in a temporary folder")
            yield path
        finally:
            with signals_held():
                removed = subprocess.run(["git", "worktree", "remove", "--force", str(path)],
                                         cwd=ROOT, capture_output=True)
                if removed.returncode != 0:  # an add cut short: git's entry outlives the tree
                    subprocess.run(["git", "worktree", "prune"], cwd=ROOT, capture_output=True)


def _env(tree: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), PYTHONDONTWRITEBYTECODE="1")
    env.pop("PYTHONSAFEPATH", None)
    return env


def check_tree(tree: Path) -> None:
    """Refuse a tree whose ``import pipeline`` resolves outside it (an installed copy
    first on the path would time the wrong code)."""
    proc = subprocess.run([sys.executable, "-c", "import pipeline; print(pipeline.__file__)"],
                          cwd=tree, env=_env(tree), capture_output=True, text=True)
    where = proc.stdout.strip()
    if proc.returncode != 0 or not Path(where).resolve().is_relative_to(tree.resolve()):
        raise BenchError(f"{tree}: 'import pipeline' gives {where or proc.stderr.strip()!r}; "
                         "expected the tree's own package")


def run_cli(tree: Path, size: float, count: int, timeout: float) -> dict:
    """One cold run of the pipeline's command line in ``tree``: seconds, peak resident
    bytes, the printed frequencies and DOF count, or ``error``."""
    with private_folder("bench_baseline_run_") as tmp:
        cmd = [sys.executable, "-m", "pipeline", "run", CONFIG, "--set", f"mesh.size={size}",
               "--set", f"modes.count={count}", "-o", str(tmp / "out.h5")]
        t0 = time.perf_counter()
        proc = run_watched(cmd, timeout, cwd=tree, env=_env(tree))
        seconds = time.perf_counter() - t0
    if proc.error or proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:]
        return {"error": proc.error or f"exit {proc.returncode}: {' | '.join(tail)}"}
    return {"seconds": seconds, "peak_bytes": proc.peak_rss_bytes,
            "frequencies": printed_frequencies(proc.stdout), "dofs": printed_dofs(proc.stdout)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", required=True,
                    help="the earlier revision (commit, tag or branch) to run beside this tree")
    ap.add_argument("--sizes", default="1M", help="comma-separated subset of " + ",".join(SIZES))
    ap.add_argument("--repeat", type=int, default=3, help="rounds per size")
    ap.add_argument("--count", type=int, default=COUNT, help="modes per run")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    ap.add_argument("--no-probe", dest="probe", action="store_false",
                    help="skip the host-speed probe before every round (about 3 s each)")
    ap.add_argument("--json", default=None, help="also write the rounds to this file")
    args = ap.parse_args(argv)
    check_json_option(ap, args.json)
    labels = [x for x in args.sizes.split(",") if x]
    unknown = [x for x in labels if x not in SIZES]
    if unknown or not labels:
        ap.error(f"--sizes: unknown size(s) {unknown}; expected some of {list(SIZES)}")
    if args.repeat < 1:
        ap.error(f"--repeat {args.repeat}: expected at least 1")
    handle_signals()  # SIGTERM and SIGHUP too: the running case and the worktree go
    try:
        commit = resolve_revision(args.baseline)
        with worktree(commit) as base:
            for tree in (base, ROOT):
                check_tree(tree)
            rows, all_rounds = [], {}
            for label in labels:
                rounds = []
                for i in range(args.repeat):
                    probe = host_speed() if args.probe else None
                    order = [("baseline", base), ("current", ROOT)]
                    runs = {}
                    for side, tree in (order if i % 2 == 0 else order[::-1]):
                        print(f"round {i + 1}/{args.repeat}, {label}: {side} ...", flush=True)
                        runs[side] = run_cli(tree, SIZES[label], args.count, args.timeout)
                    rounds.append({**runs, "host_speed": probe})
                all_rounds[label] = rounds
                rows.append(summarize(label, rounds))
    except BenchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"interrupted ({exc or 'SIGINT'}): the running case stopped, the baseline's "
              "worktree removed", file=sys.stderr)
        return 130
    print()
    print(f"Machine: {machine()}.")
    print(table(rows, args.baseline, commit[:12]))
    if args.json:
        write_whole(args.json, json.dumps({"baseline": args.baseline, "commit": commit,
                                           "rows": rows, "rounds": all_rounds}, indent=1))
    return 0 if all("speedup" in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
