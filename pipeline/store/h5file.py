"""The HDF5 file: atomic writing, checksummed, versioned reading.

Layout and units are documented in ``docs/hdf5-format.md`` (the contract with every
tool that loads our files). Writing goes to a temporary file in the target folder,
which is flushed, fsync'ed and renamed over the final name only when complete, so an
interrupted run never leaves a file under the final name that looks valid.

Integrity: the root attribute ``content_sha256`` is a SHA-256 over every dataset's
path, dtype, shape and bytes (in sorted path order). ``attrs_sha256`` covers every
attribute of every object (the metadata: units, names, filter cut-off, ...), and
``content_index`` (JSON) holds a short digest of each dataset and of each object's
attributes, so that a mismatch can be reported by name (which dataset changed, which
group is missing). :func:`open_verified` recomputes them and refuses a truncated,
bit-flipped or foreign file, or a schema version this code does not know, with a
message that says which. The writer hashes the numeric datasets from the arrays it has
just written (the same bytes; nothing is read back) and the attributes once: 0.38 ->
0.28 s for the 35 MB file of the 100k-DOF cantilever (Intel Xeon, 2 cores). Files written before ``attrs_sha256`` existed, or whose
content was re-signed by a tool that only updates ``content_sha256`` (``attrs_sha256``
records the content digest it was made with), are checked on their content only.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from pipeline._util.atomic import atomic_path, signals_held
from pipeline._util.paths import check_name
from pipeline.errors import FileFormatError, OutputError
from pipeline.store.layout import ROOT, SIMULATION_CONTENT
from pipeline.store.tree import Dataset

log = logging.getLogger(__name__)

SCHEMA = "fe-reduced-body"
#: 2 added the optional ``/rotation`` group; version 1 files (without it) keep loading
SCHEMA_VERSION = 2
KNOWN_VERSIONS = (1, 2)


#: bytes of a dataset read at once when the file is signed or verified: larger ones are
#: read in blocks of rows (the same bytes in the same order: the same digest)
READ_BLOCK_BYTES = 1 << 26
#: updates at least this long are hashed into the file's digest on the second thread
PARALLEL_HASH_BYTES = 1 << 20


def _write_dataset(h5, path: str, ds: Dataset) -> np.ndarray | None:
    """Write one dataset; returns the array it was written from when that array's bytes
    are the dataset's (numeric, C-contiguous, the stored dtype and shape), else None."""
    values = None
    if ds.written_in_blocks:  # too large for one process: written a block of rows at a time
        dset = h5.create_dataset(path, shape=ds.data.shape, dtype=ds.data.dtype)
        for start, rows in ds.data.blocks():
            dset[start:start + rows.shape[0]] = rows
    else:
        arr = ds.as_array()
        dset = _create_from_array(h5, path, arr)
        if (isinstance(arr, np.ndarray) and arr.dtype.kind in "biuf"
                and arr.flags.c_contiguous and arr.dtype == dset.dtype
                and arr.shape == dset.shape):
            values = arr
    dset.attrs["units"] = ds.units
    if ds.description:
        dset.attrs["description"] = ds.description
    for key, value in ds.attrs.items():
        dset.attrs[key] = _attr_value(value)
    return values


def _create_from_array(h5, path: str, arr: np.ndarray):
    import h5py

    if arr.dtype == object:
        dset = h5.create_dataset(path, data=[str(s) for s in arr.ravel()],
                                 dtype=h5py.string_dtype("utf-8"))
    elif arr.dtype.kind == "U":
        dset = h5.create_dataset(path, data=arr.astype(object), dtype=h5py.string_dtype("utf-8"))
    else:
        dset = h5.create_dataset(path, data=arr)
    return dset


def _attr_value(value: Any) -> Any:
    if isinstance(value, (list, tuple)) and value and isinstance(value[0], str):
        import h5py

        return np.array(value, dtype=h5py.string_dtype("utf-8"))
    return value


