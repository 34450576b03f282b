"""Reduced models of flexible bodies from 3D finite elements.

Data flow, one module per stage::

    config -> mesh -> fespace/regions -> assemble -> modes -> reduce -> store

Every stage is a function of arrays and small frozen dataclasses; :mod:`pipeline.run`
chains them and the CLI (``python -m pipeline``) calls the same functions.
"""

__version__ = "0.1.0"

from .errors import (  # noqa: E402
    ConfigError,
    FileFormatError,
    MeshError,
    PipelineError,
    RegionError,
    ResourceError,
    SolverError,
)

__all__ = [
    "__version__",
    "ConfigError",
    "FileFormatError",
    "MeshError",
    "PipelineError",
    "RegionError",
    "ResourceError",
    "SolverError",
]
