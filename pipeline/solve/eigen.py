"""Modes stage: the lowest eigenpairs of K phi = omega^2 M phi.

:func:`solve_modes` asks :func:`pipeline.solve.plan.plan_modes` which method to run (the
choice and its reasons are in :mod:`pipeline.solve.plan`) and executes that plan; when the
chosen path gives up (a slow multigrid trial, a factor that does not fit after all), it
executes the plan's fallback.

Shift-invert around sigma (0 for a supported body, slightly negative for a free one):
the shifted matrix A = K - sigma M is factorised once (:mod:`pipeline.solve.factorization`).

- With a symmetric factor A = F F^T offering half-solves (PARDISO), a **block Lanczos**
  method (:mod:`pipeline.solve.lanczos`) finds the largest eigenvalues
  theta = 1/(omega^2 - sigma) of the symmetric operator S = F^-1 M F^-T. Every step
  applies S to a whole block of vectors: one backward and one forward substitution with
  many right-hand sides, which reads the factor once for the block instead of once per
  vector (the factor is gigabytes at 1M DOFs, and reading it dominates a single-vector
  solve). The inner products are plain dot products, so the mass matrix is applied once
  per step.
  The singularity check's probe and the static loads ride along the first two steps as
  extra columns (:func:`_run_factor`): no pass over the factor of their own.
- Otherwise (SuperLU, CHOLMOD, cuDSS), scipy's ``eigsh`` (ARPACK) in shift-invert mode
  with the factorisation as its ``OPinv``.
- Without a factor of K (``multigrid``): LOBPCG (:mod:`pipeline.solve.lobpcg`)
  preconditioned by the two-grid cycle of :mod:`pipeline.solve.multigrid`, started from
  the coarse problem's own modes.

Either way the Ritz vectors are then re-orthonormalised by a small dense Rayleigh-Ritz
step with K and M, so that Phi^T M Phi = I and Phi^T K Phi = diag(omega^2) hold to
round-off even for repeated frequencies, and residuals are measured, not estimated.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import scipy.sparse as sp

from pipeline._util import progress as watch_progress
from pipeline._util.resources import (HEADROOM, LOBPCG_BLOCKS, available_memory_bytes,
                                     lobpcg_guard, lobpcg_layout, resident_bytes,
                                     retained_heap)
from pipeline.errors import ConfigError, ResourceError, SolverError
from pipeline.solve import lobpcg, mixed, multigrid, plan as planning
from pipeline.solve.batched import batched_lobpcg
from pipeline.solve.blas import is_csr, sparse_times_dense
from pipeline.solve.factorization import (backend_capabilities, check_factorization, factorize,
                                          resolve_backend)
from pipeline.solve.lanczos import block_lanczos
from pipeline.solve.modes import Modes
from pipeline.solve.plan import EigenPlan, EigenProblem, Machine
from pipeline.solve.ritz import rayleigh_ritz
from pipeline.solve.thresholds import stiffness_scale

log = logging.getLogger(__name__)

# the seed of check_factorization's probe, so that its solve can ride along in Lanczos
CHECK_SEED = 7
# Lanczos stopping test: ||S y - theta y|| <= tol * theta for every wanted Ritz pair;
# tol is modes.tolerance when given, else default_tolerance(n).
DEFAULT_TOLERANCE = 1e-10
LARGE_TOLERANCE = 1e-8
LARGE_SYSTEM = 100_000  # free DOFs from which LARGE_TOLERANCE is the default
# multigrid: at most this many static solves ride along in LOBPCG's sweeps (their
# conjugate gradients hold 6 (n, k) blocks beside LOBPCG's 9 (n, 25))
RIDING_COLUMNS = 4
# multigrid LOBPCG: stop when every wanted mode's preconditioned residual
# sqrt(r^T T r / omega^2) (r = K x - omega^2 M x, T the two-grid cycle) is below this;
# the frequency error goes as its square (on the cantilever: 1.5e-3 -> 1.7e-6,
# 2.7e-4 -> 5e-8, 1.2e-5 -> 1.1e-10), the shape error in the energy norm as itself
MULTIGRID_TOLERANCE = 1e-6
MULTIGRID_ACCEPT = 1e-4  # a stalled LOBPCG is accepted (with a warning) below this
MULTIGRID_MAX_SWEEPS = 100
# the coarse (P1) modes that start LOBPCG are only a start block (they differ from the
# P2 modes by the P1 discretisation error anyway): 1e-4 instead of 1e-8 saves a third of
# the coarse Lanczos with the same sweeps and frequencies equal to 2e-10
MULTIGRID_START_TOLERANCE = 1e-4


class _SlowMultigrid(SolverError):
    """The two-grid trial of ``method: auto`` converges too slowly: use a factor."""

    def __init__(self, message: str, summary: dict):
        super().__init__(message)
        self.summary = summary


def default_shift(K: sp.spmatrix, M: sp.spmatrix, supported: bool) -> float:
    """Shift: 0 for a supported body, a small negative value for a free one.

    For a free body K is singular; K - sigma M with sigma < 0 is positive definite.
    |sigma| is 1e-7 of the stiffness scale (the median diagonal ratio K_ii / M_ii,
    :func:`pipeline.solve.thresholds.stiffness_scale`), far below any elastic eigenvalue
    of the meshes we solve and far above round-off of the rigid-body modes.
    """
    if supported:
        return 0.0
    return -1e-7 * stiffness_scale(K, M)


def default_tolerance(n: int) -> float:
    """Default Lanczos tolerance for n free DOFs: 1e-10, or 1e-8 from 100k DOFs on.

    Eigenvalue errors go as tol^2 / gap, and from 100k DOFs on the residual measured after
    Rayleigh-Ritz is set by round-off in K phi, not by the Lanczos test: on the cantilever
    (20 modes) 1e-8 and 1e-10 both leave 5.0e-8 at 101k DOFs and 1.5e-7 at 312k, with
    frequencies equal to 4.5e-11 and 8e-11 relative, and 1e-8 takes 16 block steps
    instead of 17-18. On small meshes the residual floor is ~1e-12, and 1e-10 shows.
    """
    return LARGE_TOLERANCE if n >= LARGE_SYSTEM else DEFAULT_TOLERANCE


def _usable_bytes() -> float:
    """Bytes the solver may still allocate: HEADROOM of all this process could hold
    (what it holds now plus what the machine has available), less what it holds, so
    that the run as a whole stays within HEADROOM of the memory it started with.
    HEADROOM x available alone lets every stage take 90 % of what the earlier ones left:
    the cantilever at 5.5M DOFs then peaked at 24.1 GB with 24.25 GB available at the
    start."""
    held = resident_bytes()
    return max(0.0, HEADROOM * (available_memory_bytes() + held) - held)


def _machine(backend: str) -> Machine:
    """This machine for the plan: usable memory now and the resolved backend."""
    name = resolve_backend(backend)
    caps = backend_capabilities(name)
    return Machine(usable_bytes=_usable_bytes(), backend=name,
                   half_solves=caps.half_solves, gpu=caps.gpu)


def factor_expected(n: int, count: int, *, supported: bool = True, backend: str = "auto",
                    method: str = "auto", precision: str = "double") -> bool:
    """Whether :func:`solve_modes` will factorise K itself with PARDISO at shift 0 for
    ``n`` free DOFs (:func:`pipeline.solve.plan.factor_expected`), so that a
    :class:`~pipeline.solve.backends.pardiso.PatternAnalysis` started during the assembly
    will be used."""
    problem = EigenProblem(n=n, count=count, supported=supported, method=method,
                           precision=precision)
    return planning.factor_expected(problem, _machine(backend))


def solve_modes(K: sp.spmatrix, M: sp.spmatrix, count: int, *, supported: bool = True,
                backend: str = "auto", shift: float | None = None,
                coarse: sp.spmatrix | None = None, analysis=None, progress=None,
                expected_rigid: int = 0, loads: np.ndarray | None = None,
                **options) -> Modes:
    """The ``count`` lowest modes of (K, M), both (n x n) on the free DOFs.

    ``supported``: False for a free body (then the shift is negative, see
    :func:`default_shift`). ``backend``: the factorisation (``auto``: the fastest
    installed). ``coarse``: the (n x n_c) prolongation from a coarse space
    (:func:`pipeline.fe.coarse.p1_prolongation`), which the multigrid solver needs.
    ``analysis``: a :class:`~pipeline.solve.backends.pardiso.PatternAnalysis` of K's
    pattern started during the assembly; the factor path at shift 0 takes it; the caller
    releases what is left (its ``with`` block). ``progress``, if given, is called with
    the number of right-hand sides of every solve. ``expected_rigid``: the rigid-body
    modes the supports leave (:func:`pipeline.fe.supports.rigid_freedoms`, exact null
    vectors of K): the first that many count as rigid. ``loads``: (n, k) right-hand sides
    of static solves with the kept solver to come (the factor-free path starts them in
    its sweeps, :meth:`pipeline.solve.multigrid.TwoGrid.ride`), or None.

    ``options``: the fields of :class:`pipeline.solve.plan.EigenProblem`: ``method``
    (auto, lanczos, arpack, dense, factor, multigrid), ``precision`` (double, mixed,
    auto), ``tolerance`` (relative residual of the shift-inverted problem at which a mode
    counts as converged; 0: :func:`default_tolerance` for Lanczos, machine precision for
    ARPACK, :data:`MULTIGRID_TOLERANCE` for multigrid), ``block_size``, ``max_basis`` and
    ``keep``: for a supported body solved with a factor, return the factorisation of K
    in :attr:`Modes.factorization` instead of freeing it (the static correction solves
    with the same K); the caller then owns it (:meth:`Modes.release_factorization`).
    """
    t0 = time.perf_counter()
    n = K.shape[0]
    problem = EigenProblem(n=n, count=count, supported=supported,
                           has_coarse=coarse is not None, **options)
    planning.check_problem(problem)
    K = K if is_csr(K) else sp.csr_matrix(K)
    M = M if is_csr(M) else sp.csr_matrix(M)
    problem = dataclasses.replace(
        problem, shift=default_shift(K, M, supported) if shift is None else float(shift))
    stats: dict = {"n": n, "count": count}
    while True:
        plan = planning.plan_modes(problem, _machine(backend))
        try:
            v, run_stats, kept, name = _RUNNERS[plan.method](K, M, count, plan, coarse,
                                                             analysis, progress, loads)
            break
        except (ResourceError, _SlowMultigrid) as exc:
            slow = isinstance(exc, _SlowMultigrid)
            if plan.fallback is None or slow != (plan.method == "multigrid"):
                raise
            if slow:
                log.warning("%s: solving with a factor instead", exc)
                stats["multigrid_trial"] = exc.summary
            else:
                log.warning(_GIVING_UP[plan.method])
            problem, analysis = plan.fallback, None
    stats.update(run_stats)
    try:
        t3 = time.perf_counter()
        w, v, residuals = rayleigh_ritz(K, M, v, plan.shift)
        stats["rayleigh_ritz_seconds"] = time.perf_counter() - t3
        rigid = np.zeros(w.size, dtype=bool)
        if not supported:
            rigid = np.abs(w) < 1e-6 * abs(plan.shift)
        # the rigid modes the supports leave are exact null vectors, so the lowest r
        # below a negative shift; their Ritz values are zero only to the round-off of K
        # (of K with stiff springs: ~eps x their stiffness, far above the free body's
        # threshold)
        rigid[:min(int(expected_rigid), w.size)] = True
        w = np.where(rigid, 0.0, w)
        if (w < 0).any():
            raise SolverError(f"negative eigenvalue {w.min():.3e} rad^2/s^2: the stiffness "
                              "matrix is indefinite; check the material (E > 0, -1 < nu < 0.5)")
    except BaseException:
        if kept is not None:
            kept.release()
        raise
    return Modes(omega2=w, frequencies_hz=np.sqrt(w) / (2 * np.pi), shapes=v,
                 residuals=residuals, n_rigid=int(rigid.sum()), backend=name,
                 shift=plan.shift, seconds=time.perf_counter() - t0, stats=stats,
                 factorization=kept)


_GIVING_UP = {"mixed": "a float32 factor does not fit either: the factor-free multigrid "
                       "solver",
              "lanczos": "a double-precision factor does not fit: mixed precision",
              "arpack": "a double-precision factor does not fit: mixed precision"}


# --------------------------------------------------------------------------- the methods
# each: (K, M, count, plan, coarse, analysis, progress, loads) -> (eigenvectors (n, count),
# statistics, the kept factorisation of K or None, the backend's name for the result)
def _run_factor(K, M, count, plan: EigenPlan, coarse, analysis, progress, loads):
    """Shift-invert with a factor of K - shift M: block Lanczos or ARPACK.

    At shift 0 with a factor that can :meth:`remember` solves (PARDISO), the probe of
    :func:`check_factorization` and the static ``loads`` of a kept factor ride along in
    Lanczos' first two steps as extra columns, and the check runs after it (also when
    Lanczos fails, so a singular K is still reported as such)."""
    sigma = plan.shift
    shifted = K - sigma * M if sigma != 0.0 else K
    t1 = time.perf_counter()
    fact = factorize(shifted, plan.backend, positive_definite=True, check=False,
                     analysis=analysis if sigma == 0.0 else None)
    ride = None
    if sigma == 0.0 and plan.method == "lanczos" and hasattr(fact, "remember"):
        B = [K @ np.random.default_rng(CHECK_SEED).standard_normal(K.shape[0])]
        if plan.keep_factor and loads is not None:
            B += list(np.asarray(loads, dtype=float).reshape(K.shape[0], -1).T)
        ride = (np.array(B), np.empty((len(B), K.shape[0])))
    else:
        try:
            check_factorization(shifted, fact, seed=CHECK_SEED)
        except SolverError:
            fact.release()
            raise
    del shifted
    t2 = time.perf_counter()
    stats = {"backend": fact.backend, "factor_seconds": t2 - t1, **fact.info}
    log.info("factorised %d DOFs with %s in %.2f s (shift %.3g, factor %.2f GB)", K.shape[0],
             fact.backend, t2 - t1, sigma, fact.memory_bytes / 1e9)
    try:
        try:
            if plan.method == "lanczos":
                v, lstats = _lanczos_modes(fact, M, count, plan.tolerance, plan.block_size,
                                           plan.max_basis, progress, ride)
            else:
                v, lstats = _arpack_modes(fact, K, M, count, sigma, plan.tolerance, progress)
        except Exception:
            if ride is not None:  # a singular K: say so rather than how Lanczos failed
                check_factorization(K, fact, seed=CHECK_SEED)
            raise
        if ride is not None:
            fact.remember(ride[0].T, ride[1].T)
            check_factorization(K, fact, seed=CHECK_SEED)  # its probe is solved already
    except BaseException:
        fact.release()
        raise
    kept = fact if plan.keep_factor else None
    if kept is None:
        fact.release()
    stats.update(lstats)
    stats["eigensolver_seconds"] = time.perf_counter() - t2
    log.info("%s: %d solves (%d calls) in %.2f s", stats["method"], stats["solves"],
             stats["calls"], stats["eigensolver_seconds"])
    return v, stats, kept, fact.backend


def _run_dense(K, M, count, plan: EigenPlan, coarse, analysis, progress, loads):
    """A dense generalized eigh (small problems)."""
    v = _dense_modes(K, M, count, plan.shift)
    return v, {"method": "dense"}, None, f"dense ({plan.backend} not needed)"


def _run_mixed(K, M, count, plan: EigenPlan, coarse, analysis, progress, loads):
    """Block Lanczos on a float32 factor, refined in double."""
    v, stats = _mixed_modes(K, M, count, plan, progress)
    kept = stats.pop("kept", None)
    return v, stats, kept, "pardiso (float32 factor, double refinement)"


def _run_multigrid(K, M, count, plan: EigenPlan, coarse, analysis, progress, loads):
    """Factor-free LOBPCG with the two-grid preconditioner (a trial under a budget)."""
    v, stats = _multigrid_modes(K, M, coarse, count, plan, progress, loads)
    kept = stats.pop("kept", None)
    return v, stats, kept, f"multigrid (coarse factor: {stats['backend']})"


_RUNNERS = {"lanczos": _run_factor, "arpack": _run_factor, "dense": _run_dense,
            "mixed": _run_mixed, "multigrid": _run_multigrid}


def _mixed_modes(K, M, count, plan: EigenPlan, progress=None):
    """Eigenvectors (n, count) from a float32 factor, refined in double
    (:mod:`pipeline.solve.mixed`), and the statistics; with ``plan.keep_factor``,
    ``stats["kept"]`` is K^-1 by PCG with that factor (:func:`mixed.static_solver`) for
    the static correction (the caller owns it)."""
    sigma = plan.shift
    if not backend_capabilities(plan.backend).single_precision:
        raise ConfigError.field("modes.precision", "mixed",
                                "double, or the 'pardiso' backend for mixed precision")
    t1 = time.perf_counter()
    sigma_f = mixed.mixed_shift(K, M, sigma)
    fact = mixed.factorize_single(K, M, sigma_f)
    t2 = time.perf_counter()
    stats = {"backend": "pardiso", "precision": "mixed", "mixed_shift": sigma_f,
             "factor_seconds": t2 - t1,
             **fact.info}
    try:
        v, lstats = _lanczos_modes(fact, M, count,
                                   max(plan.tolerance, mixed.LANCZOS_TOLERANCE),
                                   plan.block_size, plan.max_basis, progress)
        v, rstats = mixed.refine(K, M, v, fact, sigma)
    except BaseException:
        fact.release()
        raise
    stats.update(lstats, **rstats)
    stats["eigensolver_seconds"] = time.perf_counter() - t2
    log.info("mixed precision: %d Lanczos solves, %d refinement sweeps, preconditioned "
             "residual %.1e", lstats["solves"], rstats["refine_sweeps"],
             rstats["refine_residual"])
    if plan.keep_factor:
        stats["kept"] = mixed.static_solver(K, fact)
    else:
        fact.release()
    return v, stats


def _multigrid_modes(K, M, P, count, plan: EigenPlan, progress=None, loads=None):
    """Eigenvectors (n, count) by two-grid preconditioned LOBPCG (no factor of K), and the
    statistics; with ``plan.keep_factor``, ``stats["kept"]`` is the PCG solver of K as a
    :class:`~pipeline.solve.factorization.Factorization` for the static correction (the
    caller owns it).

    ``plan.multigrid_budget``: the trial of ``method: auto``
    (:mod:`pipeline.solve.plan`): raises :class:`_SlowMultigrid` when LOBPCG projects more
    sweeps than this or stalls above the target.

    ``loads`` (n, k), kept solver only: the static solves K X = loads to come ride along
    in the sweeps' cycles (:meth:`~pipeline.solve.multigrid.TwoGrid.ride`; up to
    :data:`RIDING_COLUMNS` of them, which add a tenth to the sweeps' memory, and only
    where LOBPCG keeps its layout beside them: one batch with every guard column, or
    the same batches, through all of which they ride): each sweep makes one of their
    PCG iterations for the price of k more columns in one cycle, about a tenth of what
    a PCG iteration of its own costs at 1M DOFs."""
    sigma, tolerance, budget = plan.shift, plan.tolerance, plan.multigrid_budget
    t1 = time.perf_counter()
    A = K - sigma * M if sigma != 0.0 else K
    tg = multigrid.TwoGrid(A, P, plan.backend)
    try:
        Mc = multigrid.coarse_matrix(tg, M)
        width = min(count + lobpcg_guard(count), tg.coarse_n // 2)
        # start block: the coarse problem's own modes, through the coarse factor; only
        # the wanted ones converge, the guard columns are the same basis' next Ritz
        # vectors (the cantilever at 999k DOFs: 13 Lanczos steps instead of 15, 2.76 s
        # against 3.14 s, the same 6 LOBPCG sweeps; bench_solvers' four bodies at
        # 100k: the same sweeps or one fewer, each set-up shorter)
        if tg.coarse.capabilities.half_solves:
            vc, _ = _lanczos_modes(tg.coarse, Mc, width, MULTIGRID_START_TOLERANCE,
                                   planning.default_block_size(width, sigma == 0.0), None,
                                   None, converge=count)
        else:
            vc, _ = _arpack_modes(tg.coarse, tg.PT @ A @ P, Mc, width, 0.0, 1e-8, None)
        del Mc
        # the modes per LOBPCG batch and its guard columns: what fits beside K, M and the
        # preconditioner (all of them in one batch unless memory is short)
        usable, riding = _usable_bytes(), 0
        batch, guard = lobpcg_layout(K.shape[0], count, width - count, usable)
        if (loads is not None and plan.keep_factor and sigma == 0.0
                and 0 < np.shape(loads)[1] <= RIDING_COLUMNS):
            # only where the rider leaves LOBPCG's layout as it is (one batch with every
            # guard column, or the same batches): it rides through all of them
            rider = multigrid.RIDER_BLOCKS * 8.0 * K.shape[0] * np.shape(loads)[1]
            if lobpcg_layout(K.shape[0], count, width - count,
                             usable - rider) == (batch, guard):
                tg.ride(loads)
                riding = int(np.shape(loads)[1])

        def start(first: int, stop: int) -> np.ndarray:
            return sparse_times_dense(tg.P, np.ascontiguousarray(vc[:, first:stop]))

        t2 = time.perf_counter()
        target = tolerance if tolerance > 0 else MULTIGRID_TOLERANCE
        with watch_progress.stage("LOBPCG", total=lobpcg.EXPECTED_SWEEPS,
                                  unit="sweep") as watch:
            def on_sweep(sweep, worst):
                watch.update(1)  # past the expected count, the total follows
                if progress is not None:
                    progress(width)
            # the sweeps free and allocate (n x width) blocks: keep them in the heap
            with retained_heap(LOBPCG_BLOCKS * 8.0 * K.shape[0] * (batch + guard)):
                result = batched_lobpcg(K, M, start, tg.precondition, count, batch, guard,
                                        sigma=sigma, target=target,
                                        max_sweeps=MULTIGRID_MAX_SWEEPS,
                                        on_sweep=on_sweep, budget=budget)
        del vc
        if budget is not None and not result.converged:
            projected = lobpcg.projected_sweeps(result.history, target)
            raise _SlowMultigrid(
                f"the factor-free multigrid eigensolver converges slowly on this body "
                f"(preconditioned residual {min(result.history):.1e} after "
                f"{result.sweeps} sweeps, about {projected:.0f} sweeps needed for "
                f"{target:.0e}; thin walls and nearly incompressible materials do this)",
                {"sweeps": result.sweeps, "seconds": time.perf_counter() - t1,
                 "history": list(result.history), "projected_sweeps": projected})
        if not result.converged and min(result.history) > MULTIGRID_ACCEPT:
            raise SolverError(
                f"multigrid eigensolver did not converge for {count} modes in "
                f"{result.sweeps} sweeps (worst preconditioned residual "
                f"{min(result.history):.1e}, tolerance {target:.1e}); try modes.method: "
                "factor on a machine with more memory, or a coarser mesh.size")
        if not result.converged:
            log.warning("multigrid eigensolver stopped at a preconditioned residual of %.1e "
                        "(tolerance %.1e): round-off floor", min(result.history), target)
    except BaseException:
        tg.release()
        raise
    stats = {"method": "multigrid-lobpcg", "backend": tg.coarse.backend,
             "coarse_dofs": tg.coarse_n,
             "factor_bytes": tg.coarse.info.get("factor_bytes", 0),
             "setup_seconds": t2 - t1, "sweeps": result.sweeps,
             "history": list(result.history), "tolerance": target, "block": batch + guard,
             "batches": -(-count // batch), "solves": result.sweeps * (batch + guard),
             "calls": result.sweeps,
             "lambda_max_dinv_k": tg.lambda_max, "riding_columns": riding,
             "eigensolver_seconds": time.perf_counter() - t1}
    log.info("multigrid LOBPCG: %d sweeps of %d vectors in %.1f s (set-up %.1f s, coarse "
             "%d DOFs), preconditioned residual %.1e", result.sweeps, batch + guard,
             result.seconds, t2 - t1, tg.coarse_n, min(result.history))
    if plan.keep_factor:
        stats["kept"] = tg.factorization()
    else:
        tg.release()
    return result.X[:, :count], stats


# --------------------------------------------------------------------------- post-processing
def _dense_modes(K, M, count: int, sigma: float) -> np.ndarray:
    from scipy.linalg import eigh

    Kd, Md = K.toarray(), M.toarray()
    Kd, Md = 0.5 * (Kd + Kd.T), 0.5 * (Md + Md.T)
    try:
        _, v = eigh(Kd - sigma * Md, Md, subset_by_index=[0, count - 1])
    except np.linalg.LinAlgError as exc:
        raise SolverError(f"dense eigensolver failed on the {K.shape[0]}-DOF problem ({exc}); "
                          "the mass matrix must be positive definite") from None
    return v


def _arpack_modes(fact, K, M, count, sigma, tolerance, progress):
    from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, eigsh

    n = K.shape[0]
    calls = [0]

    def apply(b):
        calls[0] += 1
        watch.update(1)  # the stage below: ARPACK calls this only inside it
        if progress is not None:
            progress(1)
        return fact.solve(b)

    op = LinearOperator((n, n), matvec=apply, dtype=np.float64)
    ncv = min(n, max(2 * count + 1, count + 20))
    v0 = np.random.default_rng(12345).standard_normal(n)
    try:
        with watch_progress.stage("ARPACK", unit="solve") as watch:
            _, v = eigsh(K, k=count, M=M, sigma=sigma, which="LM", OPinv=op, tol=tolerance,
                         ncv=ncv, v0=v0, maxiter=max(1000, 10 * n // ncv))
    except ArpackNoConvergence as exc:
        raise SolverError(f"eigsh did not converge for {count} modes (converged: "
                          f"{len(exc.eigenvalues)}); try a smaller modes.count or a finer "
                          "modes.tolerance") from None
    return v, {"method": "arpack", "solves": calls[0], "calls": calls[0], "ncv": ncv}


# --------------------------------------------------------------------------- block Lanczos
def _lanczos_modes(fact, M, count, tolerance, block_size, max_basis, progress, ride=None,
                   converge=None):
    """Eigenvectors (n, count) of the ``count`` largest theta of F^-1 M F^-T; only the
    leading ``converge`` of them (None: all) need meet the tolerance (:func:`block_lanczos`).

    ``ride``: (B (r, n), X (r, n)): the solves X = A^-1 B = F^-T F^-1 B ride along the
    first two steps, F^-1 B as r more columns of the first forward substitution, F^-T of
    that of the second backward one (a column more costs about a tenth of a pass over
    the factor of its own at 100k DOFs), and are written into X."""
    n = fact.n
    calls = [0, 0]
    clock = {"solve": 0.0, "mass": 0.0}
    riding = [None if ride is None else ride[0]]  # right-hand sides for the next pass

    def op(Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t0 = time.perf_counter()
        k, halfway = Y.shape[0], riding[0] is not None and riding[0] is not ride[0]
        # F^-T Y: the image kept for the Ritz vectors of the pencil
        X = fact.backward_rows(np.vstack([Y, riding[0]]) if halfway else Y)
        if halfway:
            ride[1][...], X, riding[0] = X[k:], X[:k], None
        t1 = time.perf_counter()
        MX = sparse_times_dense(M, X.T)  # (n, k), column-major
        t2 = time.perf_counter()
        first = riding[0] is not None
        out = fact.forward_rows(np.vstack([MX.T, riding[0]]) if first else MX.T)
        if first:  # F^-1 M F^-T Y, and F^-1 B for the next backward substitution
            out, riding[0] = out[:k], out[k:]
        clock["solve"] += time.perf_counter() - t2 + t1 - t0
        clock["mass"] += t2 - t1
        calls[0] += 2 * Y.shape[0]
        calls[1] += 2
        if progress is not None:
            progress(Y.shape[0])
        return out, X

    b = max(1, min(block_size, n // 4))
    tol = tolerance if tolerance > 0 else default_tolerance(n)
    if max_basis is None:
        max_basis = max(3 * count + 4 * b, count + 8 * b)
    max_basis = min(max_basis, n // 2)
    t0 = time.perf_counter()
    # total: the steps that fill the basis (convergence usually comes before; a restart
    # raises it)
    with watch_progress.stage("Lanczos", total=-(-max_basis // b), unit="step") as watch:
        _, theta, steps, restarts, X = block_lanczos(
            lambda Y: (watch.update(1), op(Y))[1], n, count, b, tol, max_basis,
            with_images=True, converge=converge)
    if riding[0] is not None:  # converged in one step: the backward half on its own
        ride[1][...] = fact.backward_rows(riding[0])
    # the Ritz vectors of the pencil, x = F^-T y, are the same combination of the
    # images F^-T v the steps computed anyway: no further pass over the factor
    return X.T, {"method": "block-lanczos", "block": b, "steps": steps, "restarts": restarts,
                 "solves": calls[0], "calls": calls[1], "tolerance": tol,
                 "max_basis": max_basis, "solve_seconds": clock["solve"],
                 "mass_seconds": clock["mass"],
                 "orthogonalisation_seconds": time.perf_counter() - t0 - clock["solve"]
                 - clock["mass"]}


