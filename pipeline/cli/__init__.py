"""Command line: ``python -m pipeline COMMAND``; one module per command.

:func:`main` is the console script's entry point (``fe-reduced-body``): it tunes this
process (:func:`pipeline.cli.process.tune_process`) and runs the command.
"""

from pipeline.cli.main import build_parser
from pipeline.cli.main import main as run_command
from pipeline.cli.process import tune_process

__all__ = ["build_parser", "main", "run_command", "tune_process"]


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``) in a tuned process;
    returns the exit code."""
    tune_process()
    return run_command(argv)
