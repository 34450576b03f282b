"""The package's layering, checked by import-linter's contracts in pyproject.toml.

Layers, lowest first: _util, config, fe, solve, reduce, store, run, apps, cli. A module
imports only from its own layer or lower ones, and the file reader and the apps that only
read result files never import the FE stack (pipeline.fe, gmsh, scikit-fem, meshio), so a
downstream tool can load a model with h5py, numpy and python-control alone.

The second test proves the check can fail: it adds one forbidden import to a copy of the
package and expects the contract to break, naming the offending import.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from conftest import ROOT

LINT = Path(sys.executable).with_name("lint-imports")


def _lint(tree: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(tree))
    return subprocess.run([str(LINT), "--config", str(tree / "pyproject.toml"), "--no-cache"],
                          cwd=tree, env=env, capture_output=True, text=True, timeout=300)


def _copy(tmp_path: Path) -> Path:
    tree = tmp_path / "tree"
    shutil.copytree(ROOT / "pipeline", tree / "pipeline",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tree / "pyproject.toml")
    return tree


def test_the_package_keeps_its_layers():
    result = _lint(ROOT)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "0 broken" in result.stdout


def test_a_forbidden_import_breaks_the_contract(tmp_path):
    tree = _copy(tmp_path)
    # a lower layer (the FE stack) importing a higher one (an app)
    space = tree / "pipeline" / "fe" / "space.py"
    space.write_text(space.read_text() + "\nimport pipeline.apps.summary  # noqa\n")
    # the file reader importing the FE stack
    reader = tree / "pipeline" / "store" / "read.py"
    reader.write_text(reader.read_text() + "\nimport meshio  # noqa\n")
    result = _lint(tree)
    assert result.returncode != 0
    assert "pipeline.fe.space -> pipeline.apps.summary" in result.stdout
    assert "pipeline.store.read -> meshio" in result.stdout
