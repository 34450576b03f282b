"""Load a reduced model from our HDF5 file, reading only the file.

``load_model(path)`` verifies the schema, version and checksum, and returns the
python-control systems with their port names, frequencies and mode labels. No mesh
or finite-element code runs on the way, so a downstream tool needs only h5py,
numpy and python-control.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from pipeline.errors import FileFormatError
from pipeline.reduce.statespace import StateSpace
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


# --------------------------------------------------------------------------- everything
@dataclass(frozen=True, eq=False)
class ModelFile:
    """Everything the stepper reads from one model file."""

    path: Path
    sha256: str
    plant: StateSpace
    filtered: StateSpace | None
    frequencies_hz: np.ndarray
    labels: tuple[str, ...]
    ports: dict[str, dict[str, Any]]        # name -> {side, kind, region, direction}
    support_regions: tuple[str, ...]
    region_centroids: dict[str, np.ndarray]
    body_mass: float
    body_com: np.ndarray
    body_inertia: np.ndarray
    lumped: dict[str, Any] | None
    in_plane: bool = False


def _region_centroid(h5, name: str) -> np.ndarray | None:
    key = f"mesh/regions/{name}"
    if key not in h5 or "mesh/points" not in h5:
        return None
    tris = np.asarray(h5[key][()], dtype=np.int64)
    if tris.ndim != 2 or tris.shape[0] == 0:
        return None
    pts = np.asarray(h5["mesh/points"][()], dtype=float)
    p = pts[tris[:, :3]]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    return (area[:, None] * p.mean(axis=1)).sum(axis=0) / area.sum()


def read_model_file(path: str | Path) -> ModelFile:
    """Read the state-space models, port data and body data of ``path``.

    Uses :func:`pipeline.store.read.load_model` (verifies schema and checksum) and h5py for
    the rest (stored config for port directions and regions, body inertia, region
    centroids, the lumped chain). Raises FileFormatError for a file without a model.
    """
    import yaml

    path = Path(path)
    lm = load_model(path)
    mats = lm.matrices
    plant = StateSpace(mats["A"], mats["B"], mats["C"], mats["D"], lm.input_names,
                       lm.output_names, lm.state_names, label="FE")
    filtered = None
    if lm.matrices_filtered is not None:
        fm = lm.matrices_filtered
        with open_verified(path, verify_checksum=False) as h5:
            names = tuple(read_strings(h5["statespace_filtered/state_names"])) \
                if "statespace_filtered/state_names" in h5 else ()
        filtered = StateSpace(fm["A"], fm["B"], fm["C"], fm["D"], lm.input_names,
                              lm.output_names, names, label="FE filtered",
                              filter_kind=lm.filter_kind, cutoff_hz=lm.cutoff_hz)
    for model in (plant,) + ((filtered,) if filtered is not None else ()):
        if not model.ports or not model.input_names:
            raise FileFormatError(f"file '{path}': the {model.label} model has no input or no "
                                  "output port")
    with open_verified(path, verify_checksum=False) as h5:
        sha = str(h5.attrs.get("content_sha256", ""))
        cfg = None
        if "config_yaml" in h5.attrs:
            try:
                cfg = yaml.safe_load(str(h5.attrs["config_yaml"]))
            except yaml.YAMLError:
                cfg = None
        ports: dict[str, dict[str, Any]] = {}
        supports: tuple[str, ...] = ()
        in_plane = False
        if isinstance(cfg, Mapping):
            in_plane = bool((cfg.get("constraints") or {}).get("in_plane", False))
            for side in ("inputs", "outputs"):
                for p in (cfg.get("ports") or {}).get(side) or []:
                    if isinstance(p, Mapping) and "name" in p:
                        d = p.get("direction")
                        ports[str(p["name"])] = {
                            "side": side, "kind": p.get("kind"), "region": p.get("region"),
                            "direction": None if d is None else np.asarray(d, float)
                            / np.linalg.norm(np.asarray(d, float))}
            supports = tuple(str(s.get("region")) for s in cfg.get("supports") or []
                             if isinstance(s, Mapping) and s.get("region"))
        centroids: dict[str, np.ndarray] = {}
        for name in set(supports) | {str(p["region"]) for p in ports.values() if p["region"]}:
            c = _region_centroid(h5, name)
            if c is not None:
                centroids[name] = c
        body_mass = float(h5["body/mass"][()]) if "body/mass" in h5 else math.nan
        body_com = np.asarray(h5["body/center_of_mass"][()], float) \
            if "body/center_of_mass" in h5 else np.full(3, np.nan)
        body_inertia = np.asarray(h5["body/inertia"][()], float) \
            if "body/inertia" in h5 else np.full((3, 3), np.nan)
        lumped = None
        if "lumped/statespace/A" in h5:
            g = h5["lumped/statespace"]
            attrs = g["A"].attrs
            lumped = {
                "A": np.asarray(g["A"][()], float), "B": np.asarray(g["B"][()], float),
                "C": np.asarray(g["C"][()], float), "D": np.asarray(g["D"][()], float),
                "input_names": tuple(read_strings(attrs.get("input_names", []))),
                "output_names": tuple(read_strings(attrs.get("output_names", []))),
                "state_names": tuple(read_strings(attrs.get("state_names", []))),
                "input_direction": np.asarray(attrs.get("input_direction", np.full(3, np.nan)),
                                              float),
                "output_direction": np.asarray(attrs.get("output_direction",
                                                         np.full(3, np.nan)), float),
            }
            for key in ("element_mass", "element_com", "element_inertia", "element_extent",
                        "joint_positions"):
                if f"lumped/{key}" in h5:
                    lumped[key] = np.asarray(h5[f"lumped/{key}"][()], float)
    return ModelFile(path, sha, plant, filtered, np.asarray(lm.frequencies_hz, float),
                     tuple(lm.labels), ports, supports, centroids, body_mass, body_com,
                     body_inertia, lumped, in_plane)
