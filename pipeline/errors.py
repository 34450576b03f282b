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

``str(exc)`` is always one line; :func:`short_repr` and :func:`describe` show a value in
it, bounded and safe on hostile input. This module imports nothing from the package
(the lowest layer), so every layer, :mod:`pipeline._util.validate` included, raises these. The CLI turns these into that line on stderr and the
class's ``exit_code``; anything else is a bug and keeps its traceback.

>>> e = ConfigError.field("mesh.size", -1.0, "a number > 0")
>>> str(e), e.key, e.value, e.exit_code
("config key 'mesh.size': got -1.0, expected a number > 0", 'mesh.size', -1.0, 2)
"""

from __future__ import annotations

import itertools
from typing import Any, Mapping


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


# ----------------------------------------------------------------- values in messages
def short_repr(value: Any, depth: int = 0) -> str:
    """repr() bounded in depth, length and size: safe on hostile input (deep nesting,
    shared sub-lists that would expand exponentially, ints of thousands of digits).
    Strings with repeated spaces, which a one-line message would collapse, have their
    spaces written as \\x20.

    >>> print(short_repr("a b"), short_repr("a  b"))
    'a b' 'a\\x20\\x20b'
    """
    if isinstance(value, bool) or value is None or isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        if value.bit_length() <= 128:
            return repr(value)
        return f"<an integer of about {int(value.bit_length() * 0.30103) + 1} digits>"
    if isinstance(value, (str, bytes)):
        text = repr(value[:100])
        if "  " in text:  # a one-line message collapses repeated spaces: keep them seen
            text = text.replace(" ", "\\x20")
        return text if len(value) <= 100 else text[:-1] + "..." + text[-1]
    if depth >= 3:
        return "[...]" if isinstance(value, (list, tuple)) else "{...}" \
            if isinstance(value, Mapping) else f"<{type(value).__name__}>"
    if isinstance(value, (list, tuple)):
        items = [short_repr(v, depth + 1) for v in value[:6]]
        if len(value) > 6:
            items.append("...")
        body = ", ".join(items)
        if isinstance(value, list):
            return f"[{body}]"
        return f"({body},)" if len(value) == 1 else f"({body})"
    if isinstance(value, Mapping):
        items = [f"{short_repr(k, depth + 1)}: {short_repr(v, depth + 1)}"
                 for k, v in itertools.islice(value.items(), 6)]
        if len(value) > 6:
            items.append("...")
        return "{" + ", ".join(items) + "}"
    try:
        return repr(value)[:100]
    except Exception:  # a hostile __repr__ must not hide the config error
        return f"<{type(value).__name__}>"


def describe(value: Any) -> str:
    """:func:`short_repr` of ``value``, at most 80 characters."""
    text = short_repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
