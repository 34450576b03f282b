"""The ``spin_up`` scenario (issue 37 item 4): a slender beam on a hub spun up through the
Kane-Ryan-Banerjee ramp, stepped as the modal model with and without geometric stiffening.

The body: a 0.5 m x 20 mm x 50 mm aluminium beam clamped at its root, spun about z through
the root's centre (in-plane bending along y, first frequency ~65.8 Hz = 413.5 rad/s), to
600 rad/s (1.45 x the first in-plane frequency) in 0.15 s: the classical setting in which
the linear floating-frame model (spin softening, no stiffening) runs away once the hub
passes the first frequency, and the stiffened one stays bounded.

References and tolerances:
- the hub profile: Omega(T) = Omega_s, alpha = Omega' and theta' = Omega by central
  differences (step 1e-6 s: truncation ~ (2 pi / T)^2 h^2 / 6 relative, below 1e-8);
- the runaway of the linear model begins where K_r - Omega^2 S_a loses definiteness: it
  must come after that instant (the deflection then grows like exp(sqrt(Omega^2 - w1^2) t),
  from ~25 mm to the body's 0.5 m within a few 1/sqrt(Omega^2 - w1^2) ~ 3 ms);
- Exudyn's geometrically nonlinear ANCF beam (ObjectANCFCable2D, 10 elements, root
  position and slope prescribed to follow the hub angle) against the stiffened modal
  model: the same in-plane bending stiffness (EI set so that the cantilever's first
  frequency equals the FE model's 65.8 Hz, removing the 3D-versus-beam-theory difference
  of ~1.4 % in w^2), mass per length and axial stiffness. What is left: the 3D body's
  shear and section effects on the deflection shape ((h/L)^2 ~ 0.2 %), the modal
  truncation (6 modes), the ANCF discretisation and the implicit time step (h = 1e-4 s,
  spectral radius 0.9), and the neglected second-order terms (deflection/L ~ 5 %, squared
  0.25 %). Measured 0.3 % at the peak; bound: 2 % of the peak deflection, for the peak and
  for the largest difference over the whole history.
"""

from __future__ import annotations

import math
import subprocess
import sys

import h5py
import numpy as np
import pytest

from conftest import record_tolerance
from pipeline.apps.simulate.spinup import hub_profile
from pipeline.errors import ConfigError, FileFormatError

L, H, B = 0.5, 0.02, 0.05
E, RHO = 69.0e9, 2700.0
SPEED, RAMP, DURATION = 600.0, 0.15, 0.3

CONFIG = f"""\
name: spin
geometry: {{kind: box, length: {L}, height: {H}, depth: {B}}}
mesh: {{order: 2, size: 0.025}}
material: {{E: {E}, nu: 0.33, rho: {RHO}}}
supports: [{{region: root, fix: all}}]
modes: {{count: 6}}
ports:
  inputs:  [{{name: pull, region: tip, kind: force, direction: [1, 0, 0]}}]
  outputs: [{{name: tip_y, region: tip, kind: displacement, direction: [0, 1, 0]}}]
reduction: {{modes: 6, static_correction: residual}}
rotation: {{axis: [0, 0, 1], point: [0, {H / 2}, {B / 2}], speeds_rad_s: [0, 300, 600],
           correction_shapes: 1}}
"""

