"""Export a small JSON summary for scripts and dashboards.

``python -m pipeline export FILE.h5 --to json`` writes (SI units)::

    {"format": "fe-reduced-body summary", "version": 1,
     "name", "source_file", "created_utc", "pipeline_version",
     "body": {"mass_kg", "center_of_mass_m"},
     "mesh": {"points", "cells", "cell_type", "dofs"},
     "modes": [{"mode": 1, "frequency_hz": ..., "label": ...}, ...],
     "ports": {"inputs": [{"name", "region", "kind", "direction", "unit"}],
               "outputs": [...]},                  # from the run's config
     "reduced_model": {"states", "retained_modes", "damping_ratios", "static_correction",
                       "inputs", "outputs",
                       "dc_gain": {input: {position output: value}},
                       "dc_gain_full_fe": {...}},  # T K^-1 F of the full FE model
     "filtered_model": {"states", "filter_kind", "cutoff_hz", "dc_gain"} | null,
     "lumped_model": {"states", "frequencies_hz"} | null}

DC gains are ``D - C A^-1 B`` of each state space, for the position outputs; ``null``
where the model has no static gain (a free body keeps rigid modes: A is singular).
Everything not finite is written as ``null``, so any JSON parser reads the file.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from pipeline._util.atomic import write_text
from pipeline.store.layout import (BODY, LUMPED, LUMPED_STATESPACE, MESH, MODES, ROOT,
                                   STATESPACE, STATESPACE_FILTERED)
from pipeline.store.read import open_verified, read_names, read_strings

log = logging.getLogger(__name__)

__all__ = ["export", "summary", "FORMAT", "VERSION"]

FORMAT = "fe-reduced-body summary"
VERSION = 1


def _clean(value: Any) -> Any:
    """Plain JSON types; NaN/inf -> None."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, (np.bool_,)):
        return bool(value)
    return value


def _names(grp, key: str) -> list[str]:
    return list(read_names(grp, key))


def _dc_gain(h5, group) -> np.ndarray | None:
    """D - C A^-1 B of the state-space ``group`` (a layout Group), None when A is singular."""
    A, B, C, D = (np.atleast_2d(np.array(h5[group.dataset(k)][()], dtype=float))
                  for k in "ABCD")
    try:
        if np.linalg.cond(A) > 1e14:
            return None
        return D - C @ np.linalg.solve(A, B)
    except np.linalg.LinAlgError:
        return None


def _gain_table(gain: np.ndarray | None, inputs: list[str], outputs: list[str]) -> dict | None:
    if gain is None:
        return None
    pos = [i for i, n in enumerate(outputs) if n.endswith("/position")] or range(len(outputs))
    return {inp: {outputs[o]: gain[o, c] for o in pos} for c, inp in enumerate(inputs)}


def _ports(config_yaml: str | None, units: tuple[list[str], list[str]]) -> dict:
    if not config_yaml:
        return {"inputs": [], "outputs": []}
    import yaml

    try:
        raw = yaml.safe_load(config_yaml) or {}
    except yaml.YAMLError:
        return {"inputs": [], "outputs": []}
    ports = raw.get("ports") or {}
    out = {}
    for side, unit_list in (("inputs", units[0]), ("outputs", units[1])):
        items = []
        for i, p in enumerate(ports.get(side) or []):
            item = {k: p.get(k) for k in ("name", "region", "kind", "direction")}
            if i < len(unit_list):
                item["unit"] = unit_list[i]
            items.append(item)
        out[side] = items
    return out


