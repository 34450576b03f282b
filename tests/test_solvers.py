"""Factorisation backends and the eigensolvers: every installed backend and method gives
the same modes, singular systems are refused with a clear message.

Tolerances (issue 16: derived from the conditioning, never tuned to one CPU's round-off;
see conftest for the first-order bounds):
- frequencies of two routes (a backend / method vs dense eigh): 0.5 eigenvalue_rtol, i.e.
  tau + c eps lambda_max / lambda_1 per route (the square root halves it).
- two solves with K by different code paths (one vs a block of right-hand sides, solve vs
  forward + backward, a second factorisation: PARDISO's threaded factorisation and MKL's
  kernels are not bitwise reproducible across CPUs): each has a forward error <=
  c eps cond(K), so they differ by <= 2 c eps cond(K) of |x|.
- residual of a solve: backward stability, ||K x - b|| <= c sqrt(n) eps ||K|| ||x||.
- M-orthonormality and Phi^T K Phi of the modes: round-off of the final Rayleigh-Ritz
  step on the small projected matrices (no solve involved), kept at 1e-8.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.linalg import eigh

from pipeline.solve import blas
from pipeline.solve import mkl as mkl_runtime
from pipeline.solve import factorization as solvers
from pipeline.solve import plan
from pipeline.solve.backends import cudss as cudss_backend
from pipeline.solve.backends import pardiso as pardiso_backend
from pipeline.fe.assemble import assemble_stiffness_mass, restrict
from pipeline.config import Geometry, Material, MeshSpec, Support
from pipeline.errors import ConfigError, SolverError
from pipeline.fe.space import build_space
from pipeline.fe.mesh import generate_mesh, read_mesh
from pipeline.solve.eigen import solve_modes
from pipeline.solve.lanczos import block_lanczos
from pipeline.fe.regions import fixed_dofs, free_dofs, resolve_regions

from conftest import (EPS, ROUND_OFF_FACTOR, assert_elementwise_within,
                      assert_relative_within, cond_eps, eigenvalue_rtol, extreme_eigenvalues,
                      record_tolerance)

ALUMINIUM = Material(E=69.0e9, nu=0.33, rho=2700.0)
BACKENDS = solvers.available_backends()
COUNT = 8


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    """A small clamped P2 beam (about 2.5k free DOFs): K, M free and full."""
    path = tmp_path_factory.mktemp("solvers") / "beam.msh"
    generate_mesh(Geometry("box", 0.1, 0.02, 0.03), MeshSpec(order=2, size=0.01,
                                                             algorithm="delaunay"), path)
    space = build_space(read_mesh(path), 2)
    K_full, M_full = assemble_stiffness_mass(space, ALUMINIUM)
    regions = resolve_regions(space, {})
    free = free_dofs(space.n_dofs, fixed_dofs(space, regions, [Support("root")], False))
    return {"K": restrict(K_full, free), "M": restrict(M_full, free), "K_full": K_full,
            "M_full": M_full, "space": space, "free": free}


@pytest.fixture(scope="module")
def rounding(beam):
    """What the bounds need from this K: c eps cond(K), ||K||_2, and the frequency bound
    of two routes (clamped; free with its six zero eigenvalues)."""
    K, M = beam["K"], beam["M"]
    return {"cond_eps": cond_eps(K), "norm_K": extreme_eigenvalues(K)[1],
            "freq_rtol": 0.5 * eigenvalue_rtol(K, M),
            "free_rtol": eigenvalue_rtol(beam["K_full"], beam["M_full"], n_zero=6)}


def _residual_bound(norm_K, X, B):
    """Backward stability: ||K X - B|| <= c sqrt(n) eps ||K|| ||X||, relative to ||B||
    (the sqrt(n) of the probabilistic round-off bound of the factor's length-n inner
    products and of forming K X, Higham & Mary 2019; the worst case is n)."""
    n = X.shape[0]
    return ROUND_OFF_FACTOR * np.sqrt(n) * EPS * norm_K * np.linalg.norm(X) / np.linalg.norm(B)


@pytest.fixture(scope="module")
def dense_reference(beam):
    K, M = beam["K"].toarray(), beam["M"].toarray()
    w = eigh(K, M, eigvals_only=True, subset_by_index=[0, COUNT - 1])
    return np.sqrt(w) / (2 * np.pi)


@pytest.fixture(scope="module")
def free_reference(beam):
    Kd, Md = beam["K_full"].toarray(), beam["M_full"].toarray()
    return eigh(Kd, Md, eigvals_only=True, subset_by_index=[6, 9])


def _check_modes(modes, K, M, count, residual: float | None = 1e-6):
    """M-orthonormality and Phi^T K Phi (round-off of the final Rayleigh-Ritz step), and
    the Euclidean residuals of a shift-invert solve (``residual``; None for the
    preconditioned-residual solvers, whose measure is checked by their own tests)."""
    Phi = modes.shapes
    assert Phi.shape == (K.shape[0], count)
    assert np.abs(Phi.T @ (M @ Phi) - np.eye(count)).max() < 1e-8
    KK = Phi.T @ (K @ Phi)
    assert np.abs(KK - np.diag(modes.omega2)).max() < 1e-8 * modes.omega2.max()
    if residual is not None:
        assert modes.residuals.max() < residual


def test_superlu_is_always_there_and_pardiso_comes_first_when_installed():
    assert "superlu" in BACKENDS
    if "pardiso" in BACKENDS:
        assert BACKENDS[0] == "pardiso"
    assert solvers.resolve_backend("auto") == BACKENDS[0]


def test_unknown_or_missing_backend_is_a_config_error():
    with pytest.raises(ConfigError, match="modes.solver.*mumps.*installed backends"):
        solvers.factorize(sp.identity(4, format="csr"), "mumps")
    with pytest.raises(ConfigError, match="nonsense"):
        solvers.resolve_backend("nonsense")


@pytest.mark.parametrize("backend", BACKENDS)
def test_every_backend_gives_the_same_frequencies(beam, dense_reference, rounding, backend):
    K, M = beam["K"], beam["M"]
    modes = solve_modes(K, M, COUNT, backend=backend, keep=False)
    assert modes.backend == backend
    assert_elementwise_within(modes.frequencies_hz, dense_reference, rounding["freq_rtol"],
                              f"test_solvers::every_backend[{backend}]")
    _check_modes(modes, K, M, COUNT)


@pytest.mark.parametrize("method", ["lanczos", "arpack"])
def test_block_lanczos_and_arpack_agree(beam, dense_reference, rounding, method):
    if "pardiso" not in BACKENDS:
        pytest.skip("block Lanczos needs the symmetric PARDISO factor")
    K, M = beam["K"], beam["M"]
    modes = solve_modes(K, M, COUNT, backend="pardiso", method=method, keep=False)
    assert modes.stats["method"] == ("block-lanczos" if method == "lanczos" else "arpack")
    assert_elementwise_within(modes.frequencies_hz, dense_reference, rounding["freq_rtol"],
                              f"test_solvers::lanczos_arpack[{method}]")
    _check_modes(modes, K, M, COUNT)


def test_lanczos_with_restarts_and_other_block_sizes(beam, dense_reference, rounding):
    if "pardiso" not in BACKENDS:
        pytest.skip("block Lanczos needs the symmetric PARDISO factor")
    K, M = beam["K"], beam["M"]
    for block, basis in ((1, 24), (3, 30), (8, 40)):
        modes = solve_modes(K, M, COUNT, backend="pardiso", method="lanczos",
                            block_size=block, max_basis=basis, keep=False)
        assert_elementwise_within(modes.frequencies_hz, dense_reference,
                                  rounding["freq_rtol"], f"test_solvers::restarts[{block}]")
    assert modes.stats["restarts"] >= 1


@pytest.mark.parametrize("backend", BACKENDS)
def test_free_body_has_six_rigid_modes(beam, free_reference, rounding, backend):
    K, M = beam["K_full"], beam["M_full"]
    modes = solve_modes(K, M, 10, supported=False, backend=backend, keep=False)
    assert modes.shift < 0
    assert modes.n_rigid == 6
    assert np.all(modes.omega2[:6] == 0.0) and modes.omega2[6] > 0
    assert_elementwise_within(modes.omega2[6:], free_reference, rounding["free_rtol"],
                              f"test_solvers::free_body[{backend}]")
    Phi = modes.shapes
    assert np.abs(Phi.T @ (M @ Phi) - np.eye(10)).max() < 1e-8


@pytest.mark.parametrize("backend", BACKENDS)
def test_singular_stiffness_is_refused_with_a_clear_message(beam, backend):
    with pytest.raises(SolverError, match="singular") as info:
        solvers.factorize(beam["K_full"], backend)
    assert "supports" in str(info.value)
    with pytest.raises(SolverError, match="supports"):
        solve_modes(beam["K_full"], beam["M_full"], 4, supported=True, backend=backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_factorisation_solves_blocks_of_right_hand_sides(beam, rounding, backend):
    K = beam["K"]
    two_paths = 2 * rounding["cond_eps"]  # two solve code paths, c eps cond(K) each
    fact = solvers.factorize(K, backend)
    B = np.random.default_rng(0).standard_normal((K.shape[0], 3))
    X = fact.solve(B)
    assert X.shape == B.shape
    for j in range(3):  # a block of right-hand sides vs one: other kernels, other round-off
        assert_relative_within(X[:, j], fact.solve(B[:, j]), two_paths,
                               f"test_solvers::block_vs_single[{backend}]")
    residual = np.linalg.norm(K @ X - B) / np.linalg.norm(B)
    bound = _residual_bound(rounding["norm_K"], X, B)
    record_tolerance(f"test_solvers::block_residual[{backend}]", residual, bound)
    assert residual <= bound, (residual, bound)
    if fact.capabilities.half_solves:  # A = F F^T: ||F^-1 b||^2 = b^T A^-1 b
        Y = fact.forward(B)
        # b^T x and ||F^-1 b||^2: first-order error x^T dK x <= c eps cond(K) b^T x each
        assert_elementwise_within((Y * Y).sum(axis=0), (B * X).sum(axis=0), two_paths,
                                  f"test_solvers::energy[{backend}]")
        assert_relative_within(fact.backward(Y), X, two_paths,
                               f"test_solvers::forward_backward[{backend}]")
    fact.release()
    if backend == "pardiso":
        with pytest.raises(SolverError, match="released"):
            fact.solve(B)


@pytest.mark.skipif("pardiso" not in BACKENDS, reason="PARDISO (MKL) is not installed")
def test_large_pardiso_factor_is_freed_in_the_background(beam, rounding, monkeypatch):
    """Factors above BACKGROUND_RELEASE_BYTES are freed by a thread: the handle is dead at
    once (solves refused), the thread finishes, and a new factorisation still works."""
    monkeypatch.setattr(pardiso_backend, "BACKGROUND_RELEASE_BYTES", 0)
    K = beam["K"]
    handle = pardiso_backend.PardisoFactorization(K, True)
    b = np.ones(K.shape[0])
    x = handle.solve(b)
    handle.release()
    with pytest.raises(SolverError, match="released"):
        handle.solve(b)
    handle.releasing.join(timeout=60)
    assert not handle.releasing.is_alive()
    assert handle.a.size == 1  # the input arrays were dropped by the thread
    again = solvers.factorize(K, "pardiso")
    # a second factorisation: threaded PARDISO is not bitwise reproducible, 2 c eps cond(K)
    assert_relative_within(again.solve(b), x, 2 * rounding["cond_eps"],
                           "test_solvers::second_factorisation")
    again.release()


def test_kept_factorisation_is_handed_on_in_the_result_and_freed_by_its_owner(beam, rounding):
    """keep=True hands the factorisation of K to the caller (no module-level cache);
    keep=False (the default) frees it inside solve_modes."""
    K, M = beam["K"].copy(), beam["M"]
    assert not hasattr(solvers, "_kept") and not hasattr(solvers, "keep_factorization")
    assert solve_modes(K, M, 4).factorization is None
    modes = solve_modes(K, M, 4, keep=True)
    assert modes.factorization is not None and modes.solve == modes.factorization.solve
    b = np.random.default_rng(1).standard_normal(K.shape[0])
    x = modes.solve(b)
    residual = np.linalg.norm(K @ x - b) / np.linalg.norm(b)
    bound = _residual_bound(rounding["norm_K"], x, b)
    record_tolerance("test_solvers::kept_residual", residual, bound)
    assert residual <= bound, (residual, bound)
    modes.release_factorization()
    modes.release_factorization()  # idempotent
    if modes.factorization.backend == "pardiso":
        with pytest.raises(SolverError, match="released"):
            modes.solve(b)


def test_upper_triangle_is_one_pass_and_32_bit(beam):
    K = beam["K"]
    U = blas.upper_triangle_csr(K)
    assert U.indices.dtype == np.int32 and U.indptr.dtype == np.int32
    assert abs(U - sp.triu(K)).max() == 0.0


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_sparse_times_dense_matches_scipy_in_every_shape(beam, dtype):
    """One column (1-D or (n, 1): MKL's matrix-vector product), several in row- or
    column-major order (its matrix-matrix product): scipy's product to round-off
    (|A| |X| per row times the precision's unit round-off times the row length), in X's
    shape and, for float32 A and X, in float32."""
    K = beam["K"]
    A = sp.csr_matrix((K.data.astype(dtype), K.indices.astype(np.int32),
                       K.indptr.astype(np.int32)), shape=K.shape)  # MKL's input
    eps = np.finfo(dtype).eps
    rng = np.random.default_rng(6)
    row_len = int(np.diff(A.indptr).max())
    for X in (rng.standard_normal(A.shape[1]), rng.standard_normal((A.shape[1], 1)),
              rng.standard_normal((A.shape[1], 3)),
              np.asfortranarray(rng.standard_normal((A.shape[1], 3)))):
        X = X.astype(dtype)
        got = blas.sparse_times_dense(A, X)
        assert got.shape == X.shape and got.dtype == dtype
        ref = A.astype(np.float64) @ X.astype(np.float64)
        scale = abs(A).astype(np.float64) @ np.abs(X.astype(np.float64))
        bound = 2 * row_len * eps * scale
        assert np.all(np.abs(got - ref) <= bound)


@pytest.mark.parametrize("mkl", [True, False])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_fused_products_and_axpby(beam, dtype, mkl, monkeypatch):
    """out = alpha A X + beta out in place (one and several columns) and y = a x + b y,
    through MKL and through the numpy fallback: the unfused numpy expression to the same
    round-off bound as above (plus one rounding of beta out); a wrong ``out`` is one
    ValueError naming the expected shape."""
    if not mkl:
        monkeypatch.setattr(mkl_runtime, "mkl_library", lambda: None)
    elif mkl_runtime.mkl_library() is None:
        pytest.skip("MKL is not installed (the 'fast' extra)")
    K = beam["K"]
    A = sp.csr_matrix((K.data.astype(dtype), K.indices.astype(np.int32),
                       K.indptr.astype(np.int32)), shape=K.shape)
    eps = np.finfo(dtype).eps
    rng = np.random.default_rng(7)
    row_len = int(np.diff(A.indptr).max())
    for shape in ((A.shape[1],), (A.shape[1], 1), (A.shape[1], 3)):
        X = rng.standard_normal(shape).astype(dtype)
        Y0 = rng.standard_normal(shape).astype(dtype)
        out = Y0.copy()
        got = blas.sparse_times_dense(A, X, out=out, alpha=-0.5, beta=2.0)
        assert got is out and got.dtype == dtype
        ref = -0.5 * (A.astype(np.float64) @ X.astype(np.float64)) + 2.0 * Y0
        scale = 0.5 * (abs(A).astype(np.float64) @ np.abs(X.astype(np.float64))) \
            + 2.0 * np.abs(Y0)
        assert np.all(np.abs(got - ref) <= 2 * (row_len + 1) * eps * scale)
    with pytest.raises(ValueError, match=r"out: expected a C-contiguous"):
        blas.sparse_times_dense(A, X, out=np.empty((3, 3), dtype=dtype))
    x, y = rng.standard_normal(50).astype(dtype), rng.standard_normal(50).astype(dtype)
    y0 = y.astype(np.float64)
    ref = 3.0 * x.astype(np.float64) - 0.25 * y0
    got = blas.axpby(3.0, x, -0.25, y)
    assert got is y
    assert np.all(np.abs(got - ref) <= 2 * eps * (3 * np.abs(x) + 0.25 * np.abs(y0)))
    with pytest.raises(ValueError, match="axpby"):
        blas.axpby(1.0, x[:10], 1.0, y)


def test_block_lanczos_on_a_diagonal_operator():
    """Largest eigenvalues of diag(d), including a 3-fold one, to round-off."""
    d = np.concatenate([[5.0, 5.0, 5.0, 4.0], np.linspace(0.1, 3.0, 400)])

    def op(Y):
        return Y * d

    Y, theta, steps, restarts = block_lanczos(op, d.size, 6, 4, 1e-12, 40)
    # a diagonal operator with eigenvalues in [0.1, 5] (cond 50): tol 1e-12 and round-off
    np.testing.assert_allclose(theta, [5, 5, 5, 4, 3.0, d[-2]], rtol=1e-12)
    assert np.abs(Y @ Y.T - np.eye(6)).max() < 1e-12


def test_block_lanczos_images_follow_the_ritz_vectors():
    """The images op returns beside S Y come back combined exactly as the Ritz vectors
    are, through restarts (max_basis forces several) and a deflated block."""
    d = np.concatenate([[5.0, 5.0, 5.0, 4.0], np.linspace(0.1, 3.0, 400)])
    P = np.random.default_rng(3).standard_normal((d.size, d.size)) * 1e-3 + np.eye(d.size)

    def op(Y):
        return Y * d, Y @ P  # any linear image of the rows of Y

    Y, theta, steps, restarts, Z = block_lanczos(op, d.size, 6, 4, 1e-12, 40,
                                                 with_images=True)
    assert restarts > 0
    np.testing.assert_allclose(theta, [5, 5, 5, 4, 3.0, d[-2]], rtol=1e-12)
    np.testing.assert_allclose(Z, Y @ P, atol=1e-12)
    assert np.abs(Y @ Y.T - np.eye(6)).max() < 1e-12


def test_block_lanczos_converges_only_the_leading_pairs_asked_for():
    """``converge``: the leading pairs meet the tolerance in fewer steps; the rest of the
    ``count`` come back as orthonormal Ritz vectors of the same basis (a start block's
    guard columns), here short of the tolerance."""
    d = np.concatenate([[5.0, 4.5, 4.0, 3.5], np.linspace(0.1, 3.0, 600)])

    def op(Y):
        return Y * d

    tol = 1e-10
    Y, theta, steps, _ = block_lanczos(op, d.size, 8, 2, tol, 60)
    Y4, theta4, steps4, _ = block_lanczos(op, d.size, 8, 2, tol, 60, converge=4)
    assert steps4 < steps
    resid = np.linalg.norm(op(Y4) - theta4[:, None] * Y4, axis=1) / np.abs(theta4)
    assert np.all(resid[:4] <= tol) and resid[4:].max() > tol
    np.testing.assert_allclose(theta4[:4], [5.0, 4.5, 4.0, 3.5], rtol=tol)
    assert np.abs(Y4 @ Y4.T - np.eye(8)).max() < 1e-12
    np.testing.assert_allclose(theta, np.sort(d)[::-1][:8], rtol=tol)


def test_orthonormal_block_cholesky_qr_and_svd_paths_agree_on_the_span():
    from pipeline.solve.lanczos import _orthonormal_block

    rng = np.random.default_rng(4)
    W = rng.standard_normal((4, 500))
    for block in (W, np.vstack([W[:3], W[0] + 1e-9 * W[3]])):  # well / ill conditioned
        V, B = _orthonormal_block(block.copy(), np.zeros((0, 500)), rng, 1.0)
        np.testing.assert_allclose(V @ V.T, np.eye(4), atol=1e-13)
        np.testing.assert_allclose(B.T @ V, block, atol=1e-12)


def test_default_tolerance_is_tighter_below_the_round_off_floor():
    from pipeline.solve.eigen import default_tolerance

    assert default_tolerance(20_000) == 1e-10
    assert default_tolerance(1_000_000) == 1e-8


def test_superlu_refuses_an_indefinite_matrix_by_its_inertia():
    A = sp.diags([1.0, 2.0, -3.0, 4.0], format="csr")
    with pytest.raises(SolverError, match="not positive definite.*1 non-positive pivot"):
        solvers.factorize(A, "superlu")
    fact = solvers.factorize(A, "superlu", positive_definite=False, check=False)
    np.testing.assert_allclose(A @ fact.solve(np.ones(4)), 1.0)


# --------------------------------------------------------------------------- mixed precision
needs_pardiso = pytest.mark.skipif("pardiso" not in BACKENDS, reason="needs MKL PARDISO")


@needs_pardiso
def test_mixed_precision_matches_double(beam):
    """A float32 factor with double-precision refinement (modes.precision: mixed) gives
    the double-precision frequencies within rho^2 / relative gap + the double route's
    eigenvalue_rtol: LOBPCG's Rayleigh quotients err by the squared preconditioned
    residual rho (<= mixed.TARGET_RESIDUAL = 1e-6) over the gap. M-orthonormality is the
    double path's own check; the Euclidean residuals (float32 noise in the
    high-frequency components, amplified by lambda_max / omega^2) are bounded by
    sqrt(lambda_max / omega_1^2) rho, the norm of T^-1 against T's energy norm."""
    from pipeline.solve import mixed

    K, M = beam["K"], beam["M"]
    double = solve_modes(K, M, COUNT, method="lanczos")
    mixed_modes = solve_modes(K, M, COUNT, method="lanczos", precision="mixed")
    lam_max = extreme_eigenvalues(K, M)[1]
    amplification = float(np.sqrt(lam_max / double.omega2[0]))
    _check_modes(mixed_modes, K, M, COUNT,
                 residual=amplification * 10 * mixed.TARGET_RESIDUAL)
    assert mixed_modes.stats["precision"] == "mixed"
    assert mixed_modes.stats["format"].endswith("float32")
    assert mixed_modes.factorization is None  # no double factor of K to hand on
    rel = np.abs(mixed_modes.frequencies_hz / double.frequencies_hz - 1).max()
    rel_gap = float(np.min(np.diff(double.omega2) / double.omega2[1:]))
    bound = 2 * (10 * mixed.TARGET_RESIDUAL) ** 2 / rel_gap + 0.5 * eigenvalue_rtol(K, M)
    record_tolerance("mixed frequencies vs double", rel, bound)
    assert rel < bound
    assert mixed_modes.stats["refine_residual"] <= 10 * mixed.TARGET_RESIDUAL
    # half the factor: float32 entries (PARDISO's own count of the factor memory)
    assert mixed_modes.stats["factor_bytes"] < 0.7 * double.stats["factor_bytes"]


@needs_pardiso
def test_mixed_refinement_fixes_the_float32_operator(beam):
    """The float32 factor alone is a poor solver for K (cond ~1e7, eps32 ~ 1e-7): the
    Lanczos vectors it gives are not converged (preconditioned residual 5e-5 on this
    beam, 3e-3 at 101k DOFs), and the double-precision refinement must bring it down by
    more than an order of magnitude, to its target."""
    from pipeline.solve import mixed

    K, M = beam["K"], beam["M"]
    modes = solve_modes(K, M, COUNT, method="lanczos", precision="mixed")
    history = modes.stats["refine_residuals"]
    assert modes.stats["refine_sweeps"] >= 1
    assert min(history) < 0.1 * history[0]
    assert min(history) <= mixed.TARGET_RESIDUAL


@needs_pardiso
def test_auto_precision_uses_mixed_only_when_a_double_factor_does_not_fit(beam, monkeypatch):
    """auto: double when it fits; mixed when the estimate says it does not, and also when
    PARDISO's exact size after its analysis (iparm[16]) does not fit."""
    from pipeline.errors import ResourceError
    from pipeline.solve import eigen

    K, M = beam["K"], beam["M"]
    fits = solve_modes(K, M, COUNT, method="lanczos", precision="auto")
    assert fits.stats.get("precision", "double") == "double"
    double_bytes = fits.stats["factor_bytes"]

    def exact_check(nbytes, n_dofs, available=None):  # room for a float32 factor only
        if nbytes > 0.75 * double_bytes:
            raise ResourceError("the factor does not fit")

    monkeypatch.setattr(pardiso_backend, "check_factor_memory", exact_check)
    with pytest.raises(ResourceError):
        solve_modes(K, M, COUNT, method="lanczos", precision="double")
    after_analysis = solve_modes(K, M, COUNT, method="lanczos", precision="auto")
    assert after_analysis.stats["precision"] == "mixed"
    monkeypatch.undo()
    monkeypatch.setattr(eigen, "available_memory_bytes", lambda: 1)
    estimated = solve_modes(K, M, COUNT, method="lanczos", precision="auto")
    assert estimated.stats["precision"] == "mixed"
    np.testing.assert_allclose(estimated.frequencies_hz, fits.frequencies_hz, rtol=1e-6)


def test_precision_key_is_validated():
    from pipeline.config import config_from_dict

    raw = {"name": "b", "geometry": {"kind": "box", "length": 0.1, "height": 0.02,
                                     "depth": 0.03},
           "mesh": {"order": 2, "size": 0.01}, "material": {"E": 69e9, "nu": 0.33,
                                                             "rho": 2700.0}}
    assert config_from_dict(raw).modes.precision == "auto"
    raw["modes"] = {"precision": "mixed"}
    assert config_from_dict(raw).modes.precision == "mixed"
    raw["modes"] = {"precision": "half"}
    with pytest.raises(ConfigError, match="modes.precision") as info:
        config_from_dict(raw)
    assert info.value.key == "modes.precision"
    with pytest.raises(ConfigError, match="modes.precision"):
        solve_modes(sp.identity(700, format="csr"), sp.identity(700, format="csr"), 2,
                    precision="half")
    with pytest.raises(ConfigError, match="modes.precision"):
        solve_modes(sp.identity(700, format="csr"), sp.identity(700, format="csr"), 2,
                    backend="superlu", precision="mixed")


# ------------------------------------------------------------------ the GPU backend (cudss)
def _cpu_stand_in_for_cudss(monkeypatch):
    """Make ``cudss`` an installed backend whose factor is SuperLU's, named cudss (no
    separate forward/backward substitutions, like cuDSS): what the pipeline does around
    the GPU factor, tested where there is no GPU."""
    from pipeline.solve.backends.superlu import SuperLUFactorization

    class StandIn(SuperLUFactorization):
        backend = "cudss"
        capabilities = solvers.Capabilities(gpu=True)

    solvers.available_backends()  # the built-in backends are registered
    monkeypatch.setitem(solvers._REGISTRY, "cudss", solvers.Backend(
        name="cudss", factor=lambda A, **options: StandIn(A), installed=lambda: True,
        capabilities=StandIn.capabilities))


def test_gpu_backend_takes_the_factor_path_with_arpack_and_no_multigrid_trial(
        beam, dense_reference, rounding, monkeypatch):
    """modes.solver: cudss keeps the factor on the GPU: no multigrid trial even from its
    size, no precision switch by host memory, ARPACK (no forward/backward) on the factor,
    and the factor kept for the static correction."""
    from pipeline.fe.coarse import p1_prolongation

    _cpu_stand_in_for_cudss(monkeypatch)
    K, M = beam["K"], beam["M"]
    monkeypatch.setattr(plan, "MULTIGRID_AUTO_DOFS", 0)  # auto would try multigrid
    coarse = p1_prolongation(beam["space"], beam["free"])
    modes = solve_modes(K, M, COUNT, backend="cudss", keep=True, precision="auto",
                        coarse=coarse)
    try:
        assert modes.backend == "cudss" and modes.stats["method"] == "arpack"
        assert "multigrid_trial" not in modes.stats
        assert modes.factorization is not None and modes.factorization.backend == "cudss"
        assert_elementwise_within(modes.frequencies_hz, dense_reference, rounding["freq_rtol"],
                                  "test_solvers::gpu_backend_routing")
        _check_modes(modes, K, M, COUNT)
    finally:
        modes.release_factorization()
    # the contrast: a host backend, same settings, tries the multigrid solver first
    host = solve_modes(K, M, COUNT, backend="superlu", keep=False, coarse=coarse)
    assert host.stats["method"] == "multigrid-lobpcg" or "multigrid_trial" in host.stats


def test_missing_gpu_backend_is_one_config_line_before_meshing(tmp_path, capsys, monkeypatch):
    """modes.solver: cudss where there is no GPU stack: the run stops before any work with
    one line naming the key, the value, what it needs and how to install it."""
    from pathlib import Path

    from pipeline.cli.main import main

    import pipeline.run

    monkeypatch.setattr(cudss_backend, "cudss_modules", lambda: None)
    meshed = []
    monkeypatch.setattr(pipeline.run, "build_fe_model", lambda *a, **k: meshed.append(1))
    config = Path(__file__).resolve().parents[1] / "configs" / "cantilever.yaml"
    out = tmp_path / "gpu.h5"
    rc = main(["run", str(config), "--set", "modes.solver=cudss", "-o", str(out)])
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert rc == ConfigError.exit_code and len(err) == 1, err
    assert "modes.solver" in err[0] and "'cudss'" in err[0] and "NVIDIA GPU" in err[0]
    assert "nvmath-python" in err[0]
    assert not meshed, "the solver is checked before the mesh stage"
    assert not out.exists() and not list(tmp_path.iterdir())


def test_gpu_backend_memory_estimate_leaves_the_factor_on_the_gpu():
    """With the factor in GPU memory, the host's estimate for a large mesh drops by the
    factor's size, so a host whose RAM could not hold the factor is not refused."""
    from pipeline._util import resources

    n_nodes, modes = 1_000_000, 20  # 3M DOFs
    host = resources.eigensolve_bytes(n_nodes, 2, modes, "factor", available=10**12)
    gpu = resources.eigensolve_bytes(n_nodes, 2, modes, "factor", available=10**12,
                                     solver="cudss")
    assert host - gpu == pytest.approx(resources.factor_bytes(3 * n_nodes), rel=1e-12)
    assert gpu < 24e9 < host


def test_cpu_backends_never_probe_the_gpu(monkeypatch):
    """Probing for cudss imports CuPy and loads cuDSS (a second or so where they are
    installed): auto and the CPU backends are resolved without it."""
    def probe():
        raise AssertionError("probed the GPU stack")

    monkeypatch.setattr(cudss_backend, "cudss_modules", probe)
    assert solvers.resolve_backend("auto") == BACKENDS[0]
    assert solvers.resolve_backend("superlu") == "superlu"
    with pytest.raises(AssertionError, match="probed"):
        solvers.resolve_backend("cudss")


# ------------------------------------------------------- PARDISO's analysis ahead of the values
@pytest.mark.skipif("pardiso" not in BACKENDS, reason="PatternAnalysis is PARDISO's")
def test_analysis_of_the_pattern_alone_factorises_the_matrix_given_later(beam, rounding):
    """The analysis runs on K's pattern (zero values) in a thread; the factorisation with
    the values then solves like a factor analysed with them (two factorisations: within
    2 c eps cond(K)); a matrix of another pattern is analysed afresh and the early
    analysis is freed."""
    K = beam["K"]
    b = np.random.default_rng(3).standard_normal(K.shape[0])
    reference = solvers.factorize(K, "pardiso")
    x_ref = reference.solve(b)
    reference.release()
    with pardiso_backend.PatternAnalysis(K.indptr, K.indices) as early:
        fact = solvers.factorize(K, "pardiso", analysis=early)
    assert fact.info["analysis_ahead"]
    x = fact.solve(b)
    fact.release()
    assert np.linalg.norm(x - x_ref) <= 2 * rounding["cond_eps"] * np.linalg.norm(x_ref)
    # another pattern (K + eps v v^T, v = e_0 + e_last, still SPD; two entries more):
    # not taken, and freed
    n = K.shape[0]
    assert K[0, n - 1] == 0.0
    v = sp.csr_matrix(([1.0, 1.0], ([0, n - 1], [0, 0])), shape=(n, 1))
    other = (K + 1e-3 * K[0, 0] * (v @ v.T)).tocsr()
    other.sort_indices()
    early = pardiso_backend.PatternAnalysis(K.indptr, K.indices)
    fact = solvers.factorize(other, "pardiso", analysis=early)
    assert not fact.info["analysis_ahead"] and early._result[0] is None
    assert np.linalg.norm(other @ fact.solve(b) - b) <= 1e-8 * np.linalg.norm(b)
    fact.release()


@pytest.mark.skipif("pardiso" not in BACKENDS, reason="PatternAnalysis is PARDISO's")
def test_analysis_ahead_refuses_unsorted_rows(beam):
    """PARDISO reads sorted rows only: a pattern whose rows are not sorted (a sparse
    product's, before sort_indices) is not analysed ahead, so the factorisation of that
    very matrix analyses afresh and solves K x = b (relative residual 1e-8: cond eps of
    this K is below 1e-9), instead of a wrong factor from a mismatched analysis."""
    K = beam["K"].copy()
    n = K.shape[0]
    lo, hi = int(K.indptr[1]), int(K.indptr[2])  # row 1's entries, reversed
    K.indices[lo:hi] = K.indices[lo:hi][::-1].copy()
    K.data[lo:hi] = K.data[lo:hi][::-1].copy()
    K.has_sorted_indices = False
    early = pardiso_backend.PatternAnalysis(K.indptr, K.indices)
    fact = solvers.factorize(K, "pardiso", analysis=early)
    assert not fact.info["analysis_ahead"]
    b = np.random.default_rng(5).standard_normal(n)
    assert np.linalg.norm(K @ fact.solve(b) - b) <= 1e-8 * np.linalg.norm(b)
    fact.release()


@pytest.mark.skipif("pardiso" not in BACKENDS, reason="PatternAnalysis is PARDISO's")
def test_solve_modes_takes_the_early_analysis_only_at_shift_zero(beam, dense_reference,
                                                                 rounding):
    K, M = beam["K"], beam["M"]
    with pardiso_backend.PatternAnalysis(K.indptr, K.indices) as early:
        modes = solve_modes(K, M, COUNT, backend="pardiso", keep=False, analysis=early)
    assert modes.stats["analysis_ahead"]
    assert_elementwise_within(modes.frequencies_hz, dense_reference, rounding["freq_rtol"],
                              "test_solvers::analysis_ahead")
    _check_modes(modes, K, M, COUNT)
    Kf, Mf = beam["K_full"], beam["M_full"]  # a free body: shift < 0, K - sigma M
    with pardiso_backend.PatternAnalysis(Kf.indptr, Kf.indices) as early:
        free = solve_modes(Kf, Mf, 10, supported=False, backend="pardiso", keep=False,
                           analysis=early)
    assert not free.stats["analysis_ahead"] and early._result[0] is None


def test_factor_expected_follows_solve_modes_rules():
    from pipeline.solve import eigen

    pardiso = "pardiso" in BACKENDS
    n = 100_000
    assert eigen.factor_expected(n, 20) == pardiso
    assert eigen.factor_expected(n, 20, method="factor") == pardiso
    assert not eigen.factor_expected(n, 20, supported=False)  # shift < 0
    assert not eigen.factor_expected(n, 20, precision="mixed")
    assert not eigen.factor_expected(n, 20, method="multigrid")
    assert not eigen.factor_expected(plan.MULTIGRID_AUTO_DOFS, 20)  # auto tries multigrid
    assert not eigen.factor_expected(plan.DENSE_MAX, 4)  # dense
    assert not eigen.factor_expected(n, 20, backend="superlu")


def test_stage_expects_factor_reads_the_modes_config():
    from pipeline.config.schema import ModesConfig
    from pipeline.solve import eigen
    from pipeline.solve.stage import expects_factor

    n = 100_000
    for cfg in (ModesConfig(count=20), ModesConfig(count=20, precision="mixed"),
                ModesConfig(count=20, method="multigrid"), ModesConfig(solver="superlu")):
        for supported in (True, False):
            assert expects_factor(n, cfg, supported=supported) == eigen.factor_expected(
                n, cfg.count, supported=supported, backend=cfg.solver, method=cfg.method,
                precision=cfg.precision)
