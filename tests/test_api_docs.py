"""The API reference (``make api``: pdoc over the docstrings) builds without a warning and
documents the public API."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import ROOT

pytest.importorskip("pdoc")


def test_api_reference_builds_without_warnings(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "api_docs.py"), str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    page = (tmp_path / "pipeline.html").read_text(encoding="utf-8")
    for name in ("run_config", "load_model", "Config", "RunResult", "ConfigError"):
        assert name in page, name
    for module in ("api", "run", "config/schema", "store/read", "cli/process"):
        assert (tmp_path / "pipeline" / f"{module}.html").is_file(), module
