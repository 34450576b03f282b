"""The batch file: read, validate, and resolve into a typed :class:`BatchSpec`.

A batch file names a base config and the cases to derive from it::

    batch:
      name: mesh_convergence              # output folder outputs/<name>/ (default: file stem)
      description: free text for the report
      base: configs/cantilever.yaml       # a config file (relative to the working directory,
                                          # else to the batch file), or an inline mapping
      set: {modes.count: 6}               # overrides applied to every case (optional)
      sweep:                              # dotted key -> list of values
        mesh.size: [0.01, 0.005, 0.0025]
        constraints.in_plane: [false, true]
      combine: product                    # product (every combination) | zip (i-th with i-th)
      cases:                              # explicit cases, after the sweep's (optional)
        - {label: steel, set: {material.E: 210e9, material.rho: 7850}}
        - {geometry.height: 0.03}         # a plain mapping of overrides also works

Overrides use the dotted paths of ``--set`` (``supports[0].fix``). Fields are checked by
:mod:`pipeline._util.validate` and the YAML is read by :mod:`pipeline._util.yamlio`; every
case is resolved and validated (:func:`pipeline.config.config_from_dict`) before anything
runs. Any error is one :class:`~pipeline.errors.ConfigError` naming the batch file, the
key and, for an invalid case, the case (all invalid cases, not just the first).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline._util import validate as v
from pipeline._util.yamlio import read_yaml
from pipeline.apps.batch.cases import (
    Case,
    CaseEntry,
    Override,
    resolve_cases,
    sweep_points,
)
from pipeline.errors import ConfigError

__all__ = ["BATCH_KEYS", "CASE_KEYS", "COMBINE", "BatchSpec", "load_batch"]

BATCH_KEYS = ("name", "description", "base", "set", "sweep", "combine", "cases")
CASE_KEYS = ("label", "set")
COMBINE = ("product", "zip")
KEY_PATH_RE = re.compile(r"^[A-Za-z0-9_\-]+(\.[A-Za-z0-9_\-]+|\[\d+\])*$")
KEY_PATH_EXPECTED = "a dotted config key path such as mesh.size or supports[0].fix"


@dataclass(frozen=True)
class BatchSpec:
    """A validated batch file with every case resolved."""

    name: str
    path: Path
    base: str                    # the base config file ("<inline>" for a mapping)
    description: str
    combine: str                 # product | zip
    common: tuple[Override, ...]
    sweep_keys: tuple[str, ...]
    case_keys: tuple[str, ...]   # every key some case overrides (sweep first)
    cases: tuple[Case, ...]


def override_items(raw: Any, where: str) -> list[Override]:
    """``{dotted key: value}`` of ``where`` as (key, value) pairs; None gives none."""
    if raw is None:
        return []
    if not isinstance(raw, Mapping):
        raise v.fail(where, raw, "a mapping of dotted config keys to values, e.g. "
                     "{mesh.size: 0.005}")
    for key in raw:
        if not isinstance(key, str) or not KEY_PATH_RE.match(key):
            raise v.fail(f"{where}.{v.key_text(key)}", key, KEY_PATH_EXPECTED)
    return list(raw.items())


def resolve_base(base: Any, batch_path: Path) -> tuple[dict, str, str]:
    """(raw config mapping, source path for relative geometry paths, display name)."""
    if isinstance(base, Mapping):
        return dict(base), str(batch_path), "<inline>"
    if not isinstance(base, str) or not base.strip():
        raise v.fail("batch.base", base, "a config file path or an inline config mapping")
    candidates = [Path(base)] if Path(base).is_absolute() else [Path(base),
                                                                 batch_path.parent / base]
    for cand in candidates:
        if cand.is_file():
            raw = read_yaml(cand, "base config file")
            if not isinstance(raw, Mapping):
                raise v.fail("batch.base", base, f"a config file holding a mapping of config "
                             f"keys ('{cand}' does not)")
            return dict(raw), str(cand), str(cand)
    looked = " or ".join(f"'{c}'" for c in dict.fromkeys(str(c) for c in candidates))
    raise ConfigError(f"config key 'batch.base': config file '{base}' not found (looked for "
                      f"{looked})", key="batch.base", value=base, expected="an existing file")


def sweep_lists(raw: Any, combine: str) -> tuple[list[str], list[list]]:
    """(swept keys, their value lists) of ``batch.sweep``."""
    if raw is None:
        return [], []
    if not isinstance(raw, Mapping) or not raw:
        raise v.fail("batch.sweep", raw, "a mapping of dotted config keys to lists of values")
    keys, lists = [], []
    for key, values in override_items(raw, "batch.sweep"):
        if not isinstance(values, list) or not values:
            raise v.fail(f"batch.sweep.{key}", values, "a non-empty list of values")
        keys.append(key)
        lists.append(values)
    lengths = {k: len(x) for k, x in zip(keys, lists)}
    if combine == "zip" and len(set(lengths.values())) > 1:
        detail = ", ".join(f"{k}: {n}" for k, n in lengths.items())
        raise ConfigError(f"config key 'batch.sweep': combine 'zip' needs lists of equal "
                          f"length, got {detail}", key="batch.sweep", value=lengths,
                          expected="lists of equal length")
    return keys, lists


def case_entries(raw: Any) -> list[CaseEntry]:
    """The explicit cases of ``batch.cases``."""
    items = v.items({"cases": raw}, "cases", "batch")
    entries = []
    for i, item in enumerate(items):
        where = f"batch.cases[{i}]"
        if isinstance(item, Mapping) and item and set(item) <= set(CASE_KEYS):
            label = item.get("label")
            if label is not None and not isinstance(label, str):
                raise v.fail(f"{where}.label", label, "text")
            entries.append(CaseEntry(label, tuple(override_items(item.get("set") or {},
                                                                 f"{where}.set")), "case"))
        elif isinstance(item, Mapping):
            entries.append(CaseEntry(None, tuple(override_items(item, where)), "case"))
        else:
            raise v.fail(where, item, "{label: ..., set: {key: value}} or a mapping of "
                         "overrides")
    return entries


def load_batch(path: str | Path) -> BatchSpec:
    """Read and validate a batch file: every case is resolved and checked here.

    Raises ConfigError naming the batch file, the case (number and overrides) and the
    config key for every invalid case (all of them, not just the first).
    """
    path = Path(path)
    file = str(path)
    try:
        return _load(path)
    except ConfigError as exc:
        text = str(exc)
        if text.startswith(f"batch file '{file}'"):
            raise
        raise ConfigError(f"batch file '{file}': {text}", key=exc.key, value=exc.value,
                          expected=exc.expected) from None


def _load(path: Path) -> BatchSpec:
    doc = read_yaml(path, "batch file")
    if not isinstance(doc, Mapping) or set(doc) != {"batch"}:
        raise v.fail("<root>", sorted(map(str, doc)) if isinstance(doc, Mapping) else doc,
                      "one top-level key 'batch'")
    raw = v.mapping(doc["batch"], "batch", BATCH_KEYS, required=("base",))
    name = v.name(raw, "name", "batch", default=path.stem)
    description = raw.get("description") or ""
    if not isinstance(description, str):
        raise v.fail("batch.description", description, "text")
    combine = raw.get("combine", "product")
    if combine not in COMBINE:
        raise v.fail("batch.combine", combine, "product or zip")
    base_raw, source, base_name = resolve_base(raw["base"], path)
    common = override_items(raw.get("set"), "batch.set")
    sweep_keys, lists = sweep_lists(raw.get("sweep"), combine)
    entries = [CaseEntry(None, point, "sweep") for point in sweep_points(sweep_keys, lists,
                                                                        combine)]
    entries += case_entries(raw.get("cases"))
    if not entries:
        entries = [CaseEntry("base", (), "base")]
    cases, errors = resolve_cases(base_raw, source, common, entries)
    if errors:
        raise ConfigError(f"batch file '{path}': {len(errors)} of {len(entries)} cases are "
                          "invalid; nothing was run:\n  " + "\n  ".join(errors))
    case_keys = list(sweep_keys)
    for entry in entries:
        case_keys += [k for k, _ in entry.overrides if k not in case_keys]
    return BatchSpec(name=name, path=path, base=base_name, description=description,
                     combine=combine, common=tuple(common), sweep_keys=tuple(sweep_keys),
                     case_keys=tuple(case_keys), cases=tuple(cases))
