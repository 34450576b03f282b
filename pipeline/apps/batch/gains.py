"""DC gains and Bode magnitudes of a case's reduced model, as the batch report uses them.

The model is the plant of a case file, read by the one reader
(:func:`pipeline.store.read.load_model`): ``x' = A x + B u``, ``y = C x + D u`` (SI units:
inputs in N or N m, outputs position / velocity / acceleration of every output port).
DC gains and frequency responses are computed with python-control (deferred import).
"""

from __future__ import annotations

import logging
import math
import warnings
from pathlib import Path

import numpy as np

from pipeline.errors import FileFormatError
from pipeline.store.read import StoredModels, load_model

log = logging.getLogger(__name__)

__all__ = ["case_models", "bode_magnitude", "dc_gains", "position_rows", "ratio_unit"]


def case_models(path: str | Path) -> StoredModels | None:
    """The reduced models of a case file, or None when it has no plant or cannot be read
    (a report never fails on one file: a warning names the file and the reason)."""
    try:
        models = load_model(path, require_plant=True, verify_checksum=False)
    except FileFormatError as exc:
        if exc.value != "no /statespace":  # a file without a reduced model: nothing to say
            log.warning("report: cannot read the model of %s: %s", path,
                        " ".join(str(exc).split())[:200])
        return None
    return models


def position_rows(model: StoredModels) -> list[tuple[int, str]]:
    """(row, name) of every position output of the plant."""
    return [(i, n) for i, n in enumerate(model.output_names) if n.endswith("/position")]


def ratio_unit(model: StoredModels, inp: str, out: str) -> str:
    """Unit of |H| from input ``inp`` to position output ``out`` ('1' if unknown)."""
    rows = [n for _, n in position_rows(model)]
    i, k = model.input_names.index(inp), rows.index(out) if out in rows else -1
    if 0 <= k < len(model.port_units) and i < len(model.input_units):
        return f"{model.port_units[k]}/{model.input_units[i]}"
    return "1"


def dc_gains(model: StoredModels) -> dict[str, float]:
    """``dc_gain[input->output/position]`` of the plant (python-control); where the model
    has no finite static gain (rigid-body modes) the stored exact static compliance is
    used when present."""
    import control as ct  # deferred: python-control is slow to import

    rows = position_rows(model)
    if not rows:
        return {}
    A, B, C, D = model.plant
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            gain = np.reshape(np.asarray(ct.dcgain(ct.ss(A, B, C, D)), dtype=float),
                              (C.shape[0], B.shape[1]))
        except Exception:
            gain = np.full((C.shape[0], B.shape[1]), np.nan)
    out = {}
    for i, name in rows:
        for j, inp in enumerate(model.input_names):
            value = float(gain[i, j])
            if not math.isfinite(value) and model.static_compliance is not None:
                port = name[: -len("/position")]
                if port in model.compliance_rows:
                    value = float(model.static_compliance[model.compliance_rows.index(port), j])
            out[f"dc_gain[{inp}->{name}]"] = value
    return out


def bode_magnitude(model: StoredModels, f_hz: np.ndarray) -> dict[tuple[str, str], np.ndarray]:
    """|H(j 2 pi f)| of every (input, position output) pair (python-control)."""
    import control as ct  # deferred: python-control is slow to import

    rows = position_rows(model)
    if not rows:
        return {}
    resp = ct.frequency_response(ct.ss(*model.plant), 2 * np.pi * np.asarray(f_hz),
                                 squeeze=False)
    mag = np.asarray(resp.magnitude)
    return {(inp, name): mag[i, j] for i, name in rows for j, inp in enumerate(model.input_names)}
