"""Rotating and preloaded bodies (issue 37): pipeline.fe.prestress, pipeline.reduce.rotation,
the ``rotation`` config section and the ``/rotation`` group of the file.

References and tolerances:
- the consistent centrifugal load is exact for the linear field x - p: its sum is
  m Omega^2 (I - a a^T)(c - p) (m the mass, c the centre of mass) to round-off;
- a uniform uniaxial stress s_xx: K_G[v, v] = s_xx int (dv/dx)^2 dV exactly (P2 on
  straight tetrahedra, the integrand is constant for a linear v), round-off only;
- Southwell: the first-order change of the first bending w^2 with Omega^2 is
  S = int T phi'^2 dx / int m phi^2 dx, T = m Omega^2 (L^2 - x^2) / 2 (Euler-Bernoulli, no
  hub), computed here by quadrature of the exact mode shape: 1.1933. Out of the plane of
  rotation w^2 = w0^2 + S Omega^2, in the plane w^2 = w0^2 + (S - 1) Omega^2. The 3D FE
  body (L/h = 25) differs from beam theory by shear and section effects of order (h/L)^2
  and by the mesh: 1 % covers both (measured 0.25 % at h = 10 mm);
- axial tension T: d(w^2)/dT = int phi'^2 dx / (m int phi^2 dx) (the Rayleigh quotient of
  the clamped-free beam under tension, same shape), 1 % for the same reasons;
- the reduced model (the first 10 modes) against the full FE prestressed frequencies:
  1 % up to the speed where f1 doubles (the issue's requirement; measured < 0.2 %).
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ALUMINIUM, build_model
from pipeline.config import Port, Ports, config_from_dict
from pipeline.config.rotation import Rotation
from pipeline.errors import ConfigError, SolverError
from pipeline.fe import prestress as ps
from pipeline.fe.assemble import restrict
from pipeline.fe.ports import port_matrices
from pipeline.reduce.rotation import build_rotation, prestress_terms
from pipeline.solve.eigen import solve_modes

L, H, B = 0.5, 0.02, 0.05
AREA = H * B
ROOT_CENTRE = (0.0, H / 2, B / 2)
BETA1 = 1.8751040687119611  # first root of cos(bL) cosh(bL) = -1


def _beam_mode(x: np.ndarray, beta: float = BETA1) -> tuple[np.ndarray, np.ndarray]:
    """The clamped-free Euler-Bernoulli mode phi and its slope phi' at x (L = 1 scaled)."""
    b = beta / L
    s = (np.cosh(beta) + np.cos(beta)) / (np.sinh(beta) + np.sin(beta))
    phi = np.cosh(b * x) - np.cos(b * x) - s * (np.sinh(b * x) - np.sin(b * x))
    dphi = b * (np.sinh(b * x) + np.sin(b * x) - s * (np.cosh(b * x) - np.cos(b * x)))
    return phi, dphi


def _integral(y: np.ndarray, x: np.ndarray) -> float:
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(x)))


def southwell_beam() -> float:
    """S of the first mode of a uniform cantilever spinning about its root (1.1933)."""
    x = np.linspace(0.0, L, 20001)
    phi, dphi = _beam_mode(x)
    return _integral(0.5 * (L ** 2 - x ** 2) * dphi ** 2, x) / _integral(phi ** 2, x)


def tension_beam() -> float:
    """d(w1^2)/dT (rad^2/s^2 per N) of the cantilever under axial tension T."""
    x = np.linspace(0.0, L, 20001)
    phi, dphi = _beam_mode(x)
    return _integral(dphi ** 2, x) / (ALUMINIUM.rho * AREA * _integral(phi ** 2, x))


@pytest.fixture(scope="module")
def body(tmp_path_factory):
    fe = build_model(tmp_path_factory.mktemp("rotation"), size=0.01)
    modes = solve_modes(fe.K, fe.M, 10, supported=True, backend="auto")
    return fe, modes


