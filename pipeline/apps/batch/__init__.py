"""Batch runs: parameter sweeps of one base config, in parallel, cached, resumable.

One module per job:

* :mod:`~pipeline.apps.batch.spec`: the batch file, read and validated into a
  :class:`BatchSpec` (its format is documented there);
* :mod:`~pipeline.apps.batch.cases`: sweeps expanded into :class:`Case` records, cache
  keys, memory estimates;
* :mod:`~pipeline.apps.batch.cache`: the :class:`CaseRecord` of every case (JSON beside
  its HDF5 file) and the cache check;
* :mod:`~pipeline.apps.batch.worker`: one case on a Dask worker, in a forked process;
* :mod:`~pipeline.apps.batch.scheduler`: :func:`run_batch`: the local or remote Dask
  cluster, memory-aware admission, locking, progress;
* :mod:`~pipeline.apps.batch.outcome`: :class:`BatchResult`, :class:`CaseOutcome`;
* :mod:`~pipeline.apps.batch.report`, :mod:`~pipeline.apps.batch.plots`,
  :mod:`~pipeline.apps.batch.gains`: ``summary.csv``, ``report.html`` and the PNG plots.

Outputs, under ``outputs/<name>/`` (or ``-o DIR``)::

    cases/<key>.h5     the HDF5 file of the case (written atomically: it exists only complete)
    cases/<key>.json   its record: status, error, DOFs, times, peak memory, frequencies
    cases/<key>.log    the pipeline's log of the run
    summary.csv, report.html, *.png

``<key>`` is a hash of the resolved config (its YAML), the pipeline version and, for a
geometry read from a file, that file's bytes. A case whose file exists and is intact is
not computed again (a re-run says so); a failed case is retried on the next run. An
interrupted batch is resumed by running it again: finished cases are kept, partial files
are removed and never taken for results.

The command line (``python -m pipeline batch``) is :mod:`pipeline.cli.batch`.
"""

from __future__ import annotations


from pipeline.apps.batch.cache import CaseRecord
from pipeline.apps.batch.cases import (
    Case,
    case_key,
    estimate_case_memory,
    portable_config,
    predict_mesh_size,
)
from pipeline.apps.batch.outcome import BatchResult, CaseOutcome
from pipeline.apps.batch.scheduler import (
    admit,
    plan_local_workers,
    run_batch,
    split_by_budget,
)
from pipeline.apps.batch.spec import BatchSpec, load_batch
from pipeline.apps.batch.worker import TaskResult, run_case_task

__all__ = [
    "BatchResult",
    "BatchSpec",
    "Case",
    "CaseOutcome",
    "CaseRecord",
    "TaskResult",
    "admit",
    "case_key",
    "estimate_case_memory",
    "load_batch",
    "plan_local_workers",
    "portable_config",
    "predict_mesh_size",
    "run_batch",
    "run_case_task",
    "split_by_budget",
]
