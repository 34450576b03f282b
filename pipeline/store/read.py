"""The one reader of our HDF5 file: every tool that uses a result file reads it here.

Each reader opens the file once (verified: schema, version, checksums, through
:func:`open_verified`) and returns one typed record of :mod:`pipeline.store.records`:

=========================  ===================================================================
:func:`load_model`         :class:`StoredModels`: every reduced model as the one
                           :class:`~pipeline.reduce.statespace.StateSpace` type (the plant,
                           its filtered twin, the lumped chain, each connection-point model)
                           and the Craig-Bampton M and K
:func:`read_model_file`    :class:`ModelFile`: the models plus what a simulation needs (ports
                           from the stored config, region centroids, body inertia)
:func:`read_stored_mesh`   :class:`StoredMesh`: the mesh, the mode shapes, the regions
:func:`read_fe_model`      :class:`StoredFEModel`: the mesh, ``/fe``'s M and K and one mode
                           basis (what the Exudyn export reads)
:func:`read_stress_modes`  :class:`StressModes`, or None for a file without them
:func:`read_rotation`      :class:`~pipeline.reduce.spin.RotationModel` (``/rotation``), or
                           None for a file without it
:func:`read_csr`           a sparse matrix of ``/fe`` (from an open file)
=========================  ===================================================================

:func:`pipeline.store.summary.read_summary` gives a file's
:class:`~pipeline.store.summary.FileSummary` (what ``inspect``, ``export --to json`` and
the batch cache read), on the same verified open.

Paths come from :mod:`pipeline.store.layout`. No mesh or finite-element code runs on the
way (this module never imports :mod:`pipeline.fe`, gmsh, meshio or scikit-fem), so a
downstream tool needs only h5py, numpy and python-control. A file that is not ours,
corrupt, or lacks what the caller needs ends in one :class:`~pipeline.errors.FileFormatError`
line (exit code 7).
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from pipeline.errors import FileFormatError, PipelineError
from pipeline.reduce.spin import RotationModel
from pipeline.reduce.statespace import StateSpace
from pipeline.store import h5file
from pipeline.store import layout as L
from pipeline.store.h5file import read_strings
from pipeline.store.physics import check_physics
from pipeline.store.records import (ModelFile, StoredBasis, StoredCraigBampton, StoredFEModel,
                                    StoredMaterials, StoredMesh, StoredModels, StressModes)

__all__ = ["load_model", "StoredModels", "StoredCraigBampton", "ModelFile", "read_model_file",
           "StoredMesh", "read_stored_mesh", "StoredFEModel", "StoredBasis", "read_fe_model",
           "open_verified", "read_strings", "StressModes",
           "read_stress_modes", "read_rotation", "read_csr", "StoredMaterials", "read_materials",
           "read_names", "LAYOUT_ERRORS", "layout_error"]


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

    Then the physics a checksum cannot vouch for
    (:func:`pipeline.store.physics.check_physics`: mesh indices, signs, symmetry, a stable
    A). Whatever the block raises while reading content that does not have the documented
    layout (a missing dataset, a wrong shape or type) becomes one FileFormatError line
    naming the file; a PipelineError raised in the block passes through unchanged.
    """
    h5 = h5file.open_verified(path, verify_checksum)
    try:
        check_physics(h5, path, remember=verify_checksum)  # what a re-signed file can hide
        yield h5
    except PipelineError:
        raise
    except LAYOUT_ERRORS as exc:
        raise layout_error(path, exc) from None
    finally:
        h5.close()


# --------------------------------------------------------------------------- arrays, names
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


def read_names(grp, key: str) -> tuple[str, ...]:
    """The names ``key`` (``input_names``, ``output_names``, ``state_names``, units) of the
    open state-space group ``grp``: its string dataset, else the attribute of its ``A``
    (the lumped chain stores them so)."""
    if key in grp:
        return tuple(read_strings(grp[key]))
    return tuple(read_strings(grp["A"].attrs.get(key, [])))


def _strings(h5, group: L.Group, key: str) -> tuple[str, ...]:
    return read_names(h5[group.path], key)


