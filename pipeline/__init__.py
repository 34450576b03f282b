"""Reduced models of flexible bodies from 3D finite elements.

Data flow, one subpackage per stage::

    config -> fe (mesh, space, regions, assemble, body, ports) -> solve (factorise,
    eigenmodes) -> reduce (StateSpace models) -> store (the HDF5 file)

:mod:`pipeline.run` chains the stages; :mod:`pipeline.apps` (simulate, batch, plots,
exports, summary) uses a result file through :mod:`pipeline.store.read` only; the CLI
(``python -m pipeline``, :mod:`pipeline.cli`) calls the same functions.
"""

__version__ = "0.1.0"

import os as _os  # noqa: E402

# OpenBLAS (numpy's and scipy's BLAS) keeps its worker threads spinning for 2^28 cycles
# (about 0.1 s) after every call; on two cores they take the CPU from MKL's threads
# (PARDISO's solves, the sparse products) that run next. Measured on the AMD machine:
# a 4-right-hand-side PARDISO solve pair after a numpy product 149-163 ms, 91-99 ms with
# 2^4 cycles; whole runs, alternated: 100k DOFs 5.4-7.1 -> 4.7-6.0 s, 1M 65-70 ->
# 61-65 s, 3M 215 -> 204 s (docs/performance.md). OpenBLAS reads this when it loads, so it is set here, before
# anything imports numpy; a value in the environment wins, and where numpy was imported
# first it has no effect (like KMP_BLOCKTIME for MKL in pipeline.solve.factorize).
_os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")

from pipeline.errors import (  # noqa: E402
    ConfigError,
    FileFormatError,
    MeshError,
    PipelineError,
    RegionError,
    ResourceError,
    SolverError,
)



def load_model(path, require_plant: bool = False):
    """Load every reduced model of an HDF5 file (see :func:`pipeline.store.read.load_model`).

    Imported on first use, so ``import pipeline`` stays light (no h5py, no control)."""
    from pipeline.store.read import load_model as _load

    return _load(path, require_plant=require_plant)


__all__ = [
    "load_model",
    "__version__",
    "ConfigError",
    "FileFormatError",
    "MeshError",
    "PipelineError",
    "RegionError",
    "ResourceError",
    "SolverError",
]
