"""Batch runs (pipeline.apps.batch, pipeline.cli.batch) on tiny cantilever meshes.

Every case here is the reference cantilever at mesh.size >= 0.01 (~11-17k DOFs, about
2 s), 4 modes and a 1-input reduced model, so a batch of three takes seconds. The
clusters are real: a LocalCluster of worker processes, and a `dask scheduler` plus a
`dask worker` started here as subprocesses on 127.0.0.1 (random ports, bounded waits,
always terminated).

gmsh meshes on one thread, so the same config gives the same mesh; the threaded
factorisation and eigensolver are not bitwise reproducible run to run, so results of two
runs are compared to 1e-3, not exactly.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed", reason="the batch extra (dask[distributed]) is not installed")

from pipeline.apps.batch import (  # noqa: E402
    Case,
    load_batch,
    predict_mesh_size,
    run_batch,
    admit,
    split_by_budget,
)
from pipeline.apps.batch import plan_local_workers as _plan_local_workers  # noqa: E402
from pipeline.cli.batch import main  # noqa: E402
from pipeline.errors import ConfigError  # noqa: E402
from pipeline.store.h5file import open_verified  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DASK = Path(sys.executable).with_name("dask")

BASE = """\
name: tiny
geometry: {kind: box, length: 0.5, height: 0.02, depth: 0.05}
mesh: {order: 2, size: 0.012}
material: {E: 69.0e9, nu: 0.33, rho: 2700.0}
supports: [{region: root, fix: all}]
modes: {count: 4}
ports:
  inputs:  [{name: tip_force_y, region: tip, kind: force, direction: [0, -1, 0]}]
  outputs: [{name: tip_y, region: tip, kind: displacement, direction: [0, 1, 0]}]
damping: {kind: uniform, ratio: 0.02}
reduction: {modes: 3, static_correction: residual}
"""

# two meshes of the same body (a convergence pair) and one explicit variant
SMALL = """\
batch:
  name: small
  description: two meshes and a steel variant
  base: base.yaml
  sweep: {mesh.size: [0.012, 0.01]}
  cases:
    - {label: steel, set: {material.E: 210e9, material.rho: 7850}}
"""


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def make_batch(folder: Path, text: str = SMALL, name: str = "batch.yaml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    write(folder / "base.yaml", BASE)
    return write(folder / name, text)


def h5_times(outdir: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in (outdir / "cases").glob("*.h5")}


def frequencies(result) -> dict[str, np.ndarray]:
    return {o.case.key: np.asarray(o.record["frequencies_hz"]) for o in result.outcomes}


@pytest.fixture(scope="module")
def local_run(tmp_path_factory):
    """The small batch through a local cluster of two worker processes."""
    folder = tmp_path_factory.mktemp("local")
    path = make_batch(folder)
    environ = dict(os.environ)
    result = run_batch(path, folder / "out", workers=2, progress=False, echo=lambda s: None)
    return path, result, environ, dict(os.environ)


def test_a_local_cluster_leaves_the_environment_as_it_was(local_run):
    """dask's nannies write their workers' variables (MKL_NUM_THREADS=1, OMP_NUM_THREADS,
    PYTHONHASHSEED) into the process that starts them; left behind, a CLI child started
    later (tests/test_api.py) solved on one MKL thread, this process on two, and their
    residual flexibilities differed by 1.6e-7 of themselves."""
    *_, before, after = local_run
    changed = {k: (before.get(k), after.get(k)) for k in set(before) | set(after)
               if before.get(k) != after.get(k)}
    assert not changed, f"environment changed: {changed}"


# --------------------------------------------------------------------------- validation
def test_invalid_cases_are_refused_before_anything_runs(tmp_path, capsys):
    path = make_batch(tmp_path, """\
batch:
  base: base.yaml
  sweep: {mesh.size: [0.012, -1.0]}
  cases:
    - {label: typo, set: {material.G: 1.0}}
    - {modes.count: 4}
