"""Command line: ``python -m pipeline COMMAND``; one module per command."""

from pipeline.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
