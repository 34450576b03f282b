"""The HDF5 layout is named once (pipeline/store/layout.py), agrees with its document
(docs/hdf5-format.md), and nothing outside pipeline/store spells a path of it.

- no string literal in pipeline/ outside pipeline/store is a path of the layout;
- every dataset and attribute the layout names is documented, and every dataset the
  doc's tables list is in the layout, section by section;
- a file the pipeline writes holds every dataset the layout (and so the doc) promises for
  each group it has, and nothing the layout does not name.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import h5py
import pytest

from pipeline.config import load_config
from pipeline.run import run_pipeline
from pipeline.store import layout as L

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "hdf5-format.md"

#: group names that mean nothing else in the code, so a bare literal of one is a path
UNAMBIGUOUS = (L.STATESPACE.path, L.STATESPACE_FILTERED.path, L.STRESS_MODES.path)
#: the first component of every path of the layout (model files and simulation results)
TOP = sorted({g.path.split("/")[0] for g in L.GROUPS} | {L.RESULT_SUMMARY.path})


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                out.add(id(body[0].value))
    return out


def _is_path(text: str) -> bool:
    if not text or any(c.isspace() for c in text):
        return False
    if text.strip("/") in UNAMBIGUOUS:
        return True
    head, sep, _ = text.lstrip("/").partition("/")
    return bool(sep) and head in TOP


def test_no_hdf5_path_literal_outside_store():
    found = []
    for path in sorted((ROOT / "pipeline").rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.parts[:2] == ("pipeline", "store"):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        skip = _docstrings(tree)
        for node in ast.walk(tree):
            if (isinstance(node, ast.Constant) and isinstance(node.value, str)
                    and id(node) not in skip and _is_path(node.value)):
                found.append(f"{rel}:{node.lineno}: {node.value!r}")
    assert not found, ("HDF5 paths spelled outside pipeline/store (use pipeline.store.layout "
                       "or a reader of pipeline.store.read):\n" + "\n".join(found))


#: what opens or indexes one of our files, kept to pipeline/store's readers
STORE_INTERNALS = {"open_verified", "read_csr", "read_strings"}


def _opens_a_file_to_read(node: ast.AST) -> bool:
    """``h5py.File(...)`` in read mode (no mode given, or ``"r"``)."""
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and node.func.attr == "File"):
        return False
    modes = [a for a in node.args[1:2]] + [k.value for k in node.keywords if k.arg == "mode"]
    return not modes or any(isinstance(m, ast.Constant) and m.value == "r" for m in modes)


def test_no_app_opens_a_result_file_itself():
    """The apps and the CLI read our files through the typed readers of pipeline.store: no
    h5py.File opened for reading, no open_verified/read_csr of their own (writing an
    export's own file with h5py is fine)."""
    found = []
    for path in sorted((ROOT / "pipeline").rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.parts[:2] not in (("pipeline", "apps"), ("pipeline", "cli")):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = ({a.name for a in node.names} if isinstance(node, ast.ImportFrom)
                     and (node.module or "").startswith("pipeline.store") else set())
            if names & STORE_INTERNALS or _opens_a_file_to_read(node):
                found.append(f"{rel}:{node.lineno}")
    assert not found, ("an app reads our HDF5 file itself (use a reader of "
                       "pipeline.store.read):\n" + "\n".join(found))
    assert _opens_a_file_to_read(ast.parse("h5py.File(p, 'r')").body[0].value)
    assert not _opens_a_file_to_read(ast.parse("h5py.File(p, 'w')").body[0].value)


def test_the_scan_sees_a_path_literal():
    assert _is_path("statespace/A") and _is_path("mesh/cells/") and _is_path("statespace")
    assert not _is_path("mesh") and not _is_path("tip_y/position") and not _is_path("a b/c")


# --------------------------------------------------------------------------- the document
def _sections(text: str) -> dict[str, str]:
    """Section text by the group path of its heading (``## `/mesh` ``)."""
    out: dict[str, str] = {}
    parts = re.split(r"^#{2,3} `/([^`]*)`.*$", text, flags=re.M)
    for path, body in zip(parts[1::2], parts[2::2]):
        out[path.strip("/").replace("<name>", "*")] = body
    return out


def _expand(name: str) -> list[str]:
    m = re.search(r"\{([^}]*)\}", name)
    if not m:
        return [name]
    return [x for part in m.group(1).split(",")
            for x in _expand(name[:m.start()] + part.strip() + name[m.end():])]


def _table_names(body: str, prefix: str) -> set[str]:
    """The dataset names of the first column of the section's tables (relative)."""
    names = set()
    for line in body.splitlines():
        if not line.startswith("|") or line.startswith("| ---"):
            continue
        first = line.split("|")[1]
        for token in re.findall(r"`([^`]+)`", first):
            for name in _expand(token):
                if prefix and name.startswith(prefix + "/"):
                    name = name[len(prefix) + 1:]
                names.add(name)
    return names


def _groups_by_doc_section() -> dict[str, L.Group]:
    return {**{g.path: g for g in L.GROUPS if g is not L.CONNECTIONS},
            "connections/*": L.connection("*"),
            "connections/*/statespace": L.connection_statespace("*")}


def _covered(name: str, names: tuple[str, ...]) -> bool:
    """A doc entry ``cells/tetra10`` or ``regions/<name>`` is the layout's ``cells``..."""
    return name in names or name.split("/")[0] in names


def test_the_layout_and_its_document_list_the_same_datasets():
    sections = _sections(DOC.read_text(encoding="utf-8"))
    problems = []
    for path, group in _groups_by_doc_section().items():
        if path not in sections:
            problems.append(f"/{path}: no section in {DOC.name}")
            continue
        prefix = path if path == L.FE.path else ""
        documented = _table_names(sections[path], prefix)
        if not documented and group.names:
            # a section without a table lists its datasets in its text
            documented = set(re.findall(r"`([A-Za-z_][A-Za-z0-9_/]*)`", sections[path]))
        for name in sorted(documented):
            if group.names and not _covered(name, group.names):
                problems.append(f"/{path}: the doc lists {name!r}, the layout does not")
        for name in group.names:
            if not any(d == name or d.startswith(name + "/") for d in documented):
                problems.append(f"/{path}: the layout names {name!r}, the doc does not")
    assert not problems, "\n".join(problems)


def test_every_attribute_the_layout_names_is_documented():
    text = DOC.read_text(encoding="utf-8")
    ticked = set(re.findall(r"`([^`]+)`", text))
    groups = list(_groups_by_doc_section().values()) + [L.LUMPED_STATESPACE]
    names = set(L.ROOT.names) | {a for g in groups for a in g.attr.names}
    missing = sorted(n for n in names if n not in ticked and not n.endswith("_s"))
    assert not missing, f"attributes named in pipeline/store/layout.py but not in {DOC.name}: " \
                        f"{missing}"


def test_the_doc_names_importable_readers():
    """Every ``pipeline.x.y.name`` the doc mentions imports."""
    import importlib

    text = DOC.read_text(encoding="utf-8")
    for dotted in sorted(set(re.findall(r"`(pipeline(?:\.\w+)+)", text))):
        module, _, attr = dotted.rpartition(".")
        try:
            mod = importlib.import_module(dotted)
        except ImportError:
            mod = importlib.import_module(module)
            assert hasattr(mod, attr), f"{DOC.name} names {dotted}, which does not exist"


# --------------------------------------------------------------------------- a written file
@pytest.fixture(scope="module")
def written(tmp_path_factory) -> list[Path]:
    """Three small runs: every model of the cantilever (plant, filtered, lumped, stress modes,
    rotation), the connection-point, Craig-Bampton and FE-matrix groups, and the materials
    group."""
    tmp = tmp_path_factory.mktemp("layout")
    plant = load_config(ROOT / "configs" / "cantilever.yaml",
                        ["mesh.size=0.025", "modes.count=4",
                         "rotation={axis: [0, 0, 1], point: [0, 0.01, 0.025], "
                         "speeds_rad_s: [0, 100]}"])
    conn = load_config(ROOT / "configs" / "cantilever_connection.yaml",
                       ["mesh.size=0.025", "modes.count=4", "craig_bampton.modes=4"])
    materials = load_config(ROOT / "configs" / "cantilever_materials.yaml",
                            ["mesh.size=0.025", "modes.count=4"])
    return [run_pipeline(plant, tmp / "plant.h5", mesh_dir=tmp).output,
            run_pipeline(conn, tmp / "conn.h5", mesh_dir=tmp).output,
            run_pipeline(materials, tmp / "materials.h5", mesh_dir=tmp).output]


def _group_of(path: str) -> L.Group | None:
    parts = path.split("/")
    if parts[0] == L.CONNECTIONS.path and len(parts) > 2:
        name = parts[1]
        return (L.connection_statespace(name) if len(parts) > 3 and parts[2] == "statespace"
                else L.connection(name))
    best = None
    for g in list(L.GROUPS) + [L.LUMPED_STATESPACE]:
        if path.startswith(g.path + "/") and (best is None or len(g.path) > len(best.path)):
            best = g
    return best


def test_a_written_file_holds_what_the_layout_promises(written):
    seen_groups = set()
    for path in written:
        with h5py.File(path, "r") as h5:
            datasets: list[str] = []
            h5.visititems(lambda name, obj: datasets.append(name)
                          if isinstance(obj, h5py.Dataset) else None)
            for name in datasets:
                group = _group_of(name)
                assert group is not None, f"{path.name}: {name} is in no group of the layout"
                rest = name[len(group.path) + 1:]
                if group.path == L.FE.path:
                    rest = rest.split("/")[0]
                assert _covered(rest, group.names), f"{path.name}: {name} is not in the layout"
                seen_groups.add(group.path.split("/")[0])
            groups = [g for g in L.GROUPS if g.path in h5 and g.names]
            for name in h5.get(L.CONNECTIONS.path, {}):
                groups += [L.connection(name), L.connection_statespace(name)]
            for g in groups:
                missing = [d for d in g.required() if d not in h5]
                assert not missing, f"{path.name}: {g.path} lacks {missing}"
            for key in L.ROOT.names:
                if key != L.ROOT.content:  # only simulation results carry it
                    assert key in h5.attrs, f"{path.name}: root attribute {key} missing"
    expected = {g.path for g in L.GROUPS} - {L.FFRF.path, L.RUN.path}
    assert expected <= seen_groups, f"no test file has {sorted(expected - seen_groups)}"


def test_the_glossary_names_records_that_exist():
    """Every **Name** (`module.py`) of docs/glossary.md is a class of that module."""
    import importlib

    text = (ROOT / "docs" / "glossary.md").read_text(encoding="utf-8")
    entries = re.findall(r"^- ((?:\*\*\w+\*\*(?:, )?)+) \(`([\w/]+)\.py`\)", text, flags=re.M)
    assert len(entries) > 20
    for names, path in entries:
        path = path.removeprefix("pipeline/")
        module = importlib.import_module("pipeline." + path.replace("/", "."))
        for name in re.findall(r"\*\*(\w+)\*\*", names):
            if name != "layout":
                assert hasattr(module, name), f"glossary: {name} is not in pipeline/{path}.py"


def test_a_group_names_its_paths_and_refuses_a_typo():
    import pickle

    assert L.MODES.frequencies_hz == "modes/frequencies_hz"
    assert L.MODES.attr.solver == "solver"
    assert L.LUMPED.section__I_y == "lumped/section/I_y" == L.LUMPED.dataset("section/I_y")
    assert L.connection("root").D_P == "connections/root/D_P"
    assert L.cells("tetra10") == "mesh/cells/tetra10"
    with pytest.raises(AttributeError, match="frequencies_hz"):
        L.MODES.frequency_hz  # noqa: B018 - the typo names what the layout has
    with pytest.raises(AttributeError):
        L.MODES.path = "other"
    assert pickle.loads(pickle.dumps(L.STATESPACE)).required() == L.STATESPACE.required()