""")
    with pytest.raises(ConfigError) as err:
        load_batch(path)
    msg = str(err.value)
    assert str(path) in msg and "2 of 4 cases are invalid" in msg
    assert "case 2 (mesh.size=-1.0)" in msg and "'mesh.size'" in msg
    assert "case 3 (typo)" in msg and "material.G" in msg
    # the command: exit code 2, one message, nothing created
    out = tmp_path / "out"
    assert main([str(path), "-o", str(out)]) == 2
    assert "material.G" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("text, words", [
    ("batch: {base: base.yaml, sweep: {mesh.size: 0.01}}", ["batch.sweep.mesh.size", "list"]),
    ("batch: {base: base.yaml, combine: zip, sweep: {mesh.size: [0.01, 0.012], "
     "constraints.in_plane: [true]}}", ["zip", "equal length"]),
    ("batch: {base: nowhere.yaml}", ["batch.base", "nowhere.yaml", "not found"]),
    ("batch: {base: base.yaml, sweeps: {}}", ["batch.sweeps", "not known"]),
    ("batch: {base: base.yaml, combine: outer}", ["batch.combine", "product or zip"]),
    ("batch: {base: base.yaml, cases: [{label: x, set: {mesh..size: 1}}]}",
     ["batch.cases[0].set.mesh..size", "dotted"]),
    ("base: base.yaml", ["top-level key 'batch'"]),
])
def test_batch_file_errors_name_the_key(tmp_path, text, words):
    path = make_batch(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_batch(path)
    for word in words:
        assert word in str(err.value)
    assert str(path) in str(err.value)


def test_cases_keys_and_memory_estimates(tmp_path):
    path = make_batch(tmp_path, """\
batch:
  name: grid
  base: base.yaml
  set: {modes.count: 6}
  sweep: {mesh.size: [0.012, 0.01], constraints.in_plane: [false, true]}
  cases:
    - {mesh.size: 0.012}                      # the same config as sweep case 1
    - {label: inline zip, set: {material.nu: 0.3}}
""")
    spec = load_batch(path)
    assert spec.name == "grid" and len(spec.cases) == 6
    assert spec.sweep_keys == ("mesh.size", "constraints.in_plane")
    assert [c.origin for c in spec.cases] == ["sweep"] * 4 + ["case"] * 2
    assert spec.cases[0].label == "mesh.size=0.012, constraints.in_plane=false"
    assert all(c.config.modes.count == 6 for c in spec.cases)
    assert spec.cases[4].key == spec.cases[0].key            # same resolved config, one run
    assert len({c.key for c in spec.cases}) == 5
    assert spec.cases[1].config.constraints.in_plane is True
    assert spec.cases[5].config.material.nu == 0.3
    # finer mesh, more memory; the key moves with any resolved value
    assert spec.cases[2].memory_bytes > spec.cases[0].memory_bytes > 0
    zipped = load_batch(make_batch(tmp_path / "z", """\
batch: {base: base.yaml, combine: zip,
        sweep: {mesh.size: [0.012, 0.01], constraints.in_plane: [false, true]}}
