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
from pipeline.store.read import open_verified, read_strings

log = logging.getLogger(__name__)

__all__ = ["export", "mat_variables", "MODELS"]

#: (HDF5 group, suffix of the MATLAB variable names)
MODELS = (("statespace", ""), ("statespace_filtered", "_filtered"),
          ("lumped/statespace", "_lumped"))
_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,62}$")


def cell_array(items) -> np.ndarray:
    """A column cell array of char for savemat."""
    out = np.empty((len(items), 1), dtype=object)
    for i, s in enumerate(items):
        out[i, 0] = str(s)
    return out


def _group_names(grp, key: str) -> list[str]:
    if key in grp:
        return read_strings(grp[key])
    return read_strings(grp["A"].attrs.get(key, []))


def _matlab_name(text: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_]", "_", text)
    return name if name[:1].isalpha() else "c" + name


def _other_models(h5_path: Path) -> dict[str, Any]:
    """Variables of the connection-point and Craig-Bampton models (through the reader)."""
    from pipeline.store.read import load_model

    out: dict[str, Any] = {}
    try:
        lm = load_model(h5_path)
    except FileFormatError:
        return out   # modes only: mat_variables says so
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
        out["cb_fixed_interface_frequencies_hz"] = cb.fixed_interface_frequencies_hz.reshape(-1, 1)
        with open_verified(h5_path, verify_checksum=False) as h5:
            for key in ("interface_points", "free_frequencies_hz"):
                if f"craig_bampton/{key}" in h5:
                    value = np.array(h5[f"craig_bampton/{key}"][()], dtype=float)
                    out["cb_" + key] = value.reshape(-1, 1) if value.ndim == 1 else value
    return out


def mat_variables(h5_path: str | Path) -> dict[str, Any]:
    """The variables :func:`export` writes, as a dict (verified read of ``h5_path``)."""
    h5_path = Path(h5_path)
    out: dict[str, Any] = {}
    others = _other_models(h5_path)
    out.update(others)
    with open_verified(h5_path) as h5:
        if "statespace" not in h5 and not others and "lumped/statespace" not in h5:
            raise FileFormatError(f"file '{h5_path}': has no /statespace group (the config had "
                                  "no 'reduction' section) and no connection-point, "
                                  "Craig-Bampton or lumped model, so there is no model for the "
                                  "mat export; expected a file with a reduced model")
        for group, suffix in MODELS:
            if group not in h5:
                continue
            grp = h5[group]
            mats = {k: np.atleast_2d(np.array(grp[k][()], dtype=np.float64)) for k in "ABCD"}
            n, m, p = mats["A"].shape[0], mats["B"].shape[1], mats["C"].shape[0]
            for k, shape in {"A": (n, n), "B": (n, m), "C": (p, n), "D": (p, m)}.items():
                if mats[k].shape != shape:
                    raise FileFormatError(f"file '{h5_path}': /{group}/{k} has shape "
                                          f"{mats[k].shape}, expected {shape}")
                out[k + suffix] = mats[k]
            for key in ("input_names", "output_names", "state_names"):
                names = _group_names(grp, key)
                if names:
                    out[key + suffix] = cell_array(names)
        ss = h5["statespace"] if "statespace" in h5 else {}
        ss_attrs = h5["statespace"].attrs if "statespace" in h5 else {}
        for key in ("input_units", "output_units"):
            if key in ss_attrs:
                out[key] = cell_array(read_strings(ss_attrs[key]))
        if "damping_ratios" in ss:
            out["damping_ratios"] = np.array(ss["damping_ratios"][()], dtype=float).reshape(-1, 1)
        if "static_compliance" in ss:
            out["static_compliance"] = np.atleast_2d(np.array(ss["static_compliance"][()],
                                                              dtype=float))
        if "statespace_filtered" in h5:
            attrs = h5["statespace_filtered"].attrs
            out["filter_kind"] = str(attrs.get("filter_kind", "unknown"))
            if "cutoff_hz" in attrs:
                out["cutoff_hz"] = float(attrs["cutoff_hz"])
        out["frequencies_hz"] = np.array(h5["modes/frequencies_hz"][()], dtype=float).reshape(-1, 1)
        out["mode_labels"] = cell_array(read_strings(h5["modes/labels"]))
        if "body/mass" in h5:
            out["mass_kg"] = float(h5["body/mass"][()])
        out["model_name"] = str(h5.attrs.get("name", h5_path.stem))
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
