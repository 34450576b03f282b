"""Reduced models of flexible bodies from 3D finite elements.

Data flow, one module per stage::

    config -> mesh -> fespace/regions -> assemble -> modes -> reduce -> store

Every stage is a function of arrays and small frozen dataclasses; :mod:`pipeline.run`
chains them and the CLI (``python -m pipeline``) calls the same functions.
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



def load_model(path):
    """Load a reduced model from an HDF5 file (see :func:`pipeline.store.read.load_model`)."""
    from pipeline.store.read import load_model as _load

    return _load(path)


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
