"""The library leaves its host process alone.

A fresh interpreter plays a host (a notebook, a co-simulation, a test suite): it loads
numpy, scipy and MKL itself, picks a matplotlib backend, and records its environment,
every thread pool's size (threadpoolctl), MKL's thread count and the backend. Then it
imports the package, runs a small config through :func:`pipeline.run_config`, loads the
result, steps it through a scenario and draws its plots, and records all of it again:
nothing may have changed. The command line tunes its own process instead
(:mod:`pipeline.cli.process`, tested in test_resources.py).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from conftest import ROOT

pytest.importorskip("threadpoolctl")
pytest.importorskip("matplotlib")

_HOST = r"""
import ctypes, glob, json, os, sys
from pathlib import Path

import matplotlib
matplotlib.use("svg")  # the host's choice: not the Agg a library might force
import numpy, scipy.sparse.linalg  # the host's BLAS pools
from threadpoolctl import ThreadpoolController, threadpool_info

# the host's choices: OpenBLAS and MKL (as a numpy built on MKL would load it) on one thread
ThreadpoolController().select(internal_api="openblas").limit(limits=1)
mkl = None
for path in sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")), key=len):
    mkl = ctypes.CDLL(path)
    mkl.MKL_Set_Num_Threads(1)
    break

def state():
    return {"env": dict(os.environ),
            "pools": {p["filepath"]: [p["internal_api"], p["num_threads"]]
                      for p in threadpool_info()},
            "mkl_threads": mkl.MKL_Get_Max_Threads() if mkl is not None else None,
            "backend": matplotlib.get_backend()}

out = Path(sys.argv[1])
before = state()
import pipeline
from pipeline.apps.plots import plot_file
from pipeline.apps.simulate import simulate

result = pipeline.run_config(Path("configs/cantilever.yaml"), output=out / "model.h5",
                             overrides=["mesh.size=0.02", "modes.count=6"])
pipeline.load_model(result.output)
simulate(result.output, [Path("configs/scenarios/step_load.yaml")], out / "sim.h5",
         plots=True)
plot_file(result.output, out / "plots", modes=2)
after = state()
print(json.dumps({"before": before, "after": after,
                  "pngs": sorted(p.name for p in out.rglob("*.png"))}))
"""


@pytest.fixture(scope="module")
def host(tmp_path_factory):
    """(before, after, PNG names) of one host process's run."""
    from pipeline.cli.process import PROCESS_SETTINGS

    out = tmp_path_factory.mktemp("host")
    # a host that has not tuned its process (the CLI's settings may be in this one)
    env = {k: v for k, v in os.environ.items()
           if k not in PROCESS_SETTINGS and k != "MKL_NUM_THREADS"}
    env["PYTHONPATH"] = str(ROOT)
    proc = subprocess.run([sys.executable, "-c", _HOST, str(out)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    seen = json.loads(proc.stdout.strip().splitlines()[-1])
    return seen["before"], seen["after"], seen["pngs"]


def _env_changes(before, after) -> dict:
    return {k: (before["env"].get(k), after["env"].get(k))
            for k in set(before["env"]) | set(after["env"])
            if before["env"].get(k) != after["env"].get(k)}


def test_a_run_leaves_the_host_process_as_it_was(host):
    before, after, pngs = host
    changed = _env_changes(before, after)
    assert not changed, f"environment changed: {changed}"
    assert after["backend"] == before["backend"] == "svg"
    for lib, (api, threads) in before["pools"].items():
        if api == "openblas":
            assert after["pools"][lib] == [api, threads] and threads == 1, (lib, after["pools"])
    assert "sim.step_load.png" in pngs and "mode_01.png" in pngs


def test_a_run_leaves_mkl_as_it_was(host):
    """MKL's thread count and its OpenMP pool: the solver scopes them per call."""
    before, after, _ = host
    assert after["mkl_threads"] == before["mkl_threads"]
    for lib, (api, threads) in before["pools"].items():  # MKL and its OpenMP runtime
        assert after["pools"][lib] == [api, threads], (lib, after["pools"])


_ONE_THREAD_HOST = r"""
import json, sys
from pathlib import Path
from threadpoolctl import ThreadpoolController
import numpy
import pipeline
from pipeline.solve import mkl

mkl.mkl_library()  # loaded, so that threadpoolctl sees it
ThreadpoolController().select(internal_api="mkl").limit(limits=1)  # as joblib/sklearn do
result = pipeline.run_config(Path("configs/cantilever.yaml"), output=Path(sys.argv[1]),
                             overrides=["mesh.size=0.02", "modes.count=4"])
print(json.dumps(list(result.frequencies_hz)))
"""


def test_a_host_that_limits_mkl_to_one_thread_gets_the_same_modes(tmp_path):
    """A host's MKL limit (threadpoolctl, one thread) once made PARDISO's factor in a
    background analysis thread disagree with the caller's and report a false singular
    stiffness: the modes must be those of an unlimited run, to the eigensolver's tolerance."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    runs = []
    for script in (_ONE_THREAD_HOST, _ONE_THREAD_HOST.replace(
            'ThreadpoolController().select(internal_api="mkl").limit(limits=1)', "")):
        proc = subprocess.run([sys.executable, "-c", script, str(tmp_path / f"{len(runs)}.h5")],
                              cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    # the same factorisation path on 1 or 2 threads: frequencies agree far inside the
    # 1e-8 relative eigenvalue tolerance the block Lanczos solve converges to
    assert runs[0] == pytest.approx(runs[1], rel=1e-8)


_FORKING_HOST = r"""
import os, sys, time
from pathlib import Path
import pipeline

out = Path(sys.argv[1])
overrides = ["mesh.size=0.02", "modes.count=4"]
pipeline.run_config(Path("configs/cantilever.yaml"), output=out / "parent.h5", overrides=overrides)
pid = os.fork()
if pid == 0:
    pipeline.run_config(Path("configs/cantilever.yaml"), output=out / "child.h5",
                        overrides=overrides)
    os._exit(0)
deadline = time.monotonic() + 120
while time.monotonic() < deadline:
    got, status = os.waitpid(pid, os.WNOHANG)
    if got:
        print("exit", os.waitstatus_to_exitcode(status))
        break
    time.sleep(0.1)
else:
    os.kill(pid, 9)
    print("hung")
"""


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_of_a_host_that_ran_the_pipeline_runs_it_too(tmp_path):
    """A batch case runs in a forked child of a process that has already factorised: MKL
    must run on a threading layer whose pool survives fork (gmsh loads GNU OpenMP, which
    MKL took when it came first, and whose pool hangs a forked child's first parallel
    PARDISO call)."""
    env = {k: v for k, v in os.environ.items() if k not in ("MKL_THREADING_LAYER",)}
    env["PYTHONPATH"] = str(ROOT)
    proc = subprocess.run([sys.executable, "-c", _FORKING_HOST, str(tmp_path)], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().splitlines()[-1] == "exit 0"
    assert (tmp_path / "child.h5").is_file()
