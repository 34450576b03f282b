"""The one reader of our HDF5 file: every tool that uses a result file reads it here.

``load_model(path)`` verifies the schema, version and checksum (through
:func:`open_verified`), and returns every model the file holds as the one
:class:`~pipeline.reduce.statespace.StateSpace` type (and as python-control systems):
the plant (``/statespace``), its filtered twin, the lumped chain, each connection-point
model and the Craig-Bampton model (second order: reduced M and K).
``read_model_file(path)`` adds what a simulation needs (ports from the stored config,
region centroids, body inertia). Inspect, simulate, plots, exports and the batch report
open files only through this module (``open_verified``, ``read_strings``).

No mesh or finite-element code runs on the way (this module never imports
:mod:`pipeline.fe`, gmsh, meshio or scikit-fem), so a downstream tool needs only h5py,
numpy and python-control. A file that is not ours, corrupt, or lacks what the caller
needs ends in one :class:`~pipeline.errors.FileFormatError` line (exit code 7).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from pipeline.errors import FileFormatError
from pipeline.reduce.statespace import StateSpace
from pipeline.errors import PipelineError
from pipeline.store import h5file
from pipeline.store.h5file import read_strings

__all__ = ["load_model", "LoadedModel", "SecondOrderModel", "ModelFile", "read_model_file",
           "ModeSet", "read_modes", "open_verified", "read_strings", "StressModes",
           "read_stress_modes"]


#: what h5py and numpy raise on content that does not have the documented layout
LAYOUT_ERRORS = (KeyError, IndexError, ValueError, TypeError, AttributeError, OSError,
                 RuntimeError)


def layout_error(path: str | Path, exc: BaseException) -> FileFormatError:
    """The one-line error for a file whose content does not follow docs/hdf5-format.md."""
    text = " ".join(str(exc).split())[:200]
    return FileFormatError(f"file '{path}': inconsistent with the layout of "
                           f"docs/hdf5-format.md ({type(exc).__name__}: {text})",
                           key=str(path), value=f"{type(exc).__name__}: {text}",
                           expected="the layout of docs/hdf5-format.md")


@contextlib.contextmanager
def open_verified(path: str | Path, verify_checksum: bool = True) -> Iterator[Any]:
    """Open one of our files read-only, verified (schema, version, checksums: see
    :func:`pipeline.store.h5file.open_verified`), for reading in a ``with`` block.

    Whatever the block raises while reading content that does not have the documented
    layout (a missing dataset, a wrong shape or type) becomes one FileFormatError line
    naming the file; a PipelineError raised in the block passes through unchanged.
    """
    h5 = h5file.open_verified(path, verify_checksum)
    try:
        yield h5
    except PipelineError:
        raise
    except LAYOUT_ERRORS as exc:
        raise layout_error(path, exc) from None
    finally:
        h5.close()


@dataclass(frozen=True)
class LoadedModel:
    """A reduced model read back from an HDF5 file.

    ss: python-control StateSpace of the plant (inputs: ``input_names``; outputs:
        ``output_names``, position/velocity/acceleration of every output port).
    ss_filtered: the loop-breaking filtered model (D = 0), or None.
    frequencies_hz (n_m,), labels (n_m,): all modes in the file.
    damping_ratios (n_r,): of the retained modes. static_compliance: (n_y x n_u) full-FE
    T K^-1 F, or None. matrices / matrices_filtered: the raw A, B, C, D arrays.
    plant, filtered, lumped: the same models as :class:`StateSpace` (None when absent);
    connections: connection-point models by name; craig_bampton: the reduced M, K.
    :attr:`models` lists every model the file holds; :meth:`model` picks one by name.
    The plant's fields (ss, matrices, names) are None or empty in a file without
    ``/statespace`` (connection-point or Craig-Bampton models only).
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
    plant: StateSpace | None = None
    filtered: StateSpace | None = None
    lumped: StateSpace | None = None
    connections: dict[str, StateSpace] = field(default_factory=dict)
    craig_bampton: "SecondOrderModel | None" = None

    @property
    def models(self) -> dict[str, Any]:
        """Every model in the file by name: ``plant``, ``filtered``, ``lumped``,
        ``connection/<name>`` (StateSpace) and ``craig_bampton`` (SecondOrderModel)."""
        out: dict[str, Any] = {"plant": self.plant, "filtered": self.filtered,
                               "lumped": self.lumped}
        out.update({f"connection/{k}": v for k, v in self.connections.items()})
        out["craig_bampton"] = self.craig_bampton
        return {k: v for k, v in out.items() if v is not None}

    def model(self, name: str):
        """One model of :attr:`models` by name; FileFormatError naming what the file has."""
        try:
            return self.models[name]
        except KeyError:
            raise FileFormatError(f"file '{self.path}': holds no '{name}' model; it holds "
                                  f"{', '.join(self.models) or 'none'}", key=str(self.path),
                                  value=name, expected="one of " + ", ".join(self.models)
                                  ) from None


