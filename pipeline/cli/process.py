"""How the command line tunes its own process; the library never changes its host.

:func:`tune_process` is the first thing ``python -m pipeline`` and the
``fe-reduced-body`` console script do, before numpy, scipy or MKL load. A script that
wants the same throughput as the CLI (the benchmark's child processes) calls it first
too; a notebook or co-simulation that imports :mod:`pipeline` keeps its process as it is.
"""

from __future__ import annotations

import os

__all__ = ["PROCESS_SETTINGS", "tune_process"]

#: environment variables the CLI sets unless they are already set. OpenBLAS's worker
#: threads spin about 0.1 s after each call (and MKL's OpenMP threads 0.2 s), taking the
#: cores from the other library's threads on a 2-core machine; both read these when they
#: load, so they only act when set before numpy and MKL are imported.
#: ``PIPELINE_RETAIN_HEAP``: :func:`pipeline._util.resources.retained_heap` may keep freed
#: memory in glibc's heap during iterative solves (inherited by batch workers).
PROCESS_SETTINGS = {"OPENBLAS_THREAD_TIMEOUT": "4", "KMP_BLOCKTIME": "0",
                    "PIPELINE_RETAIN_HEAP": "1"}


def tune_process() -> None:
    """Set :data:`PROCESS_SETTINGS` in this process's environment (a value already in the
    environment wins). Call it before anything imports numpy."""
    for name, value in PROCESS_SETTINGS.items():
        os.environ.setdefault(name, value)