def _dataset_digests(h5, check=None, known: Mapping[str, np.ndarray] | None = None
                     ) -> tuple[str, dict[str, str]]:
    """(SHA-256 over every dataset, {path: SHA-256 of that dataset}) of an open File;
    ``check(name, array)``, if given, sees every numeric dataset as it is read.
    ``known``: {path: C-contiguous numeric array} of datasets just written from exactly
    these arrays (same dtype and shape): their bytes are hashed from memory instead of
    being read back (the writer's own digest, :func:`write_file`)."""
    digest = hashlib.sha256()
    each: dict[str, str] = {}
    paths: list[str] = []
    with signals_held():  # an exception raised inside HDF5's visit callback can crash it
        h5.visititems(lambda name, obj: paths.append(name) if hasattr(obj, "dtype") else None)
    # every byte goes into two digests: the whole file's on a second thread, in order,
    # while this one updates the dataset's and reads on (hashlib releases the GIL on
    # large updates; at most one block waits: 1.2 -> 0.7 s for a 350 MB file)
    pending = None
    one = hashlib.sha256()

    def update(data: bytes) -> None:
        nonlocal pending
        if pending is not None:
            pending.result()
            pending = None
        if len(data) < PARALLEL_HASH_BYTES:  # a name, a shape, a label
            digest.update(data)
        else:
            pending = pool.submit(digest.update, data)
        one.update(data)

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="digest") as pool:
        for name in sorted(paths):
            one = hashlib.sha256()
            _hash_dataset(h5[name], name, update, check, (known or {}).get(name))
            each[name] = one.hexdigest()
        if pending is not None:
            pending.result()
    return digest.hexdigest(), each