def _optional(h5, key: str, default=None):
    """Dataset ``key`` as an array, or ``default`` when the file lacks it."""
    return np.array(h5[key][()]) if key in h5 else default


def _statespace(h5, group: L.Group, label: str, **kw) -> StateSpace:
    """The A, B, C, D and names of ``group`` as a StateSpace (FileFormatError naming the
    matrix on a shape mismatch)."""
    mats = {k: _array(h5, group.dataset(k), "f", (None, None)) for k in "ABCD"}
    n, m, p = mats["A"].shape[0], mats["B"].shape[1], mats["C"].shape[0]
    expected = {"A": (n, n), "B": (n, m), "C": (p, n), "D": (p, m)}
    for k, shape in expected.items():
        if mats[k].shape != shape:
            raise FileFormatError(f"file '{h5.filename}': {group.dataset(k)} has shape "
                                  f"{mats[k].shape}, expected {shape}")
    if n == 0 and group is not None and group.path in _DYNAMIC_GROUPS:
        raise FileFormatError(f"file '{h5.filename}': {group.dataset('A')} has 0 states, "
                              "expected a model with at least one state (the pipeline writes "
                              "one per kept mode); the file was edited", key=group.dataset("A"),
                              value=0, expected="at least one state")
    names = {k: _strings(h5, group, k) for k in ("input_names", "output_names", "state_names")}
    # a ValueError (non-finite values) becomes the reader's FileFormatError
    return StateSpace(mats["A"], mats["B"], mats["C"], mats["D"], **names, label=label, **kw)


#: Model groups that always have states (modes, filter, lumped joints): 0 is an edited file.
_DYNAMIC_GROUPS = (L.STATESPACE.path, L.STATESPACE_FILTERED.path, L.LUMPED_STATESPACE.path)


# --------------------------------------------------------------------------- every model
#: groups that hold a model besides the plant
OTHER_MODELS = (L.LUMPED_STATESPACE.A, L.CONNECTIONS.path, L.CRAIG_BAMPTON.M)


def load_model(path: str | Path, require_plant: bool = False,
               verify_checksum: bool = True) -> StoredModels:
    """Read every reduced model of ``path`` (see :class:`StoredModels`).

    A file with connection-point, Craig-Bampton or lumped models but no ``/statespace``
    (a config without ``reduction``) loads with ``plant`` None, unless ``require_plant``.
    Raises FileFormatError for a file that is not ours, corrupt (see
    :func:`open_verified`; ``verify_checksum`` False skips only the checksums), holds modes
    only (or no plant when ``require_plant``), or lacks a dataset the layout requires.
    """
    path = Path(path)
    with open_verified(path, verify_checksum) as h5:
        return _models(h5, path, require_plant)


