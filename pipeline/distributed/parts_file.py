"""The partitioned mesh file: what rank 0 of the distributed path evaluates on the whole
mesh, written once by ``python -m pipeline partition`` (:mod:`pipeline.cli.partition`)
and read by the ranks of a run with ``mesh.parts`` (each its own part only).

Written and read here only; the layout (docs/distributed.md, "The parts file"):

* root attributes: ``schema`` (:data:`SCHEMA`), ``schema_version``
  (:data:`SCHEMA_VERSION`), ``ranks`` (the part count), ``name``, ``pipeline_version``,
  ``created_utc`` and the store's signature (``content_sha256`` over every dataset,
  ``attrs_sha256``: :func:`pipeline.store.h5file.sign`);
* ``/shared``: the counts, the free-DOF count, the mesh file's path and SHA-256, the
  added masses' (6, 6) rigid mass, the port matrices, the partition kind, the
  canonical config (``config_json``) it was made with and a rotating body's added
  masses (``spin_masses``) (:class:`Shared`);
* ``/kept``: what rank 0 keeps of the whole mesh for the writer and for judging the
  supports (:class:`Kept`);
* ``/ranks/<r>``: rank r's :class:`~pipeline.distributed.submesh.RankMesh` as arrays
  and its own :meth:`~pipeline.distributed.partition.RowPartition.local`.

Every value is a dataset (numbers, arrays, UTF-8 strings; a sparse matrix a group of
``data``, ``indices``, ``indptr``, ``shape``, ``format``; a record a group of its
fields, an absent optional field no dataset); no pickle. Each of the three kinds of
group carries the attribute ``sha256`` over its datasets (sorted paths, dtype, shape,
bytes), so that a rank verifies what it reads without reading the other ranks' parts.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import scipy.sparse as sp

from pipeline.errors import ConfigError, FileFormatError

log = logging.getLogger(__name__)

#: the root attribute ``schema`` of a parts file
SCHEMA = "fe-reduced-body-parts"
#: the layout's version; a reader refuses any other
SCHEMA_VERSION = 1
#: top-level config keys that act only after the FE stage, and so may differ between
#: the config a parts file was made with and the run's (``mesh.parts`` itself too)
RUN_ONLY_KEYS = ("name", "modes", "damping", "filter", "lumped")


@dataclass(frozen=True)
class Shared:
    """What every rank reads: ``ranks`` parts, the whole mesh's ``n_nodes`` and
    :class:`~pipeline.distributed.submesh.MeshCounts`, element ``order``, ``n_free``
    free DOFs, the port matrices (:class:`~pipeline.fe.ports.PortMatrices`, or None),
    the mesh file kept (its path, "" for none, and SHA-256), the added masses' (6, 6)
    rigid mass about the origin (kg, kg m, kg m^2; None without), the partition kind
    (``graph`` or ``slab``), the canonical config (:func:`canonical_config`) and a
    rotating body's added masses (``spin_masses``, stored as :func:`_spin_fields`)."""

    ranks: int
    n_nodes: int
    counts: Any
    order: int
    n_free: int
    ports: Any
    mesh_path: str
    mesh_sha256: str
    added_rigid: np.ndarray | None
    partition: str
    config: dict
    #: a rotating body's added masses as rank 0 evaluates them on the whole mesh
    #: (:func:`pipeline.distributed.prestress.rotation_masses`: the area masses' scalar
    #: node mass, COO kg, or None, and each distributing point mass's (dofs, G, M6,
    #: point)), or None
    spin_masses: Any = None


@dataclass(frozen=True)
class Kept:
    """What rank 0 reads besides: the points (n_points, 3) m and elements (n_el, nb)
    int32 (int64 past 2^31 points) of the whole mesh, its regions (name -> surface
    cells), the element materials where ``/materials`` stores them (else None), the
    body's :class:`~pipeline.solve.labels.LabelFrame` and the
    :class:`~pipeline.distributed.whole.SupportInputs` (the held DOFs are the file's
    ``/mesh/fixed_dofs``)."""

    node_points: np.ndarray
    element_nodes: np.ndarray
    regions: dict
    materials: Any
    label_frame: Any
    support: Any


