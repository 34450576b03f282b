"""``python -m pipeline export FILE.h5 --to FORMAT [-o OUT]``.

Dispatches through the registry of :mod:`pipeline.apps.exports` (``EXPORTERS``).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

__all__ = ["formats", "run_export", "add_export_parser"]


def formats() -> list[str]:
    """Every format the export command knows."""
    from pipeline.apps.exports import EXPORTERS

    return sorted(EXPORTERS)


def run_export(h5_path: str | Path, fmt: str, out_path: str | Path | None = None,
               **options) -> Path:
    """Export ``h5_path`` to ``fmt``; ``out_path`` defaults to ``<stem><suffix>`` beside it;
    ``options`` (e.g. ``model='filtered'`` for fmu) go to the format's writer."""
    from pipeline.apps.exports import export

    if fmt in ("exudyn", "sid") and options.get("fe_data") is None:
        options["fe_data"] = exudyn_fe_data(h5_path)
    return Path(export(Path(h5_path), fmt, out_path, **options))


def exudyn_fe_data(h5_path: str | Path):
    """The port loads and, for a file without ``/fe``, M and K re-assembled on its stored
    mesh with its stored config (:func:`pipeline.run.stored_fe_data`)."""
    from pipeline.run import stored_fe_data

    return stored_fe_data(h5_path)


def cmd_export(args: argparse.Namespace) -> int:
    print(run_export(args.file, args.to, args.output, model=getattr(args, "model", None),
                     basis=getattr(args, "basis", None),
                     fmi_version=getattr(args, "fmi_version", None)))
    return 0


def add_export_parser(subparsers) -> argparse.ArgumentParser:
    """``export FILE.h5 --to FORMAT [-o OUT]`` on the CLI's subparsers."""
    names = formats()
    p = subparsers.add_parser(
        "export", help="write an HDF5 result in another tool's format",
        description="mat: MATLAB/Simulink/Octave state space (A, B, C, D of every model, "
        "connection-point and Craig-Bampton models, names, frequencies); simscape: Reduced "
        "Order Flexible Solid parameters (.mat + .m); vtu/xdmf: mesh with every mode shape for ParaView; json: "
        "small summary (frequencies, ports, DC gains); exudyn: Exudyn FEMinterface file; fmu: "
        "FMI 2.0 or 3.0 FMU (Model Exchange + Co-Simulation) of any model of the file; sid: "
        "SID standard input data (SIMPACK) with the centrifugal stiffening terms. "
        "See docs/exports.md (installed: pipeline/docs/exports.md).")
    p.add_argument("file", help="HDF5 result of 'python -m pipeline run'")
    p.add_argument("--to", required=True, choices=names, help="output format")
    p.add_argument("-o", "--output", help="output file (default: beside FILE, named after it)")
    p.add_argument("--model",
                   help="fmu: which model goes into the FMU (default plant): plant, filtered, "
                   "lumped, connection/<name>, craig_bampton (the models 'inspect' lists)")
    p.add_argument("--fmi-version", dest="fmi_version",
                   help="fmu: FMI version, 2 (default) or 3")
    p.add_argument("--basis", choices=("auto", "modes", "craig_bampton"),
                   help="exudyn: mode basis (default auto: Craig-Bampton where the file has "
                   "it, else the modes plus the input ports' static modes)")
    p.set_defaults(func=cmd_export)
    return p
