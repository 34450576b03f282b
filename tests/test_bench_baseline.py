"""The same-window comparison against an earlier revision (benchmarks/bench_baseline.py):
what it reads off the command line's output and how it pairs the rounds.

Synthetic rounds only (the bench itself runs the pipeline twice per round)."""

import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT, bench_module

BENCH = ROOT / "benchmarks" / "bench_baseline.py"

OUTPUT = """cantilever: 101406 DOFs (100695 free), 19956 elements, solver pardiso
  mode        f [Hz]  label
     1       65.6265  bending_z_1
     2      162.5785  bending_y_1
     3      408.1858  bending_z_2
reduced model: 4 modes (4 basis vectors), static correction residual, 8 states
  model          n     f1 [Hz]     err     f2 [Hz]
  beam theory          65.3300  +0.00%    409.4164
"""


@pytest.fixture(scope="module")
def bench():
    with bench_module("bench_baseline") as module:
        yield module


def test_the_mode_table_and_dof_count_are_read_from_the_printed_summary(bench):
    assert bench.printed_frequencies(OUTPUT) == [65.6265, 162.5785, 408.1858]
    assert bench.printed_dofs(OUTPUT) == 101406
    assert bench.printed_dofs("no summary") is None


def test_frequency_difference_over_the_modes_both_list(bench):
    assert bench.frequency_difference([100.0, 200.0], [100.0, 201.0, 7.0]) == \
        pytest.approx(1.0 / 201.0, rel=1e-15)
    assert bench.frequency_difference([], [1.0]) is None


def _run(seconds, peak=1e9, freqs=(65.6, 162.5), dofs=1000):
    return {"seconds": seconds, "peak_bytes": peak, "frequencies": list(freqs), "dofs": dofs}


def test_summary_takes_the_median_of_the_round_by_round_ratios(bench):
    rounds = [{"baseline": _run(60.0), "current": _run(40.0), "host_speed": (10.0, 90.0)},
              {"baseline": _run(66.0), "current": _run(60.0), "host_speed": (9.0, 80.0)},
              {"baseline": _run(52.0), "current": _run(40.0, peak=2e9), "host_speed": None}]
    row = bench.summarize("1M", rounds)
    assert row["speedups"] == [1.5, 1.1, 1.3]
    assert row["speedup"] == 1.3  # of the ratios, not the ratio of the medians (60 / 40)
    assert (row["current_s"], row["baseline_s"]) == (40.0, 60.0)
    assert row["current_peak_gb"] == 2.0 and row["host_gbs"] == [10.0, 9.0]
    assert row["frequency_difference"] == 0.0
    text = bench.table([row], "abc", "abc123")
    assert "| 1M | 1,000 | 40.0 | 60.0 | 1.30x (1.50, 1.10, 1.30) | 2.0 / 1.0 | 0.0e+00 | " \
        "9.0-10.0 |" in text


def test_a_failed_run_drops_its_round_and_is_named(bench):
    rounds = [{"baseline": {"error": "exit 1: boom"}, "current": _run(40.0)},
              {"baseline": _run(50.0, freqs=(65.7,)), "current": _run(40.0, dofs=999)}]
    row = bench.summarize("1M", rounds)
    assert row["complete"] == 1 and row["speedups"] == [1.25]
    assert row["error"] == "exit 1: boom"
    # relative to the baseline's frequency
    assert row["frequency_difference"] == pytest.approx(0.1 / 65.7, rel=1e-12)
    assert "999 (baseline 1,000)" in bench.table([row], "b", "c")
    only_failed = bench.summarize("1M", rounds[:1])
    assert "speedup" not in only_failed
    assert "| 1M | - | - | - | exit 1: boom |" in bench.table([only_failed], "b", "c")


@pytest.mark.skipif(not (ROOT / ".git").exists(), reason="not a git checkout")
def test_an_unknown_revision_is_refused_in_one_line_before_any_run():
    proc = subprocess.run([sys.executable, str(BENCH), "--baseline", "no-such-revision-x"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "'no-such-revision-x'" in lines[0] and "expected" in lines[0]


@pytest.mark.skipif(not (ROOT / ".git").exists(), reason="not a git checkout")
def test_an_interrupted_comparison_leaves_no_case_and_no_worktree():
    import os
    import signal

    def worktrees() -> set[str]:
        out = subprocess.run(["git", "worktree", "list", "--porcelain"], cwd=ROOT,
                             capture_output=True, text=True, check=True).stdout
        return {line.split(" ", 1)[1] for line in out.splitlines()
                if line.startswith("worktree ")}

    before = worktrees()
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    proc = subprocess.Popen([sys.executable, str(BENCH), "--baseline", "HEAD", "--sizes", "20k",
                             "--repeat", "1", "--no-probe"], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()  # printed as the baseline's case starts
        assert first.startswith("round 1/1, 20k:"), first
        during = worktrees() - before
        assert len(during) == 1  # the baseline's tree exists while it runs
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    assert err.strip().splitlines() == [
        "interrupted (SIGTERM): the running case stopped, the baseline's worktree removed"]
    assert worktrees() == before
    assert not any(Path(p).exists() for p in during)
    # no case left running in the removed tree (the cases run with it as their folder)
    for cwd in Path("/proc").glob("[0-9]*/cwd"):
        try:
            where = os.readlink(cwd)
        except OSError:  # gone meanwhile, or not ours to read
            continue
        if any(where.startswith(p) for p in during):
            command = (cwd.parent / "cmdline").read_bytes().replace(b"\0", b" ")
            pytest.fail(f"a process left in the removed tree {where}: {command!r}")


@pytest.mark.parametrize("script, extra", [("bench_pipeline.py", []), ("bench_solvers.py", []),
                                           ("bench_mpi.py", []),
                                           ("bench_baseline.py", ["--baseline", "HEAD"])])
def test_a_json_destination_that_is_not_json_is_refused_before_any_case(tmp_path, script,
                                                                        extra):
    """--json names where the bench writes its rows: a config given there by mistake is
    refused (exit 2, the option and value named) and left as it was."""
    config = tmp_path / "cantilever.yaml"
    config.write_text("name: cantilever\n")
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *extra,
                           "--json", str(config)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert f"--json {config}: expected a file name ending in .json" in proc.stderr
    assert config.read_text() == "name: cantilever\n"
