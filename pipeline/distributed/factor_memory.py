"""MUMPS' own memory estimate on MPI ranks, checked after its analysis and before its
numeric factorisation.

PETSc's set-up of a Cholesky (or LU) preconditioner runs MUMPS' analysis (JOB = 1: the
ordering and the symbolic factor) and its numeric factorisation (JOB = 2) in one call.
:func:`analysed_setup` splits them: it makes the factor matrix F (MatGetFactor, through
PCFactorSetUpMatSolverType), runs the analysis on it (MatCholeskyFactorSymbolic, which
petsc4py 3.18 does not bind, called through ctypes on PETSc's own library), reads
MUMPS' estimates and checks them (:func:`check_factor_estimate`), and only then lets
KSPSetUp run: PETSc's MUMPS interface returns from the symbolic step at once for a
pattern it has analysed, so KSPSetUp factorises numerically only.

MUMPS' figures (its users' guide, INFO and INFOG; MB = 10^6 bytes; a negative entry
count c means -c 10^6 entries):

- INFO(15): after the analysis, this rank's estimate of all MUMPS' internal data for an
  in-core numeric factorisation; INFOG(16), INFOG(17) its maximum and sum over the ranks.
  ICNTL(14), the percentage added to the estimated working space for delayed pivots,
  is part of it;
- INFOG(20): the estimated entries of the factors; INFOG(29), after the factorisation,
  their actual number; INFO(16), after it, what this rank allocated (INFOG(18),
  INFOG(19): maximum and sum).

The check, on every rank and with the same outcome everywhere: the ranks sharing a node
(MPI_COMM_TYPE_SHARED) need sum_r (held_r + e_r) bytes, held_r the rank's resident
memory now (its rows of K and M, its part of the mesh, the factors already alive, the
matrix PETSc handed MUMPS) and e_r = 10^6 INFO(15) what the numeric factorisation adds;
they have sum_r held_r + a, a the node's available memory now
(:func:`available_bytes`). More than :data:`~pipeline._util.resources.HEADROOM` of it
is a one-line ResourceError on every rank before any numeric factorisation starts.
"""

from __future__ import annotations

import ctypes
import logging
import math
from dataclasses import dataclass

from pipeline._util import resources as res
from pipeline.errors import ResourceError

log = logging.getLogger(__name__)

#: MatFactorInfo is a struct of PetscReal fields (fewer than 32 in PETSc 3.18); a zeroed
#: one is what MatFactorInfoInitialize makes, and MUMPS reads none of it
_FACTOR_INFO_REALS = 64


class AnalysisFailed(Exception):
    """MUMPS' analysis returned an error (INFOG(1) < 0): its code in the message."""


def available_bytes() -> int:
    """The memory this node can still give the ranks (bytes): what the serial path's
    check reads (:func:`pipeline._util.resources.available_memory_bytes`)."""
    return res.available_memory_bytes()


def _megabytes(value: int) -> float:
    return float(value) * 1e6


def _entries(value: int) -> float:
    """MUMPS' entry counts: a negative c stands for -c 10^6."""
    return -float(value) * 1e6 if value < 0 else float(value)


@dataclass(frozen=True)
class MumpsEstimate:
    """MUMPS' figures after its analysis: this rank's in-core estimate (bytes, INFO(15)),
    its maximum and sum over the ranks (INFOG(16), INFOG(17)), the estimated entries of
    the factors (INFOG(20)) and the workspace margin in percent (ICNTL(14))."""

    rank_bytes: float
    max_bytes: float
    sum_bytes: float
    factor_entries: float
    margin_percent: int

    @classmethod
    def of(cls, F) -> "MumpsEstimate":
        return cls(_megabytes(F.getMumpsInfo(15)), _megabytes(F.getMumpsInfog(16)),
                   _megabytes(F.getMumpsInfog(17)), _entries(F.getMumpsInfog(20)),
                   int(F.getMumpsIcntl(14)))


@dataclass(frozen=True)
class MumpsFactor:
    """MUMPS' figures after its numeric factorisation: the factors' entries (INFOG(29),
    all ranks), this rank's (INFO(27)), what the ranks allocated (INFO(16) this rank,
    INFOG(18) the largest, INFOG(19) all; bytes) and of it what they used (INFOG(21)
    the largest, INFOG(22) all; bytes)."""

    entries: float
    rank_entries: float
    rank_bytes: float
    max_bytes: float
    sum_bytes: float
    max_used_bytes: float
    sum_used_bytes: float

    @classmethod
    def of(cls, F) -> "MumpsFactor":
        return cls(_entries(F.getMumpsInfog(29)), _entries(F.getMumpsInfo(27)),
                   _megabytes(F.getMumpsInfo(16)), _megabytes(F.getMumpsInfog(18)),
                   _megabytes(F.getMumpsInfog(19)), _megabytes(F.getMumpsInfog(21)),
                   _megabytes(F.getMumpsInfog(22)))


def _petsc_library(PETSc):
    """PETSc's C library, as petsc4py's extension module links it (dlsym searches the
    module's dependencies)."""
    return ctypes.CDLL(PETSc.__file__)


