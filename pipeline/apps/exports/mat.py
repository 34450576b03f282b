"""Export to a MATLAB v5 ``.mat`` file: the reduced models for MATLAB/Simulink and Octave.

``python -m pipeline export FILE.h5 --to mat`` writes, as top-level variables (so that
``load model.mat`` leaves them ready for Simulink's State-Space block, whose parameters
are typed as ``A``, ``B``, ``C``, ``D``):

==========================================  ===============================================
variable                                    content
==========================================  ===============================================
A, B, C, D                                  the reduced modal model (/statespace)
input_names, output_names, state_names      cell arrays of char (column)
input_units, output_units                   cell arrays (per input / per output port)
A_filtered, B_filtered, C_filtered, ...     the loop-breaking filtered model, D = 0
                                            (/statespace_filtered), where the file has it
filter_kind, cutoff_hz                      its filter
A_lumped, B_lumped, C_lumped, D_lumped,     the lumped-parameter chain (/lumped/statespace),
input_names_lumped, output_names_lumped     where the file has it
frequencies_hz, mode_labels                 every mode of the FE model (column, cell)
damping_ratios                              of the modes kept in the reduced model
static_compliance                           full-FE T K^-1 F (positions per input)
A_conn_<name>, B_conn_<name>, ...,          each connection-point model (/connections/<name>,
input_names_conn_<name>, output_names_...,  6 x 6 hybrid: base accelerations and child
input_units_conn_<name>, output_units_...   forces in; base forces and child
                                            accelerations out), where the file has it
M_cb, K_cb, cb_coordinate_names,            the Craig-Bampton model (/craig_bampton):
cb_coordinate_units, cb_interface_names,    6 DOFs per interface point (x y z rx ry rz),
cb_interface_points,                        then the fixed-interface modal DOFs; see also
cb_fixed_interface_frequencies_hz,          ``--to simscape``
cb_free_frequencies_hz
model_name, source_file, description        text
==========================================  ===============================================

A file without ``/statespace`` (a config with ``connections`` or ``craig_bampton`` but no
``reduction``) exports the models it has; a file with modes only is refused.

In MATLAB: ``load model.mat; sys = ss(A, B, C, D, 'InputName', input_names,
'OutputName', output_names);`` In Octave the same after ``pkg load control``.
Units are SI. Written by :func:`scipy.io.savemat` (format 5, readable by MATLAB >= 5,
Octave's ``load`` and :func:`scipy.io.loadmat`).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np

from pipeline._util.atomic import atomic_path
from pipeline.errors import FileFormatError
from pipeline.store.read import StoredModels, load_model

log = logging.getLogger(__name__)

__all__ = ["export", "mat_variables", "MODELS"]

#: (model of :class:`pipeline.store.read.StoredModels`, suffix of the MATLAB variable names)
MODELS = (("plant", ""), ("filtered", "_filtered"), ("lumped", "_lumped"))
_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,62}$")


def cell_array(items) -> np.ndarray:
    """A column cell array of char for savemat."""
    out = np.empty((len(items), 1), dtype=object)
    for i, s in enumerate(items):
        out[i, 0] = str(s)
    return out


def _matlab_name(text: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_]", "_", text)
    return name if name[:1].isalpha() else "c" + name


def _column(values) -> np.ndarray:
    return np.asarray(values, dtype=float).reshape(-1, 1)


def _other_models(lm: StoredModels) -> dict[str, Any]:
    """Variables of the connection-point and Craig-Bampton models."""
    out: dict[str, Any] = {}
    for name, ss in lm.connections.items():
        suffix = "_conn_" + _matlab_name(name)
        for k in "ABCD":
            out[k + suffix] = np.atleast_2d(np.array(getattr(ss, k), dtype=np.float64))
        for key in ("input_names", "output_names", "input_units", "output_units"):
            if getattr(ss, key):
                out[key + suffix] = cell_array(getattr(ss, key))
    cb = lm.craig_bampton
    if cb is not None:
        out["M_cb"], out["K_cb"] = np.array(cb.M), np.array(cb.K)
        out["cb_coordinate_names"] = cell_array(cb.coordinate_names)
        out["cb_coordinate_units"] = cell_array(cb.coordinate_units)
        out["cb_interface_names"] = cell_array(cb.interface_names)
        out["cb_fixed_interface_frequencies_hz"] = _column(cb.fixed_interface_frequencies_hz)
        if cb.interface_points.size:
            out["cb_interface_points"] = np.array(cb.interface_points, dtype=float)
        if cb.free_frequencies_hz.size:
            out["cb_free_frequencies_hz"] = _column(cb.free_frequencies_hz)
    return out


def mat_variables(h5_path: str | Path) -> dict[str, Any]:
    """The variables :func:`export` writes, as a dict (verified read of ``h5_path``)."""
    h5_path = Path(h5_path)
    try:
        lm = load_model(h5_path)
    except FileFormatError as exc:
        if exc.value != "no /statespace":
            raise
        raise FileFormatError(f"file '{h5_path}': has no /statespace group (the config had "
                              "no 'reduction' section) and no connection-point, "
                              "Craig-Bampton or lumped model, so there is no model for the "
                              "mat export; expected a file with a reduced model") from None
    out: dict[str, Any] = _other_models(lm)
    for model, suffix in MODELS:
        ss = getattr(lm, model)
        if ss is None:
            continue
        for k, matrix in zip("ABCD", ss):
            out[k + suffix] = np.array(matrix)
        for key in ("input_names", "output_names", "state_names"):
            if getattr(ss, key):
                out[key + suffix] = cell_array(getattr(ss, key))
    if lm.plant is not None:
        for key, units in (("input_units", lm.input_units), ("output_units", lm.port_units)):
            if units:
                out[key] = cell_array(units)
        out["damping_ratios"] = _column(lm.damping_ratios)
        if lm.static_compliance is not None:
            out["static_compliance"] = np.array(lm.static_compliance, dtype=float)
    if lm.filtered is not None:
        out["filter_kind"] = lm.filter_kind
        if lm.cutoff_hz is not None:
            out["cutoff_hz"] = float(lm.cutoff_hz)
    out["frequencies_hz"] = _column(lm.frequencies_hz)
    out["mode_labels"] = cell_array(lm.labels)
    if np.isfinite(lm.mass):
        out["mass_kg"] = lm.mass
    out["model_name"] = lm.name
    out["source_file"] = str(h5_path)
    out["description"] = (
        "Reduced model exported by fe-reduced-body (SI units). x' = A x + B u, y = C x + D u; "
        "outputs: position, velocity, acceleration of each output port (see output_names). "
        "_filtered: with the loop-breaking low-pass filter (D = 0); _lumped: the lumped chain; "
        "_conn_<name>: connection-point models; M_cb, K_cb: the Craig-Bampton model. "
        "MATLAB: sys = ss(A, B, C, D, 'InputName', input_names, 'OutputName', output_names).")
    bad = [k for k in out if not _NAME_RE.match(k)]
    if bad:  # pragma: no cover - the names above are fixed
        raise ValueError(f"not MATLAB variable names: {bad}")
    return out


def export(h5_path: str | Path, out_path: str | Path) -> Path:
    """Write the ``.mat`` file (MATLAB v5) of ``h5_path`` to ``out_path``; returns it."""
    from scipy.io import savemat

    out_path = Path(out_path)
    variables = mat_variables(h5_path)
    with atomic_path(out_path) as tmp, open(tmp, "wb") as fh:
        savemat(fh, variables, format="5", long_field_names=True, do_compression=True,
                oned_as="column")
    log.info("wrote %s (%d variables)", out_path, len(variables))
    return out_path