@dataclass(frozen=True, eq=False)
class SecondOrderModel:
    """A reduced second-order model M q'' + K q = f (Craig-Bampton).

    M, K (n, n): entries in kg m^2 / (u_i u_j) and N m / (u_i u_j), u the coordinate units;
    coordinate_names, coordinate_units (n,); interface_names (k,);
    fixed_interface_frequencies_hz (N,)."""

    M: np.ndarray
    K: np.ndarray
    coordinate_names: tuple[str, ...]
    coordinate_units: tuple[str, ...]
    interface_names: tuple[str, ...]
    fixed_interface_frequencies_hz: np.ndarray


def _group_matrices(h5, group: str) -> tuple[dict[str, np.ndarray], dict[str, tuple[str, ...]]]:
    grp = h5[group]
    mats = {k: _array(h5, f"{group}/{k}", "f", (None, None)) for k in "ABCD"}
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


REQUIRED = ("modes/frequencies_hz", "modes/labels")
REQUIRED_PLANT = ("statespace/A", "statespace/B", "statespace/C", "statespace/D",
                  "statespace/damping_ratios")
#: groups that hold a model besides the plant
OTHER_MODELS = ("lumped/statespace/A", "connections", "craig_bampton/M")


def load_model(path: str | Path, require_plant: bool = False) -> LoadedModel:
    """Read every reduced model of ``path`` (see the class docstring).

    A file with connection-point, Craig-Bampton or lumped models but no ``/statespace``
    (a config without ``reduction``) loads with ``ss``, ``plant`` and the plant's
    matrices None, unless ``require_plant``. Raises FileFormatError for a file that is
    not ours, corrupt (see :func:`open_verified`), holds modes only (or no plant when
    ``require_plant``), or lacks a dataset the layout requires.
    """
    path = Path(path)
    with open_verified(path) as h5:
        has_plant = "statespace" in h5
        if not has_plant and (require_plant or not any(k in h5 for k in OTHER_MODELS)):
            raise FileFormatError(f"file '{path}': has no /statespace group (the config had no "
                                  "'reduction' section); it holds "
                                  + ("modes only" if not any(k in h5 for k in OTHER_MODELS)
                                     else "no plant model"),
                                  key=str(path), value="no /statespace",
                                  expected="a file with a reduced model")
        missing = [k for k in REQUIRED + (REQUIRED_PLANT if has_plant else ()) if k not in h5]
        if missing:
            raise FileFormatError(f"file '{path}': dataset{'s' if len(missing) > 1 else ''} "
                                  f"{', '.join(missing)} missing (an incomplete file, not the "
                                  "layout of docs/hdf5-format.md)")
        return _read(h5, path)


def _read(h5, path: Path) -> LoadedModel:
    freqs = _array(h5, "modes/frequencies_hz", "f", (None,))
    labels = tuple(read_strings(h5["modes/labels"]))
    others = dict(lumped=_lumped(h5), connections=_connections(h5),
                  craig_bampton=_craig_bampton(h5))
    if "statespace" not in h5:
        return LoadedModel(path, None, None, (), (), (), freqs, labels, np.zeros(0), None, {},
                           None, "none", None, **others)
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
    damping = _array(h5, "statespace/damping_ratios", "f", (None,))
    plant = _statespace(mats, names, "plant")
    if not plant.ports or len(plant.output_names) != 3 * len(plant.ports):
        raise FileFormatError(f"file '{path}': statespace/output_names {list(plant.output_names)[:4]} "
                              "are not '<port>/position|velocity|acceleration' for every port",
                              key="statespace/output_names", value=plant.output_names[:4],
                              expected="<port>/position, <port>/velocity, <port>/acceleration")
    filtered = (_statespace(filt, fnames, "filtered", filter_kind=filter_kind, cutoff_hz=cutoff)
                if filt is not None else None)
    return LoadedModel(path, _to_control(mats, names),
                       _to_control(filt, fnames) if filt is not None else None,
                       names["input_names"], names["output_names"], names["state_names"],
                       freqs, labels, damping, compliance, mats, filt, filter_kind, cutoff,
                       plant=plant, filtered=filtered, **others)


def _statespace(mats: dict[str, np.ndarray], names: dict[str, tuple[str, ...]], label: str,
                **kw) -> StateSpace:
    # a ValueError (shapes, non-finite values) becomes load_model's FileFormatError
    return StateSpace(mats["A"], mats["B"], mats["C"], mats["D"], names["input_names"],
                      names["output_names"], names["state_names"], label=label, **kw)