@pytest.fixture(scope="module")
def terms(body):
    """The prestress terms about the root centre, with a tip tension port."""
    fe, _ = body
    ports = Ports(inputs=(Port("pull", "tip", "force", (1.0, 0.0, 0.0)),))
    F = port_matrices(fe.space, fe.regions, ports).F
    return prestress_terms(fe.space, ALUMINIUM, fe.free, fe.K, ROOT_CENTRE, F_inputs=F)


def test_beam_references():
    assert southwell_beam() == pytest.approx(1.1933, abs=1e-4)  # the published value


def test_centrifugal_load_is_exact_for_the_rigid_field(body):
    fe, _ = body
    m = ps.node_mass_matrix(fe.space, ALUMINIUM.rho)
    mass = float(m.sum())
    centre = (m @ fe.space.node_points).sum(axis=0) / mass
    assert mass == pytest.approx(ALUMINIUM.rho * L * H * B, rel=1e-12)
    p = np.array([0.1, -0.2, 0.3])
    loads = ps.centrifugal_loads(fe.space, m, p)
    for axis in ([0, 0, 1.0], [0, 1.0, 0], [1.0, 2.0, -0.5]):
        a = np.asarray(axis) / np.linalg.norm(axis)
        total = (loads @ ps.tensor_weights(a)).reshape(-1, 3).sum(axis=0)
        expected = mass * (np.eye(3) - np.outer(a, a)) @ (centre - p)
        np.testing.assert_allclose(total, expected, atol=1e-12 * mass * 1.0)
    # the six entries sum to |omega|^2 I - omega omega^T for any omega
    omega = np.array([0.3, -1.1, 0.7])
    A = sum(w * ps.entry_matrix(i, j) for w, (i, j) in
            zip(ps.tensor_weights(omega), ps.TENSOR_ENTRIES))
    np.testing.assert_allclose(A, omega @ omega * np.eye(3) - np.outer(omega, omega),
                               atol=1e-15)


def test_geometric_stiffness_of_a_uniform_stress(body):
    fe, _ = body
    x = fe.space.node_points
    strain, nu = 1e-4, ALUMINIUM.nu
    u = np.column_stack([strain * x[:, 0], -nu * strain * x[:, 1], -nu * strain * x[:, 2]])
    K_G = ps.geometric_stiffness(fe.space, ALUMINIUM, u.reshape(-1, 1))[0]
    sigma_xx = ALUMINIUM.E * strain
    v = np.column_stack([np.zeros(len(x)), x[:, 0], np.zeros(len(x))]).reshape(-1)
    assert v @ K_G @ v == pytest.approx(sigma_xx * L * H * B, rel=1e-10)
    w = np.column_stack([np.zeros(len(x)), x[:, 1], np.zeros(len(x))]).reshape(-1)
    assert abs(w @ K_G @ w) < 1e-10 * sigma_xx * L * H * B  # s_yy = 0
    assert abs(K_G @ np.tile([1.0, 2.0, 3.0], len(x))).max() < 1e-6  # translation: none


@pytest.mark.parametrize("axis, softening", [((0.0, 1.0, 0.0), 0.0), ((0.0, 0.0, 1.0), 1.0)])
def test_southwell_first_bending_mode(body, terms, axis, softening):
    """Mode 1 bends in y: out of the plane of a spin about y, in the plane of one about z."""
    fe, modes = body
    K_G1, M_perp = terms.spin_matrices(axis)
    phi = modes.shapes[:, 0]  # M-orthonormal
    slope = phi @ (K_G1 @ phi) - phi @ (M_perp @ phi)
    assert slope == pytest.approx(southwell_beam() - softening, rel=0.01 / (1.2 - softening))


def test_axial_tension_stiffens_like_the_beam(body, terms):
    fe, modes = body
    phi = modes.shapes[:, 0]
    assert phi @ (terms.preload_geometric[0] @ phi) == pytest.approx(tension_beam(), rel=0.01)


