"""Load a reduced model from our HDF5 file, reading only the file.

``load_model(path)`` verifies the schema, version and checksum, and returns the
python-control systems with their port names, frequencies and mode labels. No mesh
or finite-element code runs on the way, so a downstream tool needs only h5py,
numpy and python-control.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import FileFormatError
from pipeline.store.h5file import open_verified, read_strings


@dataclass(frozen=True)
class LoadedModel:
    """A reduced model read back from an HDF5 file.

    ss: python-control StateSpace of the plant (inputs: ``input_names``; outputs:
        ``output_names``, position/velocity/acceleration of every output port).
    ss_filtered: the loop-breaking filtered model (D = 0), or None.
    frequencies_hz (n_m,), labels (n_m,): all modes in the file.
    damping_ratios (n_r,): of the retained modes. static_compliance: (n_y x n_u) full-FE
    T K^-1 F, or None. matrices / matrices_filtered: the raw A, B, C, D arrays.
    """

    path: Path
    ss: Any
    ss_filtered: Any
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    state_names: tuple[str, ...]
    frequencies_hz: np.ndarray
    labels: tuple[str, ...]
    damping_ratios: np.ndarray
    static_compliance: np.ndarray | None
    matrices: dict[str, np.ndarray]
    matrices_filtered: dict[str, np.ndarray] | None
    filter_kind: str
    cutoff_hz: float | None


def _group_matrices(h5, group: str) -> tuple[dict[str, np.ndarray], dict[str, tuple[str, ...]]]:
    grp = h5[group]
    mats = {k: np.array(grp[k][()], dtype=np.float64) for k in "ABCD"}
    names = {}
    for key in ("input_names", "output_names", "state_names"):
        if key in grp:
            names[key] = tuple(read_strings(grp[key]))
        else:
            names[key] = tuple(read_strings(grp["A"].attrs.get(key, [])))
    n, m, p = mats["A"].shape[0], mats["B"].shape[1], mats["C"].shape[0]
    expected = {"A": (n, n), "B": (n, m), "C": (p, n), "D": (p, m)}
    for k, shape in expected.items():
        if mats[k].shape != shape:
            raise FileFormatError(f"file '{h5.filename}': {group}/{k} has shape {mats[k].shape}, "
                                  f"expected {shape}")
    return mats, names


def _to_control(mats: dict[str, np.ndarray], names: dict[str, tuple[str, ...]]):
    import control

    return control.ss(mats["A"], mats["B"], mats["C"], mats["D"],
                      inputs=list(names["input_names"]) or None,
                      outputs=list(names["output_names"]) or None,
                      states=list(names["state_names"]) or None)


REQUIRED = ("statespace/A", "statespace/B", "statespace/C", "statespace/D",
            "statespace/damping_ratios", "modes/frequencies_hz", "modes/labels")


def load_model(path: str | Path) -> LoadedModel:
    """Read the reduced model of ``path`` (see the class docstring).

    Raises FileFormatError for a file that is not ours, corrupt (see
    :func:`pipeline.store.h5file.open_verified`), holds modes only, or lacks a dataset the
    layout requires.
    """
    path = Path(path)
    with open_verified(path) as h5:
        if "statespace" not in h5:
            raise FileFormatError(f"file '{path}': has no /statespace group (the config had no "
                                  "'reduction' section); it holds modes only")
        missing = [k for k in REQUIRED if k not in h5]
        if missing:
            raise FileFormatError(f"file '{path}': dataset{'s' if len(missing) > 1 else ''} "
                                  f"{', '.join(missing)} missing (an incomplete file, not the "
                                  "layout of docs/hdf5-format.md)")
        try:
            return _read(h5, path)
        except FileFormatError:
            raise
        except (KeyError, IndexError, ValueError, TypeError, OSError, RuntimeError) as exc:
            text = " ".join(str(exc).split())[:200]
            raise FileFormatError(f"file '{path}': inconsistent with the layout of "
                                  f"docs/hdf5-format.md ({type(exc).__name__}: {text})") from None


def _read(h5, path: Path) -> LoadedModel:
    mats, names = _group_matrices(h5, "statespace")
    filt = None
    filter_kind, cutoff = "none", None
    if "statespace_filtered" in h5:
        filt, fnames = _group_matrices(h5, "statespace_filtered")
        attrs = h5["statespace_filtered"].attrs
        filter_kind = str(attrs.get("filter_kind", "unknown"))
        cutoff = float(attrs["cutoff_hz"]) if "cutoff_hz" in attrs else None
    compliance = (np.array(h5["statespace/static_compliance"][()])
                  if "statespace/static_compliance" in h5 else None)
    damping = np.array(h5["statespace/damping_ratios"][()])
    freqs = np.array(h5["modes/frequencies_hz"][()])
    labels = tuple(read_strings(h5["modes/labels"]))
    return LoadedModel(path, _to_control(mats, names),
                       _to_control(filt, fnames) if filt is not None else None,
                       names["input_names"], names["output_names"], names["state_names"],
                       freqs, labels, damping, compliance, mats, filt, filter_kind, cutoff)
