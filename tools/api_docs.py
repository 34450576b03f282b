"""Build the API reference (HTML, from the docstrings) with pdoc: ``make api``.

Usage: ``python tools/api_docs.py [OUTPUT_DIR]`` (default ``build/api``). Every public
module of :mod:`pipeline` gets a page (private ones, ``_util`` and ``__main__``, do not);
docstrings are read as reStructuredText, as they are written. Any warning pdoc gives
(a module that cannot be imported, a docstring it cannot convert) fails the build, so
the reference cannot rot silently: tests/test_api_docs.py runs it.
"""

from __future__ import annotations

import pkgutil
import sys
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def public_modules() -> list[str]:
    """``pipeline`` and every module below it whose dotted name has no ``_``-part."""
    import pipeline

    names = [m.name for m in pkgutil.walk_packages(pipeline.__path__, "pipeline.")]
    return ["pipeline"] + sorted(n for n in names if not any(
        part.startswith("_") for part in n.split(".")))


def module_specs(modules: list[str]) -> list[str]:
    """The fewest specs that make pdoc document every module once: pdoc walks a
    package's submodules itself, except those a package's ``__all__`` leaves out."""
    from pdoc.extract import walk_specs

    specs: list[str] = []
    covered: set[str] = set()
    for name in modules:  # sorted: a package comes before its submodules
        if name not in covered:
            specs.append(name)
            covered.update(walk_specs([name]))
    return specs


def build(output: Path) -> list[str]:
    """Write the reference into ``output``; the warnings pdoc gave (empty when clean)."""
    import pdoc
    import pdoc.render

    pdoc.render.configure(docformat="restructuredtext", show_source=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        specs = module_specs(public_modules())
        pdoc.pdoc(*specs, output_directory=output)
    return [f"{w.category.__name__}: {w.message}" for w in caught
            if issubclass(w.category, UserWarning)]


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    output = Path(args[0]) if args else ROOT / "build" / "api"
    sys.path.insert(0, str(ROOT))
    problems = build(output)
    for line in problems:
        print(line, file=sys.stderr)
    if problems:
        print(f"API reference: {len(problems)} warning(s)", file=sys.stderr)
        return 1
    print(f"API reference: {output / 'index.html'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
