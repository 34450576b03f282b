"""Exception types of the pipeline.

Every error a user can cause (a bad config, a mesh gmsh cannot make, a singular
system, a file that is not ours) is raised as a subclass of :class:`PipelineError`
with one message that names the key or file, the value received and what was
expected. The CLI turns these into one line on stderr and a non-zero exit code;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class PipelineError(Exception):
    """Base class of every error the pipeline reports to a user."""

    exit_code = 1


class ConfigError(PipelineError, ValueError):
    """A config key is unknown, missing, of the wrong type or out of range."""

    exit_code = 2


class MeshError(PipelineError):
    """gmsh could not mesh the geometry, or the mesh is empty or inverted."""

    exit_code = 3


class RegionError(PipelineError, ValueError):
    """A named region is missing or empty, or a port on it is ill-posed."""

    exit_code = 4


class SolverError(PipelineError):
    """A factorisation failed (singular system) or an eigensolver did not converge."""

    exit_code = 5


class ResourceError(PipelineError):
    """The problem would need more memory than the machine has."""

    exit_code = 6


class FileFormatError(PipelineError):
    """An HDF5 file is not ours, has an unknown schema version, or is corrupt."""

    exit_code = 7