def _hash_dataset(dset, name: str, update, check, values: np.ndarray | None = None) -> None:
    """Feed ``update`` the canonical bytes of one dataset: name, shape, then the
    strings, or the dtype and the values a block of rows at a time (``values``: the
    C-contiguous array the dataset was written from, hashed instead of read back)."""
    update(name.encode())
    update(str(dset.shape).encode())
    if values is not None:
        update(dset.dtype.str.encode())
        update(values.reshape(-1).view(np.uint8))  # len() is the byte count
        return
    if dset.dtype.kind == "O" or dset.dtype.kind == "S":
        data = dset.asstr()[()] if dset.shape else dset.asstr()[()]
        items = np.atleast_1d(np.asarray(data, dtype=object)).ravel()
        update(b"str")
        for item in items:
            update(str(item).encode("utf-8", "surrogateescape") + b"\0")
    else:
        update(dset.dtype.str.encode())
        rows = max(1, READ_BLOCK_BYTES // max(dset.dtype.itemsize * dset.size
                                              // max(dset.shape[0], 1), 1)) \
            if dset.shape else 0
        for start in range(0, dset.shape[0], rows) if dset.shape and dset.size else [None]:
            data = np.ascontiguousarray(dset[()] if start is None
                                        else dset[start:start + rows])
            if check is not None:
                check(name, data)
            update(data.tobytes())


def content_digest(h5) -> str:
    """SHA-256 over every dataset (path, dtype, shape, bytes) of an open h5py File."""
    return _dataset_digests(h5)[0]


# root attributes that are not themselves covered by attrs_sha256
_SIGNATURES = (ROOT.content_sha256, ROOT.attrs_sha256)


def _attr_bytes(value: Any) -> bytes:
    """A canonical byte form of an attribute value as h5py reads it back."""
    if isinstance(value, str):
        return b"s" + value.encode("utf-8", "surrogateescape")
    if isinstance(value, bytes):
        return b"b" + value
    arr = np.asarray(value)
    if arr.dtype.kind == "O":
        return b"o" + str(arr.shape).encode() + b"\0".join(
            (v if isinstance(v, bytes) else str(v).encode("utf-8", "surrogateescape"))
            for v in arr.ravel())
    return arr.dtype.str.encode() + str(arr.shape).encode() + np.ascontiguousarray(arr).tobytes()


def _attrs_digests(h5) -> tuple[str, dict[str, str]]:
    """(SHA-256 over every attribute of every object, {object path: SHA-256 of its
    attributes}). The root's signatures are left out; ``content_index`` is in the total
    but not in the root's own entry (the index cannot hold its own digest)."""
    each = _object_attr_digests(h5)
    return _attrs_total(h5, each), each


def _object_attr_digests(h5) -> dict[str, str]:
    """{object path: SHA-256 of its attributes}, the root's signatures and
    ``content_index`` left out (so the entries do not change when those are set)."""
    objects = ["/"]
    with signals_held():
        h5.visit(lambda name: objects.append(name))
    each: dict[str, str] = {}
    for name in sorted(objects):
        obj = h5[name]
        one = hashlib.sha256()
        for key in sorted(obj.attrs):
            if name == "/" and key in _SIGNATURES + (ROOT.content_index,):
                continue
            one.update(key.encode() + b"=" + _attr_bytes(obj.attrs[key]) + b"\0")
        each[name] = one.hexdigest()
    return each


def _attrs_total(h5, each: Mapping[str, str]) -> str:
    """The SHA-256 over every object's attribute digest ``each`` (sorted by path) and the
    root's ``content_index`` as the file holds it now."""
    digest = hashlib.sha256()
    for name in sorted(each):
        digest.update(name.encode() + b":" + each[name].encode() + b"\n")
    if ROOT.content_index in h5.attrs:
        index = h5.attrs[ROOT.content_index]
        digest.update(ROOT.content_index.encode() + b"=" + _attr_bytes(index))
    return digest.hexdigest()


def sign(h5, known: Mapping[str, np.ndarray] | None = None) -> str:
    """Write the integrity attributes of an open, writable File (after its last change):
    ``content_index``, ``content_sha256`` and ``attrs_sha256``. Returns the content digest.
    A tool that adds datasets to one of our files calls this to re-sign it.
    ``known``: datasets written from these arrays (see :func:`_dataset_digests`).

    The objects' attribute digests are computed once: they leave out the root's
    signatures and index, so setting those does not change them, and the total over
    them then takes the index as stored."""
    content, datasets = _dataset_digests(h5, known=known)
    for key in _SIGNATURES + (ROOT.content_index,):
        if key in h5.attrs:
            del h5.attrs[key]
    objects = _object_attr_digests(h5)
    index = {"datasets": {k: v[:16] for k, v in datasets.items()},
             "attrs": {k: v[:16] for k, v in objects.items()}}
    text = json.dumps(index, sort_keys=True, separators=(",", ":"))
    if len(text) < 60000:  # an attribute lives in a 64 kB object header
        h5.attrs[ROOT.content_index] = text
    h5.attrs[ROOT.content_sha256] = content
    h5.attrs[ROOT.attrs_sha256] = f"{content[:16]}:{_attrs_total(h5, objects)}"
    return content


def write_file(path: str | Path, tree: Mapping[str, Dataset],
               group_attrs: Mapping[str, Mapping[str, Any]] | None = None,
               root_attrs: Mapping[str, Any] | None = None) -> Path:
    """Write ``tree`` (path -> Dataset) to ``path`` atomically, with the schema header."""
    import h5py

    from pipeline._version import __version__

    path = Path(path)
    for name in tree:  # every part of a key is a plain name (a region, port or case name)
        for part in name.split("/"):
            check_name(part, f"HDF5 key '{name}': part", error=OutputError)
    # signals are held while HDF5 writes (an interrupt inside it crashed the interpreter
    # at exit, SIGSEGV); one that arrives meanwhile is delivered before the rename, so the
    # temporary file is removed and nothing appears under the final name
    with atomic_path(path) as tmp, signals_held():
        with h5py.File(tmp, "w") as h5:
            h5.attrs[ROOT.schema] = SCHEMA
            h5.attrs[ROOT.schema_version] = SCHEMA_VERSION
            h5.attrs[ROOT.pipeline_version] = __version__
            h5.attrs[ROOT.created_utc] = _dt.datetime.now(_dt.timezone.utc).strftime(
                "%Y-%m-%dT%H:%M:%SZ")
            for key, value in (root_attrs or {}).items():
                h5.attrs[key] = _attr_value(value)
            known = {}  # hashed from memory by sign(): nothing is read back
            for name in sorted(tree):
                values = _write_dataset(h5, name, tree[name])
                if values is not None:
                    known[h5[name].name.lstrip("/")] = values
            for group, attrs in (group_attrs or {}).items():
                grp = h5.require_group(group)
                for key, value in attrs.items():
                    grp.attrs[key] = _attr_value(value)
            sign(h5, known)
            del known
    log.info("wrote %s (%.1f MB)", path, path.stat().st_size / 1e6)
    return path


HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _short(value: Any) -> str:
    if isinstance(value, np.generic):
        value = value.item()  # 1.5, not np.float64(1.5)
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _has_hdf5_signature(path: Path, size: int) -> bool:
    """The HDF5 signature at offset 0, 512, 1024, 2048, ... (after a user block)."""
    with open(path, "rb") as fh:
        offset = 0
        while offset + 8 <= size:
            fh.seek(offset)
            if fh.read(8) == HDF5_SIGNATURE:
                return True
            offset = 512 if offset == 0 else 2 * offset
    return False


def _open_h5(path: Path):
    """h5py.File(path, "r"), or FileFormatError saying why it is not a readable HDF5 file."""
    import h5py

    if not path.exists():
        raise FileFormatError(f"file '{path}': not found")
    if path.is_dir():
        raise FileFormatError(f"file '{path}': is a directory, not an HDF5 file")
    if not path.is_file():
        raise FileFormatError(f"file '{path}': not a regular file")
    try:
        size = path.stat().st_size
        signed = _has_hdf5_signature(path, size)
    except OSError as exc:
        raise FileFormatError(f"file '{path}': cannot be read ({exc})") from None
    if size == 0:
        raise FileFormatError(f"file '{path}': not a readable HDF5 file: it is empty (0 bytes; "
                              "truncated to nothing?)")
    if not signed:
        raise FileFormatError(f"file '{path}': not a readable HDF5 file: no HDF5 signature in "
                              f"its {size} bytes (not an HDF5 file, or its start is corrupt)")
    try:
        return h5py.File(path, "r")
    except Exception as exc:  # OSError mostly; h5py raises others on corrupt metadata
        text = " ".join(str(exc).split())
        m = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", text)
        if m:
            raise FileFormatError(
                f"file '{path}': not a readable HDF5 file: truncated ({m.group(1)} bytes, its "
                f"HDF5 header says {m.group(2)}): an incomplete copy, download or write") from None
        raise FileFormatError(f"file '{path}': not a readable HDF5 file (truncated or corrupt: "
                              f"{text[:200]})") from None


def _schema_version(h5, path: Path) -> int:
    if ROOT.schema_version not in h5.attrs:
        raise FileFormatError(f"file '{path}': has no schema_version attribute")
    raw = h5.attrs[ROOT.schema_version]
    value = raw.item() if isinstance(raw, np.ndarray) and raw.size == 1 else raw
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise FileFormatError(f"file '{path}': schema_version {_short(value)} is not an integer; "
                              f"this pipeline reads version(s) "
                              f"{', '.join(map(str, KNOWN_VERSIONS))}")
    return int(value)


def _diagnose(h5, stored_index: Any, actual: dict[str, str], kind: str) -> str:
    """Which datasets (kind 'datasets') or objects' attributes (kind 'attrs') differ from the
    index written with the file; '' when the index is missing or unreadable."""
    try:
        listed = json.loads(str(stored_index))[kind]
        assert isinstance(listed, dict)
    except Exception:
        return ""
    actual = {k: v[:16] for k, v in actual.items()}
    missing = sorted(set(listed) - set(actual))
    added = sorted(set(actual) - set(listed))
    changed = sorted(k for k in listed if k in actual and actual[k] != listed[k])
    parts = []
    if missing:
        groups = sorted({m.split("/")[0] for m in missing if "/" in m})
        gone = [g for g in groups if g not in h5]
        if gone:
            parts.append(f"group{'s' if len(gone) > 1 else ''} "
                         f"{', '.join('/' + g for g in gone)} missing")
        rest = [m for m in missing if m.split("/")[0] not in gone]
        if rest:
            parts.append(f"{'dataset' if kind == 'datasets' else 'object'}"
                         f"{'s' if len(rest) > 1 else ''} {', '.join(rest[:4])}"
                         f"{' ...' if len(rest) > 4 else ''} missing")
    if changed:
        what = "dataset" if kind == "datasets" else "attributes of"
        parts.append(f"{what} {', '.join(changed[:4])}{' ...' if len(changed) > 4 else ''} "
                     "changed")
    if added:
        parts.append(f"{', '.join(added[:4])}{' ...' if len(added) > 4 else ''} added")
    return "; ".join(parts)


def _verify(h5, path: Path, verify_checksum: bool) -> None:
    schema = h5.attrs.get(ROOT.schema)
    if isinstance(schema, bytes):
        schema = schema.decode("utf-8", "replace")
    if not isinstance(schema, str) or schema != SCHEMA:
        raise FileFormatError(f"file '{path}': schema attribute is {_short(schema)}, expected "
                              f"'{SCHEMA}' (not a file written by this pipeline)")
    version = _schema_version(h5, path)
    if version not in KNOWN_VERSIONS:
        raise FileFormatError(f"file '{path}': schema_version {version} is not known to this "
                              f"pipeline, which reads version(s) "
                              f"{', '.join(map(str, KNOWN_VERSIONS))}")
    if not verify_checksum:
        return
    stored = h5.attrs.get(ROOT.content_sha256)
    if stored is None:
        raise FileFormatError(f"file '{path}': has no content_sha256 attribute")
    stored = stored.decode("utf-8", "replace") if isinstance(stored, bytes) else str(stored)
    index = h5.attrs.get(ROOT.content_index)
    actual, each = _dataset_digests(h5, _finite_check(h5, path))
    _require_digest(h5, path, index, "content", stored, actual, each, "datasets",
                    "the file was modified or corrupted after it was written")
    signed = h5.attrs.get(ROOT.attrs_sha256)
    if signed is None:
        return  # written before attribute checksums existed
    signed = signed.decode("utf-8", "replace") if isinstance(signed, bytes) else str(signed)
    bound, _, stored_attrs = signed.partition(":")
    if bound != stored[:16]:
        # the content was re-signed by a tool that does not know attrs_sha256
        log.debug("%s: attrs_sha256 belongs to an earlier content; attributes not checked", path)
        return
    actual_attrs, each_attrs = _attrs_digests(h5)
    _require_digest(h5, path, index, "attribute", stored_attrs, actual_attrs, each_attrs,
                    "attrs", "the metadata (units, names, settings) was modified or corrupted "
                    "after it was written")


def _require_digest(h5, path, index, what: str, stored: str, actual: str, each, part: str,
                    meaning: str) -> None:
    """Raise FileFormatError naming what differs when the ``what`` checksum does not match."""
    if actual != stored:
        detail = _diagnose(h5, index, each, part)
        raise FileFormatError(f"file '{path}': {what} checksum mismatch (stored "
                              f"{stored[:12]}..., computed {actual[:12]}...)"
                              f"{': ' + detail if detail else ''}: {meaning}")


#: the most objects (groups, datasets, links) a file of ours may hold
MAX_OBJECTS = 200_000
#: data a file may declare beyond its own size (our writer never compresses; a small file
#: that declares gigabytes is a decompression bomb or sparse storage, refused unread)
DECLARED_SLACK_BYTES = 1 << 20


def _check_structure(h5, path: Path) -> None:
    """Refuse what the checksums do not cover, before any dataset is read: soft and
    external links, external raw storage, virtual datasets, committed datatypes, compound
    or complex values, more than :data:`MAX_OBJECTS` objects, and datasets declaring more
    data than the file holds (compression or sparse storage: a decompression bomb)."""
    import h5py

    try:
        size = path.stat().st_size
    except OSError:
        size = 0
    declared, count, seen = 0, 0, set()
    stack = [("", h5)]
    while stack:
        prefix, group = stack.pop()
        for name in group:
            full = f"{prefix}/{name}"
            count += 1
            if count > MAX_OBJECTS:
                raise FileFormatError(f"file '{path}': holds more than {MAX_OBJECTS} objects "
                                      "(not a file written by this pipeline)")
            link = group.get(name, getlink=True)
            if isinstance(link, h5py.ExternalLink):
                raise FileFormatError(f"file '{path}': {full} is an external link to "
                                      f"'{link.filename}:{link.path}'; links are not covered "
                                      "by the checksum and are refused")
            if isinstance(link, h5py.SoftLink):
                raise FileFormatError(f"file '{path}': {full} is a soft link to {link.path}; "
                                      "links are not covered by the checksum and are refused")
            obj = group[name]
            info = h5py.h5o.get_info(obj.id)
            key = getattr(info, "token", None) or info.addr
            if key in seen:
                raise FileFormatError(f"file '{path}': {full} is a second hard link to an "
                                      "object (not written by this pipeline)")
            seen.add(key)
            if isinstance(obj, h5py.Group):
                stack.append((full, obj))
            elif isinstance(obj, h5py.Dataset):
                if obj.is_virtual:
                    raise FileFormatError(f"file '{path}': {full} is a virtual dataset (data "
                                          "in other files); refused")
                if obj.external:
                    raise FileFormatError(f"file '{path}': {full} keeps its data in external "
                                          f"file(s) {obj.external[0][0]!r}; refused")
                kind = obj.dtype.kind
                if kind in "cV" or obj.dtype.fields is not None:
                    raise FileFormatError(f"file '{path}': {full} has dtype {obj.dtype}, "
                                          "expected real numbers or strings")
                declared += int(obj.size) * obj.dtype.itemsize
            else:
                raise FileFormatError(f"file '{path}': {full} is a {type(obj).__name__}, "
                                      "expected groups and datasets only")
    if declared > size + DECLARED_SLACK_BYTES:
        raise FileFormatError(f"file '{path}': its datasets declare {declared} bytes in a file "
                              f"of {size} bytes (compressed or sparse data, which this "
                              "pipeline never writes); refused unread")


FINITE_GROUPS = ("mesh", "body", "modes", "fe")
FINITE_MATRICES = ("A", "B", "C", "D")


def _finite_check(h5, path: Path):
    """A check(name, array) refusing NaN/inf where the schema has finite numbers: the
    state-space matrices A, B, C, D of every model, and every float dataset under
    /mesh, /body, /modes and /fe (elsewhere NaN has a meaning: no filter cut-off, a
    comparison that does not apply, a quantity a simulation cannot measure)."""
    content = h5.attrs.get(ROOT.content)
    if isinstance(content, bytes):
        content = content.decode("utf-8", "replace")
    if content == SIMULATION_CONTENT:
        return None

    def check(name: str, data: np.ndarray) -> None:
        parts = name.split("/")
        must = parts[0] in FINITE_GROUPS or parts[-1] in FINITE_MATRICES
        if must and data.dtype.kind == "f" and not np.all(np.isfinite(data)):
            raise FileFormatError(f"file '{path}': dataset {name} holds NaN or infinite "
                                  "values, expected finite numbers")

    return check


def open_verified(path: str | Path, verify_checksum: bool = True):
    """Open one of our HDF5 files read-only after checking schema, version and checksums.

    Returns an open ``h5py.File`` (use it as a context manager). Raises
    FileFormatError naming the file and what is wrong: not found, not HDF5, truncated,
    foreign (schema), unknown version, content or attribute checksum mismatch (naming the
    changed datasets or missing groups when the file has a ``content_index``), metadata
    too corrupt to read; and, before reading any data, what the checksums do not cover
    (links, external or virtual storage, compressed data: :func:`_check_structure`); NaN
    or infinite values in a model's numbers.
    """
    path = Path(path)
    h5 = _open_h5(path)
    try:
        _check_structure(h5, path)
        _verify(h5, path, verify_checksum)
    except FileFormatError:
        h5.close()
        raise
    except Exception as exc:  # h5py/HDF5 errors on corrupt metadata: OSError, RuntimeError...
        h5.close()
        text = " ".join(str(exc).split())[:200]
        raise FileFormatError(f"file '{path}': corrupt HDF5 metadata, a dataset or attribute "
                              f"cannot be read ({type(exc).__name__}: {text})") from None
    except BaseException:
        h5.close()
        raise
    return h5


def read_strings(dset) -> list[str]:
    """A string dataset or attribute as a list of str."""
    if hasattr(dset, "asstr"):
        return [str(s) for s in np.atleast_1d(dset.asstr()[()])]
    return [s.decode() if isinstance(s, bytes) else str(s) for s in np.atleast_1d(dset)]
