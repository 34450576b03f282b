"""Exports of the connection-point, Craig-Bampton and lumped models (issue 20): ``--to mat``
no longer refuses files without ``/statespace``, and ``--to simscape`` writes the Reduced
Order Flexible Solid block's parameters, checked by GNU Octave.

Octave tolerances: Octave's eig on the same (K, M) as scipy's. Elastic frequencies: the
generalized symmetric eigenproblem gives each eigenvalue to ~eps * cond(M) * ||K|| relative
to the largest; the frequencies here span 400 Hz .. 15 kHz (lambda ratio ~1e3) and
cond(M) < 1e6, so 1e-7 relative is ~1e3 above round-off. Rigid-body frequencies are
sqrt(round-off): below sqrt(1e-9) * f_max (the rigid threshold RIGID_RTOL of simscape.py).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pipeline.apps.exports.simscape import RIGID_RTOL
from pipeline.cli.export import run_export
from pipeline.config import load_config
from pipeline.errors import FileFormatError
from pipeline.run import run_pipeline
from pipeline.store.read import load_model

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def connection_h5(tmp_path_factory) -> Path:
    """Connection-point and Craig-Bampton models only (no 'reduction': no /statespace)."""
    tmp = tmp_path_factory.mktemp("conn")
    cfg = load_config(ROOT / "configs" / "cantilever_connection.yaml",
                      ["mesh.size=0.02", "modes.count=6", "craig_bampton.modes=6"])
    return run_pipeline(cfg, tmp / "conn.h5", mesh_dir=tmp).output


def test_mat_exports_connection_and_craig_bampton_models(connection_h5, tmp_path):
    """Today's main refused this file ('holds modes only' / no /statespace)."""
    from scipy.io import loadmat

    data = loadmat(run_export(connection_h5, "mat", tmp_path / "conn.mat"))
    lm = load_model(connection_h5)
    assert lm.plant is None and lm.connections and lm.craig_bampton is not None
    for name, ss in lm.connections.items():
        for k in "ABCD":
            np.testing.assert_array_equal(data[f"{k}_conn_{name}"], getattr(ss, k))
        assert [str(c[0]) for c in data[f"input_names_conn_{name}"].ravel()] == \
            list(ss.input_names)
        assert [str(c[0]) for c in data[f"output_units_conn_{name}"].ravel()] == \
            list(ss.output_units)
    np.testing.assert_array_equal(data["M_cb"], lm.craig_bampton.M)
    np.testing.assert_array_equal(data["K_cb"], lm.craig_bampton.K)
    assert [str(c[0]) for c in data["cb_coordinate_names"].ravel()][:6] == [
        "root.x", "root.y", "root.z", "root.rx", "root.ry", "root.rz"]
    assert data["cb_interface_points"].shape == (2, 3)


def test_mat_exports_a_lumped_chain_without_a_modal_model(tmp_path):
    from scipy.io import loadmat

    cfg = load_config(ROOT / "configs" / "cantilever.yaml",
                      ["mesh.size=0.025", "modes.count=3", "reduction=null", "filter=null"])
    h5 = run_pipeline(cfg, tmp_path / "lumped.h5", mesh_dir=tmp_path).output
    data = loadmat(run_export(h5, "mat", tmp_path / "lumped.mat"))
    lumped = load_model(h5).lumped
    assert "A" not in data
    for k in "ABCD":
        np.testing.assert_array_equal(data[f"{k}_lumped"], getattr(lumped, k))


def test_simscape_variables_are_what_the_block_needs(connection_h5, tmp_path):
    from scipy.io import loadmat
    import scipy.linalg as sla

    out = run_export(connection_h5, "simscape")
    assert out.name == "conn_simscape.mat" and out.with_suffix(".m").exists()
    d = loadmat(out)
    cb = load_model(connection_h5).craig_bampton
    K, M, C = d["K"], d["M"], d["C"]
    n = 6 * d["origins"].shape[0] + int(d["n_modes"].item())
    assert K.shape == M.shape == C.shape == (n, n) == cb.K.shape
    for X in (K, M, C):
        np.testing.assert_array_equal(X, X.T)
    np.testing.assert_allclose(K, cb.K, rtol=0, atol=1e-15 * np.abs(cb.K).max())
    np.testing.assert_allclose(d["origins"], [[0.0, 0.01, 0.025], [0.5, 0.01, 0.025]])
    # C is modal damping with the config's ratio 0.02 on every elastic free mode
    w2, phi = sla.eigh(K, M)
    elastic = w2 > RIGID_RTOL * w2.max()
    assert np.count_nonzero(~elastic) == 6
    modal = phi[:, elastic].T @ C @ phi[:, elastic]
    expected = 2 * 0.02 * np.sqrt(w2[elastic])
    np.testing.assert_allclose(np.diag(modal), expected, rtol=1e-8)
    assert np.abs(modal - np.diag(np.diag(modal))).max() <= 1e-8 * expected.max()
    assert d["damping_ratio"].item() == 0.02


