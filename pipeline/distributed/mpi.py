"""The MPI and PETSc entry points of the distributed path, imported lazily.

:func:`petsc` returns the petsc4py and slepc4py modules, or raises a one-line
:class:`~pipeline.errors.SolverError` naming how to get them. :func:`world` is the
communicator of every rank; :func:`allgather_rows` stacks each rank's rows of a
block into the whole block on every rank (MPI_Allgatherv).
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import SolverError

_HOW = ("run 'make mpi-env' (Debian's python3-petsc4py and python3-slepc4py with OpenMPI, "
        "in .venv-mpi) and the pipeline under mpiexec with .venv-mpi/bin/python")


def petsc():
    """(PETSc, SLEPc): the initialised petsc4py and slepc4py modules, or a one-line
    :class:`~pipeline.errors.SolverError` saying how to get them (missing, or built
    for another numpy than this interpreter's: Debian's bindings need numpy 1.x)."""
    try:
        from petsc4py import PETSc
        from slepc4py import SLEPc
    except (ImportError, ValueError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SolverError(f"modes.solver: slepc needs petsc4py, slepc4py and MPI ({reason}); "
                          f"{_HOW}", key="modes.solver", value="slepc",
                          expected="petsc4py and slepc4py importable") from None
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


def allreduce_sum(comm, local: np.ndarray, op: str = "SUM") -> np.ndarray:
    """Elementwise sum (``op``: or ``MAX``, ``MIN``) of ``local`` over the ranks, on
    every rank (float64)."""
    from mpi4py import MPI

    local = np.ascontiguousarray(local, dtype=np.float64)
    out = np.empty_like(local)
    comm.Allreduce([local, MPI.DOUBLE], [out, MPI.DOUBLE], op=getattr(MPI, op))
    return out


def log_resident(logger, comm, where: str) -> None:
    """A DEBUG line of ``logger``: this rank's resident memory (MB) at ``where``, a step
    inside a stage (``benchmarks/bench_mpi.py`` tabulates them per rank beside the
    stages' ends; nothing is read when DEBUG is off)."""
    import logging

    if logger.isEnabledFor(logging.DEBUG):
        from pipeline._util.resources import resident_bytes

        logger.debug("rank %d at %s: resident %.0f MB", comm.rank, where,
                     resident_bytes() / 1e6)
