"""FMI 3.0 export and every model of a file as an FMU (issue 40).

One small run (coarse mesh) holds the plant, the filtered model, the lumped chain, a
connection-point model and the Craig-Bampton body; each is exported once per module as
FMI 3.0 (and the connection model as FMI 2.0, beside the plant and filtered model of
test_fmu.py).

Tolerances, from what is computed:
- Co-Simulation: the C step is the zero-order-hold discretisation (exact for the held
  step input), so at the samples it equals scipy's expm of the same augmented matrix to
  round-off: 1e-9 of the peak of the outputs of the same kind (up to ~200 products of a
  matrix exponential accurate to ~1e-15; outputs near zero, such as cross-couplings of
  1e-13 m, are compared on the scale of their kind, not their own). Measured: 2e-14
  (plant) to 4e-12 (lumped); 1e-10 for the Craig-Bampton body, whose M^-1 K spans its
  near-zero rigid-body eigenvalues to (2 pi 8.5 kHz)^2 (||A h|| ~ 5 at h = 0.1 ms).
- DC gain: 20 exact steps of 0.5 s (10 s, e^(-zeta omega t) < e^-80 for the slowest
  mode: zeta >= 0.02, omega >= 400 rad/s) reach D - C A^-1 B of the stored matrices to
  the round-off of the solve (measured <= 2e-13 of the step response's peak): 1e-9.
- Model Exchange: CVode (BDF) at rtol 1e-10 with absolute tolerances rtol * nominal; its
  global error over ~10 periods of the modes measured 5e-8 (plant), 6e-7 (filtered),
  2e-7 (lumped), 7e-10 (connection) of the peak; we ask 1e-4 (the CVode error grows with
  the number of steps, and the machine's libm and BLAS change the last digits).
- Parameters: the FMU rebuilds A, C from zeta (and the filter from f_c) in C; the
  reference is the same construction in numpy (one or two roundings apart): 1e-9.
"""

from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla

from pipeline.config import load_config
from pipeline.run import run_pipeline
from pipeline.store.read import load_model

fmpy = pytest.importorskip("fmpy", reason="fmpy is in the 'test' and 'fmu' extras")
pytestmark = pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc")

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("plant", "filtered", "lumped", "connection/root", "craig_bampton")
CONFIG = """
name: beam
geometry: {kind: box, length: 0.5, height: 0.02, depth: 0.05}
mesh: {order: 2, size: 0.02}
material: {E: 69.0e9, nu: 0.33, rho: 2700.0}
supports: [{region: root, fix: all}]
modes: {count: 6}
ports:
  inputs:  [{name: tip_force_y, region: tip, kind: force, direction: [0, -1, 0]}]
  outputs: [{name: tip_y, region: tip, kind: displacement, direction: [0, 1, 0]}]
damping: {kind: uniform, ratio: 0.02}
reduction: {modes: 4, static_correction: residual}
filter: {kind: third_order, cutoff_hz: 5000}
lumped: {elements: 4, constants: refined}
connections:
  - {name: root, region: root, point: [0.0, 0.01, 0.025], coupling: rigid}
  - {name: tip, region: tip, point: [0.5, 0.01, 0.025], coupling: distributing}
craig_bampton: {modes: 4}
"""


