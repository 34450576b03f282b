"""What the docs claim holds: README.md, CHANGELOG.md and docs/*.md against the code.

- every dotted ``pipeline.xxx`` name they mention is importable: a module, or an attribute
  of the longest importable module prefix (logger names the package registers count too,
  because the guide quotes log lines such as ``pipeline.progress: ...``);
- every relative link ``[text](path#anchor)`` resolves to a file in the repository, and an
  anchor into a Markdown file names one of its headings;
- no doc points outside the repository (a path through ``../`` that leaves it, or the
  old ``shared/spec`` folder, which a clone does not have).

Each failure names the doc and the name or link, so the lead can fix renames after merging.
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted(p for p in [ROOT / "README.md", ROOT / "CHANGELOG.md", *(ROOT / "docs").glob("*.md")]
              if p.exists())
DOC_IDS = [p.relative_to(ROOT).as_posix() for p in DOCS]

DOTTED = re.compile(r"(?<![\w./-])pipeline(?:\.[A-Za-z_]\w*)+")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
UP_PATH = re.compile(r"(?:\.\./)+[\w.-][\w./-]*")
LOGGER = re.compile(r"getLogger\(\s*[\"'](pipeline(?:\.\w+)+)[\"']")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


# (doc, name) pairs a doc may name although the package lacks them, each with its reason
# in a comment; none today.
KNOWN_DRIFT: set[tuple[str, str]] = set()


def _logger_names() -> set[str]:
    names = set()
    for source in (ROOT / "pipeline").rglob("*.py"):
        names.update(LOGGER.findall(source.read_text(encoding="utf-8")))
    return names


def _resolves(dotted: str) -> bool:
    """True when ``dotted`` is a module or an attribute chain below an importable module."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for attr in parts[cut:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return False
        return True
    return False


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to dashes."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = FENCE.sub("", path.read_text(encoding="utf-8"))
    return {_slug(m) for m in re.findall(r"^#+\s+(.*)$", text, re.M)}


def test_the_docs_are_found():
    assert (ROOT / "README.md") in DOCS and len(DOCS) > 3


@pytest.mark.parametrize("doc", DOCS, ids=DOC_IDS)
def test_every_dotted_pipeline_name_is_importable(doc):
    loggers = _logger_names()
    names = sorted(set(DOTTED.findall(doc.read_text(encoding="utf-8"))))
    doc_id = doc.relative_to(ROOT).as_posix()
    missing = [n for n in names if n not in loggers and (doc_id, n) not in KNOWN_DRIFT
               and not _resolves(n)]
    assert not missing, f"{doc.relative_to(ROOT)} names what the package does not have: {missing}"


@pytest.mark.parametrize("doc", DOCS, ids=DOC_IDS)
def test_every_relative_link_resolves(doc):
    broken = []
    for target in LINK.findall(doc.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        path = (doc.parent / path_part).resolve() if path_part else doc
        if not path.is_relative_to(ROOT) or not path.exists():
            broken.append(target)
        elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
            broken.append(target)
    assert not broken, f"{doc.relative_to(ROOT)} links to what is not in the repository: {broken}"


@pytest.mark.parametrize("doc", DOCS, ids=DOC_IDS)
def test_no_doc_points_outside_the_repository(doc):
    text = doc.read_text(encoding="utf-8")
    outside = [p for p in UP_PATH.findall(text)
               if not (doc.parent / p).resolve().is_relative_to(ROOT)]
    outside += ["shared/spec"] if "shared/spec" in text else []
    assert not outside, f"{doc.relative_to(ROOT)} points outside the repository: {outside}"


def test_theory_keeps_the_section_numbers_the_code_cites():
    # docstrings cite "theory.md §N" for sections 1-8, whose numbers are kept stable
    titles = re.findall(r"^## (\d+)\. ", (ROOT / "docs" / "theory.md").read_text(), re.M)
    assert [int(t) for t in titles[:8]] == list(range(1, 9)), titles
    cited = {int(n) for p in (ROOT / "pipeline").rglob("*.py")
             for n in re.findall(r"theory\.md §(\d+)", p.read_text(encoding="utf-8"))}
    assert cited <= {int(t) for t in titles}, sorted(cited - {int(t) for t in titles})