@pytest.mark.parametrize("axis, stop, corrections", [
    ((0.0, 1.0, 0.0), 4.0, 0),   # f1 is the in-plane mode from about 2.5 w0: 2.95 f0 at 4 w0
    ((0.0, 0.0, 1.0), 6.5, 4),   # in-plane from the start: f1 doubles near 6.1 w0
])
def test_reduced_model_follows_the_full_fe_until_f1_doubles(body, axis, stop, corrections):
    """The plain modal basis (10 modes) stays within 0.2 % in the first case; in the
    second it is 2.5 % off at 5 w0 (measured), so the correction shapes are added."""
    fe, modes = body
    w0 = float(np.sqrt(modes.omega2[0]))
    rotation = Rotation(axis=axis, point=ROOT_CENTRE, correction_shapes=corrections,
                        speeds_rad_s=tuple(np.linspace(0.0, stop * w0, 4)))
    model = build_rotation(rotation, fe.space, ALUMINIUM, fe.free, fe.K, fe.M,
                           modes.shapes, modes.omega2, backend="auto")
    assert model.frequencies_hz[-1, 0] > 2 * modes.frequencies_hz[0]
    assert np.all(np.diff(model.frequencies_hz, axis=1) >= 0)
    np.testing.assert_allclose(model.frequencies_hz[0], modes.frequencies_hz, rtol=1e-8)
    ratio = model.frequencies_reduced_hz[:, :4] / model.frequencies_hz[:, :4]
    assert np.all(ratio >= 1 - 1e-8)  # Rayleigh-Ritz: upper bounds
    assert np.all(ratio < 1.01)


def test_spin_about_the_beam_axis_is_unstable_past_w0(body):
    """Spun about its own length, the beam softens (w^2 = w0^2 - Omega^2, no tension):
    the speed past w0 is named."""
    fe, modes = body
    w0 = float(np.sqrt(modes.omega2[0]))
    rotation = Rotation(axis=(1.0, 0.0, 0.0), point=ROOT_CENTRE, speeds_rad_s=(0.0, 1.5 * w0))
    with pytest.raises(SolverError, match=r"rotation\.speeds_rad_s.*%g rad/s" % (1.5 * w0)):
        build_rotation(rotation, fe.space, ALUMINIUM, fe.free, fe.K, fe.M, modes.shapes,
                       modes.omega2, backend="auto")


BASE = {"name": "spin", "geometry": {"kind": "box", "length": 0.5, "height": 0.02,
                                     "depth": 0.05},
        "mesh": {"size": 0.02}, "material": {"E": 69e9, "nu": 0.33, "rho": 2700.0},
        "supports": [{"region": "root", "fix": "all"}]}


@pytest.mark.parametrize("rotation, message", [
    ({"axis": [0, 0, 0], "point": [0, 0, 0], "speeds_rad_s": [0]}, "rotation.axis"),
    ({"axis": [0, 0, 1], "point": [0, 0, 0], "speeds_rad_s": [0, 50, 50]},
     r"rotation.speeds_rad_s\[2\].*ascending"),
    ({"axis": [0, 0, 1], "point": [0, 0, 0], "speeds_rad_s": []}, "rotation.speeds_rad_s"),
    ({"axis": [0, 0, 1], "point": [0, 0, 0], "speeds_rad_s": [0, "fast"]},
     r"rotation.speeds_rad_s\[1\]"),
    ({"axis": [0, 0, 1], "point": [0, 0], "speeds_rad_s": [0]}, "rotation.point"),
    ({"axis": [0, 0, 1], "point": [0, 0, 0], "speeds": [0]}, "rotation.speeds"),
])
def test_config_refuses_in_one_line(rotation, message):
    with pytest.raises(ConfigError, match=message) as info:
        config_from_dict({**BASE, "rotation": rotation})
    assert "\n" not in str(info.value)