SCENARIO = f"""\
- {{name: krb, kind: spin_up, final_speed: {SPEED}, ramp_time: {RAMP}, duration: {DURATION},
   output_rate: 5000, damping: false, output: tip_y}}
"""


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def spun(tmp_path_factory):
    """(model file, result file) of the spin-up through the command line."""
    tmp = tmp_path_factory.mktemp("spinup")
    (tmp / "spin.yaml").write_text(CONFIG)
    proc = _cli("run", "spin.yaml", "-o", "spin.h5", cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    (tmp / "krb.yaml").write_text(SCENARIO)
    proc = _cli("simulate", "spin.h5", "krb.yaml", "-o", "res.h5", cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    return tmp / "spin.h5", tmp / "res.h5"


def _signal(result, key: str, name: str) -> tuple[np.ndarray, np.ndarray]:
    with h5py.File(result, "r") as h5:
        return h5[f"krb/{key}/time"][()], h5[f"krb/{key}/signals/{name}"][()]


def test_hub_profile_is_the_krb_ramp():
    t = np.linspace(0.0, 2 * RAMP, 301)
    speed, alpha, angle = hub_profile(t, SPEED, RAMP)
    assert speed[0] == alpha[0] == angle[0] == 0.0
    assert speed[t >= RAMP] == pytest.approx(SPEED) and np.all(alpha[t >= RAMP] == 0.0)
    h = 1e-6
    tm = t[1:-1]
    sp, ap, thp = hub_profile(tm + h, SPEED, RAMP)
    sm, am, thm = hub_profile(tm - h, SPEED, RAMP)
    s0, a0, _ = hub_profile(tm, SPEED, RAMP)
    np.testing.assert_allclose((sp - sm) / (2 * h), a0, atol=1e-6 * SPEED / RAMP)
    np.testing.assert_allclose((thp - thm) / (2 * h), s0, atol=1e-6 * SPEED)
    assert hub_profile(RAMP, SPEED, RAMP)[2] == pytest.approx(SPEED * RAMP / 2)


def test_stiffened_stays_bounded_and_linear_runs_away(spun):
    model, result = spun
    t, y = _signal(result, "stiffened", "tip_y/position")
    assert t[-1] == pytest.approx(DURATION)
    assert np.abs(y).max() < 0.1 * L  # bounded: ~25 mm during the ramp
    after = t > RAMP
    assert np.abs(y[after]).max() < 0.05 * np.abs(y).max()  # a small free oscillation
    tl, yl = _signal(result, "linear", "tip_y/position")
    assert tl[-1] < DURATION and abs(yl[-1]) > 0.9 * L  # stopped: ran away
    with h5py.File(result, "r") as h5:
        attrs = dict(h5["krb/linear"].attrs)
        onset_s = attrs["predicted_instability_onset_s"]
        onset = attrs["predicted_instability_speed_rad_s"]
    from pipeline.store.read import read_rotation

    w1 = math.sqrt(read_rotation(model).stiffness[0, 0])
    assert onset == pytest.approx(w1, rel=0.02)  # S_a of the first in-plane mode is ~1
    assert onset_s < attrs["measured_runaway_s"] < onset_s + 0.02
    # early in the ramp both agree (the stiffening term is second order in Omega)
    early = t < 0.02
    np.testing.assert_allclose(yl[:early.sum()], y[early], atol=0.01 * np.abs(y).max())
    for ext in ("krb.csv", "krb.png"):
        assert (result.parent / f"res.{ext}").stat().st_size > 0


def test_inertia_terms_are_stored(spun):
    from pipeline.store.read import read_rotation

    rot = read_rotation(spun[0])
    n_b = rot.stiffness.shape[0]
    assert n_b == 7 and rot.centrifugal_load.shape == (6, n_b)  # 6 modes + 1 correction
    # spun about z through the root centre, the beam's centrifugal load (zz entry) is an
    # axial stretch, orthogonal to the bending modes at rest (their sections are
    # symmetric, up to the unstructured mesh's asymmetry: measured 6e-7); the xy entry
    # loads the in-plane bending (first) mode
    f = rot.centrifugal_load
    assert abs(f[2, 0]) < 1e-5 * abs(f[3, 0])
    C = rot.coriolis
    assert np.abs(C + C.transpose(0, 2, 1)).max() < 1e-12 * np.abs(C).max()  # skew
    # the Euler load of the first (in-plane) mode: int rho phi_y x dV, with the beam mode
    # normalised to unit modal mass ~ sqrt(m) * 0.5680 * L ... its sign and size
    m = RHO * L * H * B
    assert 0.5 * math.sqrt(m) * L < abs(rot.euler_load[2, 0]) < math.sqrt(m) * L


# slow (13 s, mostly Exudyn's Python user functions); the full-FE prestressed checks of the
# same spin-up run by default
@pytest.mark.slow
def test_stiffened_model_matches_exudyn_ancf(spun):
    """The independent, geometrically nonlinear solver (see the module docstring)."""
    exu = pytest.importorskip("exudyn")
    from exudyn.itemInterface import (CoordinateConstraint, MarkerNodeCoordinate,
                                      NodePoint2DSlope1, NodePointGround, ObjectANCFCable2D,
                                      SensorNode)
    from pipeline.store.read import read_rotation

    w1 = math.sqrt(read_rotation(spun[0]).stiffness[0, 0])
    rho_a = RHO * H * B
    EI = w1 ** 2 * rho_a * L ** 4 / 1.8751040687119611 ** 4
    n_el = 10
    sc = exu.SystemContainer()
    mbs = sc.AddSystem()
    nodes = [mbs.AddNode(NodePoint2DSlope1(referenceCoordinates=[L * i / n_el, 0, 1, 0]))
             for i in range(n_el + 1)]
    for a, b in zip(nodes, nodes[1:]):
        mbs.AddObject(ObjectANCFCable2D(nodeNumbers=[a, b], length=L / n_el,
                                        massPerLength=rho_a, bendingStiffness=EI,
                                        axialStiffness=E * H * B))
    ground = mbs.AddMarker(MarkerNodeCoordinate(nodeNumber=mbs.AddNode(NodePointGround()),
                                                coordinate=0))

    def angle(t):
        return float(hub_profile(t, SPEED, RAMP)[2])

    # the root follows the hub: position fixed, slope (cos theta, sin theta)
    offsets = [0, 0, lambda mbs, t, item, off: math.cos(angle(t)) - 1.0,
               lambda mbs, t, item, off: math.sin(angle(t))]
    for k, offset in enumerate(offsets):
        marker = mbs.AddMarker(MarkerNodeCoordinate(nodeNumber=nodes[0], coordinate=k))
        mbs.AddObject(CoordinateConstraint(markerNumbers=[ground, marker],
                                           offsetUserFunction=offset))
    sensor = mbs.AddSensor(SensorNode(nodeNumber=nodes[-1], storeInternal=True,
                                      outputVariableType=exu.OutputVariableType.Position))
    mbs.Assemble()
    settings = exu.SimulationSettings()
    settings.timeIntegration.numberOfSteps = int(round(DURATION / 1e-4))
    settings.timeIntegration.endTime = DURATION
    settings.timeIntegration.generalizedAlpha.spectralRadius = 0.9
    settings.timeIntegration.verboseMode = 0
    settings.solution.file.write = False
    settings.solution.sensors.writePeriod = 1e-3
    exu.SolveDynamic(mbs, settings)
    data = mbs.GetSensorStoredData(sensor)
    theta = hub_profile(data[:, 0], SPEED, RAMP)[2]
    v_exudyn = -np.sin(theta) * data[:, 1] + np.cos(theta) * data[:, 2]  # hub frame
    t, y = _signal(spun[1], "stiffened", "tip_y/position")
    ours = np.interp(data[:, 0], t, y)
    peak = np.abs(v_exudyn).max()
    peak_error = abs(np.abs(ours).max() / peak - 1.0)
    history_error = np.abs(ours - v_exudyn).max() / peak
    record_tolerance("spin_up: peak deflection vs Exudyn ANCF", peak_error, 0.02)
    record_tolerance("spin_up: history vs Exudyn ANCF (of the peak)", history_error, 0.02)
    assert peak_error < 0.02 and history_error < 0.02


@pytest.mark.parametrize("raw, key", [
    ({"final_speed": 0.0}, "scenario.final_speed"),
    ({"final_speed": 2e6}, "scenario.final_speed"),
    ({"ramp_time": -1.0}, "scenario.ramp_time"),
    ({"ramp_time": "slow"}, "scenario.ramp_time"),
    ({"mass": 1.0}, "scenario"),
])
def test_bad_spin_up_keys_are_one_line(raw, key):
    from pipeline.apps.simulate import parse_scenarios

    scenario = {"kind": "spin_up", "final_speed": 100.0, "ramp_time": 1.0, "duration": 2.0,
                **raw}
    with pytest.raises(ConfigError) as info:
        parse_scenarios(scenario)
    assert info.value.key.startswith(key) and "\n" not in str(info.value)


def _refusal(tmp_path, config: str, error) -> str:
    """Build ``config``, run SCENARIO on it: the last stderr line of the refusal, after
    checking its exit code and that nothing was written."""
    (tmp_path / "body.yaml").write_text(config)
    assert _cli("run", "body.yaml", "-o", "body.h5", cwd=tmp_path).returncode == 0
    (tmp_path / "krb.yaml").write_text(SCENARIO)
    proc = _cli("simulate", "body.h5", "krb.yaml", "-o", "res.h5", cwd=tmp_path)
    assert proc.returncode == error.exit_code
    assert not (tmp_path / "res.h5").exists()
    return proc.stderr.strip().splitlines()[-1]


def test_file_without_rotation_is_refused_in_one_line(tmp_path):
    line = _refusal(tmp_path, CONFIG.split("rotation:")[0], FileFormatError)
    assert "/rotation" in line and "krb" in line


def test_planar_chain_spinning_pendulum():
    """One rigid link on a spring, pivoted at radius R from the axis, its centre c beyond
    the pivot, spinning at a constant Omega: J phi'' + (k + m Omega^2 R c) phi = 0 for
    small phi (the centrifugal force's moment about the pivot, Mitiguy-Banerjee's
    stiffening of a rigid chain), J = I_c + m c^2. Round-off only (phi = 1e-7)."""
    from pipeline.apps.simulate.spinchain import PlanarChain

    m, length, R, k, omega = 2.0, 0.4, 0.3, 50.0, 20.0
    c = length / 2
    I_c = m * length ** 2 / 12
    chain = PlanarChain(np.array([R, 0.0]), np.array([[length, 0.0]]), np.array([m]),
                        np.array([I_c]), np.array([0]), np.array([[c, 0.0]]),
                        np.array([k]), np.array([0.0]), 1.0)
    phi = 1e-7
    acc = chain.accelerations(0.3, omega, 0.0, np.array([phi]), np.array([0.0]))[0]
    assert acc / phi == pytest.approx(-(k + m * omega ** 2 * R * c) / (I_c + m * c ** 2),
                                      rel=1e-5)
    # an angular acceleration of the hub swings it back: J phi'' = -m c (R + c) alpha... at
    # phi = 0 the Euler force's moment about the pivot is -alpha (I_c + m c (R + c))
    alpha = 3.0
    acc = chain.accelerations(0.0, 0.0, alpha, np.zeros(1), np.zeros(1))[0]
    assert acc == pytest.approx(-alpha * (I_c + m * c * (R + c)) / (I_c + m * c ** 2),
                                rel=1e-12)


@pytest.mark.slow
def test_lumped_chain_spin_up_stays_bounded(tmp_path):
    """The file's lumped chain (10 rigid elements, refined constants) stepped with its
    full rigid-body kinematics: bounded like the stiffened modal model. Its first
    frequency is 0.9 % below the FE's, so its quasi-static deflection is larger by
    (f_FE / f_chain)^2; what is left between the two peaks (measured 0.1 %) is the
    chain's discretisation of the stiffening law: bound 0.5 %."""
    text = CONFIG.replace("reduction:", "lumped: {elements: 10, constants: refined}\nreduction:")
    (tmp_path / "spin.yaml").write_text(text)
    assert _cli("run", "spin.yaml", "-o", "spin.h5", cwd=tmp_path).returncode == 0
    (tmp_path / "krb.yaml").write_text(SCENARIO)
    proc = _cli("simulate", "spin.h5", "krb.yaml", "-o", "res.h5", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    result = tmp_path / "res.h5"
    t, y = _signal(result, "lumped", "tip_y/position")
    _, y_modal = _signal(result, "stiffened", "tip_y/position")
    assert t[-1] == pytest.approx(DURATION) and np.abs(y).max() < 0.1 * L
    with h5py.File(tmp_path / "spin.h5", "r") as h5:
        ratio = (h5["modes/frequencies_hz"][0] / h5["lumped/frequencies_hz"][0]) ** 2
    peak_ratio = np.abs(y).max() / np.abs(y_modal).max()
    record_tolerance("spin_up: lumped chain peak vs modal x (f_FE/f_chain)^2",
                     abs(peak_ratio / ratio - 1), 0.005)
    assert peak_ratio == pytest.approx(ratio, rel=0.005)


def test_a_run_beyond_the_step_budget_is_refused_before_it_starts(spun, tmp_path):
    """A day of spinning (the 1.1 kHz modes for 86400 s, sampled at 20 Hz) would take
    ~1e10 right-hand sides: refused in one line, nothing written."""
    from pipeline.errors import SolverError

    (tmp_path / "long.yaml").write_text(
        f"{{name: long, kind: spin_up, final_speed: {SPEED}, ramp_time: {RAMP}, "
        "duration: 86400, output_rate: 20}")
    proc = _cli("simulate", str(spun[0]), "long.yaml", "-o", "res.h5", cwd=tmp_path)
    assert proc.returncode == SolverError.exit_code
    line = proc.stderr.strip().splitlines()[-1]
    assert "long" in line and "right-hand-side calls" in line
    assert not (tmp_path / "res.h5").exists()


def test_stiffened_peak_against_the_full_fe_prestressed_statics(spun, tmp_path):
    """The full FE body (the same box and mesh size, built here with pipeline.fe) under the
    quasi-static loads of the ramp, (K + Omega^2 (K_G1 - M_perp)) u = Omega^2 f_c -
    alpha f_e, solved sparse at every 1 ms: its worst tip deflection against the
    stepper's quasi-static prediction (6 modes: the truncation of the in-plane static
    response, measured 0.02 %; bound 0.2 %) and against the stepped peak (a slow ramp,
    T w1 = 62: the dynamic overshoot, measured 0.4 %; bound 1 %)."""
    import scipy.sparse.linalg as spla

    from conftest import ALUMINIUM, build_model
    from pipeline.config import Port, Ports
    from pipeline.fe.ports import port_matrices
    from pipeline.fe.prestress import tensor_weights
    from pipeline.reduce.rotation import prestress_terms

    fe = build_model(tmp_path, length=L, height=H, depth=B, size=0.025)
    a = np.array([0.0, 0.0, 1.0])
    terms = prestress_terms(fe.space, ALUMINIUM, fe.free, fe.K, (0.0, H / 2, B / 2))
    K_G1, M_perp = terms.spin_matrices(a)
    f_c = terms.centrifugal_loads @ tensor_weights(a)
    f_e = (terms.node_mass @ np.cross(a, terms.node_offsets)).reshape(-1)[fe.free]
    port = Port("tip_y", "tip", "displacement", (0.0, 1.0, 0.0))
    row = port_matrices(fe.space, fe.regions, Ports(outputs=(port,))).T.toarray()[0][fe.free]
    times = np.arange(0.0, RAMP + 1e-9, 1e-3)
    speeds, alphas, _ = hub_profile(times, SPEED, RAMP)
    full = [row @ spla.spsolve((fe.K + w ** 2 * (K_G1 - M_perp)).tocsc(),
                               w ** 2 * f_c - al * f_e) for w, al in zip(speeds, alphas)]
    worst = full[int(np.argmax(np.abs(full)))]
    with h5py.File(spun[1], "r") as h5:
        attrs = dict(h5["krb/stiffened"].attrs)
    assert attrs["predicted_peak_deflection"] == pytest.approx(worst, rel=2e-3)
    assert attrs["measured_peak_deflection"] == pytest.approx(worst, rel=1e-2)


def test_a_final_speed_past_the_stiffened_instability_is_named(tmp_path):
    """Spun about its own length the beam softens, w^2 = w0^2 - Omega^2 (no tension): at
    600 rad/s, past w0 = 413 rad/s, the stiffened model itself is unstable: refused in one
    line naming the speed, nothing written."""
    from pipeline.errors import SolverError

    text = CONFIG.replace("axis: [0, 0, 1]", "axis: [1, 0, 0]").replace(
        "speeds_rad_s: [0, 300, 600]", "speeds_rad_s: [0, 300]")
    line = _refusal(tmp_path, text, SolverError)
    assert "krb'.final_speed" in line and "600 rad/s" in line
