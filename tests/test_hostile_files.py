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


def test_a_piped_config_is_bounded_like_a_file(tmp_path):
    """An endless writer is refused at the size limit of files (4 MiB), in one line."""
    proc = _sh(f"yes '# padding' | {PY} -m pipeline run /dev/stdin -o x.h5", tmp_path)
    assert proc.returncode == ConfigError.exit_code, proc.stderr[-2000:]
    assert "larger than 4 MiB" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.h5").exists()
