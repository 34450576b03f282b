"""FMU export (issue 20): fmpy validates it, simulates it (Model Exchange with CVode,
Co-Simulation with its own stepping), and the responses equal python-control's on
``load_model(...).ss``; a C program with no Python loads the binary and steps it (the
FMI 2.0 and the FMI 3.0 binary; the rest of FMI 3.0 is tests/test_fmi3.py).

Tolerances, from what is computed:
- Co-Simulation: fmi2DoStep is the zero-order-hold discretisation (exact for the held
  step input), so at the sample instants it equals python-control's ``step_response``
  (scipy's expm of the same augmented matrix) to round-off. Both are a product of up to
  ~500 steps of a matrix whose exponential is computed to ~1e-15 relative (Pade (6,6)
  after scaling); 1e-9 of the peak leaves a 1e4 margin on n_steps * eps * ||Phi|| growth.
- Model Exchange: CVode's local error control at rtol = 1e-10 (absolute tolerances
  rtol * nominal); its global error grows with the number of steps over ~10 periods of the
  highest mode, so we ask 1e-5 of the peak (1e5 rtol).
- Linearisation: fmi2GetDerivatives / outputs at unit states are single dot products of
  the stored matrices, so they equal A, B, C, D to a few ulps (1e-12 relative).
"""

from __future__ import annotations

import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.errors import ResourceError
from pipeline.run import run_pipeline
from pipeline.store.read import load_model

fmpy = pytest.importorskip("fmpy", reason="fmpy is in the 'test' and 'fmu' extras")
pytestmark = pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc")

ROOT = Path(__file__).resolve().parents[1]
OUTPUTS = ["tip_y/position", "tip_y/velocity", "tip_y/acceleration"]