def _models(h5, path: Path, require_plant: bool,
            labels: tuple[str, str] = ("plant", "filtered")) -> StoredModels:
    """Every model of the open file ``h5``; ``labels``: of the plant and the filtered model."""
    has_plant = L.STATESPACE.path in h5
    others = any(k in h5 for k in OTHER_MODELS)
    if not has_plant and (require_plant or not others):
        raise FileFormatError(f"file '{path}': has no /statespace group (the config had no "
                              "'reduction' section); it holds "
                              + ("modes only" if not others else "no plant model"),
                              key=str(path), value="no /statespace",
                              expected="a file with a reduced model")
    required = (L.MODES.frequencies_hz, L.MODES.labels) + (
        (L.STATESPACE.A, L.STATESPACE.B, L.STATESPACE.C, L.STATESPACE.D,
         L.STATESPACE.damping_ratios) if has_plant else ())
    missing = [k for k in required if k not in h5]
    if missing:
        raise FileFormatError(f"file '{path}': dataset{'s' if len(missing) > 1 else ''} "
                              f"{', '.join(missing)} missing (an incomplete file, not the "
                              "layout of docs/hdf5-format.md)")
    common = dict(path=path, frequencies_hz=_array(h5, L.MODES.frequencies_hz, "f", (None,)),
                  labels=tuple(read_strings(h5[L.MODES.labels])), lumped=_lumped(h5),
                  connections=_connections(h5), craig_bampton=_craig_bampton(h5),
                  name=str(h5.attrs.get(L.ROOT.name, path.stem)),
                  mass=float(h5[L.BODY.mass][()]) if L.BODY.mass in h5 else math.nan,
                  config_yaml=str(h5.attrs.get(L.ROOT.config_yaml, "")))
    if not has_plant:
        return StoredModels(**common)
    plant = _statespace(h5, L.STATESPACE, labels[0])
    if not plant.ports or len(plant.output_names) != 3 * len(plant.ports):
        raise FileFormatError(f"file '{path}': {L.STATESPACE.output_names} "
                              f"{list(plant.output_names)[:4]} are not "
                              "'<port>/position|velocity|acceleration' for every port",
                              key=L.STATESPACE.output_names, value=plant.output_names[:4],
                              expected="<port>/position, <port>/velocity, <port>/acceleration")
    filtered = None
    if L.STATESPACE_FILTERED.path in h5:
        attrs = h5[L.STATESPACE_FILTERED.path].attrs
        cutoff = (float(attrs[L.STATESPACE_FILTERED.attr.cutoff_hz])
                  if L.STATESPACE_FILTERED.attr.cutoff_hz in attrs else None)
        filtered = _statespace(h5, L.STATESPACE_FILTERED, labels[1], cutoff_hz=cutoff,
                               filter_kind=str(attrs.get(L.STATESPACE_FILTERED.attr.filter_kind,
                                                         "unknown")))
    attrs = h5[L.STATESPACE.path].attrs
    compliance = _optional(h5, L.STATESPACE.static_compliance)
    rows: tuple[str, ...] = ()
    if compliance is not None:
        compliance = np.atleast_2d(compliance)
        rows = tuple(read_strings(h5[L.STATESPACE.static_compliance].attrs.get(
            L.STATESPACE.attr.rows, [])))
    return StoredModels(
        **common, plant=plant, filtered=filtered,
        damping_ratios=_array(h5, L.STATESPACE.damping_ratios, "f", (None,)),
        retained_frequencies_hz=np.atleast_1d(_optional(h5, L.STATESPACE.frequencies_hz,
                                                        np.zeros(0))).astype(float),
        static_compliance=compliance, compliance_rows=rows,
        input_units=tuple(read_strings(attrs.get(L.STATESPACE.attr.input_units, []))),
        port_units=tuple(read_strings(attrs.get(L.STATESPACE.attr.output_units, []))))


def _lumped(h5) -> StateSpace | None:
    """The lumped chain's state space (``/lumped/statespace``), or None."""
    if L.LUMPED_STATESPACE.A not in h5:
        return None
    return _statespace(h5, L.LUMPED_STATESPACE, "lumped")


def _connections(h5) -> dict[str, StateSpace]:
    """Each connection-point model (``/connections/<name>/statespace``) by name."""
    out: dict[str, StateSpace] = {}
    if L.CONNECTIONS.path not in h5:
        return out
    for name in sorted(h5[L.CONNECTIONS.path]):
        group = L.connection_statespace(name)
        if group.A not in h5:
            continue
        units = {k: _strings(h5, group, k) for k in ("input_units", "output_units")}
        out[name] = _statespace(h5, group, f"connection/{name}", **units)
    return out


def _craig_bampton(h5) -> StoredCraigBampton | None:
    """The Craig-Bampton model (``/craig_bampton``), or None."""
    cb = L.CRAIG_BAMPTON
    if cb.M not in h5:
        return None
    M = np.array(h5[cb.M][()], dtype=np.float64)
    K = np.array(h5[cb.K][()], dtype=np.float64)
    n = M.shape[0]
    if M.shape != (n, n) or K.shape != (n, n):
        raise FileFormatError(f"file '{h5.filename}': {cb.M} {M.shape} and K "
                              f"{K.shape} are not square matrices of one size")

    def names(key: str) -> tuple[str, ...]:
        return tuple(read_strings(h5[key])) if key in h5 else ()
    def floats(key: str, empty: tuple[int, ...]) -> np.ndarray:
        return np.array(_optional(h5, key, np.zeros(empty)), dtype=np.float64)
    return StoredCraigBampton(
        M, K, names(cb.coordinate_names), names(cb.coordinate_units), names(cb.interface_names),
        floats(cb.fixed_interface_frequencies_hz, (0,)),
        floats(cb.interface_points, (0, 3)).reshape(-1, 3),
        floats(cb.free_frequencies_hz, (0,)))