@pytest.fixture(scope="module")
def result_h5(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("fmi3")
    (tmp / "beam.yaml").write_text(CONFIG)
    return run_pipeline(load_config(tmp / "beam.yaml"), tmp / "beam.h5", mesh_dir=tmp).output


@pytest.fixture(scope="module")
def fmus(result_h5) -> dict[str, Path]:
    from pipeline.cli.export import run_export

    return {m: run_export(result_h5, "fmu", model=m, fmi_version="3") for m in MODELS}


def _model(result_h5, model):
    from pipeline.apps.exports.fmu_models import fmu_model

    return fmu_model(result_h5, model)


def _zoh(ss, t, j=0):
    """Outputs (n_t, n_y) at the samples t (uniform) for a unit step on input j."""
    A, B, C, D = ss
    n, h = A.shape[0], t[1] - t[0]
    M = np.zeros((n + B.shape[1],) * 2)
    M[:n, :n], M[:n, n:] = A * h, B * h
    E = sla.expm(M)
    x, u, ys = np.zeros(n), np.zeros(B.shape[1]), []
    u[j] = 1.0
    for _ in t:
        ys.append(C @ x + D @ u)
        x = E[:n, :n] @ x + E[:n, n:] @ u
    return np.array(ys)


def _scale(units, peaks):
    """Per output: the largest peak among the outputs of its kind (unit, rotations with
    translations: a 0.5 m body turns ~1 rad per m; moments with forces)."""
    kind = np.array([u.replace("rad", "m").replace("N m", "N") for u in units])
    return np.array([peaks[kind == k].max() for k in kind])


def _simulate(path, ss, fmi_type, t, **kw):
    inp = np.array([(0.0, 1.0), (1.0, 1.0)],
                   dtype=[("time", float), (ss.input_names[0], float)])
    res = fmpy.simulate_fmu(str(path), fmi_type=fmi_type, stop_time=t[-1],
                            output_interval=t[1] - t[0], input=inp,
                            output=list(ss.output_names), **kw)
    return np.array([np.interp(t, res["time"], res[n]) for n in ss.output_names]).T


def test_fmi3_fmus_are_valid_with_units_array_state_and_parameters(fmus, result_h5):
    from fmpy.validation import validate_fmu

    for model, path in fmus.items():
        assert validate_fmu(str(path)) == [], model
        md = fmpy.read_model_description(str(path), validate=True)
        assert md.fmiVersion == "3.0" and md.modelExchange and md.coSimulation, model
        v = {x.name: x for x in md.modelVariables}
        m = _model(result_h5, model)
        assert int(v["x"].dimensions[0].start) == m.ss.n_states, model
        assert v["der(x)"].derivative is v["x"]
        assert md.numberOfContinuousStates == m.ss.n_states
        for name, unit in zip(m.ss.input_names, m.input_units):
            assert v[name].causality == "input" and v[name].unit == unit and unit, model
        for name, unit in zip(m.ss.output_names, m.output_units):
            assert v[name].causality == "output" and v[name].unit == unit and unit, model
        assert any(n.startswith("binaries/x86_64-linux/") or n.startswith("binaries/")
                   for n in zipfile.ZipFile(path).namelist())
    v = {x.name: x for x in fmpy.read_model_description(str(fmus["plant"])).modelVariables}
    assert v["tip_force_y"].unit == "N" and v["tip_y/acceleration"].unit == "m/s2"
    assert v["damping_ratio_1"].variability == "tunable"
    assert float(v["damping_ratio_1"].start) == 0.02
    f = {x.name: x for x in fmpy.read_model_description(str(fmus["filtered"])).modelVariables}
    assert f["filter_cutoff"].unit == "Hz" and float(f["filter_cutoff"].start) == 5000.0
    # which models get which parameters
    params = {m: sorted(x.name for x in fmpy.read_model_description(str(p)).modelVariables
                        if x.causality == "parameter") for m, p in fmus.items()}
    assert params["plant"] == [f"damping_ratio_{k}" for k in range(1, 5)]
    assert params["filtered"] == params["plant"] + ["filter_cutoff"]
    assert len(params["lumped"]) == 16 and len(params["connection/root"]) == 6
    assert len(params["craig_bampton"]) == 4
    assert fmus["connection/root"].name == "beam.connection_root.fmu"


def test_fmi3_terminals_group_each_port(fmus):
    """terminalsAndIcons.xml is valid against the FMI 3.0 schema (shipped with fmpy) and
    makes one terminal of each mechanical port: the connection model's root carries its
    accelerations in and its reaction wrench out."""
    import os

    from lxml import etree

    xsd = Path(os.path.dirname(fmpy.__file__)) / "schema" / "fmi3" / "fmi3TerminalsAndIcons.xsd"
    schema = etree.XMLSchema(etree.parse(str(xsd)))
    members = {}
    for model, path in fmus.items():
        names = zipfile.ZipFile(path).namelist()
        if model == "lumped":  # tip_force, tip_position ...: no <port>/ or <port>. names
            assert not any(n.startswith("terminalsAndIcons") for n in names)
            continue
        doc = etree.fromstring(
            zipfile.ZipFile(path).read("terminalsAndIcons/terminalsAndIcons.xml"))
        assert schema.validate(doc), (model, schema.error_log)
        members[model] = {t.get("name"): [v.get("memberName") for v in t]
                          for t in doc.iter("Terminal")}
    assert members["plant"] == {"tip_y": ["position", "velocity", "acceleration"]}
    root = members["connection/root"]["root"]
    assert root == ["ax", "ay", "az", "alpha_x", "alpha_y", "alpha_z",
                    "Fx", "Fy", "Fz", "Tx", "Ty", "Tz"]
    assert set(members["craig_bampton"]) == {"root", "tip"}


@pytest.mark.parametrize("model", MODELS)
def test_co_simulation_is_the_exact_step_response(result_h5, fmus, model):
    m = _model(result_h5, model)
    t = np.linspace(0.0, 0.02, 201)
    ref = _zoh(m.ss, t)
    got = _simulate(fmus[model], m.ss, "CoSimulation", t)
    scale = _scale(m.output_units, np.abs(ref).max(axis=0))
    assert np.all(np.abs(got - ref) <= 1e-9 * scale), model


@pytest.mark.parametrize("model", ["plant", "filtered", "lumped", "connection/root"])
def test_model_exchange_matches_and_dc_gain_is_the_file_s(result_h5, fmus, model):
    stored = load_model(result_h5).model(model)  # the file's own matrices
    m = _model(result_h5, model)
    t = np.linspace(0.0, 0.02, 201)
    ref = _zoh(stored, t)
    got = _simulate(fmus[model], m.ss, "ModelExchange", t, solver="CVode",
                    relative_tolerance=1e-10)
    scale = _scale(m.output_units, np.abs(ref).max(axis=0))
    assert np.all(np.abs(got - ref) <= 1e-4 * scale), model
    # DC gain: long exact steps settle on D - C A^-1 B of the stored model
    t_long = np.arange(21) * 0.5
    end = _simulate(fmus[model], m.ss, "CoSimulation", t_long)[-1]
    dc = stored.dc_gain()[:, 0]
    assert np.all(np.abs(end - dc) <= 1e-9 * scale), model


def test_craig_bampton_fmu_is_the_stored_m_and_k(result_h5, fmus):
    """The Craig-Bampton FMU's ME linearisation gives M^-1 K and M^-1 of the file: a unit
    interface force gives the acceleration M^-1 e_j, a unit coordinate the force M^-1 K."""
    cb = load_model(result_h5).craig_bampton
    m = _model(result_h5, "craig_bampton")
    A, B, _, D = _linearise(fmus["craig_bampton"], m.ss)
    n = cb.M.shape[0]
    Minv = np.linalg.inv(cb.M)
    np.testing.assert_allclose(A[n:, :n], -Minv @ cb.K, rtol=0,
                               atol=1e-12 * np.abs(Minv @ cb.K).max())
    nb = len([c for c in cb.coordinate_names if not c.startswith("mode_")])
    np.testing.assert_allclose(B[n:], Minv[:, :nb], rtol=0, atol=1e-12 * np.abs(Minv).max())
    np.testing.assert_allclose(D[2 * nb:], Minv[:nb, :nb], rtol=0, atol=1e-12 * np.abs(Minv).max())
    # damping_ratio_2 = 0.3: C_d = diag(0, 2 zeta_k omega_k) on the fixed-interface modes
    zeta = np.full(n - nb, 0.02)  # the config's uniform ratio
    zeta[1] = 0.3
    omega = 2 * np.pi * cb.fixed_interface_frequencies_hz
    Cd = np.zeros((n, n))
    Cd[nb:, nb:] = np.diag(2 * zeta * omega)
    A, _, C, _ = _linearise(fmus["craig_bampton"], m.ss, {"damping_ratio_2": 0.3})
    np.testing.assert_allclose(A[n:, n:], -Minv @ Cd, rtol=0, atol=1e-9 * np.abs(Minv @ Cd).max())
    np.testing.assert_allclose(C[2 * nb:], A[n:n + nb], rtol=0, atol=1e-12 * np.abs(A[n:]).max())


def _linearise(path, ss, parameters=None):
    """A, B, C, D read back through the FMI 3.0 ME interface (unit states and inputs),
    with ``parameters`` (name -> value) set in initialization mode."""
    from fmpy import extract, read_model_description
    from fmpy.fmi3 import FMU3Model

    md = read_model_description(str(path))
    vr = {x.name: x.valueReference for x in md.modelVariables}
    fmu = FMU3Model(guid=md.guid, unzipDirectory=extract(str(path)),
                    modelIdentifier=md.modelExchange.modelIdentifier, instanceName="t")
    fmu.instantiate()
    fmu.enterInitializationMode()
    for name, value in (parameters or {}).items():
        fmu.setFloat64([vr[name]], [value])
    fmu.exitInitializationMode()
    fmu.enterContinuousTimeMode()
    nx, nu, ny = ss.n_states, ss.n_inputs, ss.n_outputs
    u_vr, y_vr = list(range(3, 3 + nu)), list(range(3 + nu, 3 + nu + ny))
    cols = []
    for j in range(nx + nu):
        e = np.zeros(nx + nu)
        e[j] = 1.0
        fmu.setFloat64([1], list(e[:nx]))
        fmu.setFloat64(u_vr, list(e[nx:]))
        cols.append((np.array(fmu.getFloat64([2], nx)), np.array(fmu.getFloat64(y_vr))))
    fmu.terminate()
    fmu.freeInstance()
    dx, y = np.array([c[0] for c in cols]).T, np.array([c[1] for c in cols]).T
    return dx[:, :nx], dx[:, nx:], y[:, :nx], y[:, nx:]


def test_parameters_rebuild_the_model(result_h5, fmus):
    """damping_ratio_1 = 0.1 in the connection FMU gives A[v1, v1] = -2 0.1 w1 and
    C[:, v1] = C[:, e1] 2 0.1 / w1 (theory of the connection model); filter_cutoff = 2 kHz
    in the filtered FMU gives the filtered model pipeline.reduce.filters builds at 2 kHz."""
    from pipeline.reduce.filters import filtered_model
    from pipeline.reduce.modal import StateSpaceModel

    lm = load_model(result_h5)
    conn = lm.model("connection/root")
    A, B, C, D = (np.array(x) for x in conn)
    names = list(conn.state_names)
    e, v = names.index("eta_1"), names.index("eta_1_dot")
    w = np.sqrt(-A[v, e])
    A[v, v], C[:, v] = -2 * 0.1 * w, C[:, e] * 2 * 0.1 / w
    ref = conn.with_(A=A, C=C)
    got = _linearise(fmus["connection/root"], conn, {"damping_ratio_1": 0.1})
    for g, r in zip(got, ref):
        np.testing.assert_allclose(g, r, rtol=0, atol=1e-9 * np.abs(r).max())
    p = lm.plant
    plant = StateSpaceModel(*p, input_names=p.input_names, output_names=p.output_names,
                            state_names=p.state_names)
    ref = filtered_model(plant, "third_order", 2000.0)
    t = np.linspace(0.0, 0.005, 101)
    got = _simulate(fmus["filtered"], lm.filtered, "CoSimulation", t,
                    start_values={"filter_cutoff": 2000.0})
    want = _zoh(ref, t)
    assert np.all(np.abs(got - want) <= 1e-9 * np.abs(want).max(axis=0))


def test_fmi2_export_of_every_model_is_valid_and_exact(result_h5, tmp_path):
    from fmpy.validation import validate_fmu

    from pipeline.cli.export import run_export

    for model in ("connection/root",):  # FMI 2.0 of the plant: test_fmu.py; the C core is shared
        path = run_export(result_h5, "fmu", tmp_path / "m.fmu", model=model)
        assert validate_fmu(str(path)) == [], model
        assert fmpy.read_model_description(str(path)).fmiVersion == "2.0"
        m = _model(result_h5, model)
        t = np.linspace(0.0, 0.01, 101)
        ref = _zoh(m.ss, t)
        got = _simulate(path, m.ss, "CoSimulation", t)
        assert np.all(np.abs(got - ref) <= 1e-9 * _scale(m.output_units, np.abs(ref).max(axis=0)))


@pytest.mark.parametrize("args, match, code", [
    (["--fmi-version", "4"], "--fmi-version: got '4', expected 2 or 3", 2),
    (["--model", "no_such"], "--model: got 'no_such'", 2),
    (["--model", "connection/no_such"], "holds no 'connection/no_such' model; it holds", None),
])
def test_bad_input_is_one_line_and_writes_nothing(result_h5, tmp_path, capsys, args, match, code):
    from pipeline.cli import main

    out = tmp_path / "x.fmu"
    rc = main(["export", str(result_h5), "--to", "fmu", "-o", str(out), *args])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and (code is None or rc == code)
    assert match in err and len(err.splitlines()) == 1, err
    assert not out.exists()


def test_a_file_without_the_model_and_no_compiler(tmp_path):
    """The command line (a new process, as a user runs it): one line each, exit != 0."""
    import os
    import subprocess
    import sys

    cfg = load_config(ROOT / "configs" / "cantilever.yaml", ["mesh.size=0.02", "modes.count=6"])
    h5 = run_pipeline(cfg, tmp_path / "c.h5", mesh_dir=tmp_path).output
    out = tmp_path / "x.fmu"

    def export(*args, **env):
        run = subprocess.run([sys.executable, "-m", "pipeline", "export", str(h5), "--to", "fmu",
                              "-o", str(out), *args], capture_output=True, text=True,
                             env={**os.environ, **env})
        return run.returncode, run.stderr.strip()

    rc, err = export("--model", "craig_bampton")
    assert rc != 0 and len(err.splitlines()) == 1 and "holds no 'craig_bampton' model" in err
    rc, err = export("--fmi-version", "3", CC="no-such-cc-here")
    assert rc != 0 and len(err.splitlines()) == 1
    assert "no-such-cc-here" in err and "gcc" in err and "build-essential" in err
    assert not out.exists()


def test_every_model_inspect_lists_exports(result_h5, tmp_path):
    """--model takes each name on inspect's models line (group names included)."""
    from pipeline.apps.summary import summarize
    from pipeline.cli.export import run_export

    line = next(x for x in summarize(result_h5).splitlines() if x.startswith("models"))
    names = [n.strip() for n in line.split(None, 1)[1].split(",")]
    assert names == ["statespace", "statespace_filtered", "lumped", "connection/root",
                     "craig_bampton"]
    aliases = {"statespace": "plant", "statespace_filtered": "filtered"}
    for name in names:  # each resolves to its model (the exports compile in `fmus`)
        assert _model(result_h5, name).model == aliases.get(name, name)
    path = run_export(result_h5, "fmu", tmp_path / "m.fmu", model="statespace_filtered",
                      fmi_version="3")
    md = fmpy.read_model_description(str(path))
    assert md.coSimulation.modelIdentifier == "beam_filtered"


def test_co_simulation_example_of_the_docs(tmp_path, monkeypatch, capsys):
    """The rigid-body co-simulation of docs/exports.md (run as written) follows the
    monolithic model (filtered FMU model + mass + mount, one linear system, expm): the
    explicit coupling and the semi-implicit Euler of the mass are first order, the error
    about h omega = 20 us x 126 rad/s = 2.5e-3 of the peak (measured 3e-4 and 6e-4); we
    ask 5e-3."""
    import re

    from pipeline.cli.export import run_export

    text = (ROOT / "docs" / "exports.md").read_text()
    code = next(c for c in re.findall(r"^```python\n(.*?)^```", text, re.S | re.M)
                if "FMU3Slave" in c)
    cfg = load_config(ROOT / "configs" / "cantilever.yaml", ["mesh.size=0.02", "modes.count=6"])
    h5 = run_pipeline(cfg, tmp_path / "cantilever.h5", mesh_dir=tmp_path).output
    run_export(h5, "fmu", tmp_path / "cantilever.filtered.fmi3.fmu", model="filtered",
               fmi_version="3")
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(code, "docs/exports.md co-simulation", "exec"), ns)
    assert "steps of 20 us" in capsys.readouterr().out
    tip = np.array(ns["tip"])
    m, g, k, c, h = (ns[key] for key in ("m", "g", "k", "c", "h"))
    f = load_model(h5).filtered
    A, B = f.A, f.B[:, 0]
    cp = f.C[list(f.output_names).index("tip_y/position")]
    cv = f.C[list(f.output_names).index("tip_y/velocity")]
    n = A.shape[0]
    M = np.zeros((n + 3, n + 3))  # [x; z; z'; 1]: the mount force k (z - y) + c (z' - y')
    M[:n, :n] = A + np.outer(B, k * cp + c * cv)
    M[:n, n], M[:n, n + 1] = -k * B, -c * B
    M[n, n + 1] = 1.0
    M[n + 1, :n] = (k * cp + c * cv) / m
    M[n + 1, n:] = -k / m, -c / m, -g
    E = sla.expm(M * h)
    X = np.zeros(n + 3)
    X[-1] = 1.0
    ref = []
    for _ in range(len(tip)):
        X = E @ X
        ref.append((cp @ X[:n], X[n]))
    ref = np.array(ref)
    for col, name in ((0, "tip"), (1, "mass")):
        err = np.abs(tip[:, col + 1] - ref[:, col]).max()
        assert err <= 5e-3 * np.abs(ref[:, col]).max(), name


