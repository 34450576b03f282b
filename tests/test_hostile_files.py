"""Hostile inputs end to end (issue 35, section 3): configs that come through a pipe,
and result files that pass the checksum (re-signed) but not physics.

Every case drives the command line, as a user would: a config piped in runs like the
file it came from; a re-signed file with cells past the node table, an unstable A, a
negative mass or frequency, a non-symmetric or indefinite matrix is refused by every
consumer with one line on stderr, exit code 7 and nothing written."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from pipeline.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
PY = shlex.quote(sys.executable)


def _sh(script: str, cwd: Path) -> subprocess.CompletedProcess:
    """``script`` under bash (process substitution needs it), this tree on PYTHONPATH."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(["bash", "-c", script], cwd=cwd, capture_output=True, text=True,
                          timeout=180, env=env)


# --------------------------------------------------------------------------- pipes
@pytest.mark.parametrize("how", ["process_substitution", "stdin"])
def test_config_through_a_pipe_runs_like_the_file(tmp_path, how):
    """``run <(sed ... cfg.yaml)`` and ``sed ... | run /dev/stdin`` give the same model as
    the file: the frequencies of the two results agree to the last bit."""
    cfg = shlex.quote(str(ROOT / "configs/cantilever.yaml"))
    edit = f"sed 's/size: 0.005/size: 0.02/' {cfg}"
    out = tmp_path / "piped.h5"
    run = f"{PY} -m pipeline -q run"
    script = (f"{run} <({edit}) -o piped.h5 --mesh-dir m" if how == "process_substitution"
              else f"{edit} | {run} /dev/stdin -o piped.h5 --mesh-dir m")
    proc = _sh(script, tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    ref = _sh(f"{run} {cfg} --set mesh.size=0.02 -o ref.h5 --mesh-dir m", tmp_path)
    assert ref.returncode == 0, ref.stderr[-2000:]
    with h5py.File(out) as a, h5py.File(tmp_path / "ref.h5") as b:
        np.testing.assert_array_equal(a["modes/frequencies_hz"][()],
                                      b["modes/frequencies_hz"][()])


def test_relative_paths_in_a_piped_config_resolve_against_the_current_directory(tmp_path):
    """geometry.path 'body.msh' in a piped config is looked for in the current directory
    (the pipe's own folder, /dev/fd, holds no input files): the error names that place."""
    proc = _sh(f"{PY} -m pipeline run <(printf 'name: x\\ngeometry: {{kind: mesh, path: "
               "body.msh}\\nmesh: {size: 0.01}\\nmaterial: {E: 1.0e9, nu: 0.3, rho: 1000}\\n')"
               " -o x.h5", tmp_path)
    assert proc.returncode == ConfigError.exit_code, proc.stderr[-2000:]
    line = proc.stderr.strip()
    assert len(line.splitlines()) == 1 and "geometry.path" in line, line
    assert "looked for 'body.msh'" in line and "/dev/fd/body.msh" not in line, line
    assert not (tmp_path / "x.h5").exists()


def test_scenario_and_batch_files_through_a_pipe(tmp_path):
    """A scenario file for simulate and a batch file (its cases listed) through process
    substitution, read once (the command's destination check reads it first)."""
    cfg = shlex.quote(str(ROOT / "configs/cantilever.yaml"))
    proc = _sh(f"{PY} -m pipeline -q run {cfg} --set mesh.size=0.02 --set mesh.order=1 "
               "--set lumped=null -o m.h5 --mesh-dir m && "
               f"{PY} -m pipeline -q simulate m.h5 <(printf 'kind: step_load\nforce: 1\n"
               "t_on: 0\nduration: 0.01\noutput_rate: 2000\n') -o sim.h5 && "
               f"{PY} -m pipeline batch --dry-run <(printf 'batch:\n  name: piped\n  base: "
               f"{ROOT / 'configs/cantilever.yaml'}\n  cases:\n    - label: one\n      "
               "set: {material.E: 70.0e9}\n')", tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "sim.h5").is_file()
    assert "batch 'piped'" in proc.stdout and "1 valid cases" in proc.stdout, proc.stdout


def test_dev_and_proc_paths_count_as_streams(tmp_path):
    """``run /dev/stdin < cfg.yaml`` gives a regular file under /dev: still no folder of
    its own for relative paths; a config file in a folder keeps its folder."""
    from pipeline._util.yamlio import is_stream

    cfg = tmp_path / "c.yaml"
    cfg.write_text("name: x\n")
    assert is_stream("/dev/stdin") and is_stream("/proc/self/fd/0")
    assert not is_stream(cfg) and not is_stream(tmp_path / "missing.yaml")


def test_a_piped_config_is_bounded_like_a_file(tmp_path):
    """An endless writer is refused at the size limit of files (4 MiB), in one line."""
    proc = _sh(f"yes '# padding' | {PY} -m pipeline run /dev/stdin -o x.h5", tmp_path)
    assert proc.returncode == ConfigError.exit_code, proc.stderr[-2000:]
    assert "larger than 4 MiB" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.h5").exists()


# --------------------------------------------------------------------------- re-signed files
from pipeline import load_model  # noqa: E402
from pipeline.apps.summary import summarize  # noqa: E402
from pipeline.config import load_config  # noqa: E402
from pipeline.errors import FileFormatError  # noqa: E402
from pipeline.run import run_pipeline  # noqa: E402
from pipeline.store import layout as L  # noqa: E402
from pipeline.store.h5file import sign  # noqa: E402
from pipeline.store.physics import stability_tolerance  # noqa: E402
from pipeline.store.read import read_fe_model, read_model_file, read_stored_mesh  # noqa: E402


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("physics")
    cfg = load_config(ROOT / "configs/cantilever.yaml", ["mesh.size=0.02", "mesh.order=1"])
    return run_pipeline(cfg, tmp / "good.h5", mesh_dir=tmp).output


def _replace(h5, key: str, value) -> None:
    attrs = dict(h5[key].attrs)
    del h5[key]
    h5[key] = value
    h5[key].attrs.update(attrs)


def _cells_past(h5):
    key = f"{L.MESH.cells}/{list(h5[L.MESH.cells])[0]}"
    c = h5[key][()]
    c[0, 0] = h5[L.MESH.points].shape[0]  # one past the last node
    _replace(h5, key, c)


def _region_past(h5):
    c = h5[L.region("tip")][()]
    c[-1, -1] = -1
    _replace(h5, L.region("tip"), c)


def _unstable(h5):
    """The first mode's damping term flipped: x'' - 2 zeta omega x' + omega^2 x = 0 grows."""
    A = h5[L.STATESPACE.A][()]
    n = A.shape[0] // 2
    A[n, n] = -A[n, n]
    _replace(h5, L.STATESPACE.A, A)


def _negative_mass(h5):
    _replace(h5, L.BODY.mass, -h5[L.BODY.mass][()])


def _negative_frequency(h5):
    f = h5[L.STATESPACE.frequencies_hz][()]
    f[0] = -f[0]
    _replace(h5, L.STATESPACE.frequencies_hz, f)


def _negative_damping(h5):
    z = h5[L.STATESPACE.damping_ratios][()]
    z[:] = -0.02
    _replace(h5, L.STATESPACE.damping_ratios, z)


def _asymmetric_inertia(h5):
    J = h5[L.BODY.inertia][()]
    J[0, 1] += 1e-3 * np.abs(J).max()
    _replace(h5, L.BODY.inertia, J)


def _indefinite_mass_matrix(h5):
    M = h5[L.BODY.rigid_mass_matrix][()]
    M[0, 0] = -M[0, 0]
    _replace(h5, L.BODY.rigid_mass_matrix, M)


def _modes_shape(h5):
    _replace(h5, L.MODES.omega2, h5[L.MODES.omega2][()][:-1])


EDITS = {  # edit, what the one line says
    "cells_past_nodes": (_cells_past, r"mesh/cells/tetra refers to nodes 0\.\.\d+, expected "
                                      r"nodes inside"),
    "region_past_nodes": (_region_past, r"mesh/regions/tip refers to nodes -1\.\."),
    "unstable_A": (_unstable, r"statespace/A has an eigenvalue with real part \+"),
    "negative_mass": (_negative_mass, r"body/mass holds 1 negative value"),
    "negative_frequency": (_negative_frequency, r"statespace/frequencies_hz holds 1 negative"),
    "negative_damping": (_negative_damping, r"statespace/damping_ratios holds 4 negative"),
    "asymmetric_inertia": (_asymmetric_inertia, r"body/inertia is not symmetric"),
    "indefinite_mass_matrix": (_indefinite_mass_matrix, r"body/rigid_mass_matrix is indefinite"),
    "inconsistent_shapes": (_modes_shape, r"modes/omega2 has shape \(9,\), expected \(10,\)"),
}


def _resigned(good: Path, tmp_path: Path, edit) -> Path:
    bad = tmp_path / "bad.h5"
    bad.write_bytes(good.read_bytes())
    with h5py.File(bad, "a") as h5:
        edit(h5)
        sign(h5)
    return bad


@pytest.mark.parametrize("name", list(EDITS))
def test_resigned_file_that_fails_physics_is_refused_by_every_reader(good, tmp_path, name):
    """Every reader of pipeline.store.read refuses the file with one line naming the
    dataset (every command reads through them: the next test drives each command)."""
    import re

    edit, pattern = EDITS[name]
    bad = _resigned(good, tmp_path, edit)
    for reader in (load_model, summarize, read_stored_mesh, read_fe_model, read_model_file):
        with pytest.raises(FileFormatError) as info:
            reader(bad)
        msg = str(info.value)
        assert re.search(pattern, msg) and str(bad) in msg and "\n" not in msg, (reader, msg)


@pytest.mark.parametrize("command", [
    ("inspect", "{f}"),
    ("plot", "{f}", "-o", "{out}"),
    ("export", "{f}", "--to", "vtu", "-o", "{out}.vtu"),
    ("export", "{f}", "--to", "xdmf", "-o", "{out}.xdmf"),
    ("export", "{f}", "--to", "mat", "-o", "{out}.mat"),
    ("export", "{f}", "--to", "json", "-o", "{out}.json"),
    ("export", "{f}", "--to", "fmu", "-o", "{out}.fmu"),
    ("export", "{f}", "--to", "exudyn", "-o", "{out}.hdf5"),
    ("simulate", "{f}", ROOT / "configs/scenarios/step_load.yaml", "-o", "{out}.h5"),
    ("export", "{f}", "--to", "sid", "-o", "{out}.SID_FEM"),
], ids=["inspect", "plot", "vtu", "xdmf", "mat", "json", "fmu", "exudyn", "simulate", "sid"])
def test_unstable_model_is_refused_by_every_consumer(good, tmp_path, command):
    """An unstable A (a passive body cannot gain energy) through every command: one line,
    exit code 7, nothing written."""
    bad = _resigned(good, tmp_path, _unstable)
    out = tmp_path / "out"
    out.mkdir()
    proc = subprocess.run([sys.executable, "-m", "pipeline",
                           *(str(c).format(f=bad, out=out / "x") for c in command)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == FileFormatError.exit_code, proc.stderr[-2000:]
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr[-2000:]
    assert "statespace/A has an eigenvalue with real part" in proc.stderr
    assert list(out.iterdir()) == []


def test_free_body_rigid_modes_pass_the_stability_check(tmp_path):
    """A free body's undamped rigid modes are 2x2 Jordan blocks at 0: LAPACK puts their
    eigenvalues at +-sqrt(n eps ||A||), inside the tolerance; the file loads."""
    import scipy.linalg

    cfg = load_config(ROOT / "configs/cantilever.yaml", [
        "mesh.size=0.02", "mesh.order=1", "supports=[]", "lumped=null",
        "reduction.static_correction=none", "reduction.modes=8", "damping.ratio=0"])
    out = run_pipeline(cfg, tmp_path / "free.h5", mesh_dir=tmp_path).output
    models = load_model(out)
    for model in (models.plant, models.filtered):
        A = model.A
        worst = scipy.linalg.eigvals(A).real.max()
        assert worst <= stability_tolerance(A), (model.label, worst, stability_tolerance(A))
        assert stability_tolerance(A) < 0.1  # 1/s: a doubling time of over 7 s


@pytest.fixture(scope="module")
def with_fe(tmp_path_factory) -> Path:
    """A file with /fe (sparse M and K), a Craig-Bampton model and connection models."""
    tmp = tmp_path_factory.mktemp("fe")
    cfg = load_config(ROOT / "configs/cantilever_connection.yaml",
                      ["mesh.size=0.02", "mesh.order=1"])
    return run_pipeline(cfg, tmp / "fe.h5", mesh_dir=tmp).output


def _negative_fe_mass(h5):
    key = L.csr_group(L.FE.mass_matrix).data
    _replace(h5, key, -h5[key][()])


def _indefinite_craig_bampton_K(h5):
    K = h5[L.CRAIG_BAMPTON.K][()]
    K[-1, -1] = -abs(K).max()
    _replace(h5, L.CRAIG_BAMPTON.K, K)


@pytest.mark.parametrize("edit, pattern", [
    (_negative_fe_mass, r"fe/mass_matrix has \d+ diagonal entr\(ies\) <= 0"),
    (_indefinite_craig_bampton_K, r"craig_bampton/K is indefinite"),
], ids=["negative_fe_mass", "indefinite_craig_bampton_K"])
def test_resigned_fe_and_craig_bampton_matrices_are_checked(with_fe, tmp_path, edit, pattern):
    """The honest file (free-body rigid modes, connection models, FFRF invariants) loads;
    an edited /fe mass matrix or Craig-Bampton stiffness is refused by every reader."""
    import re

    load_model(with_fe)
    read_fe_model(with_fe)
    bad = _resigned(with_fe, tmp_path, edit)
    for reader in (load_model, summarize, read_fe_model):
        with pytest.raises(FileFormatError) as info:
            reader(bad)
        assert re.search(pattern, str(info.value)), str(info.value)


# --------------------------------------------------------------------------- user mesh files
@pytest.mark.parametrize("damage", ["index_past_nodes", "nan_coordinate"])
def test_damaged_user_mesh_file_is_refused_in_one_line(good, tmp_path, damage):
    """A mesh file whose cells index past its node table, or whose used node has a NaN
    coordinate (on main: an IndexError traceback): exit code 3, one line naming the file,
    nothing written."""
    import meshio

    from pipeline.errors import MeshError
    from pipeline.store.read import read_stored_mesh

    stored = read_stored_mesh(good)
    points, tets = stored.points.copy(), stored.cells[:, :4].copy()
    if damage == "index_past_nodes":
        tets[0, 0] = points.shape[0] + 3
    else:
        points[tets[0, 0]] = [np.nan, 0.0, 0.0]
    mesh = tmp_path / "body.vtu"
    meshio.write(mesh, meshio.Mesh(points, [("tetra", tets)]))
    out = tmp_path / "out"
    out.mkdir()
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", "-q", "run", str(ROOT / "configs/cantilever.yaml"),
         "--set", f"geometry={{kind: mesh, path: {mesh}}}", "--set", "lumped=null",
         "--set", "supports=[]", "--set", "ports={}", "--set", "reduction=null",
         "--set", "mesh={order: 2}", "-o", str(out / "x.h5"), "--mesh-dir", str(out / "m")],
        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == MeshError.exit_code, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"mesh file '{mesh}'" in lines[0], proc.stderr[-2000:]
    assert [p for p in out.rglob("*") if not p.is_dir()] == []
