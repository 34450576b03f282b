"""Shared helpers for the tests: build and solve small real FE models."""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path

from pipeline.cli.process import PROCESS_SETTINGS

# The test processes are hosts that run the library in-process, two of them (`make test`'s
# workers) on a 2-core machine: without the command line's spin times, OpenBLAS's idle
# threads (about 0.1 s after each call) and MKL's OpenMP threads (0.2 s) of one worker take
# the cores from the other's (the same files took 1.3-1.5 times as long). They are set
# here, before numpy and MKL load (``import pipeline`` loads neither), unless already set;
# the CLI's heap opt-in is not (the library's default behaviour is what the tests check).
# Tests of a host's or the CLI's environment remove these variables from their child's.
for _name in ("OPENBLAS_THREAD_TIMEOUT", "KMP_BLOCKTIME"):
    os.environ.setdefault(_name, PROCESS_SETTINGS[_name])

import numpy as np  # noqa: E402 (after the spin times, which act when numpy loads)
import pytest

from pipeline.fe.assemble import assemble_stiffness_mass, restrict
from pipeline.config import Geometry, Material, MeshSpec, Support
from pipeline.fe.space import FESpace, build_space
from pipeline.fe.mesh import generate_mesh, read_mesh
from pipeline.fe.regions import fixed_dofs, free_dofs, resolve_regions

ROOT = Path(__file__).resolve().parents[1]
ALUMINIUM = Material(E=69.0e9, nu=0.33, rho=2700.0)


def rank_error_lines(stderr: str) -> list[str]:
    """Each rank's one-line error ("error on rank R of N: ...") in the combined stderr of
    an ``mpiexec`` run. mpiexec forwards the ranks' streams as they come, so two ranks'
    lines may share one line, and its abort banner (a rule of dashes) or OpenMPI's own
    log lines ("[host:pid] ... ORTE_ERROR_LOG ...") may follow a rank's line without a
    newline between them: each is cut where the next begins."""
    import re

    parts = re.split(r"error on rank", stderr)[1:]
    return [re.split(r"-{20,}|\[[\w.-]+:\d+\]", ("error on rank" + part).splitlines()[0])[0]
            for part in parts]


@contextlib.contextmanager
def bench_module(name: str):
    """The script ``benchmarks/<name>.py`` as a module, while in the ``with`` block:
    registered in ``sys.modules`` (where its dataclasses look their module up), its
    folder first on the path (the scripts import each other)."""
    import importlib.util
    import sys

    folder = str(ROOT / "benchmarks")
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    sys.path.insert(0, folder)
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)
        sys.path.remove(folder)


@dataclass
class FEModel:
    space: FESpace
    regions: dict
    K_full: object
    M_full: object
    free: np.ndarray
    K: object
    M: object


def build_model(tmp_path: Path, length=0.5, height=0.02, depth=0.05, size=0.01, order=2,
                supports=("root",), in_plane=False, material=ALUMINIUM) -> FEModel:
    """Mesh a box, assemble K and M, and condense the supports."""
    geometry = Geometry("box", length, height, depth)
    path = generate_mesh(geometry, MeshSpec(order=order, size=size, algorithm="delaunay"),
                         tmp_path / f"box_{length}_{height}_{depth}_{size}_{order}.msh")
    space = build_space(read_mesh(path), order)
    regions = resolve_regions(space, {})
    K, M = assemble_stiffness_mass(space, material)
    fixed = fixed_dofs(space, regions, [Support(r) for r in supports], in_plane)
    free = free_dofs(space.n_dofs, fixed)
    return FEModel(space, regions, K, M, free, restrict(K, free), restrict(M, free))


