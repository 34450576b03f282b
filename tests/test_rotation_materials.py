"""Rotation (issue 37) with several materials and added masses (issue 36): each element's
density in the centrifugal load and the spin-softening mass, each element's law in the
static stress and so in the geometric stiffness, area and volume masses in the mass.

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
  the axis (per unit Omega^2), to round-off.
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


def test_point_masses_with_rotation_are_refused_in_one_line():
    with pytest.raises(ConfigError) as exc:
        config_from_dict(raw_config(material=ALU, rotation=SPIN, masses=[
            {"name": "m", "mass": 0.1, "point": [L, H / 2, B / 2], "region": "tip"}]))
    assert exc.value.key == "masses[0].kind"


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
