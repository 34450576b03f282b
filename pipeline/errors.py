"""Exception types of the pipeline.

Every error a user can cause (a bad config, a mesh gmsh cannot make, a singular
system, a file that is not ours) is raised as a subclass of :class:`PipelineError`.
Each carries structured fields, so that callers and tests act on what went wrong
rather than on message text:

``key``
    the dotted config key, the file or the object concerned (``"mesh.size"``,
    ``"outputs/run.h5"``, a dataset path of :mod:`pipeline.store.layout`), or None;
``value``
    the value received (any object; shown shortened), or None;
``expected``
    what would have been accepted, in words, or None.

``str(exc)`` is always one line. The CLI turns these into that line on stderr and the
class's ``exit_code``; anything else is a bug and keeps its traceback.

>>> e = ConfigError.field("mesh.size", -1.0, "a number > 0")
>>> str(e), e.key, e.value, e.exit_code
("config key 'mesh.size': got -1.0, expected a number > 0", 'mesh.size', -1.0, 2)
"""

from __future__ import annotations

from typing import Any


class PipelineError(Exception):
    """Base class of every error the pipeline reports to a user.

    Parameters
    ----------
    message : the one-line text; built from the fields when omitted.
    key, value, expected : see the module docstring.
    """

    exit_code = 1
    #: how the ``key`` is introduced in a message built from the fields
    subject = "key"

    def __init__(self, message: str | None = None, *, key: str | None = None,
                 value: Any = None, expected: str | None = None):
        if message is None:
            from pipeline._util.validate import describe

            parts = [f"{self.subject} '{key}'" if key is not None else self.subject]
            if value is not None:
                parts.append(f"got {describe(value)}")
            if expected is not None:
                parts.append(f"expected {expected}")
            message = parts[0] + ": " + ", ".join(parts[1:]) if len(parts) > 1 else parts[0]
        message = " ".join(str(message).split())  # one line, whatever the parts held
        super().__init__(message)
        self.key = key
        self.value = value
        self.expected = expected

    @classmethod
    def field(cls, key: str, value: Any, expected: str):
        """The error for ``key`` holding ``value`` where ``expected`` was needed."""
        return cls(key=key, value=value, expected=expected)


class ConfigError(PipelineError, ValueError):
    """A config key is unknown, missing, of the wrong type or out of range."""

    exit_code = 2
    subject = "config key"


class MeshError(PipelineError):
    """gmsh could not mesh the geometry, or the mesh is empty or inverted."""

    exit_code = 3
    subject = "mesh"


class RegionError(PipelineError, ValueError):
    """A named region is missing or empty, or a port on it is ill-posed."""

    exit_code = 4
    subject = "region"


class SolverError(PipelineError):
    """A factorisation failed (singular system) or an eigensolver did not converge."""

    exit_code = 5
    subject = "solver"


class ResourceError(PipelineError):
    """The problem would need more memory than the machine has."""

    exit_code = 6
    subject = "resource"


class FileFormatError(PipelineError):
    """An HDF5 file is not ours, has an unknown schema version, or is corrupt.

    ``key`` is the file's path; ``value`` the offending object or attribute when known.
    """

    exit_code = 7
    subject = "file"


class OutputError(PipelineError):
    """A destination cannot be written: missing or read-only folder, a directory where a
    file is wanted, no space left. ``key`` is the path."""

    exit_code = 8
    subject = "output"
