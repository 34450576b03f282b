"""The one field checker: every value a user gives (config keys, scenario files, batch
files, ``--set`` overrides, CLI options) is checked by these functions, once, at the
boundary where it enters.

Each function takes the raw mapping, the key and the dotted path of the mapping, and
returns the checked value or raises :class:`~pipeline.errors.ConfigError` with ``key``
(the dotted path), ``value`` (as received) and ``expected`` (in words) set; the message
is one line. Pass ``error=`` another PipelineError subclass to report a different kind.

>>> number({"size": 0.004}, "size", "mesh", lo=0, lo_open=True)
0.004
>>> try:
...     number({"force": 1e400}, "force", "scenarios[0]")
... except Exception as exc:
...     print(exc.key, exc.expected)
scenarios[0].force a finite number
"""

from __future__ import annotations

import math
import re
from typing import Any, Mapping, Sequence

from pipeline.errors import ConfigError, describe, short_repr

MISSING = object()
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")  # use with fullmatch (no "\n")

def key_text(key: Any) -> str:
    """A config key as it appears in a message: itself if short and printable, else
    escaped (no quotes, no newlines) and shortened. Spaces that a one-line message would
    collapse or hide (leading, trailing, repeated) are written as \\x20.

    >>> key_text("  "), key_text(" name"), key_text("a b")
    ('\\\\x20\\\\x20', '\\\\x20name', 'a b')
    """
    if isinstance(key, str):
        text = key if key.isprintable() else key.encode("unicode_escape").decode("ascii")
        text = text.replace("'", "\\x27")
        if " ".join(text.split()) != text:
            text = text.replace(" ", "\\x20")
    elif key is None or isinstance(key, (bool, int, float)):
        text = short_repr(key)
    else:
        text = f"<{type(key).__name__}>"
    return text if len(text) <= 64 else text[:61] + "..."


def fail(path: str, value: Any, expected: str, error: type = ConfigError) -> Exception:
    """The error for key ``path`` holding ``value`` where ``expected`` was needed."""
    return error(f"config key '{path}': got {describe(value)}, expected {expected}",
                 key=path, value=value, expected=expected)


def missing(where: str) -> ConfigError:
    """The error for a required key ``where`` that is absent."""
    return ConfigError(f"config key '{where}' is missing; it is required", key=where,
                       expected="a value (the key is required)")


def mapping(raw: Any, path: str, allowed: Sequence[str], required: Sequence[str] = ()) -> dict:
    if not isinstance(raw, Mapping):
        raise fail(path or "<root>", raw, "a mapping of keys to values")
    for key in raw:
        if not isinstance(key, str) or key not in allowed:
            where = f"{path}.{key_text(key)}" if path else key_text(key)
            raise ConfigError(
                f"config key '{where}' is not known; expected one of: {', '.join(allowed)}",
                key=where, value=key, expected="one of: " + ", ".join(allowed))
    for key in required:
        if key not in raw:
            where = f"{path}.{key}" if path else key
            raise missing(where)
    return dict(raw)


def number(raw: Mapping, key: str, path: str, default: Any = MISSING, *, lo: float | None = None,
            hi: float | None = None, lo_open: bool = False, hi_open: bool = False) -> float:
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is MISSING:
        raise missing(where)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise fail(where, value, "a number")
    try:
        value = float(value)
    except OverflowError:  # an int beyond the float range
        raise fail(where, value, "a finite number") from None
    if not math.isfinite(value):
        raise fail(where, value, "a finite number")
    lo_ok = lo is None or (value > lo if lo_open else value >= lo)
    hi_ok = hi is None or (value < hi if hi_open else value <= hi)
    if not (lo_ok and hi_ok):
        left = "" if lo is None else ("(" if lo_open else "[") + f"{lo:g}"
        right = "" if hi is None else f"{hi:g}" + (")" if hi_open else "]")
        if lo is not None and hi is not None:
            rng = f"a number in {left}, {right}"
        elif lo is not None:
            rng = f"a number {'>' if lo_open else '>='} {lo:g}"
        else:
            rng = f"a number {'<' if hi_open else '<='} {hi:g}"
        raise fail(where, value, rng)
    return value


def integer(raw: Mapping, key: str, path: str, default: Any = MISSING, *, lo: int | None = None,
             hi: int | None = None) -> int:
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is MISSING:
        raise missing(where)
    if isinstance(value, bool) or not isinstance(value, int):
        raise fail(where, value, "an integer")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        bounds = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise fail(where, value, f"an integer {bounds}")
    return value


def choice(raw: Mapping, key: str, path: str, choices: Sequence[Any], default: Any = MISSING) -> Any:
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is MISSING:
        raise missing(where)
    if isinstance(value, bool) and not any(isinstance(c, bool) for c in choices):
        raise fail(where, value, "one of " + " | ".join(map(str, choices)))
    if not any(type(value) is type(c) and value == c for c in choices):
        raise fail(where, value, "one of " + " | ".join(map(str, choices)))
    return value


def boolean(raw: Mapping, key: str, path: str, default: bool) -> bool:
    value = raw.get(key, default)
    if not isinstance(value, bool):
        raise fail(f"{path}.{key}", value, "true or false")
    return value


def name(raw: Mapping, key: str, path: str, default: Any = MISSING) -> str:
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is MISSING:
        raise missing(where)
    if not isinstance(value, str) or not NAME_RE.fullmatch(value):
        raise fail(where, value, "a name of 1-64 letters, digits, '_', '-' or '.', "
                    "starting with a letter or digit")
    return value


def vector(raw: Mapping, key: str, path: str, default: Any = MISSING, *, nonzero: bool = False):
    where = f"{path}.{key}" if path else key
    value = raw.get(key, default)
    if value is MISSING:
        raise missing(where)
    if value is None and default is None:
        return None
    expected = "a list of three finite numbers [x, y, z]"
    if not (isinstance(value, (list, tuple)) and len(value) == 3
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise fail(where, value, expected)
    try:
        vec = tuple(float(v) for v in value)
    except OverflowError:  # an int beyond the float range
        raise fail(where, value, expected) from None
    if not all(math.isfinite(v) for v in vec):
        raise fail(where, value, expected)
    if nonzero:
        square = sum(v * v for v in vec)
        if not math.isfinite(square):  # |d|^2 overflows: normalising it would give 0
            raise fail(where, value, "a direction whose squared length is a finite number "
                        "(scale it down)")
        if math.sqrt(square) < 1e-12:
            raise fail(where, value, "a non-zero direction")
    return vec


def items(raw: Mapping, key: str, path: str) -> list:
    value = raw.get(key, [])
    if value is None:
        return []
    if not isinstance(value, list):
        raise fail(f"{path}.{key}" if path else key, value, "a list")
    return value
