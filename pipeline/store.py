"""The HDF5 file: atomic writing, checksummed, versioned reading.

Layout and units are documented in ``docs/hdf5-format.md`` (the contract with every
tool that loads our files). Writing goes to a temporary file in the target folder,
which is flushed, fsync'ed and renamed over the final name only when complete, so an
interrupted run never leaves a file under the final name that looks valid.

Integrity: the root attribute ``content_sha256`` is a SHA-256 over every dataset's
path, dtype, shape and bytes (in sorted path order). :func:`open_verified` recomputes
it and refuses a file whose content does not match, a foreign file, or a schema
version this code does not know.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import logging
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .errors import FileFormatError
from .h5tree import Dataset

log = logging.getLogger(__name__)

SCHEMA = "fe-reduced-body"
SCHEMA_VERSION = 1
KNOWN_VERSIONS = (1,)


def _write_dataset(h5, path: str, ds: Dataset) -> None:
    import h5py

    arr = ds.as_array()
    if arr.dtype == object:
        dset = h5.create_dataset(path, data=[str(s) for s in arr.ravel()],
                                 dtype=h5py.string_dtype("utf-8"))
    elif arr.dtype.kind == "U":
        dset = h5.create_dataset(path, data=arr.astype(object), dtype=h5py.string_dtype("utf-8"))
    else:
        dset = h5.create_dataset(path, data=arr)
    dset.attrs["units"] = ds.units
    if ds.description:
        dset.attrs["description"] = ds.description
    for key, value in ds.attrs.items():
        dset.attrs[key] = _attr_value(value)


def _attr_value(value: Any) -> Any:
    if isinstance(value, (list, tuple)) and value and isinstance(value[0], str):
        import h5py

        return np.array(value, dtype=h5py.string_dtype("utf-8"))
    return value


def content_digest(h5) -> str:
    """SHA-256 over every dataset (path, dtype, shape, bytes) of an open h5py File."""
    digest = hashlib.sha256()
    paths: list[str] = []
    h5.visititems(lambda name, obj: paths.append(name) if hasattr(obj, "dtype") else None)
    for name in sorted(paths):
        dset = h5[name]
        digest.update(name.encode())
        digest.update(str(dset.shape).encode())
        if dset.dtype.kind == "O" or dset.dtype.kind == "S":
            data = dset.asstr()[()] if dset.shape else dset.asstr()[()]
            items = np.atleast_1d(np.asarray(data, dtype=object)).ravel()
            digest.update(b"str")
            for item in items:
                digest.update(str(item).encode("utf-8") + b"\0")
        else:
            digest.update(dset.dtype.str.encode())
            digest.update(np.ascontiguousarray(dset[()]).tobytes())
    return digest.hexdigest()


def write_file(path: str | Path, tree: Mapping[str, Dataset],
               group_attrs: Mapping[str, Mapping[str, Any]] | None = None,
               root_attrs: Mapping[str, Any] | None = None) -> Path:
    """Write ``tree`` (path -> Dataset) to ``path`` atomically, with the schema header."""
    import h5py

    from . import __version__

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        with h5py.File(tmp, "w") as h5:
            h5.attrs["schema"] = SCHEMA
            h5.attrs["schema_version"] = SCHEMA_VERSION
            h5.attrs["pipeline_version"] = __version__
            h5.attrs["created_utc"] = _dt.datetime.now(_dt.timezone.utc).strftime(
                "%Y-%m-%dT%H:%M:%SZ")
            for key, value in (root_attrs or {}).items():
                h5.attrs[key] = _attr_value(value)
            for name in sorted(tree):
                _write_dataset(h5, name, tree[name])
            for group, attrs in (group_attrs or {}).items():
                grp = h5.require_group(group)
                for key, value in attrs.items():
                    grp.attrs[key] = _attr_value(value)
            h5.attrs["content_sha256"] = content_digest(h5)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    log.info("wrote %s (%.1f MB)", path, path.stat().st_size / 1e6)
    return path


def open_verified(path: str | Path, verify_checksum: bool = True):
    """Open one of our HDF5 files read-only after checking schema, version and checksum.

    Returns an open ``h5py.File`` (use it as a context manager). Raises
    FileFormatError naming the file and what is wrong.
    """
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileFormatError(f"file '{path}': not found")
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise FileFormatError(f"file '{path}': not a readable HDF5 file (truncated or corrupt: "
                              f"{exc})") from None
    try:
        schema = h5.attrs.get("schema")
        if schema != SCHEMA:
            raise FileFormatError(f"file '{path}': schema attribute is {schema!r}, expected "
                                  f"'{SCHEMA}' (not a file written by this pipeline)")
        version = int(h5.attrs.get("schema_version", -1))
        if version not in KNOWN_VERSIONS:
            raise FileFormatError(f"file '{path}': schema_version {version} is not known to this "
                                  f"pipeline, which reads version(s) "
                                  f"{', '.join(map(str, KNOWN_VERSIONS))}")
        if verify_checksum:
            stored = h5.attrs.get("content_sha256")
            if stored is None:
                raise FileFormatError(f"file '{path}': has no content_sha256 attribute")
            try:
                actual = content_digest(h5)
            except (OSError, KeyError, RuntimeError) as exc:
                raise FileFormatError(f"file '{path}': a dataset cannot be read (corrupt: "
                                      f"{exc})") from None
            if actual != stored:
                raise FileFormatError(f"file '{path}': content checksum mismatch (stored "
                                      f"{str(stored)[:12]}..., computed {actual[:12]}...): the "
                                      "file was modified or corrupted after it was written")
    except BaseException:
        h5.close()
        raise
    return h5


def read_strings(dset) -> list[str]:
    """A string dataset or attribute as a list of str."""
    if hasattr(dset, "asstr"):
        return [str(s) for s in np.atleast_1d(dset.asstr()[()])]
    return [s.decode() if isinstance(s, bytes) else str(s) for s in np.atleast_1d(dset)]
