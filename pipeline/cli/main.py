"""Command line: ``python -m pipeline run|inspect ...``.

The CLI parses arguments, sets up logging and progress bars, and calls the same
functions the library exposes. A :class:`~pipeline.errors.PipelineError` becomes one
line on stderr and its exit code; nothing else is caught.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from pathlib import Path

from pipeline.errors import PipelineError

log = logging.getLogger("pipeline")


#: loggers whose INFO lines a default run shows when stderr is not a terminal (one line
#: per stage with elapsed and expected time); everything else needs -v
STAGE_LOGGERS = ("pipeline.progress", "pipeline.run")


def _setup_logging(verbosity: int) -> None:
    """-q: warnings only; default: warnings, plus the stage lines when stderr is not a
    terminal (a terminal shows bars instead); -v: INFO of every logger; -vv: DEBUG.
    Under mpiexec only rank 0 logs below ERROR: the ranks run the same stages and log
    the same lines, N times over otherwise (a rank's failure is its own error line)."""
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 \
        else logging.DEBUG
    if _mpi_rank() > 0:
        level, verbosity = logging.ERROR, -1
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                                           "%H:%M:%S"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    for name in STAGE_LOGGERS:
        logging.getLogger(name).setLevel(
            logging.INFO if verbosity == 0 and not sys.stderr.isatty() else logging.NOTSET)


def _progress_reporter(verbosity: int):
    """Bars on a terminal, stage log lines otherwise, nothing with -q (nor on MPI ranks
    other than 0)."""
    from pipeline._util import progress

    if verbosity < 0 or _mpi_rank() > 0:
        return None
    if sys.stderr.isatty():
        return progress.BarReporter(sys.stderr)
    return progress.LogReporter()


def tqdm_progress(desc: str, total: int | None, unit: str):
    """The stages' ``progress(desc, total, unit)`` factory (see pipeline._util.progress)."""
    from pipeline._util import progress

    return progress.counter(desc, total, unit)


#: summary blocks (a header line and its indented lines) shown only with -v
VERBOSE_BLOCKS = ("lumped chain:",)


def summary_blocks(lines, verbose: bool) -> list[str]:
    """The stages' summary lines; a block of :data:`VERBOSE_BLOCKS` shrinks to its header
    unless ``verbose``."""
    shown, hiding = [], False
    for line in lines:
        if not line.startswith(" "):
            hiding = not verbose and line.startswith(VERBOSE_BLOCKS)
            shown.append(line.rstrip(":") + " (table with -v)" if hiding else line)
        elif not hiding:
            shown.append(line)
    return shown


def run_summary(result, verbose: bool = False) -> list[str]:
    """What ``run`` prints: the mesh, the modes, the reduced models, the file written and
    the commands to look at it."""
    from pipeline._util.progress import fmt_seconds

    lines = [f"{result.config.name}: {result.n_dofs} DOFs ({result.n_free} free), "
             f"{result.n_elements} elements, solver {result.backend}",
             f"  {'mode':>4}  {'f [Hz]':>12}  label"]
    for i, (f, lab) in enumerate(zip(result.frequencies_hz, result.labels), 1):
        lines.append(f"  {i:4d}  {f:12.4f}  {lab}")
    lines += summary_blocks(result.extras.get("summary", []), verbose)
    total = sum(result.times.values())
    times = ", ".join(f"{k} {fmt_seconds(v)}" for k, v in result.times.items())
    lines.append(f"wrote {result.output} in {fmt_seconds(total)} ({times}; peak memory "
                 f"{result.peak_memory_mb:.0f} MB)")
    prog = "fe-reduced-body" if Path(sys.argv[0]).name == "fe-reduced-body" \
        else "python -m pipeline"
    lines.append(f"look at it: {prog} inspect {result.output}")
    lines.append(f"            {prog} plot {result.output}")
    return lines


def cmd_run(args: argparse.Namespace) -> int:
    from pipeline.api import default_output, resolve_config
    from pipeline.run import run_pipeline

    # the destinations were checked before (pipeline.cli.guard): pipeline.api.run_config
    # without its second check
    cfg = getattr(args, "resolved_config", None) or resolve_config(args.config, args.set or [])
    output = Path(args.output) if args.output else default_output(cfg)
    result = run_pipeline(cfg, output, mesh_dir=args.mesh_dir, progress=tqdm_progress)
    if _mpi_rank() == 0:  # under mpiexec rank 0 speaks for all (they hold the same result)
        print("\n".join(run_summary(result, verbose=args.verbose > 0)))
    return 0


def _mpi_rank() -> int:
    """This process's MPI rank as the launcher (OpenMPI, MPICH/Hydra, Slurm) tells it,
    without importing MPI; 0 outside mpiexec."""
    import os

    for key in ("OMPI_COMM_WORLD_RANK", "PMI_RANK", "PMIX_RANK"):
        if os.environ.get(key, "").isdigit():
            return int(os.environ[key])
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    from pipeline.apps.summary import summarize

    print(summarize(args.file))
    return 0


#: (module, function registering its subcommand), in the order ``--help`` lists them
COMMAND_MODULES = [("cli.batch", "add_batch_parser"), ("cli.simulate", "add_simulate_parser"),
                   ("apps.plots", "add_plot_parser"), ("cli.export", "add_export_parser"),
                   ("cli.partition", "add_partition_parser")]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m pipeline",
                                     description="Reduced models of flexible bodies from 3D FE.")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="-v: every log line and the detail tables; -vv: debug")
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
    from pipeline._util.progress import using

    try:
        guard.check_destinations(args)  # before any work: one line if a destination is bad
        # the reporter is this command's (main may be called again in one process)
        with using(_progress_reporter(-1 if args.quiet else args.verbose)):
            return int(args.func(args) or 0)
    except PipelineError as exc:
        if guard.interrupted_by(exc):
            return _interrupted(guard.interruption(), guard)
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except BrokenPipeError:
        # the reader of stdout went away (``| head``): nothing more to say, no traceback;
        # stdout is pointed at /dev/null so the interpreter's final flush does not fail
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except Exception as exc:
        if not guard.interrupted_by(exc):
            raise  # a bug: its traceback is wanted
        return _interrupted(guard.interruption(), guard)
    except KeyboardInterrupt as exc:
        print(f"error: interrupted ({getattr(exc, 'args', None) and exc.args[0] or 'SIGINT'}); "
              "no partial output was left under the final name", file=sys.stderr)
        return guard.exit_code(exc)
