"""Build hook: the wheel carries the documentation inside the package.

The README and ``--help`` point at the pages of ``docs/``; an installed wheel has no
repository around it, so ``build_py`` copies ``docs/`` (pages, pictures, examples) and
``CHANGELOG.md`` to ``pipeline/docs/``, where the same relative links resolve. Everything
else is configured in ``pyproject.toml``.
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent


class BuildPyWithDocs(build_py):
    def run(self):
        super().run()
        target = Path(self.build_lib) / "pipeline" / "docs"
        docs = ROOT / "docs"
        pages = {p.relative_to(docs): p for p in docs.rglob("*") if p.is_file()}
        pages[Path("CHANGELOG.md")] = ROOT / "CHANGELOG.md"
        for rel, page in sorted(pages.items()):
            (target / rel).parent.mkdir(parents=True, exist_ok=True)
            self.copy_file(str(page), str(target / rel))


setup(cmdclass={"build_py": BuildPyWithDocs})
