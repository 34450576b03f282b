"""Command line: ``python -m pipeline run|inspect ...``.

The CLI parses arguments, sets up logging and progress bars, and calls the same
functions the library exposes. A :class:`~pipeline.errors.PipelineError` becomes one
line on stderr and its exit code; nothing else is caught.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
from pathlib import Path

from pipeline.errors import PipelineError

log = logging.getLogger("pipeline")


def _setup_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity < 0 else logging.INFO if verbosity == 0 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                                           "%H:%M:%S"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)


@contextlib.contextmanager
def tqdm_progress(desc: str, total: int | None, unit: str):
    """A tqdm bar on stderr (silent when stderr is not a terminal)."""
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit=unit, leave=False, disable=not sys.stderr.isatty(),
               dynamic_ncols=True)
    try:
        yield bar.update
    finally:
        bar.close()


def cmd_run(args: argparse.Namespace) -> int:
    from pipeline.config import load_config
    from pipeline.run import run_pipeline

    cfg = load_config(args.config, args.set or [])
    output = Path(args.output) if args.output else Path("outputs") / f"{cfg.name}.h5"
    result = run_pipeline(cfg, output, mesh_dir=args.mesh_dir, progress=tqdm_progress)
    total = sum(result.times.values())
    print(f"{cfg.name}: {result.n_dofs} DOFs ({result.n_free} free), {result.n_elements} "
          f"elements, solver {result.backend}")
    for i, (f, lab) in enumerate(zip(result.frequencies_hz, result.labels), 1):
        print(f"  mode {i:3d}  {f:12.4f} Hz  {lab}")
    for line in result.extras.get("summary", []):
        print(line)
    times = ", ".join(f"{k} {v:.2f} s" for k, v in result.times.items())
    print(f"wrote {result.output} in {total:.1f} s ({times}; peak {result.peak_memory_mb:.0f} MB)")
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    from pipeline.apps.summary import summarize

    print(summarize(args.file))
    return 0


#: (module, function registering its subcommand), in the order ``--help`` lists them
COMMAND_MODULES = [("cli.batch", "add_batch_parser"), ("cli.simulate", "add_simulate_parser"),
                   ("apps.plots", "add_plot_parser"), ("cli.export", "add_export_parser")]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m pipeline",
                                     description="Reduced models of flexible bodies from 3D FE.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="mesh, assemble, solve and reduce one config")
    run.add_argument("config", help="YAML config file")
    run.add_argument("-o", "--output", help="HDF5 output (default outputs/<name>.h5)")
    run.add_argument("--set", action="append", metavar="KEY=VALUE",
                     help="override a config key by its dotted path, e.g. mesh.size=0.004")
    run.add_argument("--mesh-dir", default=None,
                     help="keep the gmsh mesh there as <name>.<sha256[:12]>.msh (default: "
                     "not kept; the mesh is in the HDF5 file)")
    run.set_defaults(func=cmd_run)

    insp = sub.add_parser("inspect", help="human summary of an HDF5 file")
    insp.add_argument("file")
    insp.set_defaults(func=cmd_inspect)

    # the other commands live beside the stage they drive (light imports only here)
    import importlib

    for module, register in COMMAND_MODULES:
        getattr(importlib.import_module(f"pipeline.{module}"), register)(sub)
    from pipeline.cli.guard import add_force_flags

    add_force_flags(sub)
    return parser


def _interrupted(exc: KeyboardInterrupt, guard) -> int:
    print(f"error: interrupted ({exc.args[0] if exc.args else 'SIGINT'}); no partial output "
          "was left under the final name", file=sys.stderr)
    return guard.exit_code(exc)


def main(argv: list[str] | None = None) -> int:
    from pipeline.cli import guard

    guard.handle_signals()  # first: an interrupt while the commands are imported is handled
    try:
        parser = build_parser()
    except Exception as exc:
        if not guard.interrupted_by(exc):
            raise
        exc = guard.interruption()
        print(f"error: interrupted ({exc.args[0]}) while starting; nothing was written",
              file=sys.stderr)
        return guard.exit_code(exc)
    except KeyboardInterrupt as exc:
        print(f"error: interrupted ({exc.args[0] if exc.args else 'SIGINT'}) while starting; "
              "nothing was written", file=sys.stderr)
        return guard.exit_code(exc)
    args = parser.parse_args(argv)
    _setup_logging(-1 if args.quiet else args.verbose)
    try:
        guard.check_destinations(args)  # before any work: one line if a destination is bad
        return int(args.func(args) or 0)
    except PipelineError as exc:
        if guard.interrupted_by(exc):
            return _interrupted(guard.interruption(), guard)
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except Exception as exc:
        if not guard.interrupted_by(exc):
            raise  # a bug: its traceback is wanted
        return _interrupted(guard.interruption(), guard)
    except KeyboardInterrupt as exc:
        print(f"error: interrupted ({getattr(exc, 'args', None) and exc.args[0] or 'SIGINT'}); "
              "no partial output was left under the final name", file=sys.stderr)
        return guard.exit_code(exc)
