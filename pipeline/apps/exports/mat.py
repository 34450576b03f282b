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
model_name, source_file, description        text
==========================================  ===============================================

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


def _cell(items) -> np.ndarray:
    """A column cell array of char for savemat."""
    out = np.empty((len(items), 1), dtype=object)
    for i, s in enumerate(items):
        out[i, 0] = str(s)
    return out


def _group_names(grp, key: str) -> list[str]:
    if key in grp:
        return read_strings(grp[key])
    return read_strings(grp["A"].attrs.get(key, []))


def mat_variables(h5_path: str | Path) -> dict[str, Any]:
    """The variables :func:`export` writes, as a dict (verified read of ``h5_path``)."""
    h5_path = Path(h5_path)
    out: dict[str, Any] = {}
    with open_verified(h5_path) as h5:
        if "statespace" not in h5:
            raise FileFormatError(f"file '{h5_path}': has no /statespace group (the config had "
                                  "no 'reduction' section), so there is no model for the mat "
                                  "export; expected a file with a reduced model")
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
                    out[key + suffix] = _cell(names)
        ss = h5["statespace"]
        for key in ("input_units", "output_units"):
            if key in ss.attrs:
                out[key] = _cell(read_strings(ss.attrs[key]))
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
        out["mode_labels"] = _cell(read_strings(h5["modes/labels"]))
        if "body/mass" in h5:
            out["mass_kg"] = float(h5["body/mass"][()])
        out["model_name"] = str(h5.attrs.get("name", h5_path.stem))
    out["source_file"] = str(h5_path)
    out["description"] = (
        "Reduced model exported by fe-reduced-body (SI units). x' = A x + B u, y = C x + D u; "
        "outputs: position, velocity, acceleration of each output port (see output_names). "
        "_filtered: with the loop-breaking low-pass filter (D = 0); _lumped: the lumped chain. "
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
