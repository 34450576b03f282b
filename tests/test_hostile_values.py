"""Hostile values end to end (issue 35, section 3): every value the scenario validator
accepts either runs to a result or is refused with one line naming the key or the
system, before any long work and with nothing written; a re-signed file whose model has
zero states is refused by every consumer (plot, export, simulate) with one line and exit
code 7, nothing written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from pipeline.apps.simulate import simulate
from pipeline.config import load_config
from pipeline.errors import ConfigError, FileFormatError, SolverError
from pipeline.run import run_pipeline
from pipeline.store.h5file import sign
from pipeline._util.yamlio import parse_yaml

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("hostile")
    cfg = load_config(ROOT / "configs/cantilever.yaml", ["mesh.size=0.02"])
    return run_pipeline(cfg, tmp / "good.h5", mesh_dir=tmp).output


def scenario(kind: str, **over) -> dict:
    sc = parse_yaml((ROOT / f"configs/scenarios/{kind}.yaml").read_text(), kind)
    sc.update(duration=0.1)
    if kind == "step_load":
        sc.update(t_on=0.01, t_off=0.05)
    sc.update(over)
    return sc


TINY = 5e-324
CASES = [  # kind, overrides, None (a result) or (error class, pattern)
    ("step_load", dict(duration=1e-6, output_rate=1e8, t_on=0.0, t_off=None), None),
    ("step_load", dict(duration=1e-20, output_rate=2e21, t_on=0.0, t_off=None),
     (ConfigError, r"scenario\.duration': got 1e-20, expected a number >= 1e-06")),
    ("step_load", dict(duration=1e-200, output_rate=1e202, t_on=0.0, t_off=None),
     (ConfigError, r"scenario\.duration'")),
    ("step_load", dict(force=TINY), None),
    ("step_load", dict(force=1e-300), None),
    ("step_load", dict(t_on=1e-300), None),
    ("step_load", dict(t_on=0.01, t_off=0.010000000000000002), None),
    ("body_load", dict(preload=1e-300, gravity=False), None),
    ("body_load", dict(gravity=[0, TINY, 0]), None),
    ("body_load", dict(duration=1e-6, output_rate=1e8), None),
    ("body_load", dict(mass=1e-300), (ConfigError, r"scenario\.mass': got 1e-300, expected 0 "
                                      r"or a mass of 1e-09 to 1e\+12 kg")),
    ("body_load", dict(cutoff_hz=1e300), (ConfigError, r"scenario\.cutoff_hz'")),
    ("body_load", dict(cutoff_hz=1e9), (SolverError, r"time scales")),
    ("mass_sweep", dict(cutoff_hz=1e-3, masses=[0, 10, 20]), None),
    ("mass_sweep", dict(duration=1e-6, output_rate=1e8, cycles=None, masses=[0, 10, 20]),
     None),
    ("mass_sweep", dict(masses=[0, TINY, 1e-300]), (ConfigError, r"scenario\.masses\[1\]'")),
    ("spring_mount", dict(stiffness=TINY), (SolverError, r"no static equilibrium")),
    ("spring_mount", dict(stiffness=1e-300), None),
    ("spring_mount", dict(initial_angle=1e-300, gravity=False), None),
    ("spring_mount", dict(mass=TINY), (ConfigError, r"scenario\.mass'")),
    ("spring_mount", dict(cutoff_hz=1e300), (ConfigError, r"scenario\.cutoff_hz'")),
    ("spring_mount", dict(joint=[1e300, 0, 0]), (ConfigError, r"scenario\.joint'")),
    ("spring_mount", dict(joint=[1e6, 0, 0]), None),
]


@pytest.mark.parametrize("kind, over, outcome", CASES,
                         ids=[f"{k}-{'-'.join(f'{a}={b}' for a, b in o.items())}"
                              for k, o, _ in CASES])
def test_accepted_scenario_values_run_or_are_refused_in_one_line(good, tmp_path, kind, over,
                                                                  outcome):
    out = tmp_path / "result.h5"
    if outcome is None:
        res = simulate(good, scenario(kind, **over), out, plots=False)
        assert out.exists()
        for sr in res.scenarios:
            for run in sr.runs:
                assert run.t.size >= 2
                assert all(np.all(np.isfinite(s)) for s in run.signals.values()), run.model
        return
    cls, pattern = outcome
    with pytest.raises(cls, match=pattern) as info:
        simulate(good, scenario(kind, **over), out, plots=False)
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == []


def _cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)


def test_cli_refuses_a_tiny_duration_in_one_line(good, tmp_path):
    sc = tmp_path / "sc.yaml"
    sc.write_text("kind: step_load\nforce: 1\nt_on: 0\nduration: 1.0e-200\n"
                  "output_rate: 1.0e+202\n")
    out = tmp_path / "out"
    out.mkdir()
    proc = _cli("simulate", good, sc, "-o", out / "r.h5")
    assert proc.returncode == ConfigError.exit_code, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert "duration" in proc.stderr and list(out.iterdir()) == []


@pytest.fixture(scope="module")
def zero_states(good, tmp_path_factory) -> Path:
    """``good`` re-signed with a plant of 0 states (A 0x0, B 0xm, C px0)."""
    bad = tmp_path_factory.mktemp("zero") / "zero.h5"
    bad.write_bytes(good.read_bytes())
    with h5py.File(bad, "a") as h5:
        g = h5["statespace"]
        m, p = g["B"].shape[1], g["C"].shape[0]
        for key, shape in (("A", (0, 0)), ("B", (0, m)), ("C", (p, 0)),
                           ("state_names", (0,)), ("damping_ratios", (0,)),
                           ("frequencies_hz", (0,))):
            attrs, dtype = dict(g[key].attrs), g[key].dtype
            del g[key]
            g.create_dataset(key, shape=shape, dtype=dtype)
            g[key].attrs.update(attrs)
        sign(h5)
    return bad


@pytest.mark.parametrize("command", [
    ("plot", "{f}", "-o", "{out}"),
    ("export", "{f}", "--to", "vtu", "-o", "{out}.vtu"),
    ("export", "{f}", "--to", "mat", "-o", "{out}.mat"),
    ("simulate", "{f}", ROOT / "configs/scenarios/step_load.yaml", "-o", "{out}.h5"),
    ("simulate", "{f}", ROOT / "configs/scenarios/body_load.yaml", "-o", "{out}.h5"),
], ids=["plot", "vtu", "mat", "simulate-step", "simulate-body"])
def test_zero_state_model_is_refused_by_every_consumer(zero_states, tmp_path, command):
    out = tmp_path / "out"
    proc = _cli(*(str(c).format(f=zero_states, out=out) for c in command))
    assert proc.returncode == FileFormatError.exit_code, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "statespace/A has 0 states" in lines[0] and str(zero_states.name) in lines[0]
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- run configs
RUN_CASES = [  # --set values the field checks accept, the key the one line names
    (["geometry.height=5e-324"], "geometry.height"),
    (["geometry.length=1e-300", "geometry.height=1e-300", "geometry.depth=1e-300",
      "mesh.size=1e-300"], "geometry.length"),
    (["geometry.height=1e-5"], "mesh.size"),          # elements 2000:1 flat at size 0.02
    (["material.rho=1e-300"], "material.rho"),
    (["material.E=5e-324"], "material.E"),
    (["material.rho=1e-140", "material.E=1e13"], "material.E"),   # omega^2 ~ 1e157
    (["material.nu=0.4999999999"], "material.nu"),
    (["modes.tolerance=1e-300"], "modes.tolerance"),
    ([f"geometry={{kind: geo, path: {ROOT / 'meshes/slender_beam.geo'}, scale: 0.001}}",
      "lumped=null", "mesh.size=1e-300"], "mesh.size"),   # on main: ZeroDivisionError
    (["regions={far: {kind: sphere, point: [1e300, 0, 0], radius: 1}}",
      "ports.inputs[0].region=far"], "regions.far.point"),
    (["ports.outputs=[{name: tip_y, region: tip, kind: displacement, direction: [0, 1, 0]}, "
      "{name: g, kind: strain, point: [1e300, 0, 0], direction: [1, 0, 0]}]"],
     "ports.outputs[1].point"),                          # on main: IndexError
    (["connections=[{name: c, region: tip, point: [1e150, 0, 0]}]"], "connections[0].point"),
    (["filter.cutoff_hz=1e-300"], "filter.cutoff_hz"),   # on main: poles underflowed to 0
]


@pytest.mark.parametrize("sets, key", RUN_CASES, ids=[" ".join(s) for s, _ in RUN_CASES])
def test_run_config_values_double_precision_cannot_carry_are_refused(tmp_path, sets, key):
    """Values the field checks accept but the FE or the solver choked on (on main: a
    ZeroDivisionError, a LinAlgError, a singular K, a solver running to its step limit):
    one line naming the key, exit code 2, before meshing (no mesh, no output)."""
    args = ["run", ROOT / "configs/cantilever.yaml", "--set", "mesh.size=0.02"]
    for s in sets:
        args += ["--set", s]
    proc = _cli(*args, "-o", tmp_path / "out.h5", "--mesh-dir", tmp_path / "mesh")
    assert proc.returncode == ConfigError.exit_code, proc.stderr[-2000:]
    lines = [line for line in proc.stderr.strip().splitlines() if "WARNING" not in line]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert f"config key '{key}'" in lines[0] and "expected" in lines[0], lines[0]
    assert [p for p in tmp_path.rglob("*") if not p.is_dir()] == []


def test_extreme_but_valid_materials_follow_the_physical_scaling(tmp_path):
    """Inside the range double precision carries, a run is exact up to scaling: the
    frequencies follow sqrt(E / rho) / L. E and rho scaled together by 1e-135 (E h and
    rho h^3 near the 1e-150 floor) give the reference frequencies; E x 1e-20 gives them
    x 1e-10; rho x 1e-100 gives them x 1e50 (omega^2 ~ 1e110). Tolerance 1e-9: the
    eigensolver's relative residual is 1e-10 and a symmetric problem's eigenvalue error is
    below it (measured: 2e-12 to 1e-11)."""
    def freqs(*sets):
        cfg = load_config(ROOT / "configs/cantilever.yaml",
                          ["mesh.size=0.02", "mesh.order=1", "lumped=null", "filter.kind=none",
                           *sets])
        out = run_pipeline(cfg, tmp_path / f"{len(list(tmp_path.glob('*.h5')))}.h5",
                           mesh_dir=tmp_path).output
        with h5py.File(out) as h5:
            return h5["modes/frequencies_hz"][()]

    E, rho = 69.0e9, 2700.0
    ref = freqs()
    for sets, factor in (((f"material.E={E * 1e-135!r}", f"material.rho={rho * 1e-135!r}"),
                          1.0),
                         ((f"material.E={E * 1e-20!r}",), 1e-10),
                         ((f"material.rho={rho * 1e-100!r}",), 1e50)):
        np.testing.assert_allclose(freqs(*sets), ref * factor, rtol=1e-9, err_msg=str(sets))


def test_modes_count_near_the_free_dofs_runs_dense(tmp_path):
    """500 modes of a mesh with 795 free DOFs (on main: block Lanczos stalled after 32 s,
    residual 0.64) run with a dense eigh; its lowest 10 agree with block Lanczos' 10 to
    1e-9 (Lanczos' relative residual 1e-10 bounds a symmetric eigenvalue's error)."""
    base = ["mesh.size=0.02", "mesh.order=1", "lumped=null", "filter.kind=none"]
    outs = {}
    for count in (10, 500):
        cfg = load_config(ROOT / "configs/cantilever.yaml", base + [f"modes.count={count}"])
        res = run_pipeline(cfg, tmp_path / f"m{count}.h5", mesh_dir=tmp_path)
        with h5py.File(res.output) as h5:
            outs[count] = h5["modes/frequencies_hz"][()]
    assert outs[500].size == 500
    np.testing.assert_allclose(outs[500][:10], outs[10], rtol=1e-9)


# --------------------------------------------------------------------------- integrator
def test_integrator_tolerance_below_double_precision_is_refused(good, tmp_path):
    """rtol 1e-14 (on main: accepted, and Radau ran for minutes): refused by the field
    check, below 1e-13; Radau at rtol 1e-13 on the step load (an estimated 4.6e6
    right-hand-side calls, measured 1.8e6 calls in 140 s at 1e-14) by the step budget,
    which names the tolerance that fits. One line each, nothing written."""
    cases = (("LSODA", "1.0e-14", ConfigError, "rtol': got 1e-14, expected a number in "
              "[1e-13, 0.001]"),
             ("Radau", "1.0e-13", SolverError, "integrator.rtol = 1e-13 alone does this: "
              "use rtol >= "))
    for method, rtol, cls, says in cases:
        sc = tmp_path / "sc.yaml"
        sc.write_text("kind: step_load\nforce: 1\nt_on: 0\nduration: 0.2\noutput_rate: 2000\n"
                      f"integrator: {{method: {method}, rtol: {rtol}, atol: {rtol}}}\n")
        out = tmp_path / "out"
        out.mkdir()
        proc = _cli("simulate", good, sc, "-o", out / "r.h5")
        assert proc.returncode == cls.exit_code, proc.stderr[-2000:]
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr[-2000:]
        assert says in proc.stderr, proc.stderr
        assert list(out.iterdir()) == []
        out.rmdir()
