"""The one safe YAML reader: configs, scenario files, batch files and ``--set`` values.

Safe loading only (no tag constructs a Python object), YAML 1.2 floats (``69.0e9``),
and every failure (syntax, nesting, an unreadable scalar, an unreadable file) becomes
one :class:`~pipeline.errors.ConfigError` line naming where.

>>> parse_yaml("E: 69.0e9", "example")
{'E': 69000000000.0}
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError


def safe_loader():
    """yaml.SafeLoader that also reads YAML 1.2 floats such as ``69.0e9`` and ``1e-3``.

    PyYAML follows YAML 1.1, where an exponent needs a sign and a dot, so ``69.0e9``
    would be a string. Safe loading only: no tag constructs a Python object.
    """
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    float_re = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""", re.X)
    Loader.yaml_implicit_resolvers = {k: list(v) for k, v in
                                      yaml.SafeLoader.yaml_implicit_resolvers.items()}
    for first in list("-+0123456789."):
        Loader.yaml_implicit_resolvers[first] = [
            (tag, regexp) for tag, regexp in Loader.yaml_implicit_resolvers.get(first, [])
            if tag != "tag:yaml.org,2002:float"]
    Loader.add_implicit_resolver("tag:yaml.org,2002:float", float_re, list("-+0123456789."))
    return Loader


def parse_yaml(text: str, where: str) -> Any:
    import yaml

    try:
        return yaml.load(text, Loader=safe_loader())  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        pos = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        first = (str(exc).splitlines() or [type(exc).__name__])[0]
        problem = getattr(exc, "problem", None) or first
        raise ConfigError(f"{where}: not valid YAML{pos}: {problem}", key=where) from None
    except RecursionError:
        raise ConfigError(f"{where}: not valid YAML: nested too deeply") from None
    except (ValueError, OverflowError, TypeError) as exc:
        # a scalar the safe constructors refuse: an int of more than 4300 digits, a date
        # such as 2020-02-30, ...
        problem = (str(exc).splitlines() or [type(exc).__name__])[0][:200]
        if "integer string conversion" in problem:
            problem = "an integer of more than 4300 digits"
        raise ConfigError(f"{where}: not valid YAML: a value cannot be read ({problem})") from None


def read_yaml(path: str | Path, what: str = "file") -> Any:
    """Parse the YAML file ``path``; ``what`` names it in errors (``config file``)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{what} '{path}': not found", key=str(path)) from None
    except IsADirectoryError:
        raise ConfigError(f"{what} '{path}': is a directory, expected a YAML file",
                          key=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{what} '{path}': cannot be read ({exc})", key=str(path)) from None
    return parse_yaml(text, f"{what} '{path}'")
