"""The examples in the library's docstrings run and give what they show.

Every module under ``pipeline/`` whose source holds a ``>>>`` example is imported and
run through :mod:`doctest`; a module that gains an example is picked up without a list
to keep.
"""

from __future__ import annotations

import doctest
import importlib

import pytest

from conftest import ROOT

MODULES = sorted(
    ".".join(path.relative_to(ROOT).with_suffix("").parts)
    for path in (ROOT / "pipeline").rglob("*.py")
    if ">>>" in path.read_text(encoding="utf-8"))


def test_examples_are_found():
    assert "pipeline.solve.lobpcg" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0, f"{name}: no example ran"
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed"
