"""The lowest modes of K phi = omega^2 M phi with SLEPc on distributed K and M.

Factor path (``modes.method: factor`` or ``auto``): Krylov-Schur on the shift-and-invert
operator (K - sigma M)^-1 M with sigma = 0 (a supported body; a free body's sigma is
below zero, :func:`pipeline.solve.eigen.default_shift`), the solves by MUMPS'
distributed Cholesky factor of K - sigma M (PETSc's ``PCCHOLESKY`` with the ``mumps`` solver type).
The factor-free path (``modes.method: multigrid``) is LOBPCG on the two-grid cycle
(:mod:`pipeline.distributed.multigrid`), which uses this module for its coarse start
block. (Before it, conjugate gradients on PETSc's algebraic multigrid, GAMG, with the
rigid-body near-null space ran inside this Krylov-Schur iteration: 64 CG iterations a
solve on the cantilever; SLEPc's own LOBPCG on GAMG broke down there, LAPACK's sygvd
failing on its projected problem.)

Either way the eigenvectors come back M-normalised, each rank holding its rows; the
caller gathers them and makes the final Rayleigh-Ritz step exact on the replicated
block (:func:`pipeline.solve.eigen` does the same for the serial path), so the two
paths share the sign convention and the residual measure. PETSc's options database
(``-eps_*``, ``-st_*``, ``-mat_mumps_*`` on the command line or in PETSC_OPTIONS)
overrides the choices made here.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re

import numpy as np

from pipeline.distributed.factor_memory import AnalysisFailed, analysed_setup
from pipeline.errors import SolverError

log = logging.getLogger(__name__)

def _max():
    from mpi4py import MPI

    return MPI.MAX


def petsc_matrix(PETSc, local, n: int):
    """An MPIAIJ (n, n) matrix from this rank's CSR rows (local: (n_loc, n), global
    column numbers), marked symmetric."""
    n_loc = local.shape[0]
    # block size 3 (a point's three DOFs) where every rank holds whole points (PETSc's
    # node-block routines; MUMPS' analysis by blocks stays off, MUMPS_BLOCK_ANALYSIS_OPTION)
    whole = int(PETSc.COMM_WORLD.tompi4py().allreduce(n_loc % 3, op=_max())) == 0
    A = PETSc.Mat().createAIJ(size=((n_loc, n), (n_loc, n)), bsize=3 if whole else None,
                              csr=(local.indptr, local.indices, local.data),
                              comm=PETSc.COMM_WORLD)
    A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    A.assemble()
    return A


#: PETSc option of MUMPS' workspace margin (ICNTL(14), percent above its analysis'
#: estimate) after a factor's options prefix (the shift-invert factor's
#: ``-st_mat_mumps_icntl_14``, the inertia relief's ``-relief_mat_mumps_icntl_14``), and
#: the margins tried after a factorisation that ran out of workspace (INFOG(1) = -9 or
#: -8: cantilever_materials at mesh.size 0.02 on 3 ranks needs more than MUMPS' default)
MUMPS_WORKSPACE_OPTION = "mat_mumps_icntl_14"
MUMPS_WORKSPACE_RETRIES = (100, 300)
#: MUMPS' analysis by blocks (ICNTL(15)), which PETSc turns on (-3: blocks of a point's
#: three DOFs) for a matrix of block size 3, made PORD (the one ordering Debian's MUMPS
#: has for a distributed matrix) order the slender beam (25k DOFs) into a 4.4 GB factor
#: that took 347 s; without it: 56 MB, 1.5 s, and the 100k-DOF cantilever 505 MB against
#: 516 MB with it. Set to 0 unless the user set it (the option after a factor's
#: prefix: ``-st_mat_mumps_icntl_15``).
MUMPS_BLOCK_ANALYSIS_OPTION = "mat_mumps_icntl_15"
#: the options prefix of the inertia relief's factor (:func:`shifted_cholesky`), and its
#: MUMPS workspace and block-analysis options
RELIEF_PREFIX = "relief_"


def solve_eigen(PETSc, SLEPc, K, M, count: int, tolerance: float, shift: float = 0.0,
                prefix: str = "", ksp=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """(eigenvalues (count,), this rank's rows of the M-normalised eigenvectors
    (n_loc, count), stats) of the PETSc pair (K, M) nearest ``shift`` (rad^2/s^2: 0, or
    below zero for a free body, whose K is singular): Krylov-Schur on MUMPS' factor of
    A = K - shift M (the module).

    The factor is made first (:func:`mumps_cholesky`, options prefix ``prefix + "st_"``,
    SLEPc's own for its spectral transformation: ``-st_mat_mumps_icntl_14``, ...), so
    MUMPS' memory estimate is checked after its analysis and before its numeric
    factorisation (:mod:`pipeline.distributed.factor_memory`) and a factorisation short
    of workspace (INFOG(1) = -9 or -8) is retried with a larger ICNTL(14)
    (:data:`MUMPS_WORKSPACE_RETRIES`) unless the user set that option. SLEPc then solves
    the shifted pencil (A, M) at shift 0 with that factor (its eigenvalues lambda -
    shift; the same Krylov space as shift-invert about ``shift`` on (K, M)), and
    ``shift`` is added back. ``prefix``: the PETSc options prefix of the solve (its
    ``eps_*``, ``st_*`` options; the two-grid start block's own,
    :mod:`pipeline.distributed.multigrid`). ``ksp``: a set-up solver of K (shift 0) to
    use instead of a new factor (the two-grid cycle's coarse factor), or None; stats
    hold the solver as ``ksp`` and SLEPc's as ``eps``, which the caller destroys."""
    if ksp is not None:
        return _solve_eigen_once(PETSc, SLEPc, K, M, count, tolerance, shift, prefix, ksp)
    A = K
    if shift != 0.0:  # K - shift M: positive definite where K is only semi-definite
        A = K.copy()
        A.axpy(-shift, M, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    try:
        ksp = mumps_cholesky(PETSc, A, prefix + "st_",
                             "K" if shift == 0.0 else f"K - sigma M (sigma {shift:.3g} "
                             "rad^2/s^2)")
        try:
            values, rows, stats = _solve_eigen_once(PETSc, SLEPc, A, M, count, tolerance,
                                                    0.0, prefix, ksp)
        except BaseException:
            ksp.destroy()
            raise
    finally:
        if A is not K:  # the solvers keep their references
            A.destroy()
    return values + shift, rows, stats


def _with_workspace_retries(PETSc, option: str, retry: bool, attempt,
                            block_option: str | None = None):
    """``attempt(last)`` with MUMPS' default workspace and, while it raises
    _WorkspaceShort, with the margins :data:`MUMPS_WORKSPACE_RETRIES` set as the PETSc
    option ``option`` (not when ``retry`` is False or the user set it); ``last``: no
    margin is left to try (the attempt raises its SolverError then). ``block_option``:
    MUMPS' ICNTL(15) option of this factor, set to 0 throughout unless the user set it
    (:data:`MUMPS_BLOCK_ANALYSIS_OPTION`)."""
    options = PETSc.Options()
    user_set = options.hasName(option)
    margins = [None] + ([] if user_set or not retry else list(MUMPS_WORKSPACE_RETRIES))
    with _option_unless_set(options, block_option, 0, block_option is not None):
        for i, margin in enumerate(margins):
            if margin is not None and PETSc.COMM_WORLD.getRank() == 0:
                # the same shortage on every rank: say it once
                log.warning("MUMPS ran out of workspace: factorising again with ICNTL(14) "
                            "= %d %%", margin)
            try:
                with _option_unless_set(options, option, margin, margin is not None):
                    return attempt(i == len(margins) - 1)
            except _WorkspaceShort:
                continue
    raise AssertionError("unreachable: the last attempt raises")  # pragma: no cover


@contextlib.contextmanager
def _option_unless_set(options, name: str | None, value, wanted: bool = True):
    """PETSc option ``name`` = ``value`` for the duration (removed after, so the host
    process's options database is left as it was), unless the user set it."""
    mine = wanted and name is not None and not options.hasName(name)
    if mine:
        options.setValue(name, value)
    try:
        yield
    finally:
        if mine:
            options.delValue(name)


def _petsc_reason(exc) -> str:
    """What went wrong, from a PETSc error: its message is its call stack, "[rank]
    function() at file:line" per frame, and the last frame says it."""
    return re.split(r"\[\d+\]\s*", " ".join(str(exc).split()))[-1].strip() or str(exc)


def _workspace_short(reason: str) -> bool:
    """Whether MUMPS ran out of workspace (INFOG(1) = -9 or -8)."""
    return re.search(r"INFOG\(1\)\s*=\s*-(9|8)\b", reason) is not None


class _WorkspaceShort(Exception):
    """MUMPS ran out of workspace (INFOG(1) = -9 or -8): worth another try."""


def _solve_eigen_once(PETSc, SLEPc, K, M, count: int, tolerance: float, shift: float,
                      prefix: str, ksp):
    """:func:`solve_eigen` with the set-up solver ``ksp`` of K - shift M (its factor
    made: SLEPc's spectral transformation keeps it, its operator being the same matrix)."""
    eps = SLEPc.EPS().create(comm=PETSc.COMM_WORLD)
    if prefix:
        eps.setOptionsPrefix(prefix)
    eps.setOperators(K, M)
    eps.setProblemType(SLEPc.EPS.ProblemType.GHEP)
    eps.setDimensions(nev=count)
    eps.setTolerances(tol=tolerance, max_it=10000)
    st = eps.getST()
    eps.setType(SLEPc.EPS.Type.KRYLOVSCHUR)
    eps.setTarget(shift)
    eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_MAGNITUDE)
    st.setType(SLEPc.ST.Type.SINVERT)
    st.setShift(shift)
    st.setKSP(ksp)
    solver = "krylovschur-mumps"
    try:
        eps.setFromOptions()  # PETSc options (command line, PETSC_OPTIONS) override
        eps.solve()
    except PETSc.Error as exc:
        eps.destroy()
        reason = _petsc_reason(exc)
        if len(reason) > 240:  # some ranks add PETSc's configure hints: keep one line short
            reason = reason.split(". ")[0][:240]
        raise _slepc_failed(reason) from None
    values, rows, stats = _eigenpairs(eps, K, count, solver)
    return values, rows, {**stats, "eps": eps, "ksp": ksp}


def _slepc_failed(reason: str) -> SolverError:
    return SolverError(f"modes.solver: slepc: SLEPc failed ({reason}); expected a "
                       "solvable eigenproblem and options PETSc has (PETSC_OPTIONS: "
                       f"{os.environ.get('PETSC_OPTIONS', '')!r})", key="modes.solver",
                       value="slepc", expected="a solvable eigenproblem")


def solve_eigen_again(PETSc, eps, K, M, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(eigenvalues (count,), this rank's rows (n_loc, count)) as :func:`solve_eigen`,
    with the solver ``eps`` of an earlier :func:`solve_eigen` call, for the same PETSc
    matrices K, M holding new values in the same nonzero pattern: SLEPc's ST then keeps
    its KSP (STSetMatrices with the same matrices: ST_STATE_UPDATED), and PETSc's PC
    refactorises numerically on MUMPS' analysis of the first call (its ordering and
    symbolic factor). A failure is a SolverError (no workspace retry)."""
    eps.setOperators(K, M)
    try:
        eps.solve()
    except PETSc.Error as exc:
        raise _slepc_failed(_petsc_reason(exc)[:240]) from None
    values, rows, _ = _eigenpairs(eps, K, count, "krylovschur-mumps")
    return values, rows


def _eigenpairs(eps, K, count: int, solver: str):
    """(values (count,), this rank's rows (n_loc, count), stats) of a solved ``eps``."""
    nconv = eps.getConverged()
    if nconv < count:
        raise SolverError(f"modes.count: SLEPc ({solver}) converged {nconv} of {count} modes "
                          f"in {eps.getIterationNumber()} iterations; expected all",
                          key="modes.count", value=count, expected=f"{count} converged modes")
    vr = K.createVecRight()
    values = np.empty(count)
    rows = np.empty((vr.getLocalSize(), count))
    for i in range(count):
        values[i] = eps.getEigenpair(i, vr).real
        rows[:, i] = vr.getArray()
    vr.destroy()
    stats = {"method": f"slepc-{solver}", "iterations": int(eps.getIterationNumber()),
             "converged": int(nconv)}
    log.info("SLEPc %s: %d modes converged in %d iterations", solver, nconv,
             stats["iterations"])
    return values, rows, stats


def mumps_cholesky(PETSc, A, prefix: str, what: str):
    """A KSP that solves A x = b by MUMPS' distributed Cholesky factor of A, factorised
    now (the caller destroys it); PETSc options with ``prefix`` apply to it, a
    factorisation short of workspace is retried as the eigen solve's
    (:func:`solve_eigen`) and MUMPS' analysis by blocks is off unless set; a failure is
    one line (SolverError) naming ``what`` was factorised. MUMPS' analysis and its
    numeric factorisation are split: between them the ranks' memory is checked against
    MUMPS' own estimate (:func:`pipeline.distributed.factor_memory.analysed_setup`: a
    ResourceError on every rank, before the factor is made)."""
    def attempt(last: bool):
        ksp = PETSc.KSP().create(comm=A.getComm())
        ksp.setOptionsPrefix(prefix)
        ksp.setOperators(A)
        ksp.setType(PETSc.KSP.Type.PREONLY)
        pc = ksp.getPC()
        pc.setType(PETSc.PC.Type.CHOLESKY)
        pc.setFactorSolverType("mumps")
        try:
            ksp.setFromOptions()
            analysed_setup(PETSc, ksp, what)  # MUMPS' estimate checked before its factor
        except (PETSc.Error, AnalysisFailed) as exc:
            ksp.destroy()
            reason = _petsc_reason(exc)
            if not last and _workspace_short(reason):
                raise _WorkspaceShort(reason) from None
            raise SolverError(f"modes.solver: slepc: the factorisation of {what} failed "
                              f"({reason.split('. ')[0][:240]})",
                              key="modes.solver", value="slepc",
                              expected=f"a factorisable {what}") from None
        except BaseException:  # the memory check refused it: on every rank alike
            ksp.destroy()
            raise
        return ksp

    return _with_workspace_retries(PETSc, prefix + MUMPS_WORKSPACE_OPTION, True, attempt,
                                   prefix + MUMPS_BLOCK_ANALYSIS_OPTION)


def shifted_cholesky(PETSc, K, M, shift: float):
    """(KSP, A): a PETSc solver of A x = b, A = K - shift M (``shift`` rad^2/s^2 below
    zero: A is positive definite where K is only semi-definite), by MUMPS' distributed
    Cholesky factor (:func:`mumps_cholesky`, options prefix :data:`RELIEF_PREFIX`),
    factorised now; the caller destroys both."""
    A = K.copy()
    A.axpy(-shift, M, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
    A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    try:
        return mumps_cholesky(PETSc, A, RELIEF_PREFIX,
                              f"K - sigma M (sigma {shift:.3g} rad^2/s^2)"), A
    except BaseException:
        A.destroy()
        raise