"""))
    assert [(c.config.mesh.size, c.config.constraints.in_plane) for c in zipped.cases] == \
        [(0.012, False), (0.01, True)]


def test_key_follows_a_geometry_file_and_the_cli_parser(tmp_path):
    import argparse

    from pipeline.cli.batch import add_batch_parser, cmd_batch

    text = BASE.replace("geometry: {kind: box, length: 0.5, height: 0.02, depth: 0.05}",
                        "geometry: {kind: geo, path: part.geo}")
    folder = tmp_path / "b"
    folder.mkdir()
    write(folder / "base.yaml", text)
    path = write(folder / "batch.yaml", "batch: {base: base.yaml}")
    write(folder / "part.geo", "// version 1\n")
    first = load_batch(path).cases[0]
    assert first.label == "base" and first.memory_bytes is None   # unknown before meshing
    write(folder / "part.geo", "// version 2\n")
    assert load_batch(path).cases[0].key != first.key             # new geometry, new key
    # the subcommand as pipeline.cli registers it
    parser = argparse.ArgumentParser()
    parser.add_argument("-v", "--verbose", action="count", default=0)
    add_batch_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["batch", "f.yaml", "--workers", "2", "--scheduler",
                              "tcp://127.0.0.1:8786", "-o", "out"])
    assert (args.func, args.file, args.workers, args.scheduler, args.output) == \
        (cmd_batch, "f.yaml", 2, "tcp://127.0.0.1:8786", "out")


def test_memory_aware_admission():
    def case(i, gb):
        return Case(index=i, label=f"c{i}", overrides=(), config=None, key=f"k{i}",
                    memory_bytes=None if gb is None else int(gb * 1e9))

    big1, big2, small, unknown, huge = case(1, 10), case(2, 10), case(3, 2), case(4, None), \
        case(5, 30)
    # a 24 GB machine offers 19.2 GB to cases: never the two 10 GB cases at once, but a
    # small one beside one of them; an unknown estimate counts as nothing
    budget = 0.8 * 24e9
    assert admit([big1, big2, small], 0, 2, budget) == [big1, small]
    assert admit([big2, small, unknown], big1.memory_bytes, 1, budget) == [small]
    assert admit([big2], big1.memory_bytes, 1, budget) == []
    assert admit([big2, small], big1.memory_bytes + small.memory_bytes, 1, budget) == [small]
    assert admit([big1, big2, small], 0, 3, None) == [big1, big2, small]   # remote: Dask's
    assert admit([big1, big2], 0, 0, budget) == []                          # no free slot
    # a case larger than every worker's budget fails at once rather than waiting forever
    fits, refused = split_by_budget([big1, big2, small, unknown, huge], [budget])
    assert fits == [big1, big2, small, unknown]
    assert [c for c, _ in refused] == [huge]
    assert "30.0 GB" in refused[0][1] and "19.2 GB" in refused[0][1]
    assert split_by_budget([huge], [])[1] == []       # nobody advertises memory: run all
    assert _plan_local_workers(None, [big1] * 5) == min(os.cpu_count() or 1, 5)
    assert _plan_local_workers(None, [big1]) == 1 and _plan_local_workers(3, [big1]) == 3


# --------------------------------------------------------------------------- local cluster
def test_local_batch_writes_outputs_and_rerun_computes_nothing(local_run):
    path, result, *_ = local_run
    out = result.outdir
    assert [o.status for o in result.outcomes] == ["done"] * 3, \
        [o.record.get("error") for o in result.outcomes]
    for o in result.outcomes:
        with open_verified(o.h5) as h5:  # complete, checksummed files under the final name
            assert h5["modes/frequencies_hz"].shape == (4,)
            assert "statespace/A" in h5
        record = json.loads((out / "cases" / f"{o.case.key}.json").read_text())
        assert record["status"] == "ok" and record["n_dofs"] > 10000
        assert record["peak_memory_mb"] > 50 and record["times_s"]["modes"] > 0
        assert (out / "cases" / f"{o.case.key}.log").read_text().strip()
        # the pre-mesh estimate is close: within the 20 % of pipeline.fe.mesh.estimate
        # (these ~2k-tetrahedron meshes lose a few per cent of their DOFs to the support)
        nodes, _ = predict_mesh_size(o.case.config)
        assert 0.8 <= 3 * nodes / record["n_dofs"] < 1.2
    assert not list((out / "cases").glob(".*.partial"))

    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["case"] for r in rows] == ["1", "2", "3"]
    assert [r["mesh.size"] for r in rows] == ["0.012", "0.01", "0.012"]
    assert rows[2]["material.E"] == "210000000000.0" and rows[2]["label"] == "steel"
    gain = "dc_gain[tip_force_y->tip_y/position]"
    for r, o in zip(rows, result.outcomes):
        assert r["status"] == "done" and int(r["n_dofs"]) == o.record["n_dofs"]
        assert float(r["f1_hz"]) == pytest.approx(o.record["frequencies_hz"][0])
        with open_verified(o.h5) as h5:  # python-control DC gain == the exact FE compliance
            exact = float(h5["statespace/static_compliance"][0, 0])
        assert float(r[gain]) == pytest.approx(exact, rel=1e-6)
    # steel is stiffer in proportion to E
    assert float(rows[2][gain]) / float(rows[0][gain]) == pytest.approx(69 / 210, rel=0.02)

    html = (out / "report.html").read_text()
    for png in ("freq_vs_mesh.size.png", "freq_by_case.png", "convergence.png", "bode.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert png in html
    assert html.count("data:image/png;base64,") == 4
    assert "None: every case finished" in html

    before = h5_times(out)
    again = run_batch(path, out, workers=2, progress=False, echo=lambda s: None)
    assert [o.status for o in again.outcomes] == ["cached"] * 3
    assert again.workers == "nothing to run"          # no cluster was even started
    assert h5_times(out) == before
    for key, freqs in frequencies(result).items():
        np.testing.assert_array_equal(frequencies(again)[key], freqs)
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["status"] for r in rows] == ["cached"] * 3


def test_broken_case_is_isolated_and_listed(tmp_path, capsys):
    # a sphere region nowhere near the body passes validation and fails at run time
    path = make_batch(tmp_path, """\