def test_first_order_filter_follows_cutoff_and_damping(tmp_path):
    """A first-order filter takes every plant output, the acceleration too, so its rows of
    A follow the damping (C_acc = C_vel A): the FMU with filter_cutoff = 1.5 kHz and
    damping_ratio_1 = 0.2 is pipeline.reduce.filters' model of the plant so changed."""
    from pipeline.cli.export import run_export
    from pipeline.reduce.filters import filtered_model
    from pipeline.reduce.modal import StateSpaceModel

    (tmp_path / "b.yaml").write_text(CONFIG.replace("third_order", "first_order"))
    h5 = run_pipeline(load_config(tmp_path / "b.yaml"), tmp_path / "b.h5",
                      mesh_dir=tmp_path).output
    path = run_export(h5, "fmu", tmp_path / "b.fmu", model="filtered", fmi_version="3")
    lm = load_model(h5)
    A, B, C, D = (np.array(x) for x in lm.plant)
    names = list(lm.plant.state_names)
    i, v = names.index("eta_1"), names.index("eta_dot_1")
    A[v, v] = -2 * 0.2 * np.sqrt(-A[v, i])
    C[2], D[2] = C[1] @ A, C[1] @ B
    plant = StateSpaceModel(A, B, C, D, input_names=lm.plant.input_names,
                            output_names=lm.plant.output_names,
                            state_names=lm.plant.state_names)
    t = np.linspace(0.0, 0.005, 101)
    want = _zoh(filtered_model(plant, "first_order", 1500.0), t)
    got = _simulate(path, lm.filtered, "CoSimulation", t,
                    start_values={"filter_cutoff": 1500.0, "damping_ratio_1": 0.2})
    assert np.all(np.abs(got - want) <= 1e-9 * np.abs(want).max(axis=0))

