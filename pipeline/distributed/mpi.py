"""The MPI and PETSc entry points of the distributed path, imported lazily.

:func:`petsc` returns the petsc4py and slepc4py modules, or raises a one-line
:class:`~pipeline.errors.SolverError` naming how to get them. :func:`world` is the
communicator of every rank; :func:`allgather_rows` stacks each rank's rows of a
block into the whole block on every rank (MPI_Allgatherv).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.errors import SolverError

_HOW = ("run 'make mpi-env' (Debian's python3-petsc4py and python3-slepc4py with OpenMPI, "
        "in .venv-mpi) and the pipeline under mpiexec with .venv-mpi/bin/python")


def _debian_dir(root: str) -> str | None:
    """The newest real-scalar PETSc or SLEPc tree Debian installs under ``root``."""
    found = sorted(Path(root).glob("*/*-real"))
    return str(found[-1]) if found else None


def petsc():
    """(PETSc, SLEPc): the initialised petsc4py and slepc4py modules.

    Debian's bindings find their shared libraries through PETSC_DIR and SLEPC_DIR; when
    those are unset, the real-scalar trees under /usr/lib/petscdir and /usr/lib/slepcdir
    are looked up for this import only (the environment is put back as found)."""
    saved = {k: os.environ.get(k) for k in ("PETSC_DIR", "SLEPC_DIR")}
    try:
        for key, root in (("PETSC_DIR", "/usr/lib/petscdir"), ("SLEPC_DIR", "/usr/lib/slepcdir")):
            if not os.environ.get(key) and (found := _debian_dir(root)):
                os.environ[key] = found
        import sys

        for key in ("PETSC_DIR", "SLEPC_DIR"):  # Debian's .pth files read these at start-up
            site = Path(os.environ.get(key, "/nonexistent")) / "lib/python3/dist-packages"
            if site.is_dir() and str(site) not in sys.path:
                sys.path.append(str(site))
        from petsc4py import PETSc
        from slepc4py import SLEPc
    except ImportError as exc:
        raise SolverError(f"modes.solver: slepc needs petsc4py, slepc4py and MPI ({exc}); "
                          f"{_HOW}", key="modes.solver", value="slepc",
                          expected="petsc4py and slepc4py importable") from None
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
    return PETSc, SLEPc


def world():
    """mpi4py's COMM_WORLD (through petsc4py, so that PETSc and MPI share it)."""
    PETSc, _ = petsc()
    return PETSc.COMM_WORLD.tompi4py()


def allgather_rows(comm, local: np.ndarray) -> np.ndarray:
    """The whole (n, ...) block on every rank from each rank's (n_i, ...) rows, in rank
    order (float64)."""
    from mpi4py import MPI

    local = np.ascontiguousarray(local, dtype=np.float64)
    tail = local.shape[1:]
    width = int(np.prod(tail)) if tail else 1
    counts = np.array(comm.allgather(local.shape[0]), dtype=np.int64)
    out = np.empty((int(counts.sum()),) + tail)
    sizes = counts * width
    displs = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    comm.Allgatherv([local, MPI.DOUBLE], [out, (sizes, displs), MPI.DOUBLE])
    return out


def allreduce_sum(comm, local: np.ndarray) -> np.ndarray:
    """Elementwise sum of ``local`` over the ranks, on every rank (float64)."""
    from mpi4py import MPI

    local = np.ascontiguousarray(local, dtype=np.float64)
    out = np.empty_like(local)
    comm.Allreduce([local, MPI.DOUBLE], [out, MPI.DOUBLE], op=MPI.SUM)
    return out
