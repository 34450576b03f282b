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


#: the largest YAML file read (configs, scenarios, batch files are a few kB)
MAX_YAML_BYTES = 4 << 20
#: the most aliases (``*name``) a document may use ("billion laughs" structures)
MAX_ALIASES = 1000


def read_text_bounded(path: str | Path, what: str = "file",
                      limit: int = MAX_YAML_BYTES) -> str:
    """The UTF-8 text of ``path``, at most ``limit`` bytes.

    ``path`` is a regular file, or a pipe or character device such as ``/dev/stdin``,
    ``<(envsubst < cfg.yaml)`` (``/dev/fd/63``) or a named FIFO: those are read as a
    stream, at most ``limit`` + 1 bytes, so ``/dev/zero`` or an endless writer is refused
    as too large rather than filling memory. A FIFO is opened non-blocking (opening a named
    FIFO without a writer would wait forever) and then read blocking: a FIFO with no writer
    reads as empty. A socket or a block device is refused with one :class:`ConfigError`
    line before anything is read; so is a larger file. ``FileNotFoundError``, other
    ``OSError`` and ``UnicodeDecodeError`` propagate for the caller's own message.
    """
    import os
    import stat

    path = Path(path)
    if path.exists() and not path.is_dir() and not _readable_kind(path.stat().st_mode):
        raise ConfigError(f"{what} '{path}': not a regular file, pipe or character device "
                          "(a socket or block device); expected a YAML file", key=str(path))
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    with os.fdopen(fd, "rb") as fh:
        mode = os.fstat(fh.fileno()).st_mode
        if not _readable_kind(mode):
            raise ConfigError(f"{what} '{path}': not a regular file, pipe or character "
                              "device; expected a YAML file", key=str(path))
        if not stat.S_ISREG(mode):
            os.set_blocking(fh.fileno(), True)  # a stream: wait for its writer's data
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise ConfigError(f"{what} '{path}': larger than {limit >> 20} MiB; expected a YAML "
                          "file of a few kB", key=str(path))
    return data.decode("utf-8")


def _readable_kind(mode: int) -> bool:
    """A regular file, a FIFO/pipe or a character device (``/dev/stdin`` on a terminal)."""
    import stat

    return stat.S_ISREG(mode) or stat.S_ISFIFO(mode) or stat.S_ISCHR(mode)


def is_stream(path: str | Path) -> bool:
    """Whether ``path`` is a pipe or device rather than a file in a folder: not a regular
    file, or named under /dev or /proc (``<(...)`` is /dev/fd/63; ``/dev/stdin`` is a
    regular file when the shell redirects one into it). A config read so resolves its
    relative paths against the current directory: the folder it names holds no inputs."""
    import stat

    if str(path).startswith(("/dev/", "/proc/")):
        return True
    try:
        return not stat.S_ISREG(Path(path).stat().st_mode)
    except (OSError, ValueError):
        return False


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

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            self.n_aliases = getattr(self, "n_aliases", 0) + 1
            if self.n_aliases > MAX_ALIASES:
                event = self.peek_event()
                raise yaml.composer.ComposerError(
                    None, None, f"more than {MAX_ALIASES} aliases (a 'billion laughs' "
                    "structure?)", event.start_mark)
        return yaml.SafeLoader.compose_node(self, parent, index)

    Loader.compose_node = compose_node
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
        text = read_text_bounded(path, what)
    except FileNotFoundError:
        raise ConfigError(f"{what} '{path}': not found", key=str(path)) from None
    except IsADirectoryError:
        raise ConfigError(f"{what} '{path}': is a directory, expected a YAML file",
                          key=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{what} '{path}': cannot be read ({exc})", key=str(path)) from None
    return parse_yaml(text, f"{what} '{path}'")