def summary(h5_path: str | Path) -> dict:
    """The summary of ``h5_path`` (verified read) as a dict of plain JSON types."""
    h5_path = Path(h5_path)
    with open_verified(h5_path) as h5:
        a = h5.attrs
        freqs = np.array(h5[MODES.frequencies_hz][()], dtype=float)
        labels = read_strings(h5[MODES.labels])
        cells_group = h5[MESH.cells]
        kind = next(iter(cells_group))
        mesh_attrs = h5[MESH.path].attrs
        units: tuple[list[str], list[str]] = ([], [])
        reduced = filtered = lumped = None
        if STATESPACE.path in h5:
            ss = h5[STATESPACE.path]
            at = STATESPACE.attr
            units = (read_strings(ss.attrs[at.input_units]) if at.input_units in ss.attrs else [],
                     read_strings(ss.attrs[at.output_units]) if at.output_units in ss.attrs
                     else [])
            inputs, outputs = _names(ss, "input_names"), _names(ss, "output_names")
            damping = (np.array(h5[STATESPACE.damping_ratios][()])
                       if STATESPACE.damping_ratios in h5 else [])
            compliance = (np.atleast_2d(np.array(h5[STATESPACE.static_compliance][()]))
                          if STATESPACE.static_compliance in h5 else None)
            fe_gain = None
            if compliance is not None:
                pos = [o for o in outputs if o.endswith("/position")] or outputs
                fe_gain = {inp: {pos[o]: compliance[o, c] for o in range(min(len(pos),
                                                                             compliance.shape[0]))}
                           for c, inp in enumerate(inputs) if c < compliance.shape[1]}
            reduced = {
                "states": int(h5[STATESPACE.A].shape[0]),
                "retained_modes": int(len(damping)),
                "damping_ratios": damping,
                "static_correction": str(ss.attrs.get(at.static_correction, "")),
                "inputs": inputs,
                "outputs": outputs,
                "dc_gain": _gain_table(_dc_gain(h5, STATESPACE), inputs, outputs),
                "dc_gain_full_fe": fe_gain,
            }
            if STATESPACE_FILTERED.path in h5:
                fs = h5[STATESPACE_FILTERED.path]
                at = STATESPACE_FILTERED.attr
                f_out = _names(fs, "output_names")
                filtered = {
                    "states": int(h5[STATESPACE_FILTERED.A].shape[0]),
                    "filter_kind": str(fs.attrs.get(at.filter_kind, "")),
                    "cutoff_hz": float(fs.attrs[at.cutoff_hz]) if at.cutoff_hz in fs.attrs
                    else None,
                    "dc_gain": _gain_table(_dc_gain(h5, STATESPACE_FILTERED),
                                           _names(fs, "input_names"), f_out),
                }
        if LUMPED_STATESPACE.path in h5:
            lumped = {"states": int(h5[LUMPED_STATESPACE.A].shape[0])}
            if LUMPED.frequencies_hz in h5:
                lumped["frequencies_hz"] = np.array(h5[LUMPED.frequencies_hz][()])[:10]
        data = {
            "format": FORMAT,
            "version": VERSION,
            "name": str(a.get(ROOT.name, h5_path.stem)),
            "source_file": str(h5_path),
            "created_utc": str(a.get(ROOT.created_utc, "")),
            "pipeline_version": str(a.get(ROOT.pipeline_version, "")),
            "body": {"mass_kg": float(h5[BODY.mass][()]),
                     "center_of_mass_m": np.array(h5[BODY.center_of_mass][()])},
            "mesh": {"points": int(h5[MESH.points].shape[0]),
                     "cells": int(cells_group[kind].shape[0]), "cell_type": kind,
                     "dofs": int(mesh_attrs.get(MESH.attr.n_dofs, 3 * h5[MESH.points].shape[0]))},
            "modes": [{"mode": i + 1, "frequency_hz": f,
                       "label": labels[i] if i < len(labels) else ""} for i, f in enumerate(freqs)],
            "ports": _ports(a.get(ROOT.config_yaml), units),
            "reduced_model": reduced,
            "filtered_model": filtered,
            "lumped_model": lumped,
        }
    return _clean(data)


def export(h5_path: str | Path, out_path: str | Path) -> Path:
    """Write the JSON summary of ``h5_path`` to ``out_path``; returns it."""
    out_path = Path(out_path)
    text = json.dumps(summary(h5_path), indent=2, allow_nan=False) + "\n"
    write_text(out_path, text)
    log.info("wrote %s", out_path)
    return out_path