def _strings(h5, group: str, key: str) -> tuple[str, ...]:
    grp = h5[group]
    if key in grp:
        return tuple(read_strings(grp[key]))
    return tuple(read_strings(grp["A"].attrs.get(key, [])))


def _lumped(h5) -> StateSpace | None:
    """The lumped chain's state space (``/lumped/statespace``), or None."""
    if "lumped/statespace/A" not in h5:
        return None
    mats, names = _group_matrices(h5, "lumped/statespace")
    return _statespace(mats, names, "lumped")


def _connections(h5) -> dict[str, StateSpace]:
    """Each connection-point model (``/connections/<name>/statespace``) by name."""
    out: dict[str, StateSpace] = {}
    if "connections" not in h5:
        return out
    for name in sorted(h5["connections"]):
        group = f"connections/{name}/statespace"
        if f"{group}/A" not in h5:
            continue
        mats, names = _group_matrices(h5, group)
        units = {k: _strings(h5, group, k) for k in ("input_units", "output_units")}
        out[name] = _statespace(mats, names, f"connection/{name}", **units)
    return out


def _craig_bampton(h5) -> SecondOrderModel | None:
    """The Craig-Bampton model (``/craig_bampton``), or None."""
    if "craig_bampton/M" not in h5:
        return None
    g = h5["craig_bampton"]
    M = np.array(g["M"][()], dtype=np.float64)
    K = np.array(g["K"][()], dtype=np.float64)
    n = M.shape[0]
    if M.shape != (n, n) or K.shape != (n, n):
        raise FileFormatError(f"file '{h5.filename}': craig_bampton/M {M.shape} and K "
                              f"{K.shape} are not square matrices of one size")
    return SecondOrderModel(
        M, K, tuple(read_strings(g["coordinate_names"])) if "coordinate_names" in g else (),
        tuple(read_strings(g["coordinate_units"])) if "coordinate_units" in g else (),
        tuple(read_strings(g["interface_names"])) if "interface_names" in g else (),
        np.array(g["fixed_interface_frequencies_hz"][()], dtype=np.float64)
        if "fixed_interface_frequencies_hz" in g else np.zeros(0))


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

    Uses :func:`load_model` (verifies schema and checksum) and the stored config for port
    directions and regions, body inertia, region centroids, the lumped chain. Raises
    FileFormatError for a file without a plant model or with content off the layout.
    """
    try:
        return _read_model_file(Path(path))
    except PipelineError:
        raise
    except LAYOUT_ERRORS as exc:
        raise layout_error(path, exc) from None


def _read_model_file(path: Path) -> ModelFile:
    import yaml

    path = Path(path)
    lm = load_model(path, require_plant=True)
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


# --------------------------------------------------------------------------- mesh and modes
@dataclass(frozen=True)
class ModeSet:
    """The mesh and the mode shapes of a file: what pictures and mesh exports need.

    points (n_p, 3) m; cells (n_t, 4 | 10) node indices in meshio order, of ``cell_type``;
    shapes (n_p, 3, n_m) kg^-1/2; frequencies_hz (n_m,); labels (n_m,); fixed_dofs (n_c,)
    (DOF 3 node + component); regions: boundary triangles (n_f, 3) by name;
    retained_damping: damping ratios of the modes in ``/statespace`` (empty without it).
    """

    name: str
    points: np.ndarray
    cell_type: str
    cells: np.ndarray
    shapes: np.ndarray
    frequencies_hz: np.ndarray
    labels: tuple[str, ...]
    fixed_dofs: np.ndarray
    regions: dict[str, np.ndarray]
    retained_damping: np.ndarray
    has_statespace: bool

    @property
    def fixed_nodes(self) -> np.ndarray:
        """Nodes with at least one constrained DOF."""
        return np.unique(self.fixed_dofs // 3)


def _array(h5, key: str, kind: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """Dataset ``key`` as a float64 (kind 'f') or int64 (kind 'i') array of ``shape``
    (None: any length), finite; FileFormatError naming the dataset otherwise."""
    dset = h5[key]
    got = dset.dtype.kind
    if got not in ("f", "i", "u") or (kind == "i" and got == "f"):
        raise FileFormatError(f"file '{h5.filename}': {key} has dtype {dset.dtype}, expected "
                              f"{'real numbers' if kind == 'f' else 'integers'}",
                              key=key, value=str(dset.dtype), expected=kind)
    a = np.array(dset[()], dtype=np.float64 if kind == "f" else np.int64)
    if a.ndim != len(shape) or any(w is not None and g != w for g, w in zip(a.shape, shape)):
        want = "(" + ", ".join("n" if w is None else str(w) for w in shape) + ")"
        raise FileFormatError(f"file '{h5.filename}': {key} has shape {a.shape}, expected {want}",
                              key=key, value=a.shape, expected=want)
    if kind == "f" and not np.all(np.isfinite(a)):
        raise FileFormatError(f"file '{h5.filename}': {key} holds non-finite values", key=key,
                              value="NaN or inf", expected="finite numbers")
    return a


def read_modes(path: str | Path) -> ModeSet:
    """The mesh, modes, labels, supports and regions of a result file (verified, with
    every array's dtype and shape checked against the others)."""
    with open_verified(path) as h5:
        points = _array(h5, "mesh/points", "f", (None, 3))
        cells_group = h5["mesh/cells"]
        kind = "tetra10" if "tetra10" in cells_group else next(iter(cells_group))
        cells = _array(h5, f"mesh/cells/{kind}", "i", (None, 10 if kind == "tetra10" else 4))
        if cells.size and (cells.min() < 0 or cells.max() >= points.shape[0]):
            raise FileFormatError(f"file '{path}': mesh/cells/{kind} refers to nodes outside "
                                  f"0..{points.shape[0] - 1}", key=f"mesh/cells/{kind}")
        freqs = _array(h5, "modes/frequencies_hz", "f", (None,))
        shapes = _array(h5, "modes/shapes", "f", (points.shape[0], 3, freqs.size))
        labels = tuple(read_strings(h5["modes/labels"]))
        if len(labels) != freqs.size:
            raise FileFormatError(f"file '{path}': {len(labels)} mode labels for {freqs.size} "
                                  "modes", key="modes/labels", value=len(labels),
                                  expected=str(freqs.size))
        fixed = (_array(h5, "mesh/fixed_dofs", "i", (None,)) if "mesh/fixed_dofs" in h5
                 else np.zeros(0, np.int64))
        regions = {name: _array(h5, f"mesh/regions/{name}", "i", (None, 3))
                   for name in (h5["mesh/regions"] if "mesh/regions" in h5 else [])}
        damping = (_array(h5, "statespace/damping_ratios", "f", (None,))
                   if "statespace/damping_ratios" in h5 else np.zeros(0))
        return ModeSet(str(h5.attrs.get("name", Path(path).stem)), points, kind, cells, shapes,
                       freqs, labels, fixed, regions, damping, "statespace" in h5)


# --------------------------------------------------------------------------- stress modes
@dataclass(frozen=True)
class StressModes:
    """The ``stress_modes`` group (docs/hdf5-format.md): stress and strain at the mesh points
    of each basis vector of the plant (coordinate eta_k, m kg^1/2) and of each residual
    flexibility shape (coordinate: input j, in its unit).

    stress (n_p, 6, n_b + n_c) Pa per unit coordinate; strain (n_p, 6, n_b + n_c) 1 per unit
    coordinate, engineering shear; Voigt order ``voigt_order``; shape_names, shape_units;
    n_basis n_b, n_correction n_c; input_names: the plant's inputs (the residual shapes);
    points (n_p, 3) m, the mesh points the fields are given at.
    """

    points: np.ndarray
    stress: np.ndarray
    strain: np.ndarray
    shape_names: tuple[str, ...]
    shape_units: tuple[str, ...]
    voigt_order: tuple[str, ...]
    n_basis: int
    n_correction: int
    input_names: tuple[str, ...]


def read_stress_modes(path: str | Path) -> StressModes | None:
    """The stress modes of a result file, or None for a file without them (written before
    they existed, or without a reduced model)."""
    with open_verified(path) as h5:
        if "stress_modes" not in h5:
            return None
        try:
            points = _array(h5, "mesh/points", "f", (None, 3))
            stress = _array(h5, "stress_modes/stress", "f", (points.shape[0], 6, None))
            strain = _array(h5, "stress_modes/strain", "f", stress.shape)
            attrs = h5["stress_modes/stress"].attrs
            names = tuple(read_strings(h5["stress_modes/shape_names"]))
            units = tuple(read_strings(h5["stress_modes/shape_units"]))
            n_b, n_c = int(attrs["n_basis"]), int(attrs["n_correction"])
            inputs = _strings(h5, "statespace", "input_names")
            voigt = tuple(read_strings(attrs["voigt_order"]))
        except LAYOUT_ERRORS as exc:
            raise layout_error(path, exc) from None
        if len(names) != stress.shape[2] or n_b + n_c != stress.shape[2] \
                or n_c not in (0, len(inputs)):
            raise FileFormatError(f"file '{path}': stress_modes holds {stress.shape[2]} shapes, "
                                  f"{len(names)} names, n_basis {n_b} + n_correction {n_c}",
                                  key="stress_modes/stress", value=stress.shape,
                                  expected="n_basis + n_correction shapes, one name each")
        return StressModes(points, stress, strain, names, units, voigt, n_b, n_c, inputs)
