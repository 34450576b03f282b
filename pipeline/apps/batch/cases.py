"""The cases of a batch: sweeps expanded into cases, their cache keys and memory estimates.

A sweep of ``k`` dotted keys with value lists ``v_1 ... v_k`` gives, with ``combine:
product``, every combination (``len(v_1) * ... * len(v_k)`` points, the last key varying
fastest) and, with ``combine: zip``, the i-th values together (lists of equal length).
Each point, and each explicit case, is a list of ``(dotted key, value)`` overrides applied
to the base config (after the overrides common to every case), then resolved and
validated into a :class:`~pipeline.config.Config`.

``case_key``: 16 hex digits of SHA-256 over the resolved config's YAML, the pipeline
version and the bytes of a geometry file, if any. ``estimate_case_memory``: peak bytes
(:func:`pipeline.run.estimate_memory_bytes`) of a mesh whose size is predicted from the
config before meshing (:func:`predict_mesh_size`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pipeline._version import __version__
from pipeline.config import Config, apply_overrides, config_from_dict, config_to_yaml
from pipeline._util.paths import file_sha256
from pipeline.errors import ConfigError
from pipeline.run import estimate_box_mesh, estimate_memory_bytes

__all__ = [
    "RECORD_VERSION",
    "Case",
    "CaseEntry",
    "Override",
    "case_key",
    "estimate_case_memory",
    "format_value",
    "portable_config",
    "predict_mesh_size",
    "resolve_cases",
    "sweep_points",
]

#: version of the case record and of the key's recipe (a change recomputes every case)
RECORD_VERSION = 1

Override = tuple[str, Any]  # (dotted config key, value)


@dataclass(frozen=True)
class CaseEntry:
    """One case as the batch file lists it, before it is resolved."""

    label: str | None                   # None: made from the overrides
    overrides: tuple[Override, ...]
    origin: str                         # sweep | case (the explicit list) | base


@dataclass(frozen=True)
class Case:
    """One case of a batch: its overrides, the resolved config and its cache key."""

    index: int                          # 1-based position in the batch
    label: str
    overrides: tuple[Override, ...]     # the sweep's or the case's
    config: Config | None
    key: str
    memory_bytes: int | None            # estimated peak memory, None if unknown
    origin: str = "sweep"               # sweep | case (the explicit list) | base

    @property
    def override_strings(self) -> list[str]:
        return [f"{k}={format_value(v)}" for k, v in self.overrides]


def format_value(value: Any) -> str:
    """A value as a label or table shows it: text as is, anything else as JSON."""
    if isinstance(value, str):
        return value
    return json.dumps(value)


def sweep_points(keys: Sequence[str], lists: Sequence[list], combine: str
                 ) -> list[tuple[Override, ...]]:
    """The overrides of every point of a sweep (``combine``: product | zip; zip needs
    lists of equal length, checked by the caller)."""
    if not keys:
        return []
    points = zip(*lists) if combine == "zip" else itertools.product(*lists)
    return [tuple(zip(keys, point)) for point in points]


def resolve_cases(base: Mapping[str, Any], source: str, common: Sequence[Override],
                  entries: Sequence[CaseEntry]) -> tuple[list[Case], list[str]]:
    """Resolve and validate every entry: (the cases, one message per invalid entry)."""
    cases, errors = [], []
    for index, entry in enumerate(entries, 1):
        label = entry.label or (", ".join(f"{k}={format_value(v)}" for k, v in entry.overrides)
                                or "base")
        # JSON is YAML that the config's reader gives back unchanged
        texts = [f"{k}={json.dumps(v)}" for k, v in (*common, *entry.overrides)]
        try:
            cfg = config_from_dict(apply_overrides(dict(base), texts), source=source)
        except ConfigError as exc:
            errors.append(f"case {index} ({label}): {exc}")
            continue
        cases.append(Case(index=index, label=label, overrides=tuple(entry.overrides),
                          config=cfg, key=case_key(cfg), memory_bytes=estimate_case_memory(cfg),
                          origin=entry.origin))
    return cases, errors


# --------------------------------------------------------------------------- keys
def case_key(cfg: Config) -> str:
    """Cache key of a resolved config: 16 hex digits of a SHA-256 over its YAML, the
    pipeline version and the bytes of a geometry file, if any."""
    digest = hashlib.sha256()
    digest.update(f"fe-reduced-body batch case v{RECORD_VERSION}\n".encode())
    digest.update(f"pipeline {__version__}\n".encode())
    digest.update(config_to_yaml(cfg).encode())
    geo_path = getattr(cfg.geometry, "path", "")
    if geo_path:
        try:
            digest.update(f"geometry file {file_sha256(geo_path)}\n".encode())
        except OSError:
            digest.update(f"geometry file {geo_path} unreadable\n".encode())
    return digest.hexdigest()[:16]


def portable_config(cfg: Config) -> Config:
    """``cfg`` with a relative geometry file path made absolute, as sent to workers (whose
    working folder may differ). The cache key is computed before, from ``cfg`` itself."""
    path = getattr(cfg.geometry, "path", "")
    if path and not os.path.isabs(path):
        return dataclasses.replace(cfg, geometry=dataclasses.replace(
            cfg.geometry, path=os.path.abspath(path)))
    return cfg


# --------------------------------------------------------------------------- memory
def predict_mesh_size(cfg: Config) -> tuple[int, int] | None:
    """(nodes, tetrahedra) a gmsh mesh of ``cfg`` will have, before meshing; None if unknown.

    For the box: the estimate of :mod:`pipeline.fe.mesh.estimate` (from the volume and the
    boundary area, through :func:`pipeline.run.estimate_box_mesh`; within 20 % of gmsh on
    meshes of 20k tetrahedra and more). A body drawn in a file is only known once gmsh
    has read it.
    """
    g = cfg.geometry
    if g.kind != "box":
        return None
    return estimate_box_mesh(g.length, g.height, g.depth, cfg.mesh.size, cfg.mesh.order)


def estimate_case_memory(cfg: Config) -> int | None:
    """Peak bytes a case will need (:func:`pipeline.run.estimate_memory_bytes`), or None
    when the mesh size cannot be predicted without meshing (geometry from a file)."""
    pred = predict_mesh_size(cfg)
    if pred is None:
        return None
    n_nodes, n_tet = pred
    return int(estimate_memory_bytes(n_nodes, n_tet, cfg.mesh.order, cfg.modes.count))