def canonical_config(cfg) -> dict:
    """The config as plain JSON values (:func:`pipeline.config.config_to_dict`), without
    ``mesh.parts``: what a parts file records and a run is compared with."""
    from pipeline.config.serialize import config_to_dict

    out = json.loads(json.dumps(config_to_dict(cfg)))
    out.get("mesh", {}).pop("parts", None)
    return out


def _flat(value, key: str = ""):
    """(dotted key, leaf) pairs of a plain config value, in its order."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _flat(v, f"{key}.{k}" if key else k)
    elif isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        for i, v in enumerate(value):
            yield from _flat(v, f"{key}[{i}]")
    else:
        yield key, value


def first_difference(made: dict, run: dict) -> str | None:
    """The first config key (dotted) in which ``run`` differs from ``made`` (both
    :func:`canonical_config`), leaving out :data:`RUN_ONLY_KEYS`; None if none."""
    a = {k: v for k, v in _flat(made) if k.split(".")[0].split("[")[0] not in RUN_ONLY_KEYS}
    b = {k: v for k, v in _flat(run) if k.split(".")[0].split("[")[0] not in RUN_ONLY_KEYS}
    for key in list(a) + [k for k in b if k not in a]:
        if a.get(key, _MISSING) != b.get(key, _MISSING):
            return key
    return None


_MISSING = object()


# --------------------------------------------------------------------------- values

def _put(g, name: str, value) -> None:
    """Store ``value`` under ``name`` in group ``g`` (module: every value a dataset)."""
    import h5py

    if value is None:
        return
    if sp.issparse(value):
        fmt = "csc" if value.format == "csc" else "csr"
        m = value.asformat(fmt)
        sub = g.create_group(name)
        sub["format"] = fmt
        sub["shape"] = np.asarray(m.shape, dtype=np.int64)
        for part in ("data", "indices", "indptr"):
            sub[part] = getattr(m, part)
    elif isinstance(value, str):
        g.create_dataset(name, data=value, dtype=h5py.string_dtype())
    elif isinstance(value, (tuple, list)) and all(isinstance(v, str) for v in value):
        g.create_dataset(name, data=np.array(list(value), dtype=object),
                         dtype=h5py.string_dtype(), shape=(len(value),))
    elif dataclasses.is_dataclass(value):
        sub = g.create_group(name)
        sub.attrs["record"] = type(value).__name__
        for f in dataclasses.fields(value):
            _put(sub, f.name, getattr(value, f.name))
    elif isinstance(value, dict):
        sub = g.create_group(name, track_order=True)  # read back in the dict's order
        for k, v in value.items():
            _put(sub, k, v)
    else:
        g[name] = np.asarray(value)


def _get(obj):
    """The value of a dataset or group stored by :func:`_put` (a record as a dict of
    its fields, a dict group as a dict)."""
    import h5py

    if isinstance(obj, h5py.Group):
        if "indptr" in obj and "format" in obj:
            fmt = obj["format"].asstr()[()]
            cls = sp.csc_matrix if fmt == "csc" else sp.csr_matrix
            return cls((obj["data"][()], obj["indices"][()], obj["indptr"][()]),
                       shape=tuple(int(n) for n in obj["shape"][()]))
        return {k: _get(obj[k]) for k in obj}
    if obj.dtype.kind in "OS" or h5py.check_string_dtype(obj.dtype) is not None:
        value = obj.asstr()[()]
        return str(value) if obj.shape == () else tuple(str(v) for v in value)
    value = obj[()]
    return value.item() if obj.shape == () else value


def _record(cls, fields: dict):
    """``cls`` made from the stored ``fields``: an absent one (None when written) its
    default, else None."""
    out = {}
    for f in dataclasses.fields(cls):
        if f.name in fields:
            out[f.name] = fields[f.name]
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            out[f.name] = None
    return cls(**out)


# --------------------------------------------------------------------------- digests

def group_digest(g) -> str:
    """SHA-256 over the datasets of group ``g`` (recursively): each one's path (relative),
    dtype, shape and bytes, in sorted path order."""
    import h5py

    digest = hashlib.sha256()
    names: list[str] = []
    g.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
    for name in sorted(names):
        d = g[name]
        if h5py.check_string_dtype(d.dtype) is not None:
            data = d.asstr()[()]
            raw = (data if d.shape == () else "\0".join(data)).encode()
            kind = "str"
        else:
            raw, kind = np.ascontiguousarray(d[()]).tobytes(), d.dtype.str
        digest.update(f"{name}|{kind}|{d.shape}|".encode())
        digest.update(raw)
    return digest.hexdigest()


def _seal(g) -> None:
    g.attrs["sha256"] = group_digest(g)


def _verified(h5, name: str, path: Path):
    """Group ``name`` of the open parts file after checking its ``sha256``
    (FileFormatError, one line, when it differs)."""
    if name not in h5:
        raise FileFormatError(f"parts file '{path}': has no group /{name}; expected a file "
                              "written by 'python -m pipeline partition'")
    g = h5[name]
    stored = g.attrs.get("sha256")
    stored = stored.decode() if isinstance(stored, bytes) else stored
    if stored != group_digest(g):
        raise FileFormatError(f"parts file '{path}': the checksum of /{name} fails (the file "
                              "was modified or corrupted after it was written); expected the "
                              "file as 'python -m pipeline partition' wrote it")
    return g


# --------------------------------------------------------------------------- writing

def _rank_group(g, mesh, part) -> None:
    s = mesh.space
    for name, value in (("node_points", s.node_points), ("element_nodes", s.element_nodes),
                        ("n_vertices", s.body.vertices.shape[0]), ("order", s.order),
                        ("points", mesh.points), ("dof_rows", mesh.dof_rows), ("lo", mesh.lo),
                        ("hi", mesh.hi), ("n_free", mesh.n_free),
                        ("node_volume", mesh.node_volume),
                        ("mass_elements", mesh.mass_elements), ("materials", mesh.materials),
                        ("added", mesh.added), ("springs", mesh.springs),
                        ("row_order", part.order), ("row_starts", part.starts),
                        ("row_dofs", part.dofs), ("rank", part.rank)):
        _put(g, name, value)
    _seal(g)


#: the four arrays of a distributing point mass in ``Shared.spin_masses``
SPIN_POINT_FIELDS = ("dofs", "G", "M6", "point")


def _spin_fields(spin) -> dict | None:
    """``Shared.spin_masses`` as the stored groups: ``area`` (CSR) and ``points/<i>``
    with :data:`SPIN_POINT_FIELDS`; None stays None."""
    if spin is None:
        return None
    area, points = spin
    return {"area": None if area is None else sp.csr_matrix(area),
            "points": {str(i): dict(zip(SPIN_POINT_FIELDS, m)) for i, m in enumerate(points)}}


def _spin_masses(fields: dict | None):
    """The inverse of :func:`_spin_fields`: (area COO or None, ((dofs, G, M6, point),
    ...) in their order), or None."""
    if fields is None:
        return None
    area = fields.get("area")
    points = fields.get("points") or {}
    return (None if area is None else sp.coo_matrix(area),
            tuple(tuple(np.asarray(points[i][k]) for k in SPIN_POINT_FIELDS)
                  for i in sorted(points, key=int)))


def write_parts(path: str | Path, shared: Shared, kept: Kept, ranks: Iterable) -> Path:
    """Write the parts file ``path`` atomically (:func:`pipeline._util.atomic.atomic_path`):
    ``shared``, ``kept`` and, from ``ranks`` (an iterable of (RankMesh, this rank's own
    RowPartition) in rank order, consumed one at a time), every rank's group; signed
    as the result file is. Returns the path."""
    import h5py

    from pipeline._util.atomic import atomic_path, signals_held
    from pipeline._version import __version__
    from pipeline.store.h5file import sign

    path = Path(path)
    # signals wait while HDF5 writes (as the result file's writer: an interrupt inside
    # HDF5 crashed the interpreter), not while the next part is cut out
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        with signals_held():
            h5.attrs["schema"] = SCHEMA
            h5.attrs["schema_version"] = SCHEMA_VERSION
            h5.attrs["ranks"] = int(shared.ranks)
            h5.attrs["name"] = str(shared.config.get("name", ""))
            h5.attrs["pipeline_version"] = __version__
            h5.attrs["created_utc"] = _dt.datetime.now(_dt.timezone.utc).strftime(
                "%Y-%m-%dT%H:%M:%SZ")
            g = h5.create_group("shared")
            for f in dataclasses.fields(shared):
                value = getattr(shared, f.name)
                if f.name == "config":
                    value = json.dumps(value, sort_keys=False)
                elif f.name == "spin_masses":
                    value = _spin_fields(value)
                _put(g, "config_json" if f.name == "config" else f.name, value)
            _seal(g)
            g = h5.create_group("kept")
            for f in dataclasses.fields(kept):
                _put(g, f.name, getattr(kept, f.name))
            _seal(g)
            groups = h5.create_group("ranks")
        n = 0
        for r, (mesh, part) in enumerate(ranks):
            with signals_held():
                _rank_group(groups.create_group(str(r)), mesh, part)
            n += 1
        if n != shared.ranks:
            raise ValueError(f"{n} rank groups written for {shared.ranks} ranks")
        with signals_held():
            sign(h5)
    log.info("wrote %s (%.1f MB, %d parts)", path, path.stat().st_size / 1e6, shared.ranks)
    return path


# --------------------------------------------------------------------------- reading

def _open(path: Path):
    """The parts file open read-only after checking its schema and version."""
    import h5py

    try:
        h5 = h5py.File(path, "r")
    except (OSError, ValueError) as exc:
        text = " ".join(str(exc).split())[:160]
        raise FileFormatError(f"mesh.parts '{path}': not a parts file (not a readable HDF5 "
                              f"file: {text}); expected a file written by 'python -m "
                              "pipeline partition'") from None
    schema = h5.attrs.get("schema")
    schema = schema.decode("utf-8", "replace") if isinstance(schema, bytes) else schema
    if schema != SCHEMA:
        h5.close()
        raise FileFormatError(f"mesh.parts '{path}': not a parts file (schema {schema!r}); "
                              "expected a file written by 'python -m pipeline partition'")
    version = h5.attrs.get("schema_version")
    if version != SCHEMA_VERSION:
        h5.close()
        raise FileFormatError(f"mesh.parts '{path}': parts file schema_version {version}; "
                              f"this pipeline reads version {SCHEMA_VERSION} (make it again "
                              "with 'python -m pipeline partition')")
    return h5


def is_parts_file(path: str | Path) -> bool:
    """Whether ``path`` is a readable parts file of this package (any schema_version):
    what ``partition`` may replace without ``--force``."""
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            schema = h5.attrs.get("schema")
    except (OSError, ValueError):  # not HDF5, unreadable: not ours
        return False
    schema = schema.decode("utf-8", "replace") if isinstance(schema, bytes) else schema
    return schema == SCHEMA


def parts_digest(path: str | Path) -> str:
    """The file's signature ``content_sha256`` (the result file's ``/run`` records it)."""
    with _open(Path(path)) as h5:
        value = h5.attrs.get("content_sha256", "")
        return value.decode() if isinstance(value, bytes) else str(value)


def read_shared(path: str | Path, cfg, ranks: int) -> Shared:
    """The shared group of ``path`` for a run of ``cfg`` on ``ranks`` ranks, refused in
    one line when the file is not a parts file or of another schema_version
    (FileFormatError), holds another number of parts or was made with a config that
    differs in a key that enters the parts (ConfigError naming it), or its checksum
    fails (FileFormatError)."""
    from pipeline.distributed.submesh import MeshCounts
    from pipeline.fe.ports import PortMatrices

    path = Path(path)
    with _open(path) as h5:
        made = int(h5.attrs.get("ranks", -1))
        if made != ranks:
            raise ConfigError(f"mesh.parts '{path}': holds {made} parts, the run has {ranks} "
                              f"ranks; expected a parts file made with --ranks {ranks} (or "
                              f"the run on {made} ranks)", key="mesh.parts", value=str(path),
                              expected=f"a file of {ranks} parts")
        g = _verified(h5, "shared", path)
        fields = {k: _get(g[k]) for k in g}
    config = json.loads(fields.pop("config_json"))
    key = first_difference(config, canonical_config(cfg))
    if key is not None:
        raise ConfigError(f"mesh.parts '{path}': made with another config: key '{key}' "
                          "differs; expected the config the parts file was made with (only "
                          f"{', '.join(k + '.*' if k != 'name' else k for k in RUN_ONLY_KEYS)}"
                          " may differ)", key=key, value=str(path),
                          expected="the parts file's config")
    counts = fields.pop("counts")
    ports = fields.pop("ports", None)
    return Shared(config=config, counts=MeshCounts(**counts),
                  ports=None if ports is None else _record(PortMatrices, ports),
                  added_rigid=fields.pop("added_rigid", None),
                  spin_masses=_spin_masses(fields.pop("spin_masses", None)), **fields)


def _materials(fields: dict):
    from pipeline.config import Material
    from pipeline.fe.materials import ElementMaterials

    uniform = fields.get("uniform")
    return ElementMaterials(tuple(fields["names"]), fields["D"], fields["law_rho"],
                            fields["index"], fields["rho"],
                            None if uniform is None else _record(Material, uniform))


def read_rank(path: str | Path, rank: int):
    """(RankMesh, RowPartition) of ``rank``: its group only, checksum verified; the FE
    space of the part rebuilt from the arrays (:func:`pipeline.fe.space.sub_space`)."""
    from pipeline.distributed.partition import RowPartition
    from pipeline.distributed.submesh import RankMesh
    from pipeline.fe.space import sub_space

    path = Path(path)
    with _open(path) as h5:
        g = _verified(h5, f"ranks/{rank}", path)
        f = {k: _get(g[k]) for k in g}
    space = sub_space(int(f["order"]), f["node_points"], f["element_nodes"],
                      int(f["n_vertices"]))
    mesh = RankMesh(space=space, points=f["points"], dof_rows=f["dof_rows"], lo=int(f["lo"]),
                    hi=int(f["hi"]), n_free=int(f["n_free"]), node_volume=f["node_volume"],
                    mass_elements=f["mass_elements"], materials=_materials(f["materials"]),
                    added=f.get("added"), springs=f.get("springs"))
    part = RowPartition(f["row_order"], f["row_starts"], f.get("row_dofs"), int(f["rank"]))
    return mesh, part


def read_kept(path: str | Path) -> Kept:
    """Rank 0's :class:`Kept` (the group ``kept`` only, checksum verified)."""
    from pipeline.distributed.whole import SupportInputs
    from pipeline.solve.labels import LabelFrame

    path = Path(path)
    with _open(path) as h5:
        g = _verified(h5, "kept", path)
        f = {k: _get(g[k]) for k in g}
    materials = f.get("materials")
    return Kept(node_points=f["node_points"], element_nodes=f["element_nodes"],
                regions=dict(f.get("regions", {})),
                materials=None if materials is None else _materials(materials),
                label_frame=_record(LabelFrame, f["label_frame"]),
                support=_record(SupportInputs, f["support"]))
