"""``--set KEY=VALUE`` overrides of a raw config mapping, applied before validation.

KEY is a dotted path (``mesh.size``); list items are addressed by index
(``supports.0.region`` or ``supports[0].region``); VALUE is parsed as YAML.
"""

from __future__ import annotations

import copy
import re
from typing import Any, Mapping, Sequence

from pipeline._util import validate as v
from pipeline._util.yamlio import parse_yaml
from pipeline.errors import ConfigError


def _split_path(path: str) -> list[str]:
    parts = [p for p in re.split(r"\.|\[(\d+)\]", path) if p]
    if not parts or any(not re.fullmatch(r"[A-Za-z0-9_\-]+", p) for p in parts):
        shown = path if len(path) <= 80 and path.isprintable() else v.describe(path)[1:-1]
        raise ConfigError(f"override '{shown}': expected a dotted key path such as mesh.size")
    return parts


def apply_overrides(raw: Any, overrides: Sequence[str]) -> dict:
    """Apply ``KEY=VALUE`` overrides (VALUE parsed as YAML) to a raw config mapping.

    KEY is a dotted path (``mesh.size``); list items are addressed by index
    (``supports.0.region`` or ``supports[0].region``). Missing intermediate mappings are
    created, so the validator (not this function) decides whether a key is known.
    """
    try:
        data = copy.deepcopy(raw) if isinstance(raw, Mapping) else raw
    except RecursionError:
        raise ConfigError("config: nested too deeply to be a config") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config: got {v.describe(raw)}, expected a mapping at the top level")
    for item in overrides:
        if not isinstance(item, str):
            raise ConfigError(f"override {v.describe(item)}: expected KEY=VALUE text")
        shown = item if len(item) <= 80 and item.isprintable() else v.describe(item)[1:-1]
        if "=" not in item:
            raise ConfigError(f"override '{shown}': expected KEY=VALUE, e.g. mesh.size=0.004")
        key, text = item.split("=", 1)
        parts = _split_path(key.strip())
        value = parse_yaml(text, f"override '{shown}'")
        node: Any = data
        for depth, part in enumerate(parts[:-1]):
            nxt = parts[depth + 1]
            if isinstance(node, list):
                idx = int(part) if part.isdigit() else -1
                if not 0 <= idx < len(node):
                    raise ConfigError(f"override '{shown}': index {part} is out of range "
                                      f"(the list has {len(node)} items)")
                node = node[idx]
                continue
            if not isinstance(node, dict):
                raise ConfigError(f"override '{shown}': '{part}' is not inside a mapping")
            if part not in node or node[part] is None:
                node[part] = [] if nxt.isdigit() else {}
            node = node[part]
        last = parts[-1]
        if isinstance(node, list):
            idx = int(last) if last.isdigit() else -1
            if not 0 <= idx < len(node):
                raise ConfigError(f"override '{shown}': index {last} is out of range")
            node[idx] = value
        elif isinstance(node, dict):
            node[last] = value
        else:
            raise ConfigError(f"override '{shown}': '{last}' is not inside a mapping")
    return data