batch:
  name: broken
  base: base.yaml
  cases:
    - {label: good, set: {mesh.size: 0.012}}
    - label: probe off the body
      set:
        regions: {probe: {kind: sphere, point: [9.0, 9.0, 9.0], radius: 0.001}}
        supports: [{region: probe, fix: all}]
""")
    out = tmp_path / "out"
    code = main([str(path), "--workers", "2", "-o", str(out)])
    printed = capsys.readouterr().out
    assert code == 1
    assert "1 computed, 0 cached, 1 failed" in printed
    assert "failed cases (1):" in printed
    assert "case 2 (probe off the body)" in printed and "regions.probe" in printed
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["status"] for r in rows] == ["done", "failed"]
    assert "matches no boundary facet" in rows[1]["error"] and rows[0]["error"] == ""
    key = load_batch(path).cases[1].key
    record = json.loads((out / "cases" / f"{key}.json").read_text())
    assert record["status"] == "failed" and record["error_type"] == "RegionError"
    assert not (out / "cases" / f"{key}.h5").exists()
    html = (out / "report.html").read_text()
    assert "probe off the body" in html and "matches no boundary facet" in html


# --------------------------------------------------------------------------- interruption
def _wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


def _ok_records(out: Path) -> set[str]:
    keys = set()
    for p in (out / "cases").glob("*.json"):
        if p.name.startswith("."):  # a writer's temporary file (killed before its rename)
            continue
        with contextlib.suppress(ValueError, OSError):
            if json.loads(p.read_text()).get("status") == "ok":
                keys.add(p.stem)
    return keys


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # zombies of the group's leader count as gone
    try:
        import psutil

        return any(p.status() != psutil.STATUS_ZOMBIE for p in psutil.process_iter()
                   if _pgid(p.pid) == pgid)
    except Exception:
        return True


def _pgid(pid: int) -> int | None:
    try:
        return os.getpgid(pid)
    except OSError:
        return None


def test_killed_batch_resumes_without_redoing_finished_cases(tmp_path):
    path = make_batch(tmp_path, """\
batch:
  name: resume
  base: base.yaml
  sweep: {mesh.size: [0.012, 0.011, 0.01]}