# --------------------------------------------------------------------------- for a simulation
def _region_centroid(h5, name: str) -> np.ndarray | None:
    key = L.region(name)
    if key not in h5 or L.MESH.points not in h5:
        return None
    cells = np.asarray(h5[key][()], dtype=np.int64)
    if cells.ndim != 2 or cells.shape[0] == 0 or cells.shape[1] not in (1, 2, 3):
        return None
    p = np.asarray(h5[L.MESH.points][()], dtype=float)[cells]  # (n, k, 3)
    if cells.shape[1] == 3:  # a face: area-weighted
        size = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    elif cells.shape[1] == 2:  # a line: length-weighted
        size = np.linalg.norm(p[:, 1] - p[:, 0], axis=1)
    else:  # a point set: the mean of its vertices
        size = np.ones(cells.shape[0])
    return (size[:, None] * p.mean(axis=1)).sum(axis=0) / size.sum()


def read_model_file(path: str | Path) -> ModelFile:
    """Read the state-space models, port data and body data of ``path`` (one verified open).

    The stored config gives port directions and regions and the supports; the mesh gives
    region centroids; ``/body`` the inertia; ``/lumped`` the chain. Raises
    FileFormatError for a file without a plant model or with content off the layout.
    """
    path = Path(path)
    with open_verified(path) as h5:
        models = _models(h5, path, True, ("FE", "FE filtered"))
        for model in (models.plant, models.filtered):
            if model is not None and (not model.ports or not model.input_names):
                raise FileFormatError(f"file '{path}': the {model.label} model has no input "
                                      "or no output port")
        ports, supports, in_plane = _ports(models.config_yaml)
        centroids: dict[str, np.ndarray] = {}
        for name in set(supports) | {str(p["region"]) for p in ports.values() if p["region"]}:
            c = _region_centroid(h5, name)
            if c is not None:
                centroids[name] = c
        body_com = np.asarray(_optional(h5, L.BODY.center_of_mass, np.full(3, np.nan)), float)
        body_inertia = np.asarray(_optional(h5, L.BODY.inertia, np.full((3, 3), np.nan)), float)
        return ModelFile(path, str(h5.attrs.get(L.ROOT.content_sha256, "")), models, ports,
                         supports, centroids, models.mass, body_com, body_inertia,
                         _lumped_chain(h5, models.lumped), in_plane)


def _ports(config_yaml: str) -> tuple[dict[str, dict[str, Any]], tuple[str, ...], bool]:
    """Ports (name -> side, kind, region, unit direction), support regions and the
    in-plane flag of the stored config (empty when it is absent or unreadable)."""
    import yaml

    cfg = None
    if config_yaml:
        try:
            cfg = yaml.safe_load(str(config_yaml))
        except yaml.YAMLError:
            cfg = None
    ports: dict[str, dict[str, Any]] = {}
    if not isinstance(cfg, Mapping):
        return ports, (), False
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
    return ports, supports, in_plane


def _lumped_chain(h5, chain: StateSpace | None) -> dict[str, Any] | None:
    """The lumped chain as the stepper uses it: A, B, C, D and names of ``chain``, the
    port directions (attributes of ``/lumped/statespace/A``) and the rigid bodies."""
    if chain is None:
        return None
    attrs = h5[L.LUMPED_STATESPACE.A].attrs
    out: dict[str, Any] = dict(zip("ABCD", chain))
    out.update(input_names=chain.input_names, output_names=chain.output_names,
               state_names=chain.state_names)
    for key in ("input_direction", "output_direction"):
        out[key] = np.asarray(attrs.get(getattr(L.LUMPED_STATESPACE.attr, key),
                                        np.full(3, np.nan)), float)
    for key in ("element_mass", "element_com", "element_inertia", "element_extent",
                "joint_positions"):
        if L.LUMPED.dataset(key) in h5:
            out[key] = np.asarray(h5[L.LUMPED.dataset(key)][()], float)
    table = {}
    for key in ("joint", "dof", "axis", "stiffness", "damping"):
        path = L.LUMPED.dataset(f"joint_table/{key}")
        if path in h5:
            table[key] = (tuple(read_strings(h5[path])) if key == "dof"
                          else np.asarray(h5[path][()], float))
    if len(table) == 5:
        out["joint_table"] = table
    return out