def test_config_rotation_needs_supports_and_allows_negative_speeds():
    cfg = config_from_dict({**BASE, "rotation": {"axis": [0, 0, 2], "point": [0, 0, 0],
                                                 "speeds_rad_s": [-10, 0, 10]}})
    assert cfg.rotation.speeds_rad_s == (-10.0, 0.0, 10.0)
    with pytest.raises(ConfigError, match="rotation.*supports"):
        config_from_dict({**BASE, "supports": [], "rotation": {
            "axis": [0, 0, 1], "point": [0, 0, 0], "speeds_rad_s": [0]}})


def test_restricted_mass_is_the_pipelines(body):
    fe, _ = body
    m = ps.node_mass_matrix(fe.space, ALUMINIUM.rho)
    diff = restrict(ps.tensor_mass(m, np.eye(3)), fe.free) - fe.M
    assert abs(diff).max() < 1e-12 * abs(fe.M).max()


# --------------------------------------------------------------------------- end to end
SPIN_CONFIG = """\
name: spin
geometry: {kind: box, length: 0.5, height: 0.02, depth: 0.05}
mesh: {order: 2, size: 0.025}
material: {E: 69.0e9, nu: 0.33, rho: 2700.0}
supports: [{region: root, fix: all}]
modes: {count: 4}
ports:
  inputs:  [{name: pull, region: tip, kind: force, direction: [1, 0, 0]}]
  outputs: [{name: tip_y, region: tip, kind: displacement, direction: [0, 1, 0]}]
reduction: {modes: 4, static_correction: residual}
rotation: {axis: [0, 0, 1], point: [0, 0.01, 0.025], speeds_rad_s: %s}
"""


