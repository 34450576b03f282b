"""``python -m pipeline batch FILE.yaml``: run a batch of cases (:mod:`pipeline.apps.batch`).

Exit codes: 0 when every case finished, 1 if any failed (they are listed), 2 for an
invalid batch file (nothing runs), 130 when interrupted (finished cases are kept).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

from pipeline.cli.main import main as cli_main
from pipeline.errors import ConfigError

if TYPE_CHECKING:
    from pipeline.apps.batch import BatchResult

__all__ = ["add_batch_parser", "cmd_batch", "main"]


def print_result(result: BatchResult) -> None:
    """The counts, the report's files and every failed case with its error, on stdout."""
    n = len(result.outcomes)
    print(f"batch '{result.spec.name}': {n} cases: {result.count('done')} computed, "
          f"{result.count('cached')} cached, {len(result.failed)} failed"
          + (f", {result.count('not run')} not run" if result.count("not run") else "")
          + f" in {result.wall_s:.1f} s")
    for name in ("summary", "report"):
        if name in result.files:
            print(f"  {name}: {result.files[name]}")
    if result.failed:
        print(f"failed cases ({len(result.failed)}):")
        for o in result.failed:
            print(f"  case {o.case.index} ({o.case.label}) [{o.case.key}]: {o.error}")


def cmd_batch(args: argparse.Namespace) -> int:
    """``python -m pipeline batch FILE.yaml``: exit 0 when every case finished, 1 if any
    failed (they are listed), 2 for an invalid batch file (nothing runs)."""
    # here, not at the top: the other commands (``run`` above all) do not pay for it
    from pipeline.apps.batch import load_batch, run_batch

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: got {args.workers}, expected at least 1")
    if getattr(args, "dry_run", False):
        spec = load_batch(args.file)
        print(f"batch '{spec.name}' ({spec.path}): {len(spec.cases)} valid cases, base "
              f"{spec.base}")
        for c in spec.cases:
            est = "?" if c.memory_bytes is None else f"{c.memory_bytes / 1e9:.2f} GB"
            print(f"  case {c.index:3d} [{c.key}] memory ~{est}: {c.label}")
        return 0
    try:
        import distributed  # noqa: F401  (deferred, heavy; it configures its loggers)
    except ImportError:
        raise ConfigError("batch: Dask is not installed; expected the 'batch' extra "
                          "(pip install 'fe-reduced-body[batch]')") from None
    if logging.getLogger().level > logging.DEBUG:

        for name in ("distributed", "tornado", "bokeh"):
            logging.getLogger(name).setLevel(logging.WARNING)
    try:
        result = run_batch(getattr(args, "batch_spec", None) or args.file, args.output,
                           workers=args.workers,
                           scheduler=args.scheduler, verify=args.verify,
                           compute=not args.report_only)
    except KeyboardInterrupt as exc:
        from pipeline.cli.guard import exit_code

        print("error: batch interrupted; finished cases are kept: run the same command again "
              "to resume", file=sys.stderr)
        return exit_code(exc)
    print_result(result)
    return 1 if result.failed else 0


def add_batch_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``batch`` on the CLI's subparsers (``python -m pipeline batch ...``)."""
    p = subparsers.add_parser(
        "batch", help="run a YAML batch of cases (sweep / explicit) in parallel, cached",
        description="Run every case of a batch file on a local Dask cluster (default) or an "
                    "existing one, skip cases already computed, and write summary.csv and "
                    "report.html. Exits 1 if any case failed (listed at the end).")
    p.add_argument("file", help="batch YAML file (batch: {base, sweep, combine, cases, ...})")
    p.add_argument("--workers", type=int, metavar="N",
                   help="local worker processes (default: one per core, fewer if memory needs)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="use an existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("-o", "--output", metavar="OUTDIR",
                   help="batch output folder (default outputs/<batch name>)")
    p.add_argument("--verify", action="store_true",
                   help="verify the checksum of every cached file (slower), not only size/time")
    p.add_argument("--dry-run", action="store_true",
                   help="validate the batch and list its cases, keys and memory estimates")
    p.add_argument("--report-only", action="store_true",
                   help="compute nothing; rewrite summary.csv and report.html from the records")
    p.set_defaults(func=cmd_batch)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m pipeline.apps.batch FILE ...``: the same as ``python -m pipeline batch
    FILE ...`` (one CLI, one error handling: :func:`pipeline.cli.main.main`)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    return cli_main(argv if argv[:1] == ["batch"] else ["batch", *argv])