@pytest.fixture(scope="session")
def session_tmp(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("shared")


def add_reliability_counts(prefix: str, counts) -> None:
    """Add ``counts`` (what a reliability test file tried) to the JSON file named by
    $RELIABILITY_COUNTS, keys ``<prefix>.<name>``; ``make test-reliability`` prints it."""
    import json
    import os

    target = os.environ.get("RELIABILITY_COUNTS")
    if not target:
        return
    path = Path(target)
    old = json.loads(path.read_text()) if path.exists() else {}
    for key, value in counts.items():
        old[f"{prefix}.{key}"] = old.get(f"{prefix}.{key}", 0) + value
    path.write_text(json.dumps(old, indent=1, sort_keys=True))


# --------------------------------------------------------------------------------------
# Round-off bounds derived from the conditioning of what a test computes (issue 16, 1).
#
# Two results that reach the same quantity through different factorisations, orderings
# or eigensolvers (PARDISO threads / ordering, SuperLU, dense LAPACK, ARPACK or block
# Lanczos; MKL takes other kernels on Intel AVX-512 than on AMD Zen) are each exact for a
# matrix perturbed by dK with ||dK|| <= c eps ||K|| (backward stability). To first order:
#   static solve x = K^-1 b:      ||dx|| / ||x||    <= c eps cond(K)
#   eigenvalue of (K, M):         |d lambda|        <= c eps lambda_max   (the eigenvalue
#                                 condition number of a symmetric pencil is 1), i.e.
#                                 |d lambda|/lambda <= c eps lambda_max / lambda,
#                                 plus the iterative solver's tolerance tau (|d theta| <=
#                                 tau theta on the shift-inverted problem).
# Two such results differ by twice that. c = 10 covers the modest dimension factors of
# the norm bounds (it is not a per-CPU fudge). cond is estimated from the test's own
# matrices: extreme eigenvalues of the pencil (two sparse Lanczos runs with a loose
# tolerance, an order-of-magnitude estimate is all a bound needs), or numpy on small
# dense matrices.
EPS = float(np.finfo(float).eps)
ROUND_OFF_FACTOR = 10.0


#: extreme_eigenvalues of sparse pencils already estimated in this process, by the
#: pencil's contents (_sparse_key): the tests of one model ask for its bounds many times,
#: two sparse Lanczos runs of 2-3 s each on a 25k-DOF P2 body
_EXTREMES: dict = {}


def _sparse_key(A) -> tuple | None:
    """A key of a sparse matrix's contents: its format, shape and a digest of its stored
    pattern and values (None for None)."""
    import hashlib

    if A is None:
        return None
    digest = hashlib.blake2b(digest_size=16)
    for part in ("indptr", "indices", "data"):
        digest.update(np.ascontiguousarray(getattr(A, part)).tobytes())
    return A.format, A.shape, digest.hexdigest()


def extreme_eigenvalues(K, M=None, n_zero: int = 0) -> tuple[float, float]:
    """(lambda_min, lambda_max) of K x = lambda M x (M = I when None), the lowest nonzero
    one when the pencil has ``n_zero`` zero eigenvalues (a free body: 6). A sparse
    pencil's estimate is computed once per process (:data:`_EXTREMES`)."""
    import scipy.sparse as sp

    if not sp.issparse(K):
        import scipy.linalg as sla

        w = sla.eigvalsh(K, M)
        return float(w[n_zero]), float(w[-1])
    cacheable = K.format in ("csr", "csc") and (M is None or M.format in ("csr", "csc"))
    if not cacheable:
        return _sparse_extreme_eigenvalues(K, M, n_zero)
    key = (_sparse_key(K), _sparse_key(M), n_zero)
    if key not in _EXTREMES:
        _EXTREMES[key] = _sparse_extreme_eigenvalues(K, M, n_zero)
    return _EXTREMES[key]


def _sparse_extreme_eigenvalues(K, M, n_zero: int) -> tuple[float, float]:
    """extreme_eigenvalues of a sparse pencil: two sparse Lanczos runs."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import eigsh

    K = sp.csc_matrix(K)
    M = sp.identity(K.shape[0], format="csc") if M is None else sp.csc_matrix(M)
    high = eigsh(K, k=1, M=M, which="LA", tol=1e-3, return_eigenvectors=False)
    # shift-invert about a point just below zero (a free body's K is singular)
    sigma = -1e-6 * float(abs(K.diagonal()).max() / abs(M.diagonal()).max())
    low = eigsh(K, k=n_zero + 4, M=M, sigma=sigma, which="LM", tol=1e-6,
                return_eigenvectors=False)
    # single-vector Lanczos may miss copies of the repeated zero eigenvalue: the lowest
    # nonzero one is the lowest above round-off of zero (1e4 eps lambda_max)
    nonzero = np.sort(low[low > 1e4 * EPS * high[0]]) if n_zero else np.sort(low)
    return float(nonzero[0]), float(high[0])


def condition_number(K, M=None, n_zero: int = 0) -> float:
    """lambda_max / lambda_min of the pencil (K, M), the 2-norm cond(K) when M is None
    (for a small dense K, symmetric or not: numpy's singular-value ratio)."""
    import scipy.sparse as sp

    if M is None and n_zero == 0 and not sp.issparse(K):
        return float(np.linalg.cond(np.asarray(K)))
    low, high = extreme_eigenvalues(K, M, n_zero)
    return high / low


def cond_eps(K, M=None, n_zero: int = 0, factor: float = ROUND_OFF_FACTOR) -> float:
    """factor * cond * eps: the first-order relative forward error of one backward-stable
    solve with K (or of the lowest eigenvalue of (K, M)); twice it bounds the difference
    of two such results computed by different routes."""
    return factor * condition_number(K, M, n_zero) * EPS


def record_tolerance(name: str, measured: float, bound: float) -> None:
    """Append (name, measured, bound) to $TOLERANCE_LOG when set (the audit's table of
    measured values); does nothing otherwise."""
    import json
    import os

    target = os.environ.get("TOLERANCE_LOG")
    if target:
        with open(target, "a") as out:
            out.write(json.dumps({"name": name, "measured": float(measured),
                                  "bound": float(bound)}) + "\n")


def assert_relative_within(got, ref, bound: float, name: str, scale=None) -> float:
    """max |got - ref| / scale <= bound (scale: max |ref| unless given); records the
    measured value (see record_tolerance) and returns it."""
    got, ref = np.asarray(got), np.asarray(ref)
    scale = float(np.abs(ref).max()) if scale is None else float(scale)
    measured = float(np.abs(got - ref).max()) / scale
    record_tolerance(name, measured, bound)
    assert measured <= bound, (name, measured, bound)
    return measured


def assert_elementwise_within(got, ref, bound: float, name: str) -> float:
    """max_i |got_i - ref_i| / |ref_i| <= bound (a per-entry relative error, as rtol)."""
    got, ref = np.asarray(got), np.asarray(ref)
    measured = float(np.max(np.abs(got - ref) / np.abs(ref)))
    record_tolerance(name, measured, bound)
    assert measured <= bound, (name, measured, bound)
    return measured


def eigenvalue_rtol(K, M=None, tolerance: float | None = None, n_zero: int = 0,
                    routes: int = 2) -> float:
    """Relative bound on the difference of eigenvalues of (K, M) computed by ``routes``
    different solvers: each is within tau + c eps lambda_max / lambda_min of the exact one
    (tau: the shift-inverted solver's relative residual tolerance, |d theta| <= tau theta
    for a symmetric pencil; the round-off term: the eigenvalue condition number of a
    symmetric pencil is 1, so a backward error c eps ||K|| moves lambda by c eps
    lambda_max, worst relative on the lowest nonzero lambda). ``tolerance`` defaults to
    pipeline.solve.eigen.default_tolerance(n). For frequencies (sqrt) halve it."""
    from pipeline.solve.eigen import default_tolerance

    tau = default_tolerance(K.shape[0]) if tolerance is None else tolerance
    return routes * (tau + cond_eps(K, M, n_zero))




@pytest.fixture(autouse=True)
def _cli_process_settings_undone():
    """A test that calls the console script's ``pipeline.cli.main`` in this process gets
    the CLI's process settings (pipeline.cli.process), its log handler on the root logger
    and its signal handlers; they are undone after it, so that no later test runs in a
    tuned process by the order the tests ran in (a root handler left on a closed capsys
    stream made later tests print "Logging error: I/O operation on closed file")."""
    import logging
    import os
    import signal

    from pipeline.cli.main import STAGE_LOGGERS
    from pipeline.cli.process import PROCESS_SETTINGS

    saved = {name: os.environ.get(name) for name in PROCESS_SETTINGS}
    stage_levels = {name: logging.getLogger(name).level for name in STAGE_LOGGERS}
    signals = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    for s, h in signals.items():
        signal.signal(s, h)
    root.handlers[:] = handlers
    root.setLevel(level)
    for name, stage_level in stage_levels.items():
        logging.getLogger(name).setLevel(stage_level)
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
