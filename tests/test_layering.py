"""The package's layering, checked by import-linter's contracts in pyproject.toml.

Layers, lowest first: errors, _util, config, fe, solve, reduce, store, run, apps, cli. A module
imports only from its own layer or lower ones, and the file reader and the apps that only
read result files never import the FE stack (pipeline.fe, gmsh, scikit-fem, meshio), so a
downstream tool can load a model with h5py, numpy and python-control alone.

No package's modules or subpackages import each other in a cycle (import-linter's
acyclic_siblings contract, at every depth), and no module imports itself through others
(grimp's import graph, module by module: this also sees a package's ``__init__`` and
its own modules importing each other, which the contract, comparing siblings, does not). Every top-level module sits in a layer
(the layers contract is exhaustive), so a new one must be placed.

The tests that edit a copy of the package prove each check can fail: one forbidden
import, or one import that closes a cycle, must break the contract and be named.
"""

from __future__ import annotations

import json
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


def _append(tree: Path, module: str, line: str) -> None:
    """Add ``line`` at the end of ``module`` (a path under the copy's package folder)."""
    path = tree / "pipeline" / module
    path.write_text(path.read_text() + f"\n{line}  # noqa\n")


def test_the_package_keeps_its_layers():
    result = _lint(ROOT)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "0 broken" in result.stdout


def test_a_forbidden_import_breaks_the_contract(tmp_path):
    tree = _copy(tmp_path)
    # a lower layer (the FE stack) importing a higher one (an app)
    _append(tree, "fe/space.py", "import pipeline.apps.summary")
    # the file reader importing the FE stack
    _append(tree, "store/read.py", "import meshio")
    result = _lint(tree)
    assert result.returncode != 0
    assert "pipeline.fe.space -> pipeline.apps.summary" in result.stdout
    assert "pipeline.store.read -> meshio" in result.stdout


def test_an_import_cycle_breaks_the_acyclic_contract(tmp_path):
    tree = _copy(tmp_path)
    # the shared drawing code importing the pictures that use it
    _append(tree, "apps/mode_drawing.py", "import pipeline.apps.plots")
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


#: Imports (importer, imported) allowed to close a module-level cycle, each with its
#: reason in a comment; none today. The test fails on an entry that no longer exists.
KNOWN_CYCLE_IMPORTS: set[tuple[str, str]] = set()

_CYCLES = """
import json, sys
import grimp

graph = grimp.build_graph("pipeline", cache_dir=None)
ignored = [tuple(pair) for pair in json.loads(sys.argv[1])]
present = [pair for pair in ignored if graph.direct_import_exists(importer=pair[0],
                                                                  imported=pair[1])]
for importer, imported in present:
    graph.remove_import(importer=importer, imported=imported)
edges = {m: sorted(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
index, low, stack, on_stack, cycles = {}, {}, [], set(), []


def visit(root):  # Tarjan's strongly connected components, without recursion
    work = [(root, iter(edges[root]))]
    index[root] = low[root] = len(index)
    stack.append(root)
    on_stack.add(root)
    while work:
        node, children = work[-1]
        child = next(children, None)
        if child is not None:
            if child not in index:
                index[child] = low[child] = len(index)
                stack.append(child)
                on_stack.add(child)
                work.append((child, iter(edges[child])))
            elif child in on_stack:
                low[node] = min(low[node], index[child])
            continue
        work.pop()
        if work:
            low[work[-1][0]] = min(low[work[-1][0]], low[node])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))


for module in sorted(edges):
    if module not in index:
        visit(module)
print(json.dumps({"cycles": sorted(cycles), "present": present}))
"""


def _module_cycles(tree: Path, ignored=KNOWN_CYCLE_IMPORTS) -> dict:
    """The import cycles of the package under ``tree`` (module by module, ``ignored``
    imports left out) and which of the ``ignored`` imports exist."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    result = subprocess.run([sys.executable, "-c", _CYCLES, json.dumps(sorted(ignored))],
                            cwd=tree, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout)


def test_no_module_imports_itself_through_others():
    found = _module_cycles(ROOT)
    assert found["cycles"] == [], f"import cycles: {found['cycles']}"
    gone = KNOWN_CYCLE_IMPORTS - {tuple(pair) for pair in found["present"]}
    assert not gone, f"no longer imported, remove from KNOWN_CYCLE_IMPORTS: {sorted(gone)}"


def test_a_package_and_its_module_importing_each_other_is_a_cycle(tmp_path):
    tree = _copy(tmp_path)
    # the FE package's __init__ importing a module that imports the package back
    _append(tree, "fe/__init__.py", "from pipeline.fe import kernels")
    _append(tree, "fe/kernels.py", "import pipeline.fe")
    assert _module_cycles(tree)["cycles"] == [["pipeline.fe", "pipeline.fe.kernels"]]
