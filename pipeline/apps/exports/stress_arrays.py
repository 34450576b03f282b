"""Stress arrays for the VTU/XDMF exports (point data beside the mode shapes).

From the ``stress_modes`` group (docs/stress.md), per mesh point:

- ``stress_<shape>`` (n_points, 6), Pa per unit coordinate: the stress of basis vector
  ``eta_NN`` or of the residual shape ``residual_<input>``, in ParaView's symmetric-tensor
  order [xx, yy, zz, xy, yz, xz] (the file's Voigt order is [xx, yy, zz, yz, xz, xy]);
- ``von_mises_static_<input>`` (n_points,), Pa per unit input: the static response's von
  Mises stress (:func:`pipeline.apps.stress_fields.static_von_mises`).

A file without stress modes gives no arrays.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pipeline.store.read import read_stress_modes

__all__ = ["PARAVIEW_ORDER", "stress_point_data"]

#: file Voigt index of ParaView's [xx, yy, zz, xy, yz, xz]
PARAVIEW_ORDER = (0, 1, 2, 5, 3, 4)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", name)


def stress_point_data(h5_path: str | Path) -> dict[str, np.ndarray]:
    """Point-data arrays of the stress modes of ``h5_path`` (module docstring)."""
    from pipeline.apps.stress_fields import static_von_mises

    sm = read_stress_modes(h5_path)
    if sm is None:
        return {}
    out: dict[str, np.ndarray] = {}
    for k, name in enumerate(sm.shape_names):
        label = f"eta_{k + 1:02d}" if k < sm.n_basis else _safe(name)
        out[f"stress_{label}"] = np.ascontiguousarray(sm.stress[:, PARAVIEW_ORDER, k])
    for name, vm in static_von_mises(h5_path).items():
        out[f"von_mises_static_{_safe(name)}"] = vm
    return out
