"""The package's layering, checked by import-linter's contracts in pyproject.toml.

Layers, lowest first: errors, _util, config, fe, solve, reduce, store, run, apps, cli. A module
imports only from its own layer or lower ones, and the file reader and the apps that only
read result files never import the FE stack (pipeline.fe, gmsh, scikit-fem, meshio), so a
downstream tool can load a model with h5py, numpy and python-control alone.

No package's modules or subpackages import each other in a cycle (import-linter's
acyclic_siblings contract, at every depth). Every top-level module sits in a layer
(the layers contract is exhaustive), so a new one must be placed.

The tests that edit a copy of the package prove each check can fail: one forbidden
import, or one import that closes a cycle, must break the contract and be named.
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


def test_an_import_cycle_breaks_the_acyclic_contract(tmp_path):
    tree = _copy(tmp_path)
    # the shared drawing code importing the pictures that use it
    drawing = tree / "pipeline" / "apps" / "mode_drawing.py"
    drawing.write_text(drawing.read_text() + "\nimport pipeline.apps.plots  # noqa\n")
    result = _lint(tree)
    assert result.returncode != 0
    assert "No cycles are allowed in pipeline.apps" in result.stdout
    assert "mode_drawing -> .plots" in result.stdout or "plots -> .mode_drawing" in result.stdout


def test_a_new_top_level_module_must_be_placed_in_a_layer(tmp_path):
    tree = _copy(tmp_path)
    (tree / "pipeline" / "helpers.py").write_text("X = 1\n")
    result = _lint(tree)
    assert result.returncode != 0
    assert "pipeline.helpers" in result.stdout
