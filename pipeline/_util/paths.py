"""Destinations, inputs and names: checked before any work starts.

Every command calls :func:`check_output` for each file it will write (and
:func:`check_output_dir` for a folder), with the files it reads as ``inputs``, before it
meshes, solves or reads anything large. The rules, in order:

1. the destination is not empty and not an existing directory (a file is wanted);
2. it is none of the command's inputs: compared by resolved path (symlinks followed) and,
   where both exist, by device and inode (hard links, bind mounts) -- refused even with
   ``--force``: a command never destroys what it is reading;
3. an existing file is replaced only when it was *created for this purpose*: a file of
   the kind the command writes there, recognised by its content (``kind``, see
   :data:`KINDS`): one of our HDF5 files for a model or result, an XDMF sidecar made by
   the exporter, a JSON summary of ours, a MATLAB v5 file, a VTK/XDMF XML file, a PNG, a
   gmsh mesh file, ... Anything else (a YAML config, another tool's HDF5, a user's mesh, an
   unknown file) is replaced only with ``force=True`` (``--force``);
4. the folder exists (``create_parent=True``: or can be created: the default ``outputs/``)
   and a file can be created in it (probed with a real file, so a read-only mount or a
   folder without write permission is found even when running as root).

Each failure is one :class:`~pipeline.errors.OutputError` line naming the path.

:func:`check_name` validates a name that becomes a folder, a file name or an HDF5 key
(region names read from a user's mesh, batch and case names, port names).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Callable, Iterable

from pipeline.errors import ConfigError, OutputError

__all__ = ["KINDS", "file_sha256", "check_output", "check_output_dir", "same_file", "check_name",
           "NAME_PROBLEMS", "file_kind_matches"]

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
OUR_SCHEMA = "fe-reduced-body"


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes, read 1 MiB at a time."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _head(path: Path, n: int = 4096) -> bytes:
    try:
        with open(path, "rb") as fh:
            return fh.read(n)
    except OSError:
        return b""


def _h5_root_attrs(path: Path) -> dict | None:
    """The root attributes of an HDF5 file (strings decoded), or None if it is not one."""
    if not _head(path, 8) == HDF5_SIGNATURE:
        return None
    try:
        import h5py

        with h5py.File(path, "r") as h5:
            out = {}
            for key in ("schema", "datatype"):
                value = h5.attrs.get(key)
                out[key] = value.decode("utf-8", "replace") if isinstance(value, bytes) else value
            out["keys"] = set(h5.keys())
            return out
    except Exception:
        return None


def _ours_h5(path: Path) -> bool:
    attrs = _h5_root_attrs(path)
    return attrs is not None and attrs.get("schema") == OUR_SCHEMA


def _xdmf_sidecar(path: Path) -> bool:
    attrs = _h5_root_attrs(path)
    return (attrs is not None and attrs.get("schema") is None and "frequencies_hz" in attrs["keys"]
            and all(re.fullmatch(r"data\d+|frequencies_hz|display_scale", k) for k in attrs["keys"]))


def _exudyn(path: Path) -> bool:
    attrs = _h5_root_attrs(path)
    return attrs is not None and attrs.get("schema") is None and attrs.get("datatype") == "dict"


def _json_summary(path: Path) -> bool:
    try:
        if path.stat().st_size > 64 << 20:
            return False
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and str(data.get("format", "")).startswith(OUR_SCHEMA)


def _fmu(path: Path) -> bool:
    """An FMU this package exported: a zip whose modelDescription.xml names us as its
    generation tool (read at most 64 KiB of it)."""
    import zipfile

    if _head(path, 4) != b"PK\x03\x04":
        return False
    try:
        with zipfile.ZipFile(path) as z, z.open("modelDescription.xml") as f:
            return b'generationTool="fe-reduced-body' in f.read(65536)
    except (OSError, KeyError, zipfile.BadZipFile):
        return False


def _text(path: Path) -> str | None:
    head = _head(path)
    if b"\0" in head:
        return None
    return head.decode("utf-8", "replace")


#: kind -> test that an existing file is of that kind (and so may be replaced without --force)
KINDS: dict[str, Callable[[Path], bool]] = {
    "h5": _ours_h5,                       # a model file or a simulation result of ours
    "xdmf-sidecar": _xdmf_sidecar,        # the <stem>.h5 beside an exported .xdmf
    "exudyn": _exudyn,
    "json": _json_summary,
    "mat": lambda p: _head(p, 19) == b"MATLAB 5.0 MAT-file",
    "fmu": _fmu,
    # the .m script beside a Simscape .mat: its first line names the block
    "simscape-script": lambda p: b"Reduced Order Flexible Solid" in _head(p)
    and b"exported by fe-reduced-body" in _head(p),
    "vtu": lambda p: b"<VTKFile" in _head(p),
    "xdmf": lambda p: b"<Xdmf" in _head(p),
    "png": lambda p: _head(p, 8) == b"\x89PNG\r\n\x1a\n",
    "svg": lambda p: b"<svg" in _head(p),
    "pdf": lambda p: _head(p, 5) == b"%PDF-",
    "msh": lambda p: _head(p, 12).startswith(b"$MeshFormat"),
    "csv": lambda p: (t := _text(p)) is not None and "," in t.split("\n", 1)[0],
    "html": lambda p: (t := _text(p)) is not None and t.lstrip().lower().startswith(
        ("<!doctype html", "<html")),
    "sid": lambda p: (t := _text(p)) is not None and t.split()[:3] == ["part", "new", "modal"],
}


def kind_of_suffix(path: Path) -> str | None:
    """The kind of an output by its file ending (None: no kind; replaced only with force)."""
    name = path.name.lower()
    for ending, kind in ((".exudyn.hdf5", "exudyn"), (".h5", "h5"), (".hdf5", "h5"),
                         (".json", "json"), (".mat", "mat"), (".fmu", "fmu"), (".vtu", "vtu"), (".xdmf", "xdmf"),
                         (".png", "png"), (".svg", "svg"), (".pdf", "pdf"), (".msh", "msh"),
                         (".csv", "csv"), (".html", "html"), (".sid_fem", "sid")):
        if name.endswith(ending):
            return kind
    return None


def file_kind_matches(path: Path, kind: str | None) -> bool:
    """True when the existing file ``path`` is a file of ``kind`` this package writes."""
    test = KINDS.get(kind or "")
    return bool(test and test(path))


def same_file(a: str | Path, b: str | Path) -> bool:
    """True when ``a`` and ``b`` name the same file: same resolved path (symlinks followed),
    or, where both exist, the same device and inode (hard links)."""
    a, b = Path(a), Path(b)
    try:
        if a.resolve() == b.resolve():
            return True
    except (OSError, RuntimeError):
        pass
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _probe_folder(folder: Path, what: str, target: Path) -> None:
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-probe.", dir=folder)
    except OSError as exc:
        from pipeline._util.atomic import output_error

        err = output_error(target, exc)
        raise OutputError(f"{what} '{target}': the folder '{folder}' cannot be written to: "
                          f"{err.value}", key=str(target), value=err.value,
                          expected="a writable folder") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def _check_folder(target: Path, folder: Path, what: str, create_parent: bool) -> None:
    existing = folder
    while not existing.exists():
        if existing.parent == existing:
            break
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        raise OutputError(f"{what} '{target}': '{existing}' is a file, not a folder",
                          key=str(target), value=str(existing), expected="a folder")
    if existing != folder and not create_parent:
        raise OutputError(f"{what} '{target}': the folder '{folder}' does not exist; create it "
                          "first (or check the path for a typo)", key=str(target),
                          value=str(folder), expected="an existing folder")
    _probe_folder(existing, what, target)


def check_output(path: str | Path, *, inputs: Iterable[str | Path] = (), force: bool = False,
                 kind: str | None = None, create_parent: bool = False,
                 what: str = "output") -> Path:
    """Check that ``path`` may be written (see the module docstring); returns it.

    ``kind`` is the kind of file written there (a key of :data:`KINDS`; by default from the
    file ending); ``inputs`` the files the command reads; ``create_parent``: a missing
    folder is created on writing (default destinations) rather than refused.
    """
    raw = str(path)
    if not raw or raw.strip() != raw or any(ord(c) < 32 for c in raw):
        raise OutputError(f"{what} {raw!r}: expected a file name without control characters "
                          "or surrounding spaces", key=raw, value=raw, expected="a file name")
    path = Path(path)
    if raw.endswith(os.sep) or path.is_dir():
        raise OutputError(f"{what} '{path}': is a directory, expected a file name",
                          key=str(path), value="a directory", expected="a file path")
    for source in inputs:
        if same_file(path, source):
            raise OutputError(f"{what} '{path}': is the input '{source}' of this command; "
                              "expected another file name (an input is never written over, "
                              "even with --force)", key=str(path), value=str(source),
                              expected="a file that is not an input")
    if path.exists() or path.is_symlink():
        if not path.is_file():
            raise OutputError(f"{what} '{path}': exists and is not a regular file",
                              key=str(path), expected="a file name")
        kind = kind if kind is not None else kind_of_suffix(path)
        shown_kind = f"a '{kind}' output" if kind else "an output of this kind"
        if not force and not file_kind_matches(path, kind):
            raise OutputError(f"{what} '{path}': exists and was not written by this package "
                              f"as {shown_kind}; expected a new name, or "
                              "--force to replace it", key=str(path), value="an existing file",
                              expected="a new file, or --force")
    _check_folder(path, path.parent if str(path.parent) else Path("."), what, create_parent)
    return path


def check_output_dir(path: str | Path, *, marker: Callable[[Path], bool] | None = None,
                     force: bool = False, what: str = "output folder") -> Path:
    """Check a destination folder: absent (its parent writable), empty, or recognised by
    ``marker`` as one this package made (e.g. an earlier batch folder); else ``force``."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise OutputError(f"{what} '{path}': exists and is a file, expected a folder",
                              key=str(path), value="a file", expected="a folder")
        if any(path.iterdir()) and not force and not (marker and marker(path)):
            raise OutputError(f"{what} '{path}': exists, is not empty and was not made by "
                              "this package; expected a new or empty folder, or --force",
                              key=str(path), value="a foreign folder",
                              expected="a new or empty folder, or --force")
        _probe_folder(path, what, path)
        return path
    _check_folder(path, path.parent, what, create_parent=True)
    return path


