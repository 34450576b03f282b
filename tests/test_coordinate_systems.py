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
