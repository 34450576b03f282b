"""Reduced models of flexible bodies from 3D finite elements.

Data flow, one subpackage per stage::

    config -> fe (mesh, space, regions, assemble, body, ports) -> solve (factorise,
    eigenmodes) -> reduce (StateSpace models) -> store (the HDF5 file)

:mod:`pipeline.run` chains the stages; :mod:`pipeline.apps` (simulate, batch, plots,
exports, summary) uses a result file through :mod:`pipeline.store.read` only; the CLI
(``python -m pipeline``, :mod:`pipeline.cli`) calls the same functions.
"""

__version__ = "0.1.0"

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
