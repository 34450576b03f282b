"""``python -m pipeline export FILE.h5 --to FORMAT [-o OUT]``.

Dispatches through the registry of :mod:`pipeline.exports` (``EXPORTERS``,
``export(h5_path, fmt, out_path)``). Formats whose module exists here but which the
registry does not list yet (``mat``, ``vtu``, ``xdmf``, ``json``) are served from
:data:`FALLBACK`, so the command works before and after they are registered.
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

from .errors import ConfigError

__all__ = ["FALLBACK", "formats", "run_export", "add_export_parser"]

#: format -> (module under pipeline.exports, function, default suffix)
FALLBACK = {
    "mat": ("mat", "export", ".mat"),
    "vtu": ("vtu", "export_vtu", ".vtu"),
    "xdmf": ("vtu", "export_xdmf", ".modes.xdmf"),
    "json": ("summary_json", "export", ".json"),
}


def _registry():
    try:
        from . import exports
    except ImportError:
        return None
    return exports if hasattr(exports, "EXPORTERS") and hasattr(exports, "export") else None


def formats() -> list[str]:
    """Every format the export command knows."""
    reg = _registry()
    names = set(FALLBACK) | (set(reg.EXPORTERS) if reg is not None else set())
    return sorted(names)


def run_export(h5_path: str | Path, fmt: str, out_path: str | Path | None = None) -> Path:
    """Export ``h5_path`` to ``fmt``; ``out_path`` defaults to ``<stem><suffix>`` beside it."""
    h5_path = Path(h5_path)
    reg = _registry()
    if reg is not None and fmt in reg.EXPORTERS:
        return Path(reg.export(h5_path, fmt, out_path))
    if fmt not in FALLBACK:
        raise ConfigError(f"export --to: got {fmt!r}, expected one of {', '.join(formats())}")
    module, func, suffix = FALLBACK[fmt]
    out = Path(out_path) if out_path else h5_path.with_name(h5_path.stem + suffix)
    writer = getattr(importlib.import_module(f"pipeline.exports.{module}"), func)
    return Path(writer(h5_path, out))


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
