"""The snippets of docs/exports.md run as written (issue 20).

A module fixture makes ``cantilever.h5`` and ``cantilever_connection.h5`` (coarse meshes)
in a temporary folder and runs the doc's export commands there (the ```bash block that
does not hold placeholders); then every ```python block runs in that folder, and every
```octave block in GNU Octave (skipped, saying so, where octave-cli is missing). A snippet
that fails, or a format the table leaves out, fails the test.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from pipeline.apps.exports import EXPORTERS
from pipeline.config import load_config
from pipeline.run import run_pipeline

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "exports.md"
BLOCK = re.compile(r"^```(\w+)\n(.*?)^```", re.S | re.M)


def blocks(language: str) -> list[str]:
    return [code for lang, code in BLOCK.findall(DOC.read_text()) if lang == language]


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    pytest.importorskip("fmpy", reason="fmpy (test extra) gives the FMU export its headers")
    if shutil.which("gcc") is None:
        pytest.skip("the doc's FMU export needs gcc")
    tmp = tmp_path_factory.mktemp("docs")
    for name, overrides in (("cantilever", ["mesh.size=0.02", "modes.count=6"]),
                            ("cantilever_connection", ["mesh.size=0.02", "modes.count=6",
                                                       "craig_bampton.modes=6"])):
        cfg = load_config(ROOT / "configs" / f"{name}.yaml", overrides)
        run_pipeline(cfg, tmp / f"{name}.h5", mesh_dir=tmp)
    commands = [c for c in blocks("bash") if "RESULT.h5" not in c]
    assert len(commands) == 1
    # the command line in this process (what `python -m pipeline` runs), from that folder
    from pipeline.cli import main

    cwd = os.getcwd()
    os.chdir(tmp)
    try:
        for line in commands[0].strip().splitlines():
            argv = line.split()
            assert argv[:3] == ["python", "-m", "pipeline"], line
            assert main(argv[3:]) == 0, line
    finally:
        os.chdir(cwd)
    return tmp


def test_every_format_is_documented():
    text = DOC.read_text()
    for fmt in EXPORTERS:
        assert f"| `{fmt}` |" in text and f"--to {fmt}" in text, fmt


@pytest.mark.parametrize("index", range(len(blocks("python"))))
def test_python_snippet_runs(folder, index, monkeypatch, capsys):
    monkeypatch.chdir(folder)
    exec(compile(blocks("python")[index], f"docs/exports.md python block {index}", "exec"), {})
    assert capsys.readouterr().out.strip()   # every snippet shows something


@pytest.mark.skipif(shutil.which("octave-cli") is None,
                    reason="GNU Octave (octave-cli) is not installed: apt-get install -y octave")
@pytest.mark.parametrize("index", range(len(blocks("octave"))))
def test_octave_snippet_runs(folder, index):
    proc = subprocess.run(["octave-cli", "--quiet", "--eval", blocks("octave")[index]],
                          cwd=folder, capture_output=True, text=True, timeout=120)
    if "package control is not installed" in proc.stderr:
        pytest.skip("Octave's control package is not installed: apt-get install octave-control")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip()
