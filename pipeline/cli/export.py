"""``python -m pipeline export FILE.h5 --to FORMAT [-o OUT]``.

Dispatches through the registry of :mod:`pipeline.apps.exports` (``EXPORTERS``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["formats", "run_export", "add_export_parser"]


def formats() -> list[str]:
    """Every format the export command knows."""
    from pipeline.apps.exports import EXPORTERS

    return sorted(EXPORTERS)


def run_export(h5_path: str | Path, fmt: str, out_path: str | Path | None = None) -> Path:
    """Export ``h5_path`` to ``fmt``; ``out_path`` defaults to ``<stem><suffix>`` beside it."""
    from pipeline.apps.exports import export

    return Path(export(Path(h5_path), fmt, out_path))


def cmd_export(args: argparse.Namespace) -> int:
    print(run_export(args.file, args.to, args.output))
    return 0


def add_export_parser(subparsers) -> argparse.ArgumentParser:
    """``export FILE.h5 --to FORMAT [-o OUT]`` on the CLI's subparsers."""
    names = formats()
    p = subparsers.add_parser(
        "export", help="write an HDF5 result in another tool's format",
        description="mat: MATLAB/Simulink/Octave state space (A, B, C, D of every model, "
        "names, frequencies); vtu/xdmf: mesh with every mode shape for ParaView; json: "
        "small summary (frequencies, ports, DC gains); exudyn: Exudyn FEMinterface file.")
    p.add_argument("file", help="HDF5 result of 'python -m pipeline run'")
    p.add_argument("--to", required=True, choices=names, help="output format")
    p.add_argument("-o", "--output", help="output file (default: beside FILE, named after it)")
    p.set_defaults(func=cmd_export)
    return p