# --------------------------------------------------------------------------- mesh and modes
def _file_name(h5, path: str | Path) -> str:
    """The config's name (root attribute), or the file's stem without one."""
    name = h5.attrs.get(L.ROOT.name, Path(path).stem)
    return name.decode() if isinstance(name, bytes) else str(name)


def _mesh(h5, path: str | Path) -> tuple[np.ndarray, str, np.ndarray, np.ndarray,
                                        dict[str, np.ndarray]]:
    """(points (n_p, 3), cell type, cells, fixed DOFs, regions by name) of the open file,
    each dtype and shape checked, the cells' node indices inside the points."""
    points = _array(h5, L.MESH.points, "f", (None, 3))
    kinds = [k for k in L.CELL_TYPES if k in h5[L.MESH.cells]] or list(h5[L.MESH.cells])
    kind = kinds[0]
    key = f"{L.MESH.cells}/{kind}"
    cells = _array(h5, key, "i", (None, 10 if kind == "tetra10" else 4))
    if cells.size and (cells.min() < 0 or cells.max() >= points.shape[0]):
        raise FileFormatError(f"file '{path}': {key} refers to nodes outside "
                              f"0..{points.shape[0] - 1}", key=key)
    fixed = (_array(h5, L.MESH.fixed_dofs, "i", (None,)) if L.MESH.fixed_dofs in h5
             else np.zeros(0, np.int64))
    regions = {name: _region_cells(h5, name, points.shape[0])
               for name in (h5[L.MESH.regions] if L.MESH.regions in h5 else [])}
    return points, kind, cells, fixed, regions


def _region_cells(h5, name: str, n_points: int) -> np.ndarray:
    """Region ``name``'s vertex cells: (n, 3) triangles, (n, 2) edges or (n, 1) vertices,
    node indices inside 0..n_points-1."""
    key = L.region(name)
    cells = _array(h5, key, "i", (None, None))
    if cells.shape[1] not in (1, 2, 3):
        raise FileFormatError(f"file '{h5.filename}': {key} has shape {cells.shape}, expected "
                              "(n, 3), (n, 2) or (n, 1)", key=key, value=cells.shape,
                              expected="(n, 3), (n, 2) or (n, 1)")
    if cells.size and (cells.min() < 0 or cells.max() >= n_points):
        raise FileFormatError(f"file '{h5.filename}': {key} refers to nodes outside "
                              f"0..{n_points - 1}", key=key)
    return cells


def read_stored_mesh(path: str | Path) -> StoredMesh:
    """The mesh, modes, labels, supports and regions of a result file (verified, with
    every array's dtype and shape checked against the others)."""
    with open_verified(path) as h5:
        points, kind, cells, fixed, regions = _mesh(h5, path)
        freqs = _array(h5, L.MODES.frequencies_hz, "f", (None,))
        shapes = _array(h5, L.MODES.shapes, "f", (points.shape[0], 3, freqs.size))
        labels = tuple(read_strings(h5[L.MODES.labels]))
        if len(labels) != freqs.size:
            raise FileFormatError(f"file '{path}': {len(labels)} mode labels for {freqs.size} "
                                  "modes", key=L.MODES.labels, value=len(labels),
                                  expected=str(freqs.size))
        damping = (_array(h5, L.STATESPACE.damping_ratios, "f", (None,))
                   if L.STATESPACE.damping_ratios in h5 else np.zeros(0))
        return StoredMesh(_file_name(h5, path), points, kind, cells, shapes, freqs, labels,
                          fixed, regions, damping, L.STATESPACE.path in h5,
                          str(h5.attrs.get(L.ROOT.config_yaml, "")), _has_fe(h5))