""")
    spec = load_batch(path)
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "batch", str(path), "--workers", "1",
                             "-o", str(out)], cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        _wait_for(lambda: _ok_records(out) if (out / "cases").exists() else None, 120,
                  "the first case to finish")
    finally:  # kill the batch, its cluster and the running case at once
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    _wait_for(lambda: not _group_alive(proc.pid), 30, "the killed processes to exit")

    finished = _ok_records(out)
    assert 1 <= len(finished) < 3
    for key in finished:  # what is there under a final name is complete
        with open_verified(out / "cases" / f"{key}.h5"):
            pass
    unfinished = [c for c in spec.cases if c.key not in finished]
    # what an interrupted non-atomic writer would leave: a truncated file under the final
    # name, and a partial file; neither may be taken for a result
    victim = out / "cases" / f"{unfinished[0].key}.h5"
    some = (out / "cases" / f"{next(iter(finished))}.h5").read_bytes()
    victim.write_bytes(some[: len(some) // 3])
    write(out / "cases" / f".{unfinished[-1].key}.h5.4242.partial", "half a file")
    before = h5_times(out)

    lines: list[str] = []
    result = run_batch(path, out, workers=1, progress=False, echo=lines.append)
    status = {o.case.key: o.status for o in result.outcomes}
    assert {k for k, s in status.items() if s == "cached"} == finished
    assert {k for k, s in status.items() if s == "done"} == {c.key for c in unfinished}
    assert any(f"{len(finished)} already computed (cached, skipped)" in s for s in lines)
    after = h5_times(out)
    assert all(after[f"{k}.h5"] == before[f"{k}.h5"] for k in finished)
    for o in result.outcomes:
        with open_verified(o.h5):
            pass
    assert not list((out / "cases").glob(".*.partial"))


# --------------------------------------------------------------------------- remote cluster
@contextlib.contextmanager
def dask_cluster(folder: Path, nthreads: int, memory: int):
    """`dask scheduler` + one `dask worker` on 127.0.0.1 with random ports; yields
    (address, worker nanny process); always terminates both."""
    folder.mkdir(parents=True, exist_ok=True)
    sched_file = folder / "scheduler.json"
    procs: list[subprocess.Popen] = []
    logs = []

    def start(args, name):
        log = open(folder / f"{name}.log", "w")
        logs.append(log)
        procs.append(subprocess.Popen([str(DASK), *args], cwd=folder, stdout=log,
                                      stderr=subprocess.STDOUT, start_new_session=True))
        return procs[-1]

    try:
        start(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
               "--scheduler-file", str(sched_file)], "scheduler")
        address = _wait_for(lambda: sched_file.exists() and sched_file.stat().st_size and
                            json.loads(sched_file.read_text()).get("address"), 60,
                            "the scheduler to start")
        nanny = start(["worker", address, "--host", "127.0.0.1", "--nworkers", "1", "--nthreads",
                       str(nthreads), "--resources", f"memory={memory}", "--memory-limit", "6GB",
                       "--no-dashboard", "--death-timeout", "60", "--local-directory",
                       str(folder / "worker")], "worker")
        yield address, nanny
    finally:
        for p in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=15)
        for log in logs:
            log.close()


def test_existing_scheduler_gives_the_same_results(local_run, tmp_path):
    """The same batch file on a `dask scheduler` + `dask worker` given by address.

    The worker has two threads but advertises memory for only one case at a time, so the
    cases must run one after the other; its worker process is killed while a case runs,
    and the nanny's new worker runs it again.
    """
    import psutil

    path, local, *_ = local_run
    spec = load_batch(path)
    largest = max(c.memory_bytes for c in spec.cases)
    out = tmp_path / "out"
    with dask_cluster(tmp_path / "cluster", nthreads=2, memory=int(1.5 * largest)) as (address,
                                                                                       nanny):
        killed: list[int] = []

        def kill_worker_once():
            with contextlib.suppress(AssertionError):
                _wait_for(lambda: (out / "cases").exists() and _ok_records(out), 120,
                          "a first case")
                time.sleep(0.3)  # the next case is now running
                for child in psutil.Process(nanny.pid).children():
                    child.send_signal(signal.SIGKILL)  # the worker process, not its nanny
                    killed.append(child.pid)

        killer = threading.Thread(target=kill_worker_once, daemon=True)
        killer.start()
        remote = run_batch(path, out, scheduler=address, progress=False, echo=lambda s: None)
        killer.join(timeout=60)
    assert killed, "the worker process was not found"
    # the first case ran on the killed worker, the others on the nanny's new one
    assert len({o.record["worker"] for o in remote.outcomes}) == 2
    assert [o.status for o in remote.outcomes] == ["done"] * 3, \
        [o.record.get("error") for o in remote.outcomes]
    assert remote.workers.startswith(f"scheduler {address}")
    assert [o.case.key for o in remote.outcomes] == [o.case.key for o in local.outcomes]
    for a, b in zip(local.outcomes, remote.outcomes):
        assert b.record["mode_labels"] == a.record["mode_labels"]
        np.testing.assert_allclose(b.record["frequencies_hz"], a.record["frequencies_hz"],
                                   rtol=1e-3)
        assert abs(b.record["n_dofs"] - a.record["n_dofs"]) < 0.05 * a.record["n_dofs"]
        assert b.record["written_by_worker"] is True  # it sees the same folder
    # memory-aware: never two cases on the worker at once
    spans = sorted((o.record["started_unix"], o.record["finished_unix"])
                   for o in remote.outcomes)
    assert all(s1 >= f0 - 0.05 for (_, f0), (s1, _) in zip(spans, spans[1:])), spans
    assert (out / "report.html").exists() and (out / "summary.csv").exists()


def test_results_sent_back_when_the_worker_cannot_see_the_folder(local_run, tmp_path):
    """A worker on another machine sends the file's bytes; the client writes it."""
    from pipeline.apps.batch import run_case_task

    path, local, *_ = local_run
    case = load_batch(path).cases[0]
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    out = run_case_task(case.config, case.key, str(folder), "token", None)
    assert out["status"] == "ok" and out["written_by_worker"] is False
    assert not list(folder.iterdir())
    assert out["h5_bytes"][:8] == b"\x89HDF\r\n\x1a\n"
    assert out["peak_memory_mb"] > 50 and "mode" in out["log"]
