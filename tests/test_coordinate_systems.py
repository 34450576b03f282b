"""Named coordinate systems as material frames (``coordinate_systems:`` and a materials
entry's ``axes: <name>``, docs/materials.md): the same K as the inline axes, bit for
bit; the round trip through the YAML copy; the one-line refusals through the CLI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipeline.config import config_from_dict, config_to_yaml
from pipeline.errors import ConfigError
from pipeline.fe.model import build_fe_model

ROOT = Path(__file__).resolve().parents[1]
BOX = {"kind": "box", "length": 0.1, "height": 0.02, "depth": 0.02}
ORTHO = {"name": "cfrp", "kind": "orthotropic", "E": [140e9, 10e9, 12e9], "nu": [0.3, 0.25, 0.4],
         "G": [5e9, 4e9, 3.6e9], "rho": 1600.0, "elements": "all"}
TILTED = {"x": [1.0, 0.2, 0.1], "y": [-0.2, 1.0, 0.0]}  # y . x = 0 exactly


def raw_config(**extra) -> dict:
    return {"name": "t", "geometry": BOX, "mesh": {"order": 1, "size": 0.01},
            "supports": [{"region": "root", "fix": "all"}], **extra}


def test_named_system_gives_the_inline_k_bit_for_bit(tmp_path):
    inline = config_from_dict(raw_config(materials=[{**ORTHO, "axes": TILTED}]))
    named = config_from_dict(raw_config(
        coordinate_systems={"ply": {**TILTED, "origin": [0.05, 0.0, 0.0]}},
        materials=[{**ORTHO, "axes": "ply"}]))
    assert named.materials[0].axes == inline.materials[0].axes
    a = build_fe_model(inline, tmp_path / "a")
    b = build_fe_model(named, tmp_path / "b")
    assert (a.K != b.K).nnz == 0 and (a.M != b.M).nnz == 0
    np.testing.assert_array_equal(a.materials.D, b.materials.D)


def test_round_trip_keeps_the_name():
    cfg = config_from_dict(raw_config(coordinate_systems={"ply": TILTED},
                                      materials=[{**ORTHO, "axes": "ply"}]))
    text = config_to_yaml(cfg)
    back = yaml.safe_load(text)
    assert back["materials"][0]["axes"] == "ply"
    assert back["coordinate_systems"]["ply"]["x"] == TILTED["x"]
    assert config_from_dict(back) == cfg
    plain = config_from_dict(raw_config(materials=[{**ORTHO, "axes": TILTED}]))
    assert "coordinate_systems" not in yaml.safe_load(config_to_yaml(plain))


@pytest.mark.parametrize("systems, axes, key, words", [
    ({"ply": TILTED}, "pyl", "materials[0].axes", "coordinate system: ply"),
    ({}, "ply", "materials[0].axes", "coordinate_systems defines none"),
    ({"ply": {"x": [1, 0, 0], "y": [2, 0, 0]}}, "ply", "coordinate_systems.ply.y",
     "orthogonal"),
    ({"ply": {"x": [0, 0, 0], "y": [0, 1, 0]}}, "ply", "coordinate_systems.ply.x",
     "non-zero"),
    ({"ply": {"x": [1, 0, 0]}}, "ply", "coordinate_systems.ply.y", "missing"),
    ({"ply": {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}}, "ply",
     "coordinate_systems.ply.z", "not known"),
])
def test_refusals_name_the_key(systems, axes, key, words):
    with pytest.raises(ConfigError) as exc:
        config_from_dict(raw_config(coordinate_systems=systems,
                                    materials=[{**ORTHO, "axes": axes}]))
    assert exc.value.key == key and words in str(exc.value)


@pytest.mark.parametrize("systems, axes, words", [
    ({"ply": TILTED, "web": {"x": [0, 1, 0], "y": [0, 0, 1]}}, "flange",
     "'materials[0].axes': got 'flange', expected {x: [..], y: [..]} or the name of a "
     "coordinate system: ply, web"),
    ({"ply": {"x": [1, 1, 0], "y": [2, 2, 0]}}, "ply", "'coordinate_systems.ply.y'"),
])
def test_cli_refuses_in_one_line_and_writes_nothing(tmp_path, systems, axes, words):
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(raw_config(coordinate_systems=systems,
                                              materials=[{**ORTHO, "axes": axes}])))
    out = tmp_path / "out.h5"
    proc = subprocess.run([sys.executable, "-m", "pipeline", "run", str(path), "-o", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == ConfigError.exit_code
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and words in lines[0], proc.stderr
    assert not out.exists()


# --------------------------------------------------------------------------- cylindrical
#: transversely isotropic about material axis 3 (the tube's axis in a cylindrical system:
#: axes radial, hoop, axial): E_r = E_theta, nu_rz = nu_thetaz, G_rz = G_thetaz,
#: G_rtheta = E_r / (2 (1 + nu_rtheta))
FIBRE_AXIAL = {"name": "tube", "kind": "orthotropic", "E": [10e9, 10e9, 140e9],
               "nu": [0.4, 0.3 / 14, 0.3 / 14], "G": [10e9 / 2.8, 5e9, 5e9], "rho": 1600.0,
               "elements": "all"}
#: an axis along x that passes outside the box (every centroid has a radial direction)
AROUND_X = {"kind": "cylindrical", "axis": [2.0, 0.0, 0.0], "point": [0.0, -0.03, -0.04]}


def _relative(a, b) -> float:
    return abs(a - b).max() / abs(b).max()


def test_cylindrical_frame_equals_the_rectangular_where_they_coincide(tmp_path):
    """Fibres along the axis, isotropic across them: the law is the same in every frame
    with axis 3 along x, so the cylindrical system (a frame per element) gives the K of
    the rectangular frame {x: y, y: z} (axis 3 = x), to round-off (1e-14)."""
    cyl = build_fe_model(config_from_dict(raw_config(
        coordinate_systems={"wound": AROUND_X}, materials=[{**FIBRE_AXIAL, "axes": "wound"}])),
        tmp_path / "c")
    rect = build_fe_model(config_from_dict(raw_config(materials=[
        {**FIBRE_AXIAL, "axes": {"x": [0, 1, 0], "y": [0, 0, 1]}}])), tmp_path / "r")
    assert cyl.materials.D.shape[0] == 2 + cyl.space.body.n_tetrahedra
    assert set(cyl.materials.names[1:]) == {"tube"}
    assert _relative(cyl.K, rect.K) < 1e-14
    assert (cyl.M != rect.M).nnz == 0


def test_cylindrical_frame_leaves_an_isotropic_law_unchanged(tmp_path):
    E, nu = 69e9, 0.33
    G = E / (2 * (1 + nu))
    iso = build_fe_model(config_from_dict(raw_config(material={"E": E, "nu": nu,
                                                               "rho": 2700.0})), tmp_path / "i")
    cyl = build_fe_model(config_from_dict(raw_config(
        coordinate_systems={"wound": AROUND_X}, materials=[{
            "name": "o", "kind": "orthotropic", "E": [E] * 3, "nu": [nu] * 3, "G": [G] * 3,
            "rho": 2700.0, "axes": "wound", "elements": "all"}])), tmp_path / "c")
    assert _relative(cyl.K, iso.K) < 1e-14


def test_cylindrical_frame_differs_per_element(tmp_path):
    """Fibres along the hoop direction (axis 2): elements at different angles about the
    axis get different global laws, and the run through the file's /materials keeps
    them (one law per element)."""
    from pipeline.store.read import read_materials

    raw = raw_config(coordinate_systems={"wound": AROUND_X}, materials=[
        {**FIBRE_AXIAL, "E": [10e9, 140e9, 10e9], "nu": [0.3 / 14, 0.4, 0.3 / 14],
         "G": [5e9, 10e9 / 2.8, 5e9], "axes": "wound"}])
    fe = build_fe_model(config_from_dict(raw), tmp_path)
    D = fe.materials.element_D(np.arange(fe.space.body.n_tetrahedra))
    assert np.ptp(D[:, 1, 1]) > 1e9  # E_yy varies with the angle about x
    assert np.allclose(D[:, 0, 0], D[0, 0, 0])  # E_xx (axial) does not
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(raw))
    out = tmp_path / "c.h5"
    proc = subprocess.run([sys.executable, "-m", "pipeline", "run", str(path), "-o", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    stored = read_materials(out)
    np.testing.assert_array_equal(stored.stiffness[stored.element_material], D)


def test_cylindrical_round_trip_and_refusals(tmp_path):
    cfg = config_from_dict(raw_config(coordinate_systems={"wound": AROUND_X},
                                      materials=[{**FIBRE_AXIAL, "axes": "wound"}]))
    back = yaml.safe_load(config_to_yaml(cfg))
    assert back["coordinate_systems"]["wound"] == {"kind": "cylindrical",
                                                   "axis": [1.0, 0.0, 0.0],
                                                   "point": AROUND_X["point"]}
    assert config_from_dict(back) == cfg
    for system, key in (({"kind": "cylindrical", "point": [0, 0, 0]},
                         "coordinate_systems.s.axis"),
                        ({"kind": "cylindrical", "axis": [0, 0, 0], "point": [0, 0, 0]},
                         "coordinate_systems.s.axis"),
                        ({"kind": "cylindrical", "axis": [1, 0, 0], "point": [0, 0, 0],
                          "x": [1, 0, 0]}, "coordinate_systems.s.x"),
                        ({"kind": "spherical", "x": [1, 0, 0], "y": [0, 1, 0]},
                         "coordinate_systems.s.kind")):
        with pytest.raises(ConfigError) as exc:
            config_from_dict(raw_config(coordinate_systems={"s": system},
                                        materials=[{**FIBRE_AXIAL, "axes": "s"}]))
        assert exc.value.key == key, str(exc.value)


def test_a_centroid_on_the_cylinder_axis_is_refused():
    """No radial direction on the axis: refused naming the entry's axes key."""
    from pipeline.errors import RegionError
    from pipeline.fe.materials import cylindrical_frames

    points = np.array([[0.0, 0.1, 0.0], [0.5, 0.0, 0.0]])
    Q = cylindrical_frames(points[:1], (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), "k")
    np.testing.assert_allclose(Q[0], [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-15)
    with pytest.raises(RegionError) as exc:
        cylindrical_frames(points, (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), "materials[0].axes")
    assert "'materials[0].axes'" in str(exc.value) and "[0.5, 0.0, 0.0]" in str(exc.value)
