"""The user guide's examples run (docs/guide.md): every ``console`` block is a command
(``$ ...``) and what it prints; they are run in order, in a scratch folder that sees the
repository's configs/ and docs/, and the output is compared with the guide.

Compared: every line, text exactly (runs of blanks collapsed), numbers to 2e-4 relative
(the printed digits of frequencies and gains; the FE results agree across CPUs to ~1e-10)
or 1e-12 absolute (a relative error printed as +0.00e+00 may be 2.2e-16 elsewhere); what
``simulate`` measures comes from an integration at rtol = atol = 1e-8 (it prints them),
so its relative errors are compared to INTEGRATOR_TOL absolute (-7.56e-07 in the guide,
-7.55e-07 in a later run: the third digit of a 1e-6 error is the integrator's round-off). Not
compared: durations, memory, dates and residuals (numbers followed by s, min, MB or GB;
ISO dates; the value after 'residual'), the solver's name (pardiso without MKL is
superlu), and lines the guide elides with '...'.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

GUIDE = ROOT / "docs" / "guide.md"
NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")
VOLATILE = [(re.compile(r"[-+]?\d+(?:\.\d+)?\s*(?:s|min|MB|GB)\b"), "<t>"),
            (re.compile(r"\d{4}-\d\d-\d\dT[\d:]+Z"), "<date>"),
            (re.compile(r"residual [-+\d.e]+"), "residual <r>"),
            (re.compile(r"\b(?:pardiso|superlu|cholmod)\b"), "<solver>")]
#: commands that take long: in the slow suite (make test-all) only
SLOW = ("simulate", "batch")
#: absolute tolerance of numbers that come out of ``simulate``'s integrations (its LSODA
#: runs at rtol = atol = 1e-8, as it prints): their digits below this are round-off
INTEGRATOR_TOL = 1e-8


def guide_examples() -> list[tuple[str, list[str]]]:
    """(command, expected output lines) of every console block, in order."""
    text = GUIDE.read_text(encoding="utf-8")
    examples = []
    for block in re.findall(r"```console\n(.*?)```", text, flags=re.S):
        lines = block.rstrip("\n").split("\n")
        assert lines[0].startswith("$ "), lines[0]
        examples.append((lines[0][2:], lines[1:]))
    return examples


def _normal(line: str) -> str:
    for pattern, token in VOLATILE:
        line = pattern.sub(token, line)
    return " ".join(line.split())


def _same_line(expected: str, actual: str, atol: float = 1e-12) -> bool:
    e, a = _normal(expected), _normal(actual)
    if NUMBER.sub("#", e) != NUMBER.sub("#", a):
        return False
    for x, y in zip(NUMBER.findall(e), NUMBER.findall(a)):
        x, y = float(x), float(y)
        if abs(x - y) > 2e-4 * max(abs(x), abs(y)) + atol:
            return False
    return True


def matches(expected: list[str], actual: list[str], atol: float = 1e-12) -> str | None:
    """None when ``actual`` is ``expected`` with its '...' lines standing for any
    number of lines; else the first expected line that was not found. ``atol``: the
    absolute tolerance of the numbers (see the module doc)."""
    actual = [line for line in actual if line.strip()]
    i = 0
    skipping = False
    for line in expected:
        if line.strip() == "...":
            skipping = True
            continue
        while i < len(actual) and not _same_line(line, actual[i], atol):
            if not skipping:
                return f"expected {line!r}, got {actual[i]!r}"
            i += 1
        if i == len(actual):
            return f"expected {line!r}: not found"
        i += 1
        skipping = False
    if i < len(actual) and not skipping:
        return f"unexpected extra output {actual[i]!r}"
    return None


def test_the_comparison_is_strict_where_it_should_be():
    assert matches(["f 65.6731 Hz"], ["f 65.6735 Hz"]) is None       # 6e-6 relative
    assert matches(["f 65.6731 Hz"], ["f 65.7731 Hz"]) is not None   # 1.5e-3
    assert matches(["err -7.56e-07 Hz"], ["err -7.55e-07 Hz"]) is not None  # 1e-9: FE
    assert matches(["err -7.56e-07 Hz"], ["err -7.55e-07 Hz"], INTEGRATOR_TOL) is None
    assert matches(["err -7.56e-07 Hz"], ["err -2.56e-07 Hz"], INTEGRATOR_TOL) is not None
    assert matches(["wrote x in 5.2 s"], ["wrote x in 31 s"]) is None
    assert matches(["a", "...", "d"], ["a", "b", "c", "d"]) is None
    assert matches(["a", "d"], ["a", "b", "d"]) is not None
    assert matches(["mode 1 bending_z_1"], ["mode 1 bending_y_1"]) is not None


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("guide")
    for name in ("configs", "docs"):
        (work / name).symlink_to(ROOT / name)
    (work / "outputs").mkdir()  # as in a clone (outputs/.gitkeep): -o never creates folders
    return work


EXAMPLES = guide_examples()


@pytest.mark.parametrize("index", [
    pytest.param(i, id=cmd.split()[3], marks=[pytest.mark.slow] if cmd.split()[3] in SLOW
                 else []) for i, (cmd, _) in enumerate(EXAMPLES)])
def test_guide_example(index, workdir):
    command, expected = EXAMPLES[index]
    if index > 0 and not (workdir / "outputs" / "guide.h5").exists():
        _run(EXAMPLES[0][0], workdir)  # the later examples read the file of the first
    args = command.split()
    assert args[:3] == ["python", "-m", "pipeline"], command
    proc = _run(command, workdir)
    assert proc.returncode == 0, proc.stderr[-3000:]
    atol = INTEGRATOR_TOL if args[3] == "simulate" else 1e-12
    problem = matches(expected, proc.stdout.splitlines(), atol)
    assert problem is None, f"{command}: {problem}\n--- printed:\n{proc.stdout}"


def _run(command: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, *command.split()[1:]], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)
