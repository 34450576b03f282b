"""Config loading: strict validation with the key path, the value and the expectation."""

from __future__ import annotations

import copy

import pytest
import yaml

from conftest import ROOT
from pipeline.config import apply_overrides, config_from_dict, config_to_yaml, load_config
from pipeline.errors import ConfigError

BASE = yaml.safe_load((ROOT / "configs/cantilever.yaml").read_text().replace("69.0e9", "69.0e+9"))


def with_change(path: str, value):
    raw = copy.deepcopy(BASE)
    return apply_overrides(raw, [f"{path}={yaml.safe_dump(value, default_flow_style=True).strip()}"
                                 .replace("\n...", "")])


@pytest.mark.parametrize("name", ["cantilever", "cantilever_inplane"])
def test_shipped_configs_load_and_round_trip(name):
    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
    assert cfg.material.E == 69.0e9 and cfg.geometry.length == 0.5
    assert cfg.constraints.in_plane == (name == "cantilever_inplane")
    again = config_from_dict(yaml.safe_load(config_to_yaml(cfg)))
    assert again == config_from_dict(yaml.safe_load(config_to_yaml(again)))
    assert config_to_yaml(again) == config_to_yaml(cfg)


BODY_CONFIGS = sorted(p.name for p in (ROOT / "configs").glob("*.yaml")
                      if not p.name.startswith("batch_"))


@pytest.mark.parametrize("name", BODY_CONFIGS)
def test_every_shipped_config_round_trips(name):
    """The config stored in a result file must read back: every selector kind included."""
    cfg = load_config(ROOT / "configs" / name)
    again = config_from_dict(yaml.safe_load(config_to_yaml(cfg)))
    assert again.regions == cfg.regions and again.ports == cfg.ports
    assert config_to_yaml(again) == config_to_yaml(cfg)


def test_yaml12_floats_are_numbers(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text((ROOT / "configs/cantilever.yaml").read_text())
    assert "E: 69.0e9" in path.read_text()
    assert load_config(path).material.E == 69.0e9


def test_overrides_by_dotted_path():
    cfg = load_config(ROOT / "configs/cantilever.yaml",
                      ["mesh.size=0.004", "supports[0].fix=[y]", "modes.count=12",
                       "constraints.in_plane=true"])
    assert cfg.mesh.size == 0.004 and cfg.supports[0].fix == ("y",)
    assert cfg.modes.count == 12 and cfg.constraints.in_plane


@pytest.mark.parametrize("path, value, message", [
    ("material.E", -1.0, r"'material.E': got -1.0, expected a number in \(0, 1e\+13\]"),
    ("material.E", 0, r"'material.E': got 0(\.0)?, expected a number in \(0, "),
    ("material.nu", 0.5, r"'material.nu': got 0.5, expected a number in \(-1, 0.5\)"),
    ("material.nu", -1.0, r"'material.nu'.*\(-1, 0.5\)"),
    ("material.rho", 0.0, r"'material.rho': got 0.0, expected a number in \(0, "),
    ("material.E", "stiff", r"'material.E': got 'stiff', expected a number"),
    ("material.E", float("nan"), r"'material.E'.*expected a finite number"),
    ("mesh.size", 2.0, r"'mesh.size': got 2.0, expected a size no larger than the body's "
                       r"largest dimension \(0.5 m\)"),
    ("mesh.size", -0.1, r"'mesh.size'.*> 0"),
    ("mesh.order", 3, r"'mesh.order': got 3, expected one of 1 \| 2"),
    ("modes.count", 0, r"'modes.count': got 0, expected an integer in \[1, 500\]"),
    ("modes.count", 2.5, r"'modes.count': got 2.5, expected an integer"),
    ("modes.solver", "magic", r"'modes.solver'.*one of auto"),
    ("geometry.kind", "sphere", r"'geometry.kind': got 'sphere'"),
    ("geometry.length", True, r"'geometry.length': got True, expected a number"),
    ("supports[0].region", "nowhere", r"'supports\[0\].region': got 'nowhere'"),
    ("supports[0].fix", ["w"], r"'supports\[0\].fix'"),
    ("constraints.in_plane", "yes", r"'constraints.in_plane': got 'yes', expected true or false"),
    ("reduction.modes", 11, r"'reduction.modes': got 11, expected at most modes.count = 10"),
    ("damping.ratio", 1.5, r"'damping.ratio': got 1.5"),
    ("filter.cutoff_hz", 0, r"'filter.cutoff_hz': got 0"),
    ("lumped.elements", 0, r"'lumped.elements': got 0"),
    ("name", "a b", r"'name': got 'a b'"),
])
def test_bad_values_are_refused_with_key_value_and_expectation(path, value, message):
    with pytest.raises(ConfigError, match=message):
        config_from_dict(with_change(path, value))


@pytest.mark.parametrize("path, message", [
    ("colour", r"config key 'colour' is not known; expected one of: name, geometry"),
    ("material.youngs", r"config key 'material.youngs' is not known; expected one of: E, nu, rho"),
    ("mesh.sise", r"config key 'mesh.sise' is not known"),
])
def test_unknown_keys_are_refused(path, message):
    with pytest.raises(ConfigError, match=message):
        config_from_dict(with_change(path, 1))


def test_missing_required_key():
    raw = copy.deepcopy(BASE)
    del raw["material"]["rho"]
    with pytest.raises(ConfigError, match=r"'material.rho' is missing"):
        config_from_dict(raw)


def test_file_errors_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match=r"config file '.*nope.yaml': not found"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\ngeometry: {kind: box, length: [1\n")
    with pytest.raises(ConfigError, match=r"bad.yaml': not valid YAML \(line"):
        load_config(bad)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    with pytest.raises(ConfigError, match="is empty"):
        load_config(empty)


def test_yaml_tags_never_construct_objects(tmp_path):
    evil = tmp_path / "evil.yaml"
    evil.write_text("name: !!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(evil)


def test_override_errors():
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        apply_overrides(BASE, ["mesh.size"])
    with pytest.raises(ConfigError, match="out of range"):
        apply_overrides(BASE, ["supports[3].region=tip"])


def test_a_value_with_repeated_spaces_keeps_them_in_the_one_line_message():
    """The one-line message collapses whitespace; a string value whose spaces matter
    (two spaces where one was meant) shows them escaped, so the user sees what was read."""
    raw = copy.deepcopy(BASE)
    raw.setdefault("modes", {})["method"] = "multi  grid"
    with pytest.raises(ConfigError) as err:
        config_from_dict(raw)
    assert "multi\\x20\\x20grid" in str(err.value)
    raw["modes"]["method"] = "multi grid"
    with pytest.raises(ConfigError) as err:
        config_from_dict(raw)
    assert "'multi grid'" in str(err.value)