# --------------------------------------------------------------------------- names
#: what makes a name unusable as a path component or HDF5 key, in words
NAME_PROBLEMS = "empty, '.', '..', '/', '\\', control characters or more than 128 characters"


def check_name(name: object, what: str, *, error: type = ConfigError) -> str:
    """``name`` if it can be a file name and an HDF5 key; else one line naming it.

    Refused: not a string, empty, ``.`` or ``..``, a ``/`` or ``\\``, a control character
    (newline, tab, NUL, DEL, ...), leading or trailing spaces, more than 128 characters.
    """
    problem = None
    if not isinstance(name, str):
        problem = f"a {type(name).__name__}, not a string"
    elif not name:
        problem = "empty"
    elif name in (".", ".."):
        problem = f"'{name}' is a folder reference"
    elif "/" in name or "\\" in name:
        problem = "contains a path separator ('/' or '\\')"
    elif any(ord(c) < 32 or ord(c) == 127 for c in name):
        problem = "contains a control character (newline, tab, NUL, ...)"
    elif name.strip() != name:
        problem = "has leading or trailing spaces"
    elif len(name) > 128:
        problem = f"is {len(name)} characters long"
    if problem is None:
        return name
    shown = repr(name)[:80]
    raise error(f"{what} {shown}: {problem}; expected a name usable as a file name and an "
                f"HDF5 key (not {NAME_PROBLEMS})", key=what, value=shown,
                expected="a plain name")
