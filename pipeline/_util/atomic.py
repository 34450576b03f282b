"""The one atomic writer: every file the package writes goes through :func:`atomic_path`.

A file is written under a temporary name in its target folder,
``.<name>.<host>.<pid>.partial<suffix>`` (the suffix kept so that tools which infer a
format from the extension, gmsh, meshio, matplotlib, still do), flushed to disk
(``fsync``), renamed over the final name only when complete (``os.replace``, atomic on
POSIX), and the folder is fsync'ed so the rename survives a power loss. On any error,
or an interrupt, the temporary file is removed and the final name keeps its previous
content (or stays absent): a file under a final name is never partial.

Temporaries of writers that were killed (SIGKILL, power loss) are recognised by host
and pid and removed by the next writer of the same file on the same host; those of a
live process, or of another host, are left alone.

Writers that ignore failed writes (gmsh writes a truncated mesh and returns normally on a
full disk) are caught by checking, after the writer returns, that the device still has a
free block: if it has none the file is presumed truncated and not kept.

OS errors (no space left, read-only folder, permission) become one
:class:`~pipeline.errors.OutputError` line naming the file and the reason.

>>> import tempfile, pathlib
>>> target = pathlib.Path(tempfile.mkdtemp()) / "note.txt"
>>> write_text(target, "done")  # doctest: +ELLIPSIS
PosixPath('.../note.txt')
>>> sorted(p.name for p in target.parent.iterdir())
['note.txt']
"""

from __future__ import annotations

import contextlib
import errno
import glob
import logging
import os
import re
import socket
from pathlib import Path
from typing import Iterator

from pipeline.errors import OutputError

log = logging.getLogger(__name__)

PARTIAL = ".partial"


def host_tag() -> str:
    """This host's name as it appears in temporary names (no dots, at most 64 chars)."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname())[:64] or "host"


def temporary_path(path: Path) -> Path:
    """The temporary name this process writes ``path`` under."""
    return path.with_name(f".{path.name}.{host_tag()}.{os.getpid()}{PARTIAL}{path.suffix}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: alive, someone else's
        return True
    return True


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Remove temporaries of ``path`` left on this host by writers that are gone.

    Returns the files removed. A temporary of a live process (or of a reused pid), of
    this process, or of another host is kept.
    """
    host, removed = host_tag(), []
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.*{PARTIAL}*"):
        head = tmp.name[len(path.name) + 2:].split(PARTIAL, 1)[0]
        parts = head.rsplit(".", 1)
        if len(parts) != 2 or parts[0] != host or not parts[1].isdigit():
            continue
        pid = int(parts[1])
        if pid == os.getpid() or _pid_alive(pid):
            continue
        with contextlib.suppress(OSError):
            tmp.unlink()
            removed.append(tmp)
            log.info("removed %s, left by a writer that was killed", tmp)
    return removed


def fsync_dir(folder: Path) -> None:
    """fsync a folder (makes a rename in it durable); silently skipped where unsupported."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def device_full(folder: Path) -> bool:
    """True when the file system of ``folder`` has no free block left (for this user)."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail == 0 or st.f_bfree == 0


def output_error(path: Path, exc: OSError) -> OutputError:
    """One line for an OS error on writing ``path``, naming the reason."""
    reason = {errno.ENOSPC: "no space left on the device",
              errno.EDQUOT: "disk quota exceeded",
              errno.EROFS: "the file system is read-only",
              errno.EACCES: "permission denied",
              errno.EPERM: "permission denied",
              errno.ENOENT: "the folder does not exist",
              errno.EISDIR: "it is a directory",
              errno.ENOTDIR: "a part of the path is not a directory"}.get(
                  exc.errno, exc.strerror or type(exc).__name__)
    return OutputError(f"output '{path}': cannot be written: {reason}", key=str(path),
                       value=reason, expected="a writable file path")


def signals_held():
    """A region where SIGINT/SIGTERM/SIGHUP wait (:func:`pipeline._util.interrupts.held`):
    cleanup that a second Ctrl-C must not cut short."""
    from pipeline._util.interrupts import held

    return held()


@contextlib.contextmanager
def private_folder(prefix: str, parent: str | Path | None = None) -> Iterator[Path]:
    """A new private folder (``tempfile.mkdtemp``) removed with its content on leaving.

    Its creation and removal run with signals held (:func:`signals_held`): an interrupt
    cannot fall between creating the folder and taking charge of removing it, nor cut the
    removal short, so an interrupted command leaves no temporary folder behind.
    """
    import shutil
    import tempfile

    def remove(folder: Path) -> None:
        with signals_held():
            shutil.rmtree(folder, ignore_errors=True)

    with contextlib.ExitStack() as cleanup:
        with signals_held():
            folder = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
            cleanup.callback(remove, folder)
        yield folder


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write ``path`` to; rename it over ``path`` on success.

    The caller writes the whole file to the yielded path (with any library: h5py, gmsh,
    meshio, matplotlib, plain ``open``). Parent folders are created. On leaving the
    block normally the file is fsync'ed and renamed; on an exception it is removed and
    the exception propagates (an ``OSError`` as :class:`OutputError`).
    """
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"output '{path}': is a directory, expected a file name",
                          key=str(path), value="a directory", expected="a file path")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(path, exc) from None
    remove_stale_temporaries(path)
    tmp = temporary_path(path)
    try:
        yield tmp
        if not tmp.exists():
            raise OutputError(f"output '{path}': the writer produced no file", key=str(path))
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        if device_full(tmp.parent):
            # some writers (gmsh) ignore a failed write() and return normally: a full
            # device after writing means the file may be truncated, so it is not kept
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))
        os.replace(tmp, path)
        fsync_dir(path.parent)
    except OSError as exc:
        raise output_error(path, exc) from None
    finally:
        with signals_held(), contextlib.suppress(OSError):
            tmp.unlink()


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
    return path


def write_text(path: str | Path, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically; returns ``path``."""
    return write_bytes(path, text.encode(encoding))