def symbolic_factor(PETSc, F, A, kind: str) -> None:
    """MUMPS' analysis of A into the factor matrix F (MatCholeskyFactorSymbolic or
    MatLUFactorSymbolic, no PETSc ordering: MUMPS orders), through ctypes; a PETSc error
    code is raised as PETSc.Error."""
    lib = _petsc_library(PETSc)
    info = (ctypes.c_double * _FACTOR_INFO_REALS)()
    f, a = ctypes.c_void_p(F.handle), ctypes.c_void_p(A.handle)
    if kind == "cholesky":
        fn = lib.MatCholeskyFactorSymbolic
        fn.argtypes = [ctypes.c_void_p] * 4  # (F, A, IS perm, MatFactorInfo *)
        code = fn(f, a, None, ctypes.byref(info))
    else:
        fn = lib.MatLUFactorSymbolic
        fn.argtypes = [ctypes.c_void_p] * 5  # (F, A, IS row, IS col, MatFactorInfo *)
        code = fn(f, a, None, None, ctypes.byref(info))
    if code:
        raise PETSc.Error(code)


def analysed_setup(PETSc, ksp, what: str) -> MumpsFactor | None:
    """KSPSetUp of ``ksp`` (its operators and options set) with MUMPS' analysis and the
    memory check (:func:`check_factor_estimate`) before the numeric factorisation, when
    its preconditioner is a Cholesky or LU factor by MUMPS (the others: KSPSetUp alone,
    None). Returns MUMPS' figures after the factorisation, which the INFO log record
    also carries (``mumps_factor``, ``mumps_of``: what was factorised). Collective; a
    PETSc failure is raised as PETSc.Error, a failed analysis as AnalysisFailed, a
    factor that does not fit as ResourceError."""
    pc = ksp.getPC()
    kind = pc.getType()
    if kind not in ("cholesky", "lu") or pc.getFactorSolverType() != "mumps":
        ksp.setUp()
        return None
    _, A = ksp.getOperators()
    pc.setFactorSetUpSolverType()
    F = pc.getFactorMatrix()
    symbolic_factor(PETSc, F, A, kind)
    if F.getMumpsInfog(1) < 0:  # the analysis failed (the same INFOG on every rank)
        raise AnalysisFailed(f"MUMPS' analysis failed: INFOG(1)={F.getMumpsInfog(1)}, "
                             f"INFO(2)={F.getMumpsInfo(2)}")
    estimate = MumpsEstimate.of(F)
    check_factor_estimate(A.getComm().tompi4py(), estimate, what, A.getSize()[0])
    ksp.setUp()
    done = MumpsFactor.of(F)
    log.info("MUMPS' factor of %s: %d entries (analysis: %d), %d MB allocated on the "
             "largest rank (estimate %d MB, used %d MB), %d MB on all (estimate %d MB, used "
             "%d MB)", what, done.entries, estimate.factor_entries, done.max_bytes / 1e6,
             estimate.max_bytes / 1e6, done.max_used_bytes / 1e6, done.sum_bytes / 1e6,
             estimate.sum_bytes / 1e6, done.sum_used_bytes / 1e6,
             extra={"mumps_factor": done, "mumps_of": what})
    return done


def check_factor_estimate(comm, estimate: MumpsEstimate, what: str, n: int) -> None:
    """Refuse, on every rank, a numeric factorisation that MUMPS' analysis says will not
    fit (module doc); log MUMPS' estimate beside the model's share of the factor
    (:func:`pipeline._util.resources.factor_bytes` of n rows over the ranks)."""
    from mpi4py import MPI

    held = float(res.resident_bytes())
    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    node_ranks = node.size
    need = node.allreduce(held + estimate.rank_bytes)
    have = node.allreduce(held) + node.allreduce(available_bytes(), op=MPI.MIN)
    node.Free()
    worst = comm.allreduce(need / have, op=MPI.MAX)  # the fullest node decides
    need, have = _on_fullest(comm, need, have, worst)
    total = comm.allreduce(held + estimate.rank_bytes)
    top_held = comm.allreduce(held, op=MPI.MAX)
    log.info("MUMPS' analysis of %s (%d rows): %d MB on the largest rank, %d MB on all "
             "(ICNTL(14) %d %%; the model's factor share %d MB a rank); the ranks hold up "
             "to %d MB; %.3g GB needed of %.3g GB on the fullest node", what, n,
             estimate.max_bytes / 1e6, estimate.sum_bytes / 1e6, estimate.margin_percent,
             res.factor_bytes(n) / comm.size / 1e6, top_held / 1e6, need / 1e9, have / 1e9)
    if worst <= res.HEADROOM:
        return
    nodes = max(math.ceil(total / (res.HEADROOM * have)),
                math.ceil(comm.size / node_ranks) + 1)
    larger = res._scale_to_fit(need, have)  # the factor ~ N^(4/3) ~ mesh.size^-4
    raise ResourceError(
        f"MUMPS' analysis of {what} ({n} rows) on {comm.size} ranks: the numeric "
        f"factorisation needs {estimate.max_bytes / 1e9:.2f} GB more on a rank, "
        f"{need / 1e9:.2f} GB with what the {node_ranks} ranks of one node hold, "
        f"{res.beyond_usable(need, have, 'available to them')}; expected about {nodes} nodes "
        f"like it or a mesh about {larger:.2f} times coarser ({res.coarser_mesh(larger)})")


def _on_fullest(comm, need: float, have: float, worst: float) -> tuple[float, float]:
    """(need, have) of the node whose ratio is ``worst`` (the same on every rank)."""
    from mpi4py import MPI

    mine = need if need / have == worst else -1.0
    need = comm.allreduce(mine, op=MPI.MAX)
    have = comm.allreduce(have if mine >= 0 else -1.0, op=MPI.MAX)
    return need, have
