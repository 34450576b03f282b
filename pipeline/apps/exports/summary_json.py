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
from pipeline.store.layout import MESH, MODES, STATESPACE, STATESPACE_FILTERED
from pipeline.store.read import LAYOUT_ERRORS, layout_error
from pipeline.store.summary import ModelSummary, read_summary

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


def _dc_gain(model: ModelSummary) -> np.ndarray | None:
    """D - C A^-1 B of ``model``, None when A is singular."""
    A, B, C, D = model.matrices
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
    s = read_summary(h5_path).require("modes", "mesh", "body")
    try:
        return _clean(_data(s))
    except LAYOUT_ERRORS as exc:
        raise layout_error(h5_path, exc) from None


def _data(s) -> dict:
    """The summary of the FileSummary ``s`` (numpy values kept)."""
    freqs, labels = s.modes.frequencies_hz, s.modes.labels
    if labels is None:
        raise KeyError(f"/{MODES.labels} missing")
    kind, n_cells = next(iter(s.mesh.cells.items())) if s.mesh.cells else (None, None)
    if kind is None:
        raise KeyError(f"/{MESH.cells} missing")
    units: tuple[list[str], list[str]] = ([], [])
    reduced = filtered = lumped = None
    ss = s.plant
    if ss is not None:
        if ss.n_states is None:
            raise KeyError(f"/{STATESPACE.A} missing")
        units = (list(ss.input_units), list(ss.output_units))
        inputs, outputs = list(ss.input_names), list(ss.output_names)
        damping = ss.damping_ratios if ss.damping_ratios is not None else []
        compliance = ss.static_compliance
        fe_gain = None
        if compliance is not None:
            pos = [o for o in outputs if o.endswith("/position")] or outputs
            fe_gain = {inp: {pos[o]: compliance[o, c] for o in range(min(len(pos),
                                                                         compliance.shape[0]))}
                       for c, inp in enumerate(inputs) if c < compliance.shape[1]}
        reduced = {
            "states": ss.n_states,
            "retained_modes": int(len(damping)),
            "damping_ratios": damping,
            "static_correction": ss.static_correction or "",
            "inputs": inputs,
            "outputs": outputs,
            "dc_gain": _gain_table(_dc_gain(ss), inputs, outputs),
            "dc_gain_full_fe": fe_gain,
        }
        fs = s.filtered
        if fs is not None:
            if fs.n_states is None:
                raise KeyError(f"/{STATESPACE_FILTERED.A} missing")
            filtered = {
                "states": fs.n_states,
                "filter_kind": fs.filter_kind or "",
                "cutoff_hz": fs.cutoff_hz,
                "dc_gain": _gain_table(_dc_gain(fs), list(fs.input_names),
                                       list(fs.output_names)),
            }
    chain = s.lumped
    if chain is not None and chain.n_states is not None:
        lumped = {"states": chain.n_states}
        if s.lumped_frequencies_hz is not None:
            lumped["frequencies_hz"] = s.lumped_frequencies_hz[:10]
    return {
        "format": FORMAT,
        "version": VERSION,
        "name": s.name if s.name is not None else s.path.stem,
        "source_file": str(s.path),
        "created_utc": s.created_utc or "",
        "pipeline_version": s.pipeline_version or "",
        "body": {"mass_kg": s.body.mass, "center_of_mass_m": s.body.center_of_mass},
        "mesh": {"points": s.mesh.n_points, "cells": n_cells, "cell_type": kind,
                 "dofs": s.mesh.n_dofs if s.mesh.n_dofs is not None else 3 * s.mesh.n_points},
        "modes": [{"mode": i + 1, "frequency_hz": f,
                   "label": labels[i] if i < len(labels) else ""} for i, f in enumerate(freqs)],
        "ports": _ports(s.config_yaml, units),
        "reduced_model": reduced,
        "filtered_model": filtered,
        "lumped_model": lumped,
    }


def export(h5_path: str | Path, out_path: str | Path) -> Path:
    """Write the JSON summary of ``h5_path`` to ``out_path``; returns it."""
    out_path = Path(out_path)
    text = json.dumps(summary(h5_path), indent=2, allow_nan=False) + "\n"
    write_text(out_path, text)
    log.info("wrote %s", out_path)
    return out_path
