"""No module of the package is over :data:`MAX_LINES` lines.

A module past that size holds more than one concept and is split by concept (as
``pipeline/fe/assemble.py`` was into the pattern, the element kernels and the block
layout). The check runs in ``make test`` so that the limit is held by the tests, not by
review; the second test proves it can fail.
"""

from __future__ import annotations

from pathlib import Path

from conftest import ROOT

MAX_LINES = 600

#: Modules allowed over the limit, each with its reason in a comment; none today. An
#: entry that is no longer over the limit fails the test.
KNOWN_OVERSIZE: set[str] = set()


def oversize_modules(root: Path, limit: int = MAX_LINES) -> dict[str, int]:
    """``relative path -> line count`` of every ``*.py`` under ``root/pipeline`` over
    ``limit`` lines."""
    out = {}
    for path in sorted((root / "pipeline").rglob("*.py")):
        n = len(path.read_text(encoding="utf-8").splitlines())
        if n > limit:
            out[path.relative_to(root).as_posix()] = n
    return out


def test_no_module_is_over_the_size_limit():
    found = oversize_modules(ROOT)
    new = {p: n for p, n in found.items() if p not in KNOWN_OVERSIZE}
    assert not new, f"modules over {MAX_LINES} lines (split them by concept): {new}"
    stale = sorted(KNOWN_OVERSIZE - set(found))
    assert not stale, f"no longer over {MAX_LINES} lines, remove from KNOWN_OVERSIZE: {stale}"


def test_a_module_over_the_limit_is_found(tmp_path):
    package = tmp_path / "pipeline" / "stage"
    package.mkdir(parents=True)
    (package / "small.py").write_text("x = 1\n" * MAX_LINES)
    (package / "big.py").write_text("x = 1\n" * (MAX_LINES + 1))
    assert oversize_modules(tmp_path) == {"pipeline/stage/big.py": MAX_LINES + 1}
