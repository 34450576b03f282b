"""The API reference (``make api``: pdoc over the docstrings) builds without a warning and
documents the public API.

The default suite builds it without the highlighted source listings (pdoc's
``show_source``): they are pygments' rendering of each module's text, which gives no
warning (pdoc warns on imports, docstrings, annotations and signatures, all still built)
and took half the build's time (17.5 s of 26 s, measured under load). ``make test-all``
builds it exactly as ``make api`` does.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import ROOT

pytest.importorskip("pdoc")

#: tools/api_docs.py run as its command line, with pdoc's source listings turned off
_WITHOUT_SOURCE = """
import runpy, sys
import pdoc.render
configure = pdoc.render.configure
pdoc.render.configure = lambda **kw: configure(**{**kw, "show_source": False})
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


@pytest.mark.parametrize("source", [
    False, pytest.param(True, marks=pytest.mark.slow)], ids=["without-source", "as-make-api"])
def test_api_reference_builds_without_warnings(tmp_path, source):
    tool = str(ROOT / "tools" / "api_docs.py")
    argv = [tool] if source else ["-c", _WITHOUT_SOURCE, tool]
    proc = subprocess.run([sys.executable, *argv, str(tmp_path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    page = (tmp_path / "pipeline.html").read_text(encoding="utf-8")
    for name in ("run_config", "load_model", "Config", "RunResult", "ConfigError"):
        assert name in page, name
    for module in ("api", "run", "config/schema", "store/read", "cli/process"):
        assert (tmp_path / "pipeline" / f"{module}.html").is_file(), module
    # the build is the one named: source listings (their toggles) only as make api makes it
    assert ('class="view-source-button"' in page) == source
