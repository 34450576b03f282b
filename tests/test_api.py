"""The Python entry point :func:`pipeline.run_config`: a config as a path, a mapping or a
``Config`` runs as ``python -m pipeline run`` does, with the same errors and file."""

from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np
import pytest

import pipeline
from conftest import ROOT
from pipeline._util.yamlio import parse_yaml

CONFIG = ROOT / "configs" / "cantilever_inplane.yaml"
COARSE = ["mesh.size=0.02", "modes.count=4"]


def _datasets(path) -> dict:
    """Every dataset of an HDF5 file (run times and the checksum left out: they differ
    between any two runs)."""
    out = {}
    with h5py.File(path, "r") as h5:
        h5.visititems(lambda name, obj: out.__setitem__(name, obj[()])
                      if isinstance(obj, h5py.Dataset) else None)
        attrs = {k: v for k, v in h5.attrs.items() if "sha256" not in k and "created" not in k}
    return out, attrs


#: datasets that measure round-off: the relative residuals ||K x - w^2 M x|| / ||K x||
#: of converged modes (1e-11..1e-9 here) are sums of rounding errors, whose digits change
#: with MKL's thread count and summation order (10 % between a CLI process and a loaded
#: test worker); both files must hold converged modes: below the solver's tolerance
#: (1e-10 for block Lanczos at these sizes, times the pencil's conditioning margin)
ROUND_OFF = {"modes/residuals": 1e-8}


def _same_file(a, b) -> None:
    """Every dataset of two files equal to rtol 1e-9 (ROUND_OFF aside). The residual
    flexibility R (a difference of nearly equal terms, and D and B built from it) moves by
    1.6e-7 of itself between MKL on one thread and on two: the CLI child and this process
    must solve on the same count (the child inherits this process's environment)."""
    (da, attrs_a), (db, attrs_b) = _datasets(a), _datasets(b)
    assert sorted(da) == sorted(db)
    for name in da:
        x, y = da[name], db[name]
        if name in ROUND_OFF:
            assert np.shape(x) == np.shape(y), name
            assert np.all(np.abs(x) <= ROUND_OFF[name]), (name, x)
            assert np.all(np.abs(y) <= ROUND_OFF[name]), (name, y)
        elif isinstance(x, np.ndarray) and x.dtype.kind == "f":
            scale = float(np.nanmax(np.abs(x))) if np.isfinite(x).any() else 0.0
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12 * scale, equal_nan=True,
                                       err_msg=name)
        else:
            assert np.array_equal(x, y), name
    assert attrs_a.keys() == attrs_b.keys()


@pytest.fixture(scope="module")
def cli_file(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "cli.h5"
    args = [sys.executable, "-m", "pipeline", "-q", "run", str(CONFIG), "-o", str(out)]
    for item in COARSE:
        args += ["--set", item]
    proc = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return out


def test_path_form_writes_the_cli_file(cli_file, tmp_path):
    result = pipeline.run_config(CONFIG, output=tmp_path / "api.h5", overrides=COARSE)
    assert isinstance(result, pipeline.RunResult) and result.output == tmp_path / "api.h5"
    assert result.config.name == "cantilever_inplane" and result.frequencies_hz.size == 4
    _same_file(cli_file, result.output)


def test_mapping_and_config_forms_give_the_same_run(tmp_path):
    raw = parse_yaml(CONFIG.read_text(), 'config')
    from_dict = pipeline.run_config(raw, output=tmp_path / "dict.h5", overrides=COARSE)
    cfg = pipeline.api.resolve_config(CONFIG, COARSE)
    assert isinstance(cfg, pipeline.Config)
    from_config = pipeline.run_config(cfg, output=tmp_path / "config.h5")
    np.testing.assert_allclose(from_dict.frequencies_hz, from_config.frequencies_hz,
                               rtol=1e-9)
    assert from_dict.config.mesh == from_config.config.mesh
    # overrides apply to a Config too
    coarser = pipeline.api.resolve_config(cfg, ["modes.count=6"])
    assert coarser.modes.count == 6 and coarser.mesh == cfg.mesh


def _cli_error(*args) -> str:
    proc = subprocess.run([sys.executable, "-m", "pipeline", "run", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == pipeline.ConfigError.exit_code, proc.stderr
    return proc.stderr.strip().removeprefix("error: ")


def test_a_bad_key_is_the_cli_config_error(tmp_path):
    message = _cli_error(str(CONFIG), "--set", "materail.E=1")
    with pytest.raises(pipeline.ConfigError) as exc:
        pipeline.run_config(CONFIG, output=tmp_path / "x.h5", overrides=["materail.E=1"])
    assert str(exc.value) == message
    raw = parse_yaml(CONFIG.read_text(), 'config')
    raw["materail"] = {"E": 1}
    with pytest.raises(pipeline.ConfigError, match="config key 'materail' is not known"):
        pipeline.run_config(raw, output=tmp_path / "x.h5")
    with pytest.raises(pipeline.ConfigError, match="expected a YAML file path"):
        pipeline.run_config(42, output=tmp_path / "x.h5")
    assert not (tmp_path / "x.h5").exists()


def test_a_foreign_file_is_refused_before_any_work(tmp_path):
    foreign = tmp_path / "notes.h5"
    foreign.write_text("mine")
    with pytest.raises(pipeline.OutputError):
        pipeline.run_config(CONFIG, output=foreign, overrides=COARSE)
    assert foreign.read_text() == "mine"
    with pytest.raises(pipeline.OutputError):
        pipeline.run_config(CONFIG, output=CONFIG, overrides=COARSE, force=True)


def test_import_is_light_and_lists_the_api():
    code = ("import sys, pipeline; assert 'numpy' not in sys.modules; "
            "assert {'run_config', 'load_model', 'Config', 'RunResult'} <= set(pipeline.__all__)"
            "; assert all(hasattr(pipeline, n) for n in pipeline.__all__)")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=120)