def _cli(*args, cwd):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def spin_file(tmp_path_factory):
    """A run of SPIN_CONFIG through the command line (speeds -100, 0, 100, 800 rad/s; the
    basis: 4 modes, the centrifugal static shape, 2 correction shapes)."""
    tmp = tmp_path_factory.mktemp("spin")
    text = SPIN_CONFIG.replace("speeds_rad_s: %s", "speeds_rad_s: %s, static_shape: true, "
                               "correction_shapes: 2")
    (tmp / "spin.yaml").write_text(text % "[-100, 0, 100, 800]")
    proc = _cli("run", "spin.yaml", "-o", "spin.h5", cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    return tmp / "spin.h5"


def test_cli_run_writes_the_rotation_group(spin_file):
    from pipeline.reduce.spin import reduced_frequencies
    from pipeline.store.read import load_model, read_rotation

    model = read_rotation(spin_file)
    assert load_model(spin_file).plant is not None
    np.testing.assert_allclose(model.speeds_rad_s, [-100, 0, 100, 800])
    np.testing.assert_allclose(model.axis, [0, 0, 1])
    assert model.frequencies_hz.shape == (4, 4) and model.geometric.shape == (6, 7, 7)
    assert model.n_modes == 4 and model.static_shape
    assert model.input_names == ("pull",) and model.preload.shape == (1, 7, 7)
    np.testing.assert_allclose(model.frequencies_hz[0], model.frequencies_hz[2], rtol=1e-6)
    assert np.all(model.frequencies_hz[3] > model.frequencies_hz[1])  # stiffened
    # the stored terms rebuild the stored reduced frequencies, at any speed
    np.testing.assert_allclose(reduced_frequencies(model), model.frequencies_reduced_hz,
                               rtol=1e-12)
    ratio = model.frequencies_reduced_hz[:, :4] / model.frequencies_hz
    assert np.all((ratio > 1 - 1e-8) & (ratio < 1.01))
    # a tension preload stiffens, a compression softens
    up, down = (reduced_frequencies(model, [0.0], preload=[s * 1e4])[0, 0] for s in (1, -1))
    assert up > model.frequencies_hz[1, 0] > down


def test_cli_names_the_unstable_speed_and_writes_nothing(tmp_path):
    """Spun about its own length the beam softens: past w0 (~413 rad/s) it is unstable."""
    text = SPIN_CONFIG.replace("axis: [0, 0, 1]", "axis: [1, 0, 0]") % "[0, 300, 900]"
    (tmp_path / "spin.yaml").write_text(text)
    proc = _cli("run", "spin.yaml", "-o", "spin.h5", cwd=tmp_path)
    assert proc.returncode == SolverError.exit_code, proc.stderr
    line = proc.stderr.strip().splitlines()[-1]
    assert "rotation.speeds_rad_s" in line and "900 rad/s" in line
    assert not (tmp_path / "spin.h5").exists()


def test_version_1_files_without_rotation_still_load(tmp_path, monkeypatch):
    from pipeline.config import load_config
    from pipeline.run import run_pipeline
    from pipeline.store import h5file
    from pipeline.store.read import load_model, read_rotation

    monkeypatch.setattr(h5file, "SCHEMA_VERSION", 1)
    cfg = load_config(__import__("pathlib").Path(__file__).parents[1] / "configs"
                      / "cantilever.yaml", ["mesh.size=0.025", "modes.count=4"])
    out = run_pipeline(cfg, tmp_path / "v1.h5").output
    monkeypatch.undo()
    assert load_model(out).plant is not None and read_rotation(out) is None


# --------------------------------------------------------------------------- CalculiX
def _ccx_deck(fe, speed: float, axis, point, laws=None) -> str:
    """A CalculiX deck of the same mesh (C3D10 numbers its nodes as meshio's tetra10),
    the same material and clamp: a frequency step at rest, a linear static step under
    *DLOAD CENTRIF, and a *FREQUENCY perturbation step about it. ``laws``: (element
    indices, E, nu, rho) of each material (None: aluminium everywhere)."""
    x, elements = fe.space.node_points, fe.space.element_nodes
    fixed_nodes = np.unique(np.setdiff1d(np.arange(fe.space.n_dofs), fe.free) // 3)
    lines = ["*NODE, NSET=Nall"]
    lines += [f"{i + 1}, {a:.17g}, {b:.17g}, {c:.17g}" for i, (a, b, c) in enumerate(x)]
    lines.append("*ELEMENT, TYPE=C3D10, ELSET=Eall")
    for e, nodes in enumerate(elements + 1):
        lines += [f"{e + 1}, " + ", ".join(map(str, nodes[:8])) + ",",
                  ", ".join(map(str, nodes[8:]))]
    lines += ["*NSET, NSET=Fix"] + [f"{n + 1}," for n in fixed_nodes]
    lines += ["*BOUNDARY", "Fix, 1, 3"]
    if laws is None:
        laws = [(np.arange(len(elements)), ALUMINIUM.E, ALUMINIUM.nu, ALUMINIUM.rho)]
    for k, (ids, E, nu, rho) in enumerate(laws):
        lines += [f"*ELSET, ELSET=E{k}"] + [f"{i + 1}," for i in ids]
        lines += [f"*MATERIAL, NAME=M{k}", "*ELASTIC", f"{E:.17g}, {nu}", "*DENSITY",
                  f"{rho}", f"*SOLID SECTION, ELSET=E{k}, MATERIAL=M{k}"]
    centrif = (f"Eall, CENTRIF, {speed ** 2:.17g}, " + ", ".join(f"{v:.17g}" for v in point)
               + ", " + ", ".join(f"{v:.17g}" for v in axis))
    lines += ["*STEP", "*FREQUENCY", "6", "*END STEP",
              "*STEP", "*STATIC", "*DLOAD", centrif, "*END STEP",
              "*STEP, PERTURBATION", "*FREQUENCY", "6", "*END STEP"]
    return "\n".join(lines) + "\n"


def _ccx_frequencies(dat: str) -> list[np.ndarray]:
    """The frequencies (Hz) of every eigenvalue table of a CalculiX .dat file."""
    import re

    out = []
    for block in dat.split("E I G E N V A L U E   O U T P U T")[1:]:
        rows = re.findall(r"^\s+\d+\s+\S+\s+\S+\s+(\S+)\s+\S+\s*$", block, re.M)
        out.append(np.array([float(r) for r in rows]))
    return out


@pytest.mark.slow
@pytest.mark.skipif(__import__("shutil").which("ccx") is None, reason="CalculiX not installed")
def test_prestressed_frequencies_agree_with_calculix(body, terms, tmp_path):
    """The same mesh in CalculiX (C3D10, linear static *DLOAD CENTRIF, then a *FREQUENCY
    perturbation step, which adds the stress stiffness and the centrifugal softening). At
    rest the two agree to CalculiX's printed digits (1e-6). Spinning at 300 rad/s (f1 up
    4.9 %), the four bending modes agree to 5e-5 (the stiffening increment of f1^2 to
    0.08 %), the first torsion mode to 1.8e-4: its increment is a near-cancellation of
    K_G and softening, and the two codes' increments differ by half. Ruled out as causes
    (measured): the quadrature of the load and of K_G (degree 2 to 4 rules change our
    frequencies by < 1e-8), a lumped softening mass, softening inside the static step.
    Bounds: 1e-4 on the bending modes, 3e-4 on all six."""
    import subprocess

    fe, modes = body
    speed, axis = 300.0, (0.0, 0.0, 1.0)
    (tmp_path / "spin.inp").write_text(_ccx_deck(fe, speed, axis, ROOT_CENTRE))
    subprocess.run(["ccx", "-i", "spin"], cwd=tmp_path, capture_output=True, timeout=600,
                   check=True)
    at_rest, spinning = _ccx_frequencies((tmp_path / "spin.dat").read_text())
    K_G1, M_perp = terms.spin_matrices(axis)
    from pipeline.reduce.rotation import full_frequencies

    ours = full_frequencies(fe.K, fe.M, K_G1, M_perp, [speed], 6)[0]
    np.testing.assert_allclose(at_rest[:6], modes.frequencies_hz[:6], rtol=2e-6)
    error = np.abs(spinning[:6] / ours - 1)
    bending = [0, 1, 2, 3]  # the torsion mode is the fifth
    assert np.all(error[bending] < 1e-4) and np.all(error < 3e-4)
    assert np.all(spinning[:6] > at_rest[:6])


def test_inspect_prints_and_plot_draws_the_campbell_diagram(spin_file, tmp_path):
    from pipeline.apps.summary import summarize
    from pipeline.store.read import read_rotation

    text = summarize(spin_file)
    assert "rotation  axis [0.0, 0.0, 1.0]" in text and "max rel. diff" in text
    pytest.importorskip("matplotlib")
    from pipeline.apps.campbell import plot_campbell

    out = plot_campbell(read_rotation(spin_file), tmp_path / "campbell.png")
    assert out.stat().st_size > 10_000


@pytest.mark.parametrize("load", [8e3, -8e3])  # tension, compression (P_cr = 22.8 kN)
def test_reduced_preload_follows_the_full_fe(body, terms, load):
    """K + lambda K_G(unit tip tension): the reduced model from the stored projection P
    (diag(w0^2) + lambda P on the 10 modes) against the full FE, 1 % on the first four
    modes (measured 8e-5 at +-8 kN), and above it (Rayleigh-Ritz)."""
    from pipeline.reduce.rotation import full_frequencies

    fe, modes = body
    K_G = terms.preload_geometric[0]
    full = full_frequencies(fe.K, fe.M, load * K_G, 0.0 * K_G, [1.0], 4)[0]
    P = modes.shapes.T @ (K_G @ modes.shapes)
    w2 = np.linalg.eigvalsh(np.diag(modes.omega2) + load * P)
    reduced = np.sqrt(w2[:4]) / (2 * np.pi)
    assert np.all(reduced / full - 1 > -1e-8) and np.all(reduced / full - 1 < 0.01)
    assert (full[0] > modes.frequencies_hz[0]) == (load > 0)
