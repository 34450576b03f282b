"""What every command checks before it starts work, and how it ends on a signal.

:func:`check_destinations` runs right after the arguments are parsed, before any
meshing, solving or large read: every file and folder the command will write is
checked with :func:`pipeline._util.paths.check_output` (not an input, not a foreign
existing file unless ``--force``, a writable folder). :func:`add_force_flags` adds
``--force`` to every command that writes.

:func:`handle_signals` turns SIGTERM (and SIGHUP) into the same
:class:`KeyboardInterrupt` as Ctrl-C, so that every writer's cleanup runs (the atomic
writer removes its temporary file, private folders are deleted) and the command ends with
one line. A signal that lands in code where Python would swallow the exception (a
weakref callback, a finaliser) is delivered again 50 ms later; the atomic writer blocks
signals while it removes its temporary file, so a second Ctrl-C cannot skip that.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from pipeline._util.interrupts import Terminated, handle_signals, received
from pipeline._util.paths import check_output, check_output_dir, file_kind_matches

__all__ = ["Terminated", "handle_signals", "add_force_flags", "check_destinations"]

WRITING_COMMANDS = ("run", "simulate", "export", "plot", "batch", "partition")

#: export format -> kind of the file it writes (see pipeline._util.paths.KINDS)
EXPORT_KINDS = {"json": "json", "mat": "mat", "vtu": "vtu", "xdmf": "xdmf", "exudyn": "exudyn",
                "fmu": "fmu", "simscape": "mat", "sid": "sid"}


def interrupted_by(exc: BaseException) -> bool:
    """True when ``exc`` came while an interrupt was being handled (a library turned the
    KeyboardInterrupt into another exception): the command reports the interrupt."""
    return bool(received())


def interruption() -> KeyboardInterrupt:
    """The exception of the interrupt received (for its message and exit code)."""
    signum = received() or int(signal.SIGINT)
    return KeyboardInterrupt("SIGINT") if signum == signal.SIGINT else Terminated(signum)


def _forget_unhandled_interrupt() -> bool:
    """CPython marks a KeyboardInterrupt that left code run by ``PyRun_String`` (some
    extension modules run Python code that way while they are imported) as unhandled, and
    then kills itself with SIGINT at exit although the interrupt was handled here (exit
    status -2 instead of ours). Running an empty string through the same path clears the
    mark; there is no Python-level call for it, so CPython's documented C function
    ``PyRun_SimpleString`` is called through ctypes. Returns whether it ran.

    Fallback, where the interpreter is not CPython or the function cannot be found: do
    nothing (no such mark elsewhere; at worst the exit is by SIGINT, which a shell reports
    as status 130 too)."""
    import ctypes

    if sys.implementation.name != "cpython":
        return False
    try:
        run = ctypes.PYFUNCTYPE(ctypes.c_int, ctypes.c_char_p)(
            ("PyRun_SimpleString", ctypes.pythonapi))
    except (AttributeError, OSError):
        return False
    return run(b"") == 0


def exit_code(exc: KeyboardInterrupt) -> int:
    """128 + the signal number (130 for Ctrl-C, 143 for SIGTERM). The command is ending:
    further signals are ignored, so that they cannot interrupt the interpreter's exit."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    _forget_unhandled_interrupt()
    return 128 + getattr(exc, "signum", int(signal.SIGINT))


def add_force_flags(subparsers) -> None:
    for name in WRITING_COMMANDS:
        p = subparsers.choices.get(name)
        if p is not None and not any("--force" in a.option_strings for a in p._actions):
            p.add_argument("--force", action="store_true",
                           help="replace existing files that were not written by this "
                           "package for this purpose (never the command's own inputs)")


def _run(args) -> None:
    from pipeline.api import check_run_destinations, resolve_config

    # kept for cmd_run: a config from a pipe (<(...), /dev/stdin) can be read only once
    args.resolved_config = resolve_config(args.config, args.set or [])
    check_run_destinations(args.resolved_config, args.output or None,
                           config_path=args.config, mesh_dir=getattr(args, "mesh_dir", None),
                           force=args.force)


def _simulate(args) -> None:
    model = Path(args.model)
    output = Path(args.output) if args.output else Path("outputs") / f"{model.stem}_simulate.h5"
    check_output(output, inputs=[model, *args.scenarios], force=args.force, kind="h5",
                 create_parent=not args.output)


def _export(args) -> None:
    from pipeline.apps.exports import default_output

    out = (Path(args.output) if args.output
           else default_output(args.file, args.to, getattr(args, "model", None)))
    check_output(out, inputs=[args.file], force=args.force, kind=EXPORT_KINDS.get(args.to))
    if args.to == "simscape":
        from pipeline.apps.exports.simscape import script_path

        check_output(script_path(out), inputs=[args.file], force=args.force,
                     kind="simscape-script", what="output (Simscape .m script)")
    if args.to == "xdmf":
        check_output(out.with_suffix(".h5"), inputs=[args.file], force=args.force,
                     kind="xdmf-sidecar", what="output (XDMF data file)")


def _ours_only(folder: Path) -> bool:
    """Every file in ``folder`` is a picture or table this package writes."""
    files = [p for p in folder.iterdir() if not p.name.startswith(".")]
    return all(p.is_file() and (file_kind_matches(p, "png") or file_kind_matches(p, "csv"))
               for p in files)


def _plot(args) -> None:
    path = Path(args.file)
    out_dir = Path(args.output_dir) if args.output_dir else path.with_name(f"{path.stem}_plots")
    check_output_dir(out_dir, marker=_ours_only, force=args.force, what="plot folder")


def _batch_folder(folder: Path) -> bool:
    return (folder / "cases").is_dir() or (folder / "summary.csv").is_file()


def _batch(args) -> None:
    if getattr(args, "dry_run", False):
        return
    from pipeline.apps.batch import load_batch

    spec = load_batch(args.file)
    args.batch_spec = spec  # kept for cmd_batch: a batch file from a pipe is read once
    outdir = Path(args.output) if args.output else Path("outputs") / spec.name
    check_output_dir(outdir, marker=_batch_folder, force=args.force, what="batch folder")


def _partition(args) -> None:
    from pipeline.cli.partition import check_partition_destination

    check_partition_destination(args)


CHECKS = {"run": _run, "simulate": _simulate, "export": _export, "plot": _plot,
          "batch": _batch, "partition": _partition}


def check_destinations(args: argparse.Namespace) -> None:
    """Check every destination of the parsed command (raises OutputError / ConfigError)."""
    check = CHECKS.get(getattr(args, "command", None))
    if check is not None:
        check(args)
