"""Modes stage: the lowest eigenpairs of K phi = omega^2 M phi.

Shift-invert around sigma (0 for a supported body, slightly negative for a free one):
the shifted matrix A = K - sigma M is factorised once by :mod:`pipeline.solve.factorization`.

- With a symmetric factor A = F F^T (PARDISO), a **block Lanczos** method with full
  re-orthogonalisation and thick restarts finds the largest eigenvalues
  theta = 1/(omega^2 - sigma) of the symmetric operator S = F^-1 M F^-T. Every step
  applies S to a whole block of vectors: one backward and one forward substitution
  with many right-hand sides, which reads the factor once for the block instead of
  once per vector (the factor is gigabytes at 1M DOFs, and reading it dominates a
  single-vector solve). The inner products are plain dot products, so the mass
  matrix is applied once per step.
- Otherwise (SuperLU), scipy's ``eigsh`` (ARPACK) in shift-invert mode with the
  factorisation as its ``OPinv``.

- Without a factor of K (``method="multigrid"``; under ``auto`` when a coarse space is
  given and the problem has :data:`~pipeline._util.resources.MULTIGRID_AUTO_DOFS` free
  DOFs or more, or no factor fits in memory): LOBPCG (:mod:`pipeline.solve.lobpcg`)
  preconditioned by the two-grid cycle of :mod:`pipeline.solve.multigrid`, started from
  the coarse problem's own modes.

Why ``auto`` switches at a size (measured on the cantilever, AMD EPYC Zen 4, 2 cores,
20 modes, whole run): the factor path takes 32 s at 312k free DOFs and 166 s at 996k
(factorisation flops grow like n^2 for a 3D body, the factor like n^(4/3)), the
two-grid path 37 s and 107-118 s (about linear in n; peak 6.4 GB against 12.4 GB at
996k). The two-grid cycle (P2 -> P1 on the same mesh, Jacobi-Chebyshev smoothing) is
not robust for every body: on 100k-DOF problems it took 15 sweeps at nu = 0.45, 27 at
0.49 and 84 at 0.499; 40-57 sweeps on 1-2 mm strips, and it stalled on a 0.5 mm
strip and a slender 10 mm square beam (the P1 coarse space locks in bending and in
volume), where a factor costs a few seconds. So under ``auto`` it runs on a budget of
:data:`MULTIGRID_AUTO_SWEEPS` sweeps: from the fourth sweep on, as soon as the rate so
far projects more (:func:`pipeline.solve.lobpcg.projected_sweeps`), or it stalls, the
trial is given up and the factor path solves the problem instead -- when a factor fits;
when none does, the two-grid solve goes on as far as ``method: multigrid`` would.

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
from pipeline._util.resources import (HEADROOM, LOBPCG_BLOCKS, MULTIGRID_AUTO_DOFS,
                                      available_memory_bytes, factor_path_bytes,
                                      retained_heap)
from pipeline.errors import ConfigError, ResourceError, SolverError
from pipeline.solve import lobpcg, mixed, multigrid
from pipeline.solve.blas import is_csr, sparse_times_dense
from pipeline.solve.factorization import check_factorization, factorize, resolve_backend
from pipeline.solve.modes import Modes

log = logging.getLogger(__name__)

# Lanczos stopping test: ||S y - theta y|| <= tol * theta for every wanted Ritz pair;
# tol is modes.tolerance when given, else default_tolerance(n).
DEFAULT_TOLERANCE = 1e-10
LARGE_TOLERANCE = 1e-8
LARGE_SYSTEM = 100_000  # free DOFs from which LARGE_TOLERANCE is the default
DENSE_MAX = 600  # below this many free DOFs, a dense generalized eigh
# multigrid LOBPCG: stop when every wanted mode's preconditioned residual
# sqrt(r^T T r / omega^2) (r = K x - omega^2 M x, T the two-grid cycle) is below this;
# the frequency error goes as its square (measured on the cantilever: 1.5e-3 -> 1.7e-6,
# 2.7e-4 -> 5e-8, 1.2e-5 -> 1.1e-10), the shape error in the energy norm as itself
MULTIGRID_TOLERANCE = 1e-6
MULTIGRID_ACCEPT = 1e-4  # a stalled LOBPCG is accepted (with a warning) below this
MULTIGRID_MAX_SWEEPS = 100
# the coarse (P1) modes that start LOBPCG: only a start block (they differ from the P2
# modes by the P1 discretisation error anyway); 1e-4 instead of 1e-8 saves a third of
# the coarse Lanczos (0.4-0.6 s at 312k DOFs) with the same 11 sweeps and frequencies
# equal to 2e-10 (measured at 312k DOFs, 1e-8 ... 1e-2)
MULTIGRID_START_TOLERANCE = 1e-4
# under method auto: the two-grid trial is given up for the factor path as soon as it
# projects more sweeps than this (5 x the cantilever's 8; 12 before LOBPCG's SVQB
# scaling). At 1M DOFs the two paths broke even near 22 sweeps; 40 lets a body that
# converges steadily but slowly (nu = 0.49: 24 sweeps, half the factor path's memory)
# finish instead of wasting 16 sweeps, and still gives up on nu = 0.499 and the 0.5 mm
# strip after 7-10 sweeps (projected 44-53); the 2 mm strip (10 sweeps) and the slender
# beam (11) now converge (docs/performance.md, seventh session)
MULTIGRID_AUTO_SWEEPS = 40


class _SlowMultigrid(SolverError):
    """The two-grid trial of ``method: auto`` converges too slowly: use a factor."""

    def __init__(self, message: str, summary: dict):
        super().__init__(message)
        self.summary = summary


def default_shift(K: sp.spmatrix, M: sp.spmatrix, supported: bool) -> float:
    """Shift: 0 for a supported body, a small negative value for a free one.

    For a free body K is singular; K - sigma M with sigma < 0 is positive definite.
    |sigma| is 1e-7 of the median diagonal ratio K_ii / M_ii (a stiffness scale of
    the finest element), far below any elastic eigenvalue of the meshes we solve and far
    above round-off of the rigid-body modes.
    """
    if supported:
        return 0.0
    ratio = np.median(K.diagonal() / M.diagonal())
    return -1e-7 * float(ratio)


def default_tolerance(n: int) -> float:
    """Default Lanczos tolerance for n free DOFs: 1e-10, or 1e-8 from 100k DOFs on.

    Eigenvalue errors go as tol^2 / gap, and from 100k DOFs on the residual measured after
    Rayleigh-Ritz is set by round-off in K phi, not by the Lanczos test: on the cantilever
    (20 modes) 1e-8 and 1e-10 both leave 5.0e-8 at 101k DOFs and 1.5e-7 at 312k, with
    frequencies equal to 4.5e-11 and 8e-11 relative, and 1e-8 takes 16 block steps
    instead of 17-18. On small meshes the residual floor is ~1e-12, and 1e-10 shows.
    """
    return LARGE_TOLERANCE if n >= LARGE_SYSTEM else DEFAULT_TOLERANCE


def default_block_size(count: int, supported: bool = True) -> int:
    """Lanczos block size: 4 for a supported body, 8 for a free one.

    A block of b vectors costs one pass over the factor plus b vectors' arithmetic;
    larger blocks need more vectors in all before the wanted modes converge (20 modes
    of the cantilever: b = 4: 68 vectors in 17 blocks; 8: 104 in 13; 20: 180 in 9), so
    small blocks win as soon as the arithmetic per vector dominates, which it does at
    100k DOFs and more. A free body needs b >= 7: its six rigid-body modes share one
    eigenvalue, and a block Krylov space holds at most b copies of one eigenvalue.
    """
    return int(min(max(count, 1), 4)) if supported else 8


def factor_expected(n: int, count: int, *, supported: bool = True, backend: str = "auto",
                    method: str = "auto", precision: str = "double") -> bool:
    """Whether :func:`solve_modes` will factorise K itself with PARDISO at shift 0 for
    ``n`` free DOFs (by its own rules, before the values exist), so that a
    :class:`~pipeline.solve.backends.pardiso.PatternAnalysis` started during the assembly will
    be used. A wrong guess costs only the background analysis."""
    return (supported and n > DENSE_MAX and precision != "mixed"
            and (method == "factor" or (method == "auto" and n < MULTIGRID_AUTO_DOFS))
            and resolve_backend(backend) == "pardiso"
            and factor_path_bytes(n, count) <= HEADROOM * available_memory_bytes())


def solve_modes(K: sp.spmatrix, M: sp.spmatrix, count: int, *, supported: bool = True,
                backend: str = "auto", tolerance: float = 0.0, shift: float | None = None,
                progress=None, method: str = "auto", block_size: int | None = None,
                max_basis: int | None = None, keep: bool = False,
                precision: str = "double", coarse: sp.spmatrix | None = None,
                analysis=None) -> Modes:
    """The ``count`` lowest modes of (K, M), both (n x n) on the free DOFs.

    ``supported``: False for a free body (then the shift is negative, see
    :func:`default_shift`). ``tolerance``: relative residual of the shift-inverted
    problem at which a mode counts as converged (0: :func:`default_tolerance` for
    Lanczos, machine precision for ARPACK, :data:`MULTIGRID_TOLERANCE` for multigrid).
    ``method``: ``auto`` (block Lanczos when the backend offers a symmetric factor, else
    ARPACK; with ``coarse`` given, multigrid when no factor fits, and a multigrid trial
    from :data:`~pipeline._util.resources.MULTIGRID_AUTO_DOFS` free DOFs when
    ``precision`` is not ``mixed`` and ``tolerance`` is 0, see the module doc),
    ``lanczos``,
    ``arpack``, ``dense``, ``factor`` (``auto`` without multigrid) or ``multigrid``
    (factor-free; needs ``coarse``, the (n x n_c) prolongation from a coarse space, see
    :func:`pipeline.fe.coarse.p1_prolongation`). ``progress``, if given, is called with the number of right-hand sides
    of every solve. ``keep``: for a supported body (shift 0) solved by factorisation,
    return the factorisation of K in :attr:`Modes.factorization` instead of freeing it
    (the static correction solves with the same K); the caller then owns it and frees
    it with :meth:`Modes.release_factorization`. ``precision``: ``double``; ``mixed``
    (a float32 PARDISO factor, answers refined in double: :mod:`pipeline.solve.mixed`;
    no factor is kept); ``auto``: mixed when a double factor would not fit in memory
    (the size estimate, or PARDISO's exact size after its analysis), else double.
    ``analysis``: a :class:`~pipeline.solve.backends.pardiso.PatternAnalysis` of K's pattern
    started during the assembly; the factor path at shift 0 takes it (PARDISO then only
    factorises numerically); the caller releases what is left (its ``with`` block).
    ``backend`` ``cudss`` (the factor on an NVIDIA GPU) keeps ``auto`` on the factor
    (no multigrid trial, double precision: the host-memory rules do not apply) and
    solves with ARPACK, cuDSS having no separate forward and backward substitutions.
    """

    t0 = time.perf_counter()
    n = K.shape[0]
    if count >= n - 1:
        raise SolverError(f"config key 'modes.count': got {count}, expected fewer than the "
                          f"{n - 1} free degrees of freedom of this mesh (refine the mesh)")
    if method not in ("auto", "lanczos", "arpack", "dense", "factor", "multigrid"):
        raise ValueError(f"method '{method}': expected auto, lanczos, arpack, dense, factor "
                         "or multigrid")
    if method == "multigrid" and coarse is None:
        raise ConfigError.field("modes.method", "multigrid", "'auto' or 'factor' (the "
                                "multigrid solver needs a quadratic mesh: mesh.order 2)")
    K = K if is_csr(K) else sp.csr_matrix(K)
    M = M if is_csr(M) else sp.csr_matrix(M)
    sigma = default_shift(K, M, supported) if shift is None else float(shift)
    stats: dict = {"n": n, "count": count}
    kept = None
    if precision not in mixed.PRECISIONS:
        raise ConfigError.field("modes.precision", precision, "double, mixed or auto")
    dense = method == "dense" or (method in ("auto", "factor") and n <= DENSE_MAX)
    # the GPU factor (cuDSS) lives in GPU memory, checked by the backend itself: no
    # host-memory rule below applies, and no multigrid trial (its factor is fast)
    gpu = not dense and method != "multigrid" and resolve_backend(backend) == "cudss"
    if gpu and precision == "auto":
        precision = "double"
    usable = HEADROOM * available_memory_bytes()  # K and M are already held
    any_factor_fits = factor_path_bytes(n, count, single=True) <= usable
    if not dense and precision == "auto" and factor_path_bytes(n, count) > usable:
        precision = "mixed"  # the estimate already says a double factor will not fit
        if method == "auto" and coarse is not None and not any_factor_fits:
            method = "multigrid"  # nor a float32 one
    budget = None
    if (method == "auto" and coarse is not None and not dense and n >= MULTIGRID_AUTO_DOFS
            and precision != "mixed" and tolerance == 0.0 and not gpu):
        # large enough for the two-grid path to be faster (module doc): a trial, given
        # up for a factor if it converges slowly and a factor fits
        method = "multigrid"
        budget = MULTIGRID_AUTO_SWEEPS if any_factor_fits else None
    if method == "multigrid":
        trial = None
        try:
            v, mstats = _multigrid_modes(K, M, coarse, count, sigma, tolerance, progress,
                                         backend, keep=keep and sigma == 0.0,
                                         budget=budget)
        except _SlowMultigrid as slow:
            log.warning("%s: solving with a factor instead", slow)
            trial = slow.summary  # outside this block the trial's arrays are freed
        if trial is not None:
            result = solve_modes(K, M, count, supported=supported, backend=backend,
                                 tolerance=tolerance, shift=shift, progress=progress,
                                 method="factor", block_size=block_size,
                                 max_basis=max_basis, keep=keep, precision=precision)
            return dataclasses.replace(
                result, seconds=time.perf_counter() - t0,
                stats={**(result.stats or {}), "multigrid_trial": trial})
        kept = mstats.pop("kept", None)
        stats.update(mstats)
        backend_name = f"multigrid (coarse factor: {stats['backend']})"
    elif not dense and precision == "mixed":
        try:
            v, mstats = _mixed_modes(K, M, count, sigma, tolerance,
                                     block_size or default_block_size(count, supported),
                                     max_basis, progress, backend,
                                     keep=keep and sigma == 0.0)
            kept = mstats.pop("kept", None)
        except ResourceError:  # the float32 factor's exact size: does not fit either
            if method != "auto" or coarse is None:
                raise
            log.warning("a float32 factor does not fit either: the factor-free multigrid "
                        "solver")
            return solve_modes(K, M, count, supported=supported, backend=backend,
                               tolerance=tolerance, shift=shift, progress=progress,
                               method="multigrid", keep=keep, precision="double",
                               coarse=coarse)
        stats.update(mstats)
        backend_name = "pardiso (float32 factor, double refinement)"
    elif dense:
        backend_name = f"dense ({resolve_backend(backend)} not needed)"
        v = _dense_modes(K, M, count, sigma)
        stats["method"] = "dense"
    else:
        shifted = K - sigma * M if sigma != 0.0 else K
        t1 = time.perf_counter()
        try:
            fact = factorize(shifted, backend, positive_definite=True, check=False,
                             analysis=analysis if sigma == 0.0 else None)
        except ResourceError:  # PARDISO's exact size after the analysis: does not fit
            if precision != "auto":
                raise
            log.warning("a double-precision factor does not fit: mixed precision")
            return solve_modes(K, M, count, supported=supported, backend=backend,
                               tolerance=tolerance, shift=shift, progress=progress,
                               method=method, block_size=block_size, max_basis=max_basis,
                               keep=keep, precision="mixed", coarse=coarse)
        try:
            check_factorization(shifted, fact)
        except SolverError:
            fact.release()
            raise
        del shifted
        t2 = time.perf_counter()
        stats.update(backend=fact.backend, factor_seconds=t2 - t1,
                     **fact.info)
        log.info("factorised %d DOFs with %s in %.2f s (shift %.3g, factor %.2f GB)", n,
                 fact.backend, t2 - t1, sigma, fact.info.get("factor_bytes", 0) / 1e9)
        backend_name = fact.backend
        use_lanczos = method == "lanczos" or (method in ("auto", "factor")
                                               and fact.capabilities.half_solves)
        try:
            if use_lanczos:
                if not fact.capabilities.half_solves:
                    raise SolverError(f"method 'lanczos' needs a symmetric factor; backend "
                                      f"'{fact.backend}' has none (use method 'arpack')")
                v, lstats = _lanczos_modes(fact, M, count, tolerance,
                                           block_size or default_block_size(count, supported),
                                           max_basis, progress)
            else:
                v, lstats = _arpack_modes(fact, K, M, count, sigma, tolerance, progress)
        except BaseException:
            fact.release()
            raise
        if sigma == 0.0 and keep:
            kept = fact  # handed to the caller: the static correction solves with this K
        else:
            fact.release()
        stats.update(lstats)
        stats["eigensolver_seconds"] = time.perf_counter() - t2
        log.info("%s: %d solves (%d calls) in %.2f s", stats["method"], stats["solves"],
                 stats["calls"], stats["eigensolver_seconds"])
    try:
        t3 = time.perf_counter()
        w, v, residuals = _rayleigh_ritz(K, M, v, sigma)
        stats["rayleigh_ritz_seconds"] = time.perf_counter() - t3
        rigid = np.zeros(w.size, dtype=bool)
        if not supported:
            rigid = np.abs(w) < 1e-6 * abs(sigma)
        w = np.where(rigid, 0.0, w)
        if (w < 0).any():
            raise SolverError(f"negative eigenvalue {w.min():.3e} rad^2/s^2: the stiffness matrix is "
                              "indefinite; check the material (E > 0, -1 < nu < 0.5)")
    except BaseException:
        if kept is not None:
            kept.release()
        raise
    seconds = time.perf_counter() - t0
    return Modes(omega2=w, frequencies_hz=np.sqrt(w) / (2 * np.pi), shapes=v,
                 residuals=residuals, n_rigid=int(rigid.sum()), backend=backend_name,
                 shift=sigma, seconds=seconds, stats=stats, factorization=kept)


def _mixed_modes(K, M, count, sigma, tolerance, block_size, max_basis, progress, backend,
                 keep=False):
    """Eigenvectors (n, count) from a float32 factor, refined in double
    (:mod:`pipeline.solve.mixed`), and the statistics; with ``keep``,
    ``stats["kept"]`` is K^-1 by PCG with that factor (:func:`mixed.static_solver`) for
    the static correction (the caller owns it)."""
    if resolve_backend(backend) != "pardiso":
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
        v, lstats = _lanczos_modes(fact, M, count, max(tolerance, mixed.LANCZOS_TOLERANCE),
                                   block_size, max_basis, progress)
        v, rstats = mixed.refine(K, M, v, fact, sigma)
    except BaseException:
        fact.release()
        raise
    stats.update(lstats, **rstats)
    stats["eigensolver_seconds"] = time.perf_counter() - t2
    log.info("mixed precision: %d Lanczos solves, %d refinement sweeps, preconditioned "
             "residual %.1e", lstats["solves"], rstats["refine_sweeps"],
             rstats["refine_residual"])
    if keep:
        stats["kept"] = mixed.static_solver(K, fact)
    else:
        fact.release()
    return v, stats


def _multigrid_modes(K, M, P, count, sigma, tolerance, progress, backend, keep,
                     budget=None):
    """Eigenvectors (n, count) by two-grid preconditioned LOBPCG (no factor of K), and the
    statistics; with ``keep``, ``stats["kept"]`` is the PCG solver of K as a
    :class:`Factorization` for the static correction (the caller owns it).

    ``budget``: the trial of ``method: auto`` (module doc): raises :class:`_SlowMultigrid`
    when LOBPCG projects more sweeps than this or stalls above the target."""
    t1 = time.perf_counter()
    A = K - sigma * M if sigma != 0.0 else K
    tg = multigrid.TwoGrid(A, P, backend)
    try:
        Mc = multigrid.coarse_matrix(tg, M)
        guard = max(3, count // 4)
        width = min(count + guard, tg.coarse_n // 2)
        # start block: the coarse problem's own modes, through the coarse factor
        if tg.coarse.capabilities.half_solves:
            vc, _ = _lanczos_modes(tg.coarse, Mc, width, MULTIGRID_START_TOLERANCE,
                                   default_block_size(width, sigma == 0.0), None, None)
        else:
            vc, _ = _arpack_modes(tg.coarse, tg.PT @ A @ P, Mc, width, 0.0, 1e-8, None)
        del Mc
        X0 = sparse_times_dense(tg.P, np.ascontiguousarray(vc))
        del vc
        t2 = time.perf_counter()
        target = tolerance if tolerance > 0 else MULTIGRID_TOLERANCE
        with watch_progress.stage("LOBPCG", total=lobpcg.EXPECTED_SWEEPS,
                                  unit="sweep") as watch:
            def on_sweep(sweep, worst):
                watch.update(1)  # past the expected count, the total follows
                if progress is not None:
                    progress(width)
            # the sweeps free and allocate (n x width) blocks: keep them in the heap
            with retained_heap(LOBPCG_BLOCKS * 8.0 * K.shape[0] * width):
                result = lobpcg.lobpcg(K, M, X0, tg.apply_single, count, sigma=sigma,
                                       target=target, max_sweeps=MULTIGRID_MAX_SWEEPS,
                                       on_sweep=on_sweep, budget=budget)
        del X0
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
             "history": list(result.history), "tolerance": target, "block": width,
             "solves": result.sweeps * width, "calls": result.sweeps,
             "lambda_max_dinv_k": tg.lambda_max,
             "eigensolver_seconds": time.perf_counter() - t1}
    log.info("multigrid LOBPCG: %d sweeps of %d vectors in %.1f s (set-up %.1f s, coarse "
             "%d DOFs), preconditioned residual %.1e", result.sweeps, width,
             result.seconds, t2 - t1, tg.coarse_n, min(result.history))
    if keep:
        stats["kept"] = tg.factorization()
    else:
        tg.release()
    return result.X[:, :count], stats


# --------------------------------------------------------------------------- post-processing
def _rayleigh_ritz(K, M, v: np.ndarray, sigma: float):
    """Exact M-orthonormality and diagonal K in span(v); sorted; sign convention."""
    from scipy.linalg import eigh

    v = np.ascontiguousarray(v)
    Kv, Mv = sparse_times_dense(K, v), sparse_times_dense(M, v)
    Kr, Mr = v.T @ Kv, v.T @ Mv
    Kr, Mr = 0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T)
    w, Q = eigh(Kr, Mr)
    order = np.argsort(w)  # ordering and signs go into the small Q, not the (n, m) arrays
    w, Q = w[order], Q[:, order]
    v = v @ Q
    # sign convention: the largest-magnitude entry of every mode is positive
    idx = np.abs(v).argmax(axis=0)
    signs = np.sign(v[idx, np.arange(v.shape[1])])
    signs[signs == 0] = 1.0
    v *= signs
    Q *= signs
    Kv, Mv = Kv @ Q, Mv @ Q
    scale = np.maximum(np.linalg.norm(Kv, axis=0), abs(sigma) * np.linalg.norm(Mv, axis=0))
    Mv *= w
    Kv -= Mv  # K phi - omega^2 M phi, in place
    residuals = np.linalg.norm(Kv, axis=0) / np.where(scale > 0, scale, 1.0)
    return w, v, residuals


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
def _lanczos_modes(fact, M, count, tolerance, block_size, max_basis, progress):
    """Eigenvectors (n, count) of the ``count`` largest theta of F^-1 M F^-T."""
    n = fact.n
    calls = [0, 0]
    clock = {"solve": 0.0, "mass": 0.0}

    def op(Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t0 = time.perf_counter()
        X = fact.backward_rows(Y)  # F^-T Y: the image kept for the Ritz vectors of the pencil
        t1 = time.perf_counter()
        MX = sparse_times_dense(M, X.T)  # (n, k), column-major
        t2 = time.perf_counter()
        out = fact.forward_rows(MX.T)  # F^-1 M F^-T Y
        del MX
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
            with_images=True)
    # the Ritz vectors of the pencil, x = F^-T y, are the same combination of the
    # images F^-T v the steps computed anyway: no further pass over the factor
    return X.T, {"method": "block-lanczos", "block": b, "steps": steps, "restarts": restarts,
                 "solves": calls[0], "calls": calls[1], "tolerance": tol,
                 "max_basis": max_basis, "solve_seconds": clock["solve"],
                 "mass_seconds": clock["mass"],
                 "orthogonalisation_seconds": time.perf_counter() - t0 - clock["solve"]
                 - clock["mass"]}


def _orthonormal_block(W: np.ndarray, basis: np.ndarray, rng, scale: float):
    """Orthonormal rows V spanning the rows of W (k, n), already orthogonal to ``basis``.

    Returns (V, B) with W = B^T V. A well-conditioned W (smallest singular value above
    1e-6 of the largest and of ``scale``) goes through Cholesky QR twice: two (k x k) Gram matrices and two
    thin products, where an SVD of the (n x k) block costs several passes over it. Else
    the SVD: directions of W below round-off of ``scale`` are replaced by random
    vectors orthogonal to ``basis`` (rows) and to the rest (their coupling row is 0).
    """
    s2, E = np.linalg.eigh(W @ W.T)
    if s2[-1] > 0.0 and np.sqrt(max(s2[0], 0.0)) > 1e-6 * max(np.sqrt(s2[-1]), scale):
        s = np.sqrt(s2)
        V = (E.T @ W) / s[:, None]
        B = s[:, None] * E.T
        L = np.linalg.cholesky(V @ V.T)  # = I + O(cond^2 eps): one more pass fixes it
        V = np.linalg.inv(L) @ V
        return V, L.T @ B
    U, s, Vt = np.linalg.svd(W.T, full_matrices=False)  # W^T = U s Vt
    V = np.ascontiguousarray(U.T)
    B = s[:, None] * Vt
    small = s <= 1e-12 * scale
    if small.any():
        good = V[~small]
        R = rng.standard_normal((int(small.sum()), W.shape[1]))
        for _ in range(2):
            for Q in (basis, good):
                R -= (R @ Q.T) @ Q
        Ur, _, _ = np.linalg.svd(R.T, full_matrices=False)
        V[small] = Ur.T
        B[small] = 0.0
    return V, B


def block_lanczos(op, n: int, count: int, b: int, tol: float, max_basis: int,
                  seed: int = 12345, max_restarts: int = 50, with_images: bool = False):
    """The ``count`` largest eigenpairs of the symmetric operator ``op`` (n x n).

    ``op(Y)`` applies the operator to the rows of Y (k, n). Block Lanczos with full
    two-pass re-orthogonalisation; the projected matrix is built from the projection
    coefficients themselves, which makes thick restarts (keep the best Ritz vectors,
    continue from the residual block) exact. The basis lives in one preallocated
    (max_basis + b, n) array, so each projection is one matrix product.
    Returns (Y (count, n) orthonormal Ritz vectors, theta (count,), steps, restarts).

    ``with_images``: ``op`` returns (S Y, Z) where Z (k, n) is some linear image of the
    rows of Y (for the shift-invert operator: F^-T Y); the same combinations of the
    images as of the basis are returned as a fifth item (count, n).
    """
    rng = np.random.default_rng(seed)
    cap = max_basis + b
    basis = np.empty((cap, n))  # pages are touched only as rows are filled
    images = np.empty((cap, n)) if with_images else None
    V, _ = _orthonormal_block(rng.standard_normal((b, n)), basis[:0], rng, 1.0)
    size = 0  # rows in basis
    H = np.zeros((cap, cap))
    steps = restarts = 0
    scale = 0.0
    while True:
        lo, hi = size, size + V.shape[0]
        basis[lo:hi] = V
        size = hi
        out = op(V)
        if with_images:
            W, images[lo:hi] = out
        else:
            W = out
        W = np.array(W, dtype=np.float64)  # own copy: modified in place below
        del out
        steps += 1
        scale = max(scale, float(np.sqrt((W * W).sum(axis=1).max())))
        Q = basis[:hi]
        for _ in range(2):  # classical Gram-Schmidt, twice
            C = Q @ W.T  # (hi, k)
            H[:hi, lo:hi] += C
            W -= C.T @ Q
        Hs = np.triu(H[:hi, :hi])
        Hs = Hs + np.triu(Hs, 1).T
        theta, U = np.linalg.eigh(Hs)
        theta, U = theta[::-1], U[:, ::-1]  # largest first
        V, B = _orthonormal_block(W, Q, rng, scale)
        del W
        want = min(count, hi)
        resid = np.linalg.norm(B @ U[lo:hi, :want], axis=0)
        converged = want == count and bool(
            np.all(resid <= tol * np.abs(theta[:want])))
        if converged or hi >= n - b:
            if want < count:
                raise SolverError(f"block Lanczos: the Krylov space of this {n}-DOF problem "
                                  f"holds only {want} of the {count} modes asked for")
            Ut = np.ascontiguousarray(U[:, :count].T)
            Y = Ut @ Q
            if with_images:
                return Y, theta[:count], steps, restarts, Ut @ images[:hi]
            return Y, theta[:count], steps, restarts
        if hi + V.shape[0] > max_basis:
            if restarts >= max_restarts:
                worst = float(np.max(resid / np.abs(theta[:want])))
                raise SolverError(f"block Lanczos did not converge for {count} modes in "
                                  f"{steps} steps (worst relative residual {worst:.1e}, "
                                  f"tolerance {tol:.1e}); try a smaller modes.count or a "
                                  "larger modes.tolerance")
            keep = min(hi - V.shape[0], max(count + V.shape[0], max_basis // 2))
            Ut = np.ascontiguousarray(U[:, :keep].T)
            basis[:keep] = Ut @ Q
            if with_images:
                images[:keep] = Ut @ images[:hi]
            H[:] = 0.0
            H[np.arange(keep), np.arange(keep)] = theta[:keep]
            # H[:keep, keep:] (the coupling B U_last of V to the kept vectors) is found
            # again by the next step's projections
            size = keep
            restarts += 1
            log.debug("block Lanczos: restart %d after %d steps, kept %d", restarts, steps,
                      keep)