@pytest.fixture(scope="module")
def result_h5(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("fmu")
    cfg = load_config(ROOT / "configs" / "cantilever.yaml", ["mesh.size=0.02", "modes.count=6"])
    return run_pipeline(cfg, tmp / "cantilever.h5", mesh_dir=tmp).output


@pytest.fixture(scope="module")
def fmus(result_h5) -> dict[str, Path]:
    from pipeline.cli.export import run_export

    return {m: run_export(result_h5, "fmu", model=m) for m in ("plant", "filtered")}


def _system(result_h5, model):
    lm = load_model(result_h5)
    return lm.ss if model == "plant" else lm.ss_filtered


def _step(path, fmi_type, t, **kw):
    inp = np.array([(0.0, 1.0), (1.0, 1.0)], dtype=[("time", float), ("tip_force_y", float)])
    return fmpy.simulate_fmu(str(path), fmi_type=fmi_type, stop_time=t[-1],
                             output_interval=t[1] - t[0], input=inp, output=OUTPUTS, **kw)


def test_fmu_is_valid_holds_sources_and_named_variables(fmus):
    from fmpy.validation import validate_fmu

    for model, path in fmus.items():
        assert validate_fmu(str(path)) == [], model
        md = fmpy.read_model_description(str(path), validate=True)
        assert md.modelExchange is not None and md.coSimulation is not None
        vars_ = {v.name: v for v in md.modelVariables}
        assert vars_["tip_force_y"].causality == "input" and vars_["tip_force_y"].unit == "N"
        assert [vars_[o].unit for o in OUTPUTS] == ["m", "m/s", "m/s2"]
        assert "eta_1" in vars_ and "der(eta_1)" in vars_
        assert vars_["damping_ratio_1"].causality == "parameter"
        assert float(vars_["damping_ratio_1"].start) == 0.02
        names = zipfile.ZipFile(path).namelist()
        assert {"sources/fmu.c", "sources/model_data.h",
                "sources/buildDescription.xml"} <= set(names)
        assert any(n.startswith("binaries/") for n in names)
    assert fmus["plant"].name == "cantilever.plant.fmu"


@pytest.mark.parametrize("model", ["plant", "filtered"])
def test_co_simulation_step_response_is_exact_at_the_samples(result_h5, fmus, model):
    import control

    t = np.linspace(0.0, 0.05, 501)
    ref = np.squeeze(control.step_response(_system(result_h5, model), T=t).outputs)
    res = _step(fmus[model], "CoSimulation", t)
    np.testing.assert_allclose(res["time"], t, rtol=0, atol=1e-12)
    for i, name in enumerate(OUTPUTS):
        peak = np.max(np.abs(ref[i]))
        assert np.max(np.abs(res[name] - ref[i])) <= 1e-9 * peak, name


@pytest.mark.parametrize("model", ["plant", "filtered"])
def test_model_exchange_with_cvode_matches_python_control(result_h5, fmus, model):
    import control

    t = np.linspace(0.0, 0.05, 501)
    ref = np.squeeze(control.step_response(_system(result_h5, model), T=t).outputs)
    res = _step(fmus[model], "ModelExchange", t, solver="CVode", relative_tolerance=1e-10)
    for i, name in enumerate(OUTPUTS):
        y = np.interp(t, res["time"], res[name])
        assert np.max(np.abs(y - ref[i])) <= 1e-5 * np.max(np.abs(ref[i])), name


def _instance(path, fmi_type):
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Model, FMU2Slave

    md = read_model_description(str(path))
    unzipped = extract(str(path))
    cls, ident = ((FMU2Model, md.modelExchange.modelIdentifier) if fmi_type == "ME"
                  else (FMU2Slave, md.coSimulation.modelIdentifier))
    fmu = cls(guid=md.guid, unzipDirectory=unzipped, modelIdentifier=ident, instanceName="t")
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    return md, fmu


def _linearise(path, nx, nu, ny):
    """A, B, C, D read back through the FMU's ME interface (unit states and inputs)."""
    md, fmu = _instance(path, "ME")
    fmu.enterContinuousTimeMode()
    A, B, C, D = np.zeros((nx, nx)), np.zeros((nx, nu)), np.zeros((ny, nx)), np.zeros((ny, nu))
    u_vr = list(range(2 * nx, 2 * nx + nu))
    y_vr = list(range(2 * nx + nu, 2 * nx + nu + ny))
    for j in range(nx + nu):
        x = np.zeros(nx)
        u = np.zeros(nu)
        (x if j < nx else u)[j if j < nx else j - nx] = 1.0
        fmu.setContinuousStates(x.ctypes.data_as(fmpy.fmi2.POINTER(fmpy.fmi2.fmi2Real)), nx)
        fmu.setReal(u_vr, list(u))
        dx = np.zeros(nx)
        fmu.getDerivatives(dx.ctypes.data_as(fmpy.fmi2.POINTER(fmpy.fmi2.fmi2Real)), nx)
        y = np.array(fmu.getReal(y_vr))
        if j < nx:
            A[:, j], C[:, j] = dx, y
        else:
            B[:, j - nx], D[:, j - nx] = dx, y
    fmu.terminate()
    fmu.freeInstance()
    return A, B, C, D


@pytest.mark.parametrize("model", ["plant", "filtered"])
def test_fmu_frequency_response_equals_python_control(result_h5, fmus, model):
    """The FMU's own linearisation (ME) and its one-step map (CS) give python-control's
    continuous and zero-order-hold frequency responses."""
    import control

    sys_c = _system(result_h5, model)
    nx, nu, ny = sys_c.nstates, sys_c.ninputs, sys_c.noutputs
    A, B, C, D = _linearise(fmus[model], nx, nu, ny)
    fmu_sys = control.ss(A, B, C, D)
    w = 2 * np.pi * np.logspace(0, 4, 60)
    ref = control.frequency_response(sys_c, w)
    got = control.frequency_response(fmu_sys, w)
    np.testing.assert_allclose(got.complex, ref.complex, rtol=1e-12,
                               atol=1e-12 * np.abs(ref.complex).max())
    # CS: Phi, Gamma from one doStep of each unit state / input
    h = 2e-4
    Phi, Gam = np.zeros((nx, nx)), np.zeros((nx, nu))
    md, fmu = _instance(fmus[model], "CS")
    x_vr, u_vr = list(range(nx)), list(range(2 * nx, 2 * nx + nu))
    for j in range(nx + nu):
        fmu.setReal(x_vr, [1.0 if i == j else 0.0 for i in range(nx)])
        fmu.setReal(u_vr, [1.0 if j - nx == i else 0.0 for i in range(nu)])
        fmu.doStep(0.0, h)
        col = np.array(fmu.getReal(x_vr))
        (Phi[:, j] if j < nx else Gam[:, j - nx])[:] = col
    fmu.terminate()
    fmu.freeInstance()
    ref_d = control.sample_system(sys_c, h, method="zoh")
    np.testing.assert_allclose(Phi, ref_d.A, rtol=0, atol=1e-11 * np.abs(ref_d.A).max())
    np.testing.assert_allclose(Gam, ref_d.B, rtol=0, atol=1e-11 * np.abs(ref_d.B).max())
    wd = w[w < np.pi / h]
    got_d = control.frequency_response(control.ss(Phi, Gam, C, D, h), wd).complex
    ref_dr = control.frequency_response(ref_d, wd).complex
    np.testing.assert_allclose(got_d, ref_dr, rtol=0, atol=1e-8 * np.abs(ref_dr).max())


def test_damping_parameter_changes_the_model(result_h5, fmus):
    """damping_ratio_1 = 0.1 in the FMU gives the model with A[v1, v1] = -2 0.1 w1 and
    the acceleration row C_acc = C_vel A (the same construction as the reduction)."""
    import control

    lm = load_model(result_h5)
    A, B, C, D = (np.array(m) for m in (lm.plant.A, lm.plant.B, lm.plant.C, lm.plant.D))
    names = list(lm.plant.state_names)
    i, v = names.index("eta_1"), names.index("eta_dot_1")
    A[v, v] = -2 * 0.1 * np.sqrt(-A[v, i])
    C[2], D[2] = C[1] @ A, C[1] @ B
    t = np.linspace(0.0, 0.05, 501)
    ref = np.squeeze(control.step_response(control.ss(A, B, C, D), T=t).outputs)
    inp = np.array([(0.0, 1.0), (1.0, 1.0)], dtype=[("time", float), ("tip_force_y", float)])
    res = fmpy.simulate_fmu(str(fmus["plant"]), fmi_type="CoSimulation", stop_time=t[-1],
                            output_interval=t[1] - t[0], input=inp, output=OUTPUTS,
                            start_values={"damping_ratio_1": 0.1})
    for k, name in enumerate(OUTPUTS):
        assert np.max(np.abs(res[name] - ref[k])) <= 1e-9 * np.max(np.abs(ref[k])), name


DRIVER = r"""
#include <dlfcn.h>
#include <stdio.h>
#include <stdarg.h>
#include "fmi2Functions.h"
static void logger(fmi2ComponentEnvironment e, fmi2String n, fmi2Status s, fmi2String c,
                   fmi2String m, ...) { (void)e; (void)n; (void)s; (void)c; puts(m); }
int main(int argc, char **argv) {
    void *lib = dlopen(argv[1], RTLD_NOW);
    if (!lib) { fprintf(stderr, "%s\n", dlerror()); return 2; }
    fmi2InstantiateTYPE *inst = (fmi2InstantiateTYPE *)dlsym(lib, "fmi2Instantiate");
    fmi2SetupExperimentTYPE *setup = (fmi2SetupExperimentTYPE *)dlsym(lib, "fmi2SetupExperiment");
    fmi2EnterInitializationModeTYPE *enter = (fmi2EnterInitializationModeTYPE *)dlsym(lib, "fmi2EnterInitializationMode");
    fmi2ExitInitializationModeTYPE *leave = (fmi2ExitInitializationModeTYPE *)dlsym(lib, "fmi2ExitInitializationMode");
    fmi2SetRealTYPE *set = (fmi2SetRealTYPE *)dlsym(lib, "fmi2SetReal");
    fmi2GetRealTYPE *get = (fmi2GetRealTYPE *)dlsym(lib, "fmi2GetReal");
    fmi2DoStepTYPE *step = (fmi2DoStepTYPE *)dlsym(lib, "fmi2DoStep");
    fmi2CallbackFunctions cb = {logger, 0, 0, 0, 0};
    fmi2Component c = inst("driver", fmi2CoSimulation, argv[2], "", &cb, fmi2False, fmi2False);
    fmi2ValueReference u = (fmi2ValueReference)atoi(argv[3]), y = u + 1;
    double one = 1.0, out, t = 0.0, h = 1e-4;
    int k;
    if (!c) return 3;
    setup(c, fmi2False, 0.0, 0.0, fmi2False, 0.0); enter(c); leave(c);
    set(c, &u, 1, &one);
    for (k = 0; k < 500; k++) {
        if (step(c, t, h, fmi2True) != fmi2OK) return 4;
        t += h;
        get(c, &y, 1, &out);
        printf("%.17g\n", out);
    }
    return 0;
}
"""


def _driver_output(path, source: str, version: str, tmp_path) -> np.ndarray:
    """The tip positions a C program (no Python in the process) prints: it dlopens the
    binary of the FMU ``path``, steps it with a unit step input and reads the output
    after the input's value reference."""
    from pipeline.apps.exports.fmu import fmi_headers

    md = fmpy.read_model_description(str(path))
    folder = tmp_path / "unzipped"
    zipfile.ZipFile(path).extractall(folder)
    lib = next((folder / "binaries").glob("*/*"))
    symbols = subprocess.run(["nm", "-D", "--defined-only", str(lib)], capture_output=True,
                             text=True, check=True).stdout
    for name in ("Instantiate" if version == "2" else "InstantiateCoSimulation", "DoStep",
                 "GetDerivatives" if version == "2" else "GetContinuousStateDerivatives"):
        assert f" fmi{version}{name}\n" in symbols
    (tmp_path / "driver.c").write_text(source)
    subprocess.run(["gcc", "-std=c99", f"-I{fmi_headers(version)}", "-o",
                    str(tmp_path / "driver"), str(tmp_path / "driver.c"), "-ldl"], check=True)
    u_vr = next(v.valueReference for v in md.modelVariables if v.causality == "input")
    run = subprocess.run([str(tmp_path / "driver"), str(lib), md.guid, str(u_vr)],
                         capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stdout + run.stderr
    return np.array([float(v) for v in run.stdout.split()])


def test_fmu_binary_runs_from_c_without_python(result_h5, fmus, tmp_path):
    """A C program (no Python in the process) dlopens the FMU binary, steps it 500 times
    with a unit step input and prints the tip position, which equals python-control's."""
    import control

    y = _driver_output(fmus["plant"], DRIVER.replace(
        "#include <stdarg.h>", "#include <stdarg.h>\n#include <stdlib.h>"), "2", tmp_path)
    t = np.arange(1, 501) * 1e-4
    ref = np.squeeze(control.step_response(load_model(result_h5).ss, T=np.r_[0, t]).outputs)[0, 1:]
    assert np.max(np.abs(y - ref)) <= 1e-9 * np.max(np.abs(ref))


DRIVER3 = r"""
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include "fmi3Functions.h"
static void logger(fmi3InstanceEnvironment e, fmi3Status s, fmi3String c, fmi3String m) {
    (void)e; (void)s; (void)c; puts(m);
}
int main(int argc, char **argv) {
    void *lib = dlopen(argv[1], RTLD_NOW);
    if (!lib) { fprintf(stderr, "%s\n", dlerror()); return 2; }
    fmi3InstantiateCoSimulationTYPE *inst =
        (fmi3InstantiateCoSimulationTYPE *)dlsym(lib, "fmi3InstantiateCoSimulation");
    fmi3EnterInitializationModeTYPE *enter =
        (fmi3EnterInitializationModeTYPE *)dlsym(lib, "fmi3EnterInitializationMode");
    fmi3ExitInitializationModeTYPE *leave =
        (fmi3ExitInitializationModeTYPE *)dlsym(lib, "fmi3ExitInitializationMode");
    fmi3SetFloat64TYPE *set = (fmi3SetFloat64TYPE *)dlsym(lib, "fmi3SetFloat64");
    fmi3GetFloat64TYPE *get = (fmi3GetFloat64TYPE *)dlsym(lib, "fmi3GetFloat64");
    fmi3DoStepTYPE *step = (fmi3DoStepTYPE *)dlsym(lib, "fmi3DoStep");
    fmi3Instance c = inst("driver", argv[2], "", fmi3False, fmi3False, fmi3False, fmi3False,
                          NULL, 0, NULL, logger, NULL);
    fmi3ValueReference u = (fmi3ValueReference)atoi(argv[3]), y = u + 1;
    double one = 1.0, out, t = 0.0, h = 1e-4, last;
    fmi3Boolean event, terminate, early;
    int k;
    if (!c) return 3;
    enter(c, fmi3False, 0.0, 0.0, fmi3False, 0.0);
    leave(c);
    set(c, &u, 1, &one, 1);
    for (k = 0; k < 500; k++) {
        if (step(c, t, h, fmi3True, &event, &terminate, &early, &last) != fmi3OK) return 4;
        t += h;
        get(c, &y, 1, &out, 1);
        printf("%.17g\n", out);
    }
    return 0;
}
"""


def test_fmi3_binary_runs_from_c_without_python(result_h5, tmp_path):
    """The same with the FMI 3.0 binary (fmi3InstantiateCoSimulation, fmi3DoStep, 500
    steps): the exact step response."""
    import control

    from pipeline.cli.export import run_export

    path = run_export(result_h5, "fmu", tmp_path / "p3.fmu", fmi_version="3")
    y = _driver_output(path, DRIVER3, "3", tmp_path)
    t = np.arange(1, 501) * 1e-4
    ref = np.squeeze(control.step_response(load_model(result_h5).ss, T=np.r_[0, t]).outputs)[0, 1:]
    assert np.max(np.abs(y - ref)) <= 1e-9 * np.max(np.abs(ref))


def test_missing_compiler_is_one_line_naming_it(result_h5, tmp_path, monkeypatch):
    from pipeline.apps.exports.fmu import export_fmu

    monkeypatch.setenv("CC", "no-such-cc-here")
    with pytest.raises(ResourceError, match="C compiler.*no-such-cc-here.*install gcc"):
        export_fmu(result_h5, tmp_path / "x.fmu")
    assert not (tmp_path / "x.fmu").exists()


def test_model_option_is_checked(result_h5, tmp_path):
    from pipeline.cli.export import run_export
    from pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="--model"):
        run_export(result_h5, "fmu", tmp_path / "x.fmu", model="no_such_model")
    assert not (tmp_path / "x.fmu").exists()
    with pytest.raises(ConfigError, match="--model: does not apply to --to mat"):
        run_export(result_h5, "mat", tmp_path / "x.mat", model="plant")
