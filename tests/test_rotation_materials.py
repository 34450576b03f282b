"""Rotation (issue 37) with several materials and added masses (issue 36): each element's
density in the centrifugal load and the spin-softening mass, each element's law in the
static stress and so in the geometric stiffness, area and volume masses in the mass,
point masses on distributing couplings through their six motions G u (load, softening
and their own geometric stiffness as rigid bodies); rigid couplings stay refused.

References and tolerances:
- one material given as ``materials: [{..., elements: all}]`` is the plain ``material:``
  run bit for bit (the file's /rotation group compared with ==);
- a volume mass gives the body with its density raised (to the eigensolver's 1e-10: the
  per-element mass sums the same values in another order);
- a two-material bar (steel root half, aluminium tip half) against CalculiX on the same
  mesh (C3D10, one *SOLID SECTION per material, *DLOAD CENTRIF in a linear static step,
  then a *FREQUENCY perturbation step): the bounds of tests/test_rotation.py's
  single-material comparison, 1e-4 on the bending modes and 3e-4 on all six (CalculiX's
  4-point C3D10 mass rule and its stress-stiffness increments differ from ours by that);
- an area mass's centrifugal load sums to its mass times its centroid's distance from
  the axis (per unit Omega^2), to round-off;
- a point mass's rigid-body terms against a particle cloud of the same mass, centre and
  inertia (the gradient and Hessian of its centrifugal potential), and a tip mass
  against CalculiX (docstrings below).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from pipeline.config import config_from_dict
from pipeline.errors import ConfigError
from pipeline.fe.model import build_fe_model
from pipeline.reduce.rotation import full_frequencies, prestress_terms
from test_rotation import _ccx_deck, _ccx_frequencies

ROOT = Path(__file__).resolve().parents[1]
L, H, B = 0.2, 0.02, 0.02
STEEL = {"E": 210e9, "nu": 0.3, "rho": 7850.0}
ALU = {"E": 69e9, "nu": 0.33, "rho": 2700.0}
ROOT_HALF = {"kind": "box", "lower": [-1, -1, -1], "upper": [L / 2, 1, 1]}
POINT = (0.0, H / 2, B / 2)
SPIN = {"axis": [0, 0, 1], "point": list(POINT), "speeds_rad_s": [0.0, 1500.0]}


def raw_config(**extra) -> dict:
    return {"name": "spin", "geometry": {"kind": "box", "length": L, "height": H, "depth": B},
            "mesh": {"order": 2, "size": 0.01}, "supports": [{"region": "root", "fix": "all"}],
            "modes": {"count": 6}, **extra}


def _cli(raw: dict, tmp_path: Path, name: str) -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(raw))
    out = tmp_path / f"{name}.h5"
    proc = subprocess.run([sys.executable, "-m", "pipeline", "run", str(path), "-o", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out


def _rotation_group(path: Path) -> dict:
    with h5py.File(path) as h5:
        return {k: np.asarray(v) for k, v in h5["rotation"].items()
                if isinstance(v, h5py.Dataset)}


def test_one_material_claiming_all_is_the_plain_run_bit_for_bit(tmp_path):
    plain = _rotation_group(_cli(raw_config(material=ALU, rotation=SPIN), tmp_path, "plain"))
    claimed = _rotation_group(_cli(raw_config(material=STEEL, rotation=SPIN, materials=[
        {"name": "alu", **ALU, "elements": "all"}]), tmp_path, "claimed"))
    assert plain.keys() == claimed.keys() and "frequencies_hz" in plain
    for key in plain:
        np.testing.assert_array_equal(plain[key], claimed[key], err_msg=key)


def _spin_hz(cfg, tmp_path, speed, axis=(0.0, 0.0, 1.0)):
    fe = build_fe_model(cfg, tmp_path)
    terms = prestress_terms(fe.space, fe.materials, fe.free, fe.K, POINT)
    K_G1, M_perp = terms.spin_matrices(axis)
    return fe, terms, full_frequencies(fe.K, fe.M, K_G1, M_perp, [0.0, speed], 6)


def test_volume_mass_is_the_denser_body(tmp_path):
    """rho + 500 kg/m^3 as a volume mass or as the material's density: the same
    prestressed frequencies (the mass and load use rho_e; the stiffness does not)."""
    _, _, added = _spin_hz(config_from_dict(raw_config(
        material=ALU, masses=[{"name": "fill", "kind": "volume", "density": 500.0,
                               "elements": "all"}])), tmp_path / "a", 1500.0)
    _, _, denser = _spin_hz(config_from_dict(raw_config(
        material={**ALU, "rho": ALU["rho"] + 500.0})), tmp_path / "b", 1500.0)
    np.testing.assert_allclose(added, denser, rtol=1e-9)  # the eigensolver's tolerance


def test_area_mass_centrifugal_load(tmp_path):
    """An area mass of mu kg/m^2 on the tip face adds mu H B Omega^2 L (per unit
    Omega^2 along x: the face's centroid lies at distance L from the axis) to the load's
    sum, exactly (the consistent surface mass integrates the linear field exactly)."""
    mu = 3.0
    plain = config_from_dict(raw_config(material=ALU, rotation=SPIN))
    painted = config_from_dict(raw_config(material=ALU, rotation=SPIN, masses=[
        {"name": "paint", "kind": "area", "density": mu, "region": "tip"}]))
    from pipeline.config.rotation import tensor_weights
    from pipeline.fe.added_mass import area_node_mass

    sums = []
    for cfg, name in ((plain, "p"), (painted, "q")):
        fe = build_fe_model(cfg, tmp_path / name)
        extra = area_node_mass(fe.space, fe.regions, cfg.masses)
        terms = prestress_terms(fe.space, fe.materials, fe.free, fe.K, POINT,
                                extra_node_mass=extra)
        loads = np.zeros((fe.space.n_dofs, 6))
        loads[fe.free] = terms.centrifugal_loads
        weights = tensor_weights(np.array([0.0, 0.0, 1.0]))
        f = (loads @ weights).reshape(-1, 3)
        sums.append(f.sum(axis=0))
    # the supported root nodes lie on x = 0, where the load's x component vanishes
    assert sums[1][0] - sums[0][0] == pytest.approx(mu * H * B * L, rel=1e-12)


@pytest.mark.skipif(shutil.which("ccx") is None, reason="CalculiX not installed")
def test_two_material_bar_against_calculix(tmp_path):
    """At 1000 rad/s the out-of-plane bending f1 rises 3.6 % and the in-plane one 0.7 %
    (spin softening nearly cancels its stiffening). Measured: at rest 1e-7 to 2.4e-5
    apart (CalculiX's mass rule), spinning 7.6e-5 on the first two bending modes; the
    same bar of aluminium alone is 1.0e-4 apart at 1500 rad/s, the two-material one
    1.7e-4 there: the same small difference in the stress-stiffness increment that
    tests/test_rotation.py measures on one material. Bounds: those of that test (1e-4 on
    the bending modes, 3e-4 on all six) and the out-of-plane increment of f^2 within 1 %."""
    speed, axis = 1000.0, (0.0, 0.0, 1.0)
    cfg = config_from_dict(raw_config(material=ALU, materials=[
        {"name": "steel", **STEEL, "elements": ROOT_HALF}]))
    fe, _, (at_rest, spinning) = _spin_hz(cfg, tmp_path, speed, axis)
    assert set(np.unique(fe.materials.index)) == {0, 1}
    laws = [(np.flatnonzero(fe.materials.index == k), p["E"], p["nu"], p["rho"])
            for k, p in ((0, ALU), (1, STEEL))]
    (tmp_path / "spin.inp").write_text(_ccx_deck(fe, speed, axis, POINT, laws))
    subprocess.run(["ccx", "-i", "spin"], cwd=tmp_path, capture_output=True, timeout=600,
                   check=True)
    ccx_rest, ccx_spin = _ccx_frequencies((tmp_path / "spin.dat").read_text())
    np.testing.assert_allclose(ccx_rest[:6], at_rest, rtol=1e-4)
    assert spinning[1] > 1.03 * at_rest[1]  # the check sees the stiffening
    bending = [0, 1, 2, 3]
    error = np.abs(ccx_spin[:6] / spinning - 1)
    assert np.all(error[bending] < 1e-4) and np.all(error < 3e-4), error
    increment = (ccx_spin[1] ** 2 - ccx_rest[1] ** 2) / (spinning[1] ** 2 - at_rest[1] ** 2)
    assert abs(increment - 1) < 1e-2, increment


def _cloud(seed: int = 0):
    """A rigid cloud of 7 particles (kg, m, centre of mass at P) and its M6 about P."""
    from pipeline.fe.added_mass import point_rigid_mass

    rng = np.random.default_rng(seed)
    m = rng.uniform(0.1, 1.0, 7)
    r = rng.normal(size=(7, 3)) * 0.05
    r -= m @ r / m.sum()
    J = sum(mk * (rk @ rk * np.eye(3) - np.outer(rk, rk)) for mk, rk in zip(m, r))
    inertia = (J[0, 0], J[1, 1], J[2, 2], J[0, 1], J[0, 2], J[1, 2])
    return m, r, point_rigid_mass(m.sum(), inertia)


@pytest.mark.parametrize("entry", range(6))
def test_rigid_mass_terms_are_the_particle_clouds(entry):
    """A point mass's load, softening and own geometric stiffness against a cloud of
    particles with the same mass, centre and inertia: the centrifugal potential
    V = -1/2 sum m_k (x_k - p)^T A (x_k - p) with x_k = P + u + R(theta) r_k, its
    gradient (the load) to 1e-12 and its Hessian in (u, theta) by central differences
    (step 1e-4: error ~1e-8 of the largest entry) against K_G - M_A."""
    from scipy.spatial.transform import Rotation as Rot

    from pipeline.config.rotation import TENSOR_ENTRIES, entry_matrix
    from pipeline.fe.prestress import (rigid_centrifugal_load, rigid_geometric_stiffness,
                                       rigid_mass_of)

    m, r, M6 = _cloud()
    A = entry_matrix(*TENSOR_ENTRIES[entry])
    P, p = np.array([0.3, -0.1, 0.2]), np.array([0.0, 0.05, -0.02])

    def V(q):
        x = P + q[:3] + Rot.from_rotvec(q[3:]).apply(r)
        d = x - p
        return -0.5 * np.einsum("k,ki,ij,kj->", m, d, A, d)

    h = 1e-4
    E = np.eye(6) * h
    grad = np.array([(V(E[i]) - V(-E[i])) / (2 * h) for i in range(6)])
    hess = np.array([[(V(E[i] + E[j]) - V(E[i] - E[j]) - V(-E[i] + E[j]) + V(-E[i] - E[j]))
                      / (4 * h * h) for j in range(6)] for i in range(6)])
    load = rigid_centrifugal_load(M6, P - p, A)
    np.testing.assert_allclose(-grad, load, atol=1e-8 * np.abs(load).max())
    stiffness = rigid_geometric_stiffness(M6, A) - rigid_mass_of(M6, A)
    np.testing.assert_allclose(hess, stiffness, atol=1e-6 * np.abs(stiffness).max())
    # a rotation about the spin axis leaves a spinning rigid body's potential unchanged
    if entry == 2:  # W_zz: a spin about z
        assert abs(stiffness[5, 5]) < 1e-15 * np.abs(stiffness).max()


def test_rigid_couplings_with_rotation_are_refused_in_one_line():
    with pytest.raises(ConfigError) as exc:
        config_from_dict(raw_config(material=ALU, rotation=SPIN, masses=[
            {"name": "m", "mass": 0.1, "point": [L, H / 2, B / 2], "region": "tip",
             "coupling": "rigid"}]))
    assert exc.value.key == "masses[0].coupling" and "distributing" in str(exc.value)


TIP_MASS = {"name": "m", "mass": 0.05, "point": [L, H / 2, B / 2], "region": "tip"}


def _point_mass_terms(cfg, tmp_path):
    """The FE model of ``cfg`` and its prestress terms with its area and point masses."""
    from pipeline.fe.added_mass import area_node_mass, distributing_point_masses

    fe = build_fe_model(cfg, tmp_path)
    return fe, prestress_terms(
        fe.space, fe.materials, fe.free, fe.K, POINT,
        extra_node_mass=area_node_mass(fe.space, fe.regions, cfg.masses),
        point_masses=distributing_point_masses(fe.space, fe.regions, cfg.masses))


@pytest.mark.skipif(shutil.which("ccx") is None, reason="CalculiX not installed")
def test_tip_mass_under_rotation_against_calculix(tmp_path):
    """A 0.05 kg tip mass (a quarter of the bar's) at the tip face's centre, tied by a
    distributing coupling, spinning at 1000 rad/s about z, against CalculiX (a MASS
    element on a *DISTRIBUTING COUPLING reference node, *DLOAD CENTRIF on the body and
    the mass). CalculiX's perturbation step leaves out the MASS element's spin softening
    (measured: the in-plane bending mode, where that softening acts, sits 6.5 % above
    ours; with our point-mass softening removed 1.0e-4, and the out-of-plane mode, which
    has none, 8.6e-5 either way), so the comparison removes it from ours; its terms are
    checked against a particle cloud above. Bounds: at rest 1e-4 (the mass rule), the
    four bending modes' stiffening increments of f^2 within 2 % (measured 0.4 % to
    1.5 %; the bar alone: 1.2 %, the same difference as tests/test_rotation.py's)."""
    import ccx_deck

    from pipeline.fe.space import weighted_region

    speed, axis = 1000.0, (0.0, 0.0, 1.0)
    cfg = config_from_dict(raw_config(material=ALU, masses=[TIP_MASS]))
    fe, terms = _point_mass_terms(cfg, tmp_path)
    body_only = prestress_terms(fe.space, fe.materials, fe.free, fe.K, POINT)
    K_G1, M_perp = terms.spin_matrices(axis)
    rest, ours = full_frequencies(fe.K, fe.M, K_G1, M_perp, [0.0, speed], 6)
    no_soft = full_frequencies(fe.K, fe.M, K_G1, body_only.spin_matrices(axis)[1], [speed], 6)[0]
    space = fe.space
    sr = weighted_region(space, "tip", fe.regions["tip"])
    ref, n_e = space.n_nodes + 1, space.body.n_tetrahedra
    P = TIP_MASS["point"]
    lines = [f"*NODE\n{ref}, {P[0]!r}, {P[1]!r}, {P[2]!r}",
             f"*ELEMENT, TYPE=DCOUP3D, ELSET=DC\n{n_e + 1}, {ref}",
             "*DISTRIBUTING COUPLING, ELSET=DC"]
    lines += [f"{n + 1}, {w / sr.weights.max():.12e}" for n, w in zip(sr.nodes, sr.weights)
              if w > 0]
    lines += [f"*ELEMENT, TYPE=MASS, ELSET=PM\n{n_e + 2}, {ref}", "*MASS, ELSET=PM",
              f"{TIP_MASS['mass']!r}", "*ELSET, ELSET=SPUN\nM0, PM",
              "*STEP", "*FREQUENCY", "6", "*END STEP", "*STEP", "*STATIC", "*DLOAD",
              "SPUN, CENTRIF, " + ", ".join(f"{v!r}" for v in (speed ** 2, *POINT, *axis)),
              "*END STEP", "*STEP, PERTURBATION", "*FREQUENCY", "6", "*END STEP"]
    deck = tmp_path / "pm.inp"
    ccx_deck.write_deck(deck, space, [{"kind": "isotropic", **ALU}], fe.materials.index,
                        np.unique(fe.fixed // 3), "\n".join(lines))
    ccx_rest, ccx_spin = _ccx_frequencies(ccx_deck.run(deck))
    np.testing.assert_allclose(ccx_rest[:6], rest, rtol=1e-4)
    bending = slice(0, 4)
    increment = (ccx_spin[bending] ** 2 - ccx_rest[bending] ** 2) / (
        no_soft[bending] ** 2 - rest[bending] ** 2)
    assert np.all(np.abs(increment - 1) < 2e-2), increment
    assert ccx_spin[0] > 1.05 * ours[0]  # the mass's softening, ours only
    assert abs(ccx_spin[1] / ours[1] - 1) < 1e-4


def test_cli_rotation_with_a_tip_mass_and_two_materials(tmp_path):
    """End to end: a tip mass, an area mass and two materials under rotation through the
    CLI; the file's prestressed frequencies are those of the prestress terms (to the
    eigensolver's tolerance)."""
    raw = raw_config(material=ALU, materials=[{"name": "steel", **STEEL,
                                               "elements": ROOT_HALF}],
                     masses=[TIP_MASS, {"name": "paint", "kind": "area", "density": 2.0,
                                        "region": "top"}], rotation=SPIN)
    spun = _rotation_group(_cli(raw, tmp_path, "tip"))
    fe, terms = _point_mass_terms(config_from_dict(raw), tmp_path)
    K_G1, M_perp = terms.spin_matrices(SPIN["axis"])
    expected = full_frequencies(fe.K, fe.M, K_G1, M_perp, SPIN["speeds_rad_s"], 6)
    np.testing.assert_allclose(spun["frequencies_hz"], expected, rtol=1e-8)


def test_inertia_loads_carry_the_point_mass(tmp_path):
    """The Euler load of a point mass on its six motions equals its mass matrix
    G^T M6 G times the rigid field e_k x (x - p) (G R = I: the fit of a rigid field is
    exact), and the Coriolis matrices stay skew (the rigid-body mass of a skew matrix is
    skew), to round-off."""
    from pipeline.fe.added_mass import added_mass_matrix
    from pipeline.fe.prestress import tensor_mass
    from pipeline.reduce.rotation import inertia_loads

    cfg = config_from_dict(raw_config(material=ALU, masses=[
        {**TIP_MASS, "inertia": [2e-5, 2.5e-5, 3e-5, 1e-6, 0, 2e-6]}]))
    fe, terms = _point_mass_terms(cfg, tmp_path)
    V = np.random.default_rng(1).normal(size=(fe.free.size, 3))
    _, euler, coriolis = inertia_loads(terms, fe.free, V)
    full = np.zeros((fe.space.n_dofs, 3))
    full[fe.free] = V
    M_all = tensor_mass(terms.node_mass, np.eye(3)) + added_mass_matrix(fe.space, fe.regions,
                                                                        cfg.masses)
    for k, e in enumerate(np.eye(3)):
        field = np.cross(e, terms.node_offsets).reshape(-1)
        expected = full.T @ (M_all @ field)
        np.testing.assert_allclose(euler[k], expected, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(coriolis[k], -coriolis[k].T, atol=1e-15)