def test_simscape_refuses_a_file_without_craig_bampton_naming_the_config_key(tmp_path):
    cfg = load_config(ROOT / "configs" / "cantilever.yaml",
                      ["mesh.size=0.025", "modes.count=4", "lumped=null"])
    h5 = run_pipeline(cfg, tmp_path / "c.h5", mesh_dir=tmp_path).output
    with pytest.raises(FileFormatError, match="'craig_bampton' section"):
        run_export(h5, "simscape", tmp_path / "x.mat")
    assert not (tmp_path / "x.mat").exists()


def _octave():
    return shutil.which("octave-cli")


@pytest.mark.skipif(_octave() is None, reason="GNU Octave (octave-cli) is not installed: "
                    "apt-get install -y octave")
def test_octave_runs_the_script_and_reproduces_the_craig_bampton_frequencies(connection_h5,
                                                                              tmp_path):
    out = run_export(connection_h5, "simscape", tmp_path / "body.mat")
    script = f"""
run('{out.with_suffix(".m")}');
f_free = sqrt(abs(eig(rofs_K, rofs_M))) / (2 * pi);
nb = 6 * size(rofs_origins, 1);
f_fixed = sqrt(abs(eig(rofs_K(nb+1:end, nb+1:end), rofs_M(nb+1:end, nb+1:end)))) / (2 * pi);
printf('FREE %s\\n', sprintf('%.17g ', sort(f_free)));
printf('FIXED %s\\n', sprintf('%.17g ', sort(f_fixed)));
"""
    proc = subprocess.run([_octave(), "--quiet", "--eval", script], capture_output=True,
                          text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "Reduced Order Flexible Solid parameters ready" in proc.stdout
    lines = {ln.split()[0]: np.array([float(v) for v in ln.split()[1:]])
             for ln in proc.stdout.splitlines() if ln.startswith(("FREE", "FIXED"))}
    cb = load_model(connection_h5).craig_bampton
    np.testing.assert_allclose(lines["FIXED"], cb.fixed_interface_frequencies_hz, rtol=1e-7)
    import h5py

    with h5py.File(connection_h5, "r") as h5:
        free = h5["craig_bampton/free_frequencies_hz"][()]
    assert np.all(lines["FREE"][:6] <= np.sqrt(RIGID_RTOL) * free.max())
    np.testing.assert_allclose(lines["FREE"][6:], free[6:], rtol=1e-7)


def test_exudyn_export_says_when_its_statics_are_truncated(connection_h5, tmp_path):
    """A body without input ports gets no static modes: metaData/statics says so, and
    which basis it is; the --basis option reaches the exporter."""
    import argparse

    import h5py

    from pipeline.cli.export import add_export_parser

    parser = argparse.ArgumentParser()
    add_export_parser(parser.add_subparsers(dest="command"))
    for basis, start in (("modes", "truncated: the config has no input ports"),
                         ("craig_bampton", "exact for forces and moments at the other")):
        out = tmp_path / f"{basis}.hdf5"
        args = parser.parse_args(["export", str(connection_h5), "--to", "exudyn",
                                  "--basis", basis, "-o", str(out)])
        assert args.func(args) == 0
        with h5py.File(out, "r") as h5:
            assert h5["metaData/statics"][()].decode().startswith(start)
            assert h5["metaData/matrices"][()].decode() == "M and K stored by the run (/fe)"


def test_exudyn_export_of_a_config_with_region_selectors(tmp_path):
    """The stored config of a body with a 'regions:' selector (here a sphere around the
    tip, carrying the input port) does not parse back as written (a sphere selector is
    stored with a 'tolerance'), and a CAD geometry's file may be gone: the export takes
    only the material and ports from it and the regions from the stored mesh."""
    import h5py

    cfg = load_config(ROOT / "configs" / "cantilever.yaml", [
        "mesh.size=0.025", "modes.count=4", "lumped=null",
        "regions={load_patch: {kind: sphere, point: [0.5, 0.01, 0.025], radius: 0.03}}",
        "ports.inputs[0].region=load_patch"])
    h5 = run_pipeline(cfg, tmp_path / "patch.h5", mesh_dir=tmp_path).output
    out = run_export(h5, "exudyn", tmp_path / "patch.hdf5")
    with h5py.File(out, "r") as f:
        assert f["metaData/statics"][()].decode().startswith("exact")
        assert "re-assembled" in f["metaData/matrices"][()].decode()
        assert f["modeBasis/matrix"].shape[1] == 5   # 4 modes + the port's static mode