def _has_fe(h5) -> bool:
    return L.FE.mass_matrix in h5 and L.FE.stiffness_matrix in h5


#: the mode bases :func:`read_fe_model` reads (``auto``: Craig-Bampton where the file has it)
BASES = ("auto", "modes", "craig_bampton")


def read_fe_model(path: str | Path, basis: str = "auto") -> StoredFEModel:
    """The full FE body of a result file in one verified open: mesh, regions, fixed DOFs,
    ``/fe``'s M and K (None without it) and the mode basis ``basis`` (one of
    :data:`BASES`). FileFormatError when the file lacks the basis asked for."""
    if basis not in BASES:
        raise ValueError(f"basis {basis!r} is not one of {', '.join(BASES)}")
    with open_verified(path) as h5:
        points, kind, cells, fixed, regions = _mesh(h5, path)
        M = K = None
        if _has_fe(h5):
            M, K = read_csr(h5, L.FE.mass_matrix), read_csr(h5, L.FE.stiffness_matrix)
        return StoredFEModel(_file_name(h5, path), points, kind, cells, fixed, regions, M, K,
                             _basis(h5, basis, 3 * points.shape[0]))


def _basis(h5, basis: str, n_dofs: int) -> StoredBasis:
    """The mode basis ``basis`` of the open file on all ``n_dofs`` DOFs."""
    cb = L.CRAIG_BAMPTON
    if basis == "auto":
        basis = "craig_bampton" if cb.shapes in h5 else "modes"
    if basis == "craig_bampton":
        if cb.shapes not in h5:
            raise FileFormatError(f"file '{h5.filename}': has no /craig_bampton/shapes; expected "
                                  "a run with a craig_bampton section (or use basis='modes')")
        shapes = _array(h5, cb.shapes, "f", (n_dofs // 3, 3, None))
        return StoredBasis("craig_bampton", shapes.reshape(n_dofs, -1),
                           tuple(read_strings(h5[cb.coordinate_names])),
                           interface_names=tuple(read_strings(h5[cb.interface_names])))
    n_modes = h5[L.MODES.omega2].shape[0]
    shapes = _array(h5, L.MODES.shapes, "f", (n_dofs // 3, 3, n_modes))
    return StoredBasis("modes", shapes.reshape(n_dofs, -1), (),
                       int(h5[L.MODES.path].attrs.get(L.MODES.attr.n_rigid, 0)))


# --------------------------------------------------------------------------- stress modes
def read_stress_modes(path: str | Path) -> StressModes | None:
    """The stress modes of a result file, or None for a file without them (written before
    they existed, or without a reduced model)."""
    sm = L.STRESS_MODES
    with open_verified(path) as h5:
        if sm.path not in h5:
            return None
        try:
            points = _array(h5, L.MESH.points, "f", (None, 3))
            stress = _array(h5, sm.stress, "f", (points.shape[0], 6, None))
            strain = _array(h5, sm.strain, "f", stress.shape)
            attrs = h5[sm.stress].attrs
            names = tuple(read_strings(h5[sm.shape_names]))
            units = tuple(read_strings(h5[sm.shape_units]))
            n_b, n_c = int(attrs[sm.attr.n_basis]), int(attrs[sm.attr.n_correction])
            inputs = _strings(h5, L.STATESPACE, "input_names")
            voigt = tuple(read_strings(attrs[sm.attr.voigt_order]))
        except LAYOUT_ERRORS as exc:
            raise layout_error(path, exc) from None
        if len(names) != stress.shape[2] or n_b + n_c != stress.shape[2] \
                or n_c not in (0, len(inputs)):
            raise FileFormatError(f"file '{path}': {sm.path} holds {stress.shape[2]} shapes, "
                                  f"{len(names)} names, n_basis {n_b} + n_correction {n_c}",
                                  key=sm.stress, value=stress.shape,
                                  expected="n_basis + n_correction shapes, one name each")
        return StressModes(points, stress, strain, names, units, voigt, n_b, n_c, inputs)


# --------------------------------------------------------------------------- rotation
def read_rotation(path: str | Path) -> RotationModel | None:
    """The ``/rotation`` group of a result file (prestressed frequencies and the reduced
    terms of geometric stiffening), or None for a file without it."""
    R = L.ROTATION
    with open_verified(path) as h5:
        if R.path not in h5:
            return None
        speeds = _array(h5, R.speeds_rad_s, "f", (None,))
        K = _array(h5, R.basis_stiffness, "f", (None, None))
        n_b = K.shape[0]
        names = tuple(read_strings(h5[R.input_names])) if R.input_names in h5 else ()
        attrs = h5[R.path].attrs
        return RotationModel(
            axis=_array(h5, R.axis, "f", (3,)), point=_array(h5, R.point, "f", (3,)),
            speeds_rad_s=speeds,
            frequencies_hz=_array(h5, R.frequencies_hz, "f", (speeds.size, None)),
            frequencies_reduced_hz=_array(h5, R.frequencies_reduced_hz, "f",
                                          (speeds.size, n_b)),
            stiffness=K, mass=_array(h5, R.basis_mass, "f", (n_b, n_b)),
            geometric=_array(h5, R.geometric_stiffness, "f", (6, n_b, n_b)),
            softening=_array(h5, R.spin_softening, "f", (6, n_b, n_b)),
            preload=(_array(h5, R.preload_stiffness, "f", (len(names), n_b, n_b)) if names
                     else np.zeros((0, n_b, n_b))),
            input_names=names, n_modes=int(attrs[R.attr.n_modes]),
            static_shape=bool(attrs[R.attr.static_shape]),
            **({} if R.centrifugal_load not in h5 else dict(
                centrifugal_load=_array(h5, R.centrifugal_load, "f", (6, n_b)),
                euler_load=_array(h5, R.euler_load, "f", (3, n_b)),
                coriolis=_array(h5, R.coriolis, "f", (3, n_b, n_b)))))


# --------------------------------------------------------------------------- sparse matrices
def read_csr(h5, group: str):
    """The full sparse matrix (scipy CSR) stored at ``group`` (e.g. ``layout.FE.mass_matrix``)
    of an open file by :func:`pipeline.store.schema.csr_datasets`; the upper triangle is
    mirrored when ``data`` says ``storage = "upper"``. FileFormatError if it is missing."""
    import scipy.sparse as sp

    g = L.csr_group(group)
    if group not in h5 or g.data not in h5:
        raise FileFormatError(f"file '{h5.filename}': has no sparse matrix /{group}")
    shape = tuple(int(v) for v in h5[g.shape][()])
    A = sp.csr_matrix((h5[g.data][()], h5[g.indices][()], h5[g.indptr][()]), shape=shape)
    storage = h5[g.data].attrs.get(g.attr.storage, "full")
    if isinstance(storage, bytes):
        storage = storage.decode()
    if storage == "upper":
        A = (A + sp.triu(A, k=1, format="csr").T).tocsr()
    return A


def read_materials(path: str | Path) -> StoredMaterials | None:
    """The material of every element (``/materials``), None for a file without it (one
    material: the stored config's ``material``); shapes checked against each other."""
    with open_verified(path) as h5:
        if L.MATERIALS.path not in h5:
            return None
        names = tuple(read_strings(h5[L.MATERIALS.material_names]))
        n = len(names)
        index = _array(h5, L.MATERIALS.element_material, "i", (None,))
        if index.size and (index.min() < 0 or index.max() >= n):
            raise FileFormatError(f"file '{path}': {L.MATERIALS.element_material} refers to "
                                  f"materials outside 0..{n - 1}", key=L.MATERIALS.element_material)
        return StoredMaterials(names, _array(h5, L.MATERIALS.stiffness, "f", (n, 6, 6)),
                               _array(h5, L.MATERIALS.density, "f", (n,)), index,
                               _array(h5, L.MATERIALS.element_density, "f", (index.size,)))
