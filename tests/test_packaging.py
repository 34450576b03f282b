"""Packaging: ``python -m build`` makes a wheel that holds every module, the licence and
the console script, with the extras users install (``pip install 'fe-reduced-body[fast]'``),
and no packaging deprecation warnings (slow: the build runs in an isolated environment)."""

from __future__ import annotations

import subprocess
import sys
import zipfile

import pytest

from conftest import ROOT


@pytest.mark.slow
def test_wheel_holds_every_module_the_entry_point_and_the_extras(tmp_path):
    pytest.importorskip("build")
    proc = subprocess.run([sys.executable, "-m", "build", "--wheel", "--outdir", str(tmp_path),
                           str(ROOT)], capture_output=True, text=True, timeout=600)
    if proc.returncode != 0 and "Could not find a version" in proc.stdout + proc.stderr:
        pytest.skip("no package index reachable for the isolated build environment")
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    output = proc.stdout + proc.stderr
    assert "deprecated" not in output.lower(), [line for line in output.splitlines()
                                                 if "deprecat" in line.lower()]
    wheel = next(tmp_path.glob("fe_reduced_body-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    sources = {p.relative_to(ROOT).as_posix() for p in (ROOT / "pipeline").rglob("*.py")}
    assert sources <= names, sorted(sources - names)[:5]
    info = next(n.split("/")[0] for n in names if n.endswith(".dist-info/METADATA"))
    zf = zipfile.ZipFile(wheel)
    entry = zf.read(f"{info}/entry_points.txt").decode()
    assert "fe-reduced-body = pipeline.cli:main" in entry
    meta = zf.read(f"{info}/METADATA").decode()
    assert "License-Expression: MIT" in meta and f"{info}/licenses/LICENSE" in names
    for extra in ("fast", "plots", "batch", "test"):
        assert f"Provides-Extra: {extra}" in meta
    assert not any(n.startswith(("tests/", "configs/")) for n in names)


def test_console_script_target_runs_every_command():
    # what the wheel's fe-reduced-body script calls: pipeline.cli:main
    from pipeline.cli import main

    for command in ("run", "inspect", "plot", "simulate", "batch", "export"):
        with pytest.raises(SystemExit) as exc:
            main([command, "--help"])
        assert exc.value.code == 0
