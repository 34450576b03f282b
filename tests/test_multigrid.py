"""The factor-free modes solver (issue 18: 3M DOFs in 24 GB): the P1 coarse space of a P2
mesh, the two-grid preconditioner, LOBPCG, and the whole pipeline under
``modes.method: multigrid``.

Tolerances:
- the prolongation reproduces linear fields exactly: round-off of a mean of two numbers
  (1e-15 of the field's scale; 1e-12 used);
- PCG to a recursive residual of 1e-12: the true residual differs from the recursive one
  by O(eps cond(K)) relative (the updates' round-off), so the solution differs from a
  direct solve by <= 1e-12 cond(K) + 2 c eps cond(K); both bounded by cond_eps;
- frequencies: the multigrid solver stops at a preconditioned residual rho <= 1e-6 and
  its eigenvalue error is <= rho^2 / relative gap (LOBPCG's Rayleigh quotient is
  quadratic in the energy-norm error; the smallest relative gap of the test beam is
  above 1e-2), i.e. <= 1e-10; plus the factor route's own eigenvalue_rtol;
- shapes and reduced matrices: energy-norm error <= rho / gap = 1e-4 of the shape,
  compared in the max norm with that bound.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import time

import numpy as np
import pytest
import scipy.sparse as sp

from conftest import (ALUMINIUM, build_model, cond_eps, condition_number, eigenvalue_rtol,
                      record_tolerance)
from pipeline.config import config_from_dict
from pipeline.errors import ConfigError
from pipeline.fe.coarse import p1_prolongation
from pipeline.solve import eigen, multigrid, plan, ritz
from pipeline.solve.eigen import solve_modes
from pipeline.solve.refine import backward_errors
from pipeline.solve.lobpcg import PROJECT_FROM, lobpcg, projected_sweeps
from pipeline.solve.pcg import pcg

COUNT = 8


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    return build_model(tmp_path_factory.mktemp("mg"), length=0.3, height=0.02, depth=0.03,
                       size=0.006)


@pytest.fixture(scope="module")
def free_beam(tmp_path_factory):
    return build_model(tmp_path_factory.mktemp("mgfree"), length=0.3, height=0.02,
                       depth=0.03, size=0.008, supports=())


def test_prolongation_reproduces_linear_fields_and_respects_supports(beam):
    """P maps the vertex values of a linear field to its P2 nodal values
    (midpoint = mean of the ends), with zero on held DOFs; P^T K P is symmetric positive
    definite (the P1 stiffness of the clamped mesh)."""
    space, free = beam.space, beam.free
    P = p1_prolongation(space, free)
    assert P.shape[0] == free.size and P.shape[1] < free.size / 4
    c = np.array([1e-3, -2e-3, 3e-3])
    field = space.node_points[:, :1] * c  # u = x c vanishes at x = 0: fits the clamp
    full = field.ravel()
    n_v = space.body.n_vertices
    coarse_dofs = free[free < 3 * n_v]
    got = P @ full[coarse_dofs]
    scale = np.abs(full).max()
    assert np.abs(got - full[free]).max() <= 1e-12 * scale
    Kc = (P.T @ beam.K @ P).toarray()
    assert np.allclose(Kc, Kc.T, rtol=0, atol=1e-12 * np.abs(Kc).max())
    np.linalg.cholesky(Kc)  # positive definite, or LinAlgError
    assert p1_prolongation(build_model_order1(beam), np.arange(3)) is None


def test_galerkin_product_in_row_slabs_is_the_single_product_bit_for_bit(beam, monkeypatch):
    """P^T K P made in row slabs on threads (pipeline.solve.blas.galerkin_product) equals
    scipy's one product exactly: same structure, same values to the last bit (each row
    is summed in the same order), for any slab count."""
    from pipeline.solve import blas

    P = sp.csr_matrix(p1_prolongation(beam.space, beam.free))
    PT = sp.csr_matrix(P.T)
    expected = PT @ beam.K @ P
    monkeypatch.setattr(blas, "GALERKIN_THREAD_ROWS", 1)
    for threads in (1, 2, 3, 7):
        got = blas.galerkin_product(PT, beam.K, P, threads=threads)
        assert got.shape == expected.shape
        assert np.array_equal(got.indptr, expected.indptr)
        assert np.array_equal(got.indices, expected.indices)
        assert np.array_equal(got.data, expected.data)


def test_rayleigh_ritz_on_mkl_equals_numpys_to_round_off(beam, monkeypatch):
    """The Rayleigh-Ritz step of tall blocks (MKL's dgemm, one-pass norms, signs from
    column extrema) gives numpy's eigenvalues, vectors (same signs) and residuals to
    round-off: eigenvalues to 1e-13 relative (cond of the 8 x 8 projected pencil ~1),
    vectors to 1e-10 of their largest entry (gap-limited: min gap / max omega^2 ~1e-3
    here, times eps n), residuals to 1e-8 of themselves (each is a difference of nearly
    equal terms); and the sign rule takes the first largest entry on exact ties."""
    rng = np.random.default_rng(4)
    v0 = rng.standard_normal((beam.K.shape[0], COUNT))
    w_np, v_np, r_np = ritz.rayleigh_ritz(beam.K, beam.M, v0, 0.0)
    monkeypatch.setattr(ritz, "RAYLEIGH_RITZ_BLAS_ROWS", 1)
    w_mkl, v_mkl, r_mkl = ritz.rayleigh_ritz(beam.K, beam.M, v0, 0.0)
    assert np.abs(w_mkl - w_np).max() <= 1e-13 * np.abs(w_np).max()
    assert np.abs(v_mkl - v_np).max() <= 1e-10 * np.abs(v_np).max()
    assert np.allclose(r_mkl, r_np, rtol=1e-8, atol=0)
    ties = np.array([[2.0, -2.0, 0.0, 1.0], [-2.0, 2.0, 0.0, -3.0], [1.0, 0.5, 0.0, 3.0]])
    expected = np.array([1.0, -1.0, 1.0, -1.0])  # the first largest entry's sign
    for tall in (True, False):
        assert np.array_equal(ritz._largest_entry_signs(ties, tall), expected)


def test_column_dots_in_row_halves(monkeypatch):
    """column_dots from HALVES_ROWS rows adds the two row halves' sums (one on a thread
    of its own): equal to one einsum to round-off of a sum of n products (n eps of the
    sum of |a_i b_i|), the same whether one core or two run it, and a failure in either
    half is raised in the caller."""
    from pipeline.solve import blas

    rng = np.random.default_rng(2)
    A, B = rng.standard_normal((1001, 5)), rng.standard_normal((1001, 5))
    whole = np.einsum("ij,ij->j", A, B)
    monkeypatch.setattr(blas, "HALVES_ROWS", 2)
    halves = blas.column_dots(A, B)
    assert np.all(np.abs(halves - whole) <= 1001 * np.finfo(float).eps
                  * np.einsum("ij,ij->j", abs(A), abs(B)))
    assert np.array_equal(blas.column_norms(A), np.sqrt(blas.column_dots(A, A)))
    monkeypatch.setattr(blas, "usable_cores", lambda: 1)
    assert np.array_equal(blas.column_dots(A, B), halves)

    def fail(rows):
        if rows.start:
            raise ValueError("second half")
        return 0

    monkeypatch.setattr(blas, "usable_cores", lambda: 2)
    with pytest.raises(ValueError, match="second half"):
        blas.in_halves(fail, 10)


def test_float32_cycle_in_row_halves_is_bitwise_the_one_piece_cycle(beam, monkeypatch):
    """The cycle's element-wise passes (column scales, casts, copies, the unscaling, and
    the float32 D^-1 K made once) run in two row halves on two threads from HALVES_ROWS rows: element-wise, so the result
    is bit for bit the one-piece cycle's, for one block and for the riding solve's list
    of blocks, and with a column of zeros (scale 1) and a tiny one (no underflow)."""
    from pipeline.solve import blas

    P = p1_prolongation(beam.space, beam.free)
    tg = multigrid.TwoGrid(beam.K, P)
    try:
        rng = np.random.default_rng(7)
        R = rng.standard_normal((beam.K.shape[0], 5))
        R[:, 1] = 0.0
        R[:, 2] *= 1e-300
        S = rng.standard_normal((beam.K.shape[0], 2))
        whole = tg.apply_single(R)
        whole_list = tg._apply_single([R, S])
        operator = tg._operator(True)[0].data.copy()
        monkeypatch.setattr(blas, "HALVES_ROWS", 2)
        tg._single = None  # the float32 D^-1 K made again, in row halves
        assert np.array_equal(tg._operator(True)[0].data, operator)
        halves = tg.apply_single(R)
        halves_list = tg._apply_single([R, S])
        assert np.array_equal(halves, whole)
        assert all(np.array_equal(a, b) for a, b in zip(halves_list, whole_list))
        assert np.array_equal(halves_list[0], whole)
        assert not np.any(whole[:, 1]) and np.all(np.isfinite(whole))
        assert np.abs(whole[:, 2]).max() > 0.0
    finally:
        tg.release()


def build_model_order1(beam):
    from pipeline.fe.space import build_space

    return build_space(beam.space.body, 1)


# also covered by test_solver_comparison.py (PCG + two-grid vs a direct solve): make test-all
@pytest.mark.slow
def test_two_grid_pcg_matches_a_direct_solve(beam):
    """PCG with the two-grid cycle solves K x = b: its true relative residual is the
    recursive target PCG_RTOL plus the drift of the recurrence (O(eps cond(K))), and its
    forward error against a direct solve is at most cond(K) times that residual plus the
    direct solve's own c eps cond(K); in a number of iterations far below n
    (mesh-independent: the coarse problem is solved exactly)."""
    P = p1_prolongation(beam.space, beam.free)
    tg = multigrid.TwoGrid(beam.K, P)
    try:
        b = np.random.default_rng(4).standard_normal((beam.K.shape[0], 2))
        x = tg.solve(b)
        ref = sp.linalg.spsolve(beam.K.tocsc(), b)
        cond = condition_number(beam.K)
        residual = float((np.linalg.norm(b - beam.K @ x, axis=0)
                          / np.linalg.norm(b, axis=0)).max())
        res_bound = multigrid.PCG_RTOL + cond_eps(beam.K)
        record_tolerance("multigrid PCG true residual", residual, res_bound)
        assert residual <= res_bound
        bound = cond * residual + cond_eps(beam.K)
        err = float(np.linalg.norm(x - ref) / np.linalg.norm(ref))
        record_tolerance("multigrid PCG vs direct", err, bound)
        assert err <= bound
        assert tg.iterations <= 60
        assert tg.factorization().solve(b[:, 0]).shape == (beam.K.shape[0],)
    finally:
        tg.release()


@pytest.mark.parametrize("single", [False, True], ids=["double-cycle", "float32-cycle"])
def test_pcg_stops_at_the_round_off_floor(beam, single):
    """With rtol = 0 (unreachable), PCG still ends: once the normwise backward error of
    its recursive residual is eps, the true one has stopped falling (pcg module doc). It
    ends there with a true backward error below iterative refinement's floor (16 eps, so
    no refinement solve follows) and in fewer iterations than rtol = 1e-12 takes. Without
    the floor test it ran into max_iter. The float32 cycle (what static solves use) only
    chooses search directions: X and its residual stay in double, so it reaches the same
    floor."""
    P = p1_prolongation(beam.space, beam.free)
    tg = multigrid.TwoGrid(beam.K, P)
    cycle = tg.apply_single if single else tg.apply
    try:
        b = np.random.default_rng(8).standard_normal((beam.K.shape[0], 2))
        x, its = pcg(beam.K, b, cycle, rtol=0.0)
        _, its_rtol = pcg(beam.K, b, cycle, rtol=1e-12, max_iter=10_000)
    finally:
        tg.release()
    eta = backward_errors(beam.K, x, b)
    record_tolerance("PCG at the round-off floor: backward error", float(eta.max()),
                     16 * np.finfo(float).eps)
    assert eta.max() <= 16 * np.finfo(float).eps
    assert its <= its_rtol


def test_float32_cycle_is_scale_invariant(beam):
    """The float32 cycle scales each column to unit max (in double) before the cast, so a
    tiny or huge residual (PCG near its floor, any unit system) neither underflows, goes
    subnormal nor overflows: for s = 2^-150 (below float32's smallest subnormal) and
    2^120 (near its largest value), T32 (s r) / s matches the double cycle T r as T32 r
    does. Bound: float32 rounding (6e-8) amplified by the cycle's cancellations, which
    moves the result by 2e-7 to 1.4e-5 between inputs that differ by rounding only
    (measured on this beam over scales and columns; MKL's kernels need not be bitwise
    reproducible across allocations), so 1e-4. Without the scaling the first is all
    zeros (error 1)."""
    P = p1_prolongation(beam.space, beam.free)
    tg = multigrid.TwoGrid(beam.K, P)
    try:
        r = np.random.default_rng(9).standard_normal((beam.K.shape[0], 2))
        z = tg.apply(r)
        for s in (1.0, 2.0**-150, 2.0**120):
            zs = tg.apply_single(r * s) / s
            error = np.linalg.norm(zs - z, axis=0) / np.linalg.norm(z, axis=0)
            assert error.max() <= 1e-4, (s, error)
    finally:
        tg.release()


# also covered by test_solver_comparison.py (LOBPCG + two-grid vs dense eigh) and
# test_pipeline_under_multigrid_matches_the_factor_route: make test-all
@pytest.mark.slow
def test_multigrid_modes_match_the_factor_route(beam):
    """Frequencies and shapes of the factor-free solver against the shift-invert Lanczos
    route (module doc for the bounds)."""
    P = p1_prolongation(beam.space, beam.free)
    ref = solve_modes(beam.K, beam.M, COUNT, method="factor")
    mg = solve_modes(beam.K, beam.M, COUNT, method="multigrid", coarse=P)
    assert mg.stats["method"] == "multigrid-lobpcg"
    assert mg.backend.startswith("multigrid")
    assert min(mg.stats["history"]) <= eigen.MULTIGRID_TOLERANCE
    rel_gap = float(np.min(np.diff(ref.omega2) / ref.omega2[1:]))
    assert rel_gap > 1e-2
    bound = 2 * eigen.MULTIGRID_TOLERANCE ** 2 / rel_gap + 0.5 * eigenvalue_rtol(
        beam.K, beam.M)
    err = float(np.abs(mg.frequencies_hz / ref.frequencies_hz - 1).max())
    record_tolerance("multigrid frequencies vs Lanczos", err, bound)
    assert err <= bound
    # shapes: sign convention shared; energy-norm error ~ rho / gap
    shape_bound = 10 * eigen.MULTIGRID_TOLERANCE / rel_gap
    d = np.abs(mg.shapes - ref.shapes).max() / np.abs(ref.shapes).max()
    record_tolerance("multigrid shapes vs Lanczos", d, shape_bound)
    assert d <= shape_bound


def test_float32_cycle_preconditions_lobpcg_to_the_same_eigenpairs(beam):
    """LOBPCG preconditioned by the float32 cycle (what the solver uses) and by the
    double cycle reach the same target, and their eigenvalues agree within the bound of
    both (2 rho^2 / gap each, plus the Rayleigh quotients' round-off, eigenvalue_rtol):
    the preconditioner's precision only chooses directions.
    The float32 cycle hands back float64 blocks of the input's shape."""
    P = p1_prolongation(beam.space, beam.free)
    tg = multigrid.TwoGrid(beam.K, P)
    try:
        X0 = np.random.default_rng(4).standard_normal((beam.K.shape[0], 11))
        Z = tg.apply_single(X0[:, :3])
        assert Z.dtype == np.float64 and Z.shape == (beam.K.shape[0], 3)
        assert tg.apply_single(X0[:, 0]).shape == (beam.K.shape[0],)
        target = eigen.MULTIGRID_TOLERANCE
        double = lobpcg(beam.K, beam.M, X0, tg.apply, COUNT, target=target)
        single = lobpcg(beam.K, beam.M, X0, tg.apply_single, COUNT, target=target)
    finally:
        tg.release()
    assert double.converged and single.converged
    _assert_same_lobpcg_eigenvalues(beam, double, single, target,
                                    "float32 vs double cycle: LOBPCG eigenvalues")


def _assert_same_lobpcg_eigenvalues(beam, reference, other, target, name):
    """Two LOBPCG runs to the preconditioned residual ``target`` agree within the bound
    of both: 2 target^2 / relative gap each, plus the Rayleigh quotients' round-off."""
    w = reference.omega2[:COUNT]
    rel_gap = float(np.min(np.diff(w) / w[1:]))
    bound = 2 * 2 * target ** 2 / rel_gap + eigenvalue_rtol(beam.K, beam.M)
    err = float(np.abs(other.omega2[:COUNT] / w - 1).max())
    record_tolerance(name, err, bound)
    assert err <= bound


def test_static_solves_ride_along_in_lobpcg_sweeps(beam):
    """The static correction's conjugate gradients started by ``ride`` advance one
    iteration per LOBPCG sweep in the sweep's own cycle (``precondition``) and are
    finished by ``solve`` when it is asked for exactly those loads: the same recurrence
    (pcg.Pcg) with the same cycle, so the solution meets the same bounds as a PCG of
    its own (true residual PCG_RTOL + cond eps; the two differ by at most cond(K) times
    the sum of their residuals) and the eigenpairs are those of LOBPCG without riders
    (bound of test_float32_cycle_preconditions_lobpcg_to_the_same_eigenpairs). The
    riding solve is handed out once: other loads, or the same loads again, get a PCG of
    their own."""
    P = p1_prolongation(beam.space, beam.free)
    n = beam.K.shape[0]
    F = np.random.default_rng(12).standard_normal((n, 2))
    X0 = np.random.default_rng(4).standard_normal((n, 11))
    target = eigen.MULTIGRID_TOLERANCE
    tg = multigrid.TwoGrid(beam.K, P)
    try:
        alone = tg.solve(F)
        its_alone = tg.iterations
        plain = lobpcg(beam.K, beam.M, X0, tg.apply_single, COUNT, target=target)
        tg.ride(F)
        assert tg.solve(F[:, :1]).shape == (n, 1)  # other loads: not the riding solve
        riding = lobpcg(beam.K, beam.M, X0, tg.precondition, COUNT, target=target)
        rode = tg._riding[1].iterations
        X = tg.solve(np.asfortranarray(F))  # refined_solve hands F over in column order
        its = tg.iterations
        again = tg.solve(F)
        its_again = tg.iterations
    finally:
        tg.release()
    assert plain.converged and riding.converged
    assert rode == min(riding.sweeps + 1, its)  # one iteration per cycle
    assert its_again == its_alone and np.array_equal(again, alone)
    assert its <= its_alone + 2  # the same recurrence: the same count, to round-off
    residual = float((np.linalg.norm(F - beam.K @ X, axis=0)
                      / np.linalg.norm(F, axis=0)).max())
    res_bound = multigrid.PCG_RTOL + cond_eps(beam.K)
    record_tolerance("riding PCG true residual", residual, res_bound)
    assert residual <= res_bound
    bound = condition_number(beam.K) * 2 * res_bound
    err = float(np.linalg.norm(X - alone) / np.linalg.norm(alone))
    record_tolerance("riding PCG vs its own PCG", err, bound)
    assert err <= bound
    _assert_same_lobpcg_eigenvalues(beam, plain, riding, target,
                                    "LOBPCG with riding PCG: eigenvalues")


def test_static_loads_ride_only_where_lobpcg_keeps_its_layout(beam, monkeypatch):
    """solve_modes with ``loads`` and a kept solver rides them along (stats), and its
    kept solver returns the solution of those loads (true residual as a PCG of its
    own, test_static_solves_ride_along_in_lobpcg_sweeps); where memory would hold
    LOBPCG's whole layout but not the rider's 6 (n, k) blocks beside it, no rider."""
    from pipeline._util.resources import LOBPCG_BLOCKS

    P = p1_prolongation(beam.space, beam.free)
    n = beam.K.shape[0]
    F = np.random.default_rng(13).standard_normal((n, 2))
    modes = solve_modes(beam.K, beam.M, COUNT, method="multigrid", coarse=P, keep=True,
                        loads=F)
    try:
        assert modes.stats["riding_columns"] == 2
        X = modes.factorization.solve(F)
    finally:
        modes.release_factorization()
    residual = float((np.linalg.norm(F - beam.K @ X, axis=0)
                      / np.linalg.norm(F, axis=0)).max())
    assert residual <= multigrid.PCG_RTOL + cond_eps(beam.K)
    block = modes.stats["block"]
    monkeypatch.setattr(eigen, "_usable_bytes", lambda: 8.0 * n * LOBPCG_BLOCKS * block)
    tight = solve_modes(beam.K, beam.M, COUNT, method="multigrid", coarse=P, keep=True,
                        loads=F)
    tight.release_factorization()
    assert tight.stats["riding_columns"] == 0 and tight.stats["block"] == block


def test_lobpcg_converges_without_plateaus(beam):
    """With the two-grid cycle, every sweep cuts the worst preconditioned residual by at
    least 2 until it nears the target (measured: 4-8 per sweep). Without the column
    scaling of the SVQB step (lobpcg module doc), the short directions of nearly
    converged columns were lost and the lowest modes stalled for 2-4 sweeps: here 13
    sweeps with ratios of 1.0 at the plateaus, against 10 with the scaling."""
    P = p1_prolongation(beam.space, beam.free)
    tg = multigrid.TwoGrid(beam.K, P)
    try:
        X0 = np.random.default_rng(4).standard_normal((beam.K.shape[0], 11))
        target = eigen.MULTIGRID_TOLERANCE
        r = lobpcg(beam.K, beam.M, X0, tg.apply_single, COUNT, target=target)
    finally:
        tg.release()
    assert r.converged
    h = np.array(r.history)
    far = h[1:-1] > 10 * target  # sweep 0 is the random start block
    ratios = h[2:][far] / h[1:-1][far]
    assert ratios.size >= 4
    assert ratios.max() <= 0.5, ratios


def test_multigrid_free_body_finds_the_rigid_modes(free_beam):
    """A free body (shift < 0): six rigid-body modes at zero, then the elastic ones as the
    factor route gives them."""
    P = p1_prolongation(free_beam.space, free_beam.free)
    ref = solve_modes(free_beam.K, free_beam.M, 10, supported=False, method="factor")
    mg = solve_modes(free_beam.K, free_beam.M, 10, supported=False, method="multigrid",
                     coarse=P)
    assert mg.n_rigid == ref.n_rigid == 6
    el = slice(6, 10)
    rel_gap = float(np.min(np.diff(ref.omega2[el]) / ref.omega2[el][1:]))
    bound = 2 * eigen.MULTIGRID_TOLERANCE ** 2 / rel_gap + 0.5 * eigenvalue_rtol(
        free_beam.K, free_beam.M, n_zero=6)
    err = float(np.abs(mg.frequencies_hz[el] / ref.frequencies_hz[el] - 1).max())
    record_tolerance("multigrid free-body frequencies vs Lanczos", err, bound)
    assert err <= bound


def test_auto_takes_multigrid_only_when_no_factor_fits(beam, monkeypatch, caplog):
    """Below MULTIGRID_AUTO_DOFS, auto factorises whenever a factor fits."""
    assert beam.K.shape[0] < plan.MULTIGRID_AUTO_DOFS
    P = p1_prolongation(beam.space, beam.free)
    fits = solve_modes(beam.K, beam.M, COUNT, coarse=P, precision="auto")
    assert fits.stats["method"] == "block-lanczos"
    monkeypatch.setattr(eigen, "available_memory_bytes", lambda: 1)
    with caplog.at_level(logging.INFO):
        tight = solve_modes(beam.K, beam.M, COUNT, coarse=P, precision="auto")
    assert tight.stats["method"] == "multigrid-lobpcg"
    # without a coarse space (a P1 mesh) auto stays with a (float32) factor
    mixed = solve_modes(beam.K, beam.M, COUNT, precision="auto")
    assert mixed.stats["precision"] == "mixed"


def test_auto_tries_multigrid_from_its_size(beam, monkeypatch):
    """From MULTIGRID_AUTO_DOFS free DOFs (lowered here to the test beam's size) auto
    solves a compact body without a factor, to the bound of
    test_multigrid_modes_match_the_factor_route; an explicit mixed precision or
    tolerance (both defined for the factor path), or no coarse space, keep the factor."""
    P = p1_prolongation(beam.space, beam.free)
    ref = solve_modes(beam.K, beam.M, COUNT, method="factor")
    monkeypatch.setattr(plan, "MULTIGRID_AUTO_DOFS", beam.K.shape[0])
    auto = solve_modes(beam.K, beam.M, COUNT, coarse=P, precision="auto")
    assert auto.stats["method"] == "multigrid-lobpcg"
    assert "multigrid_trial" not in auto.stats
    rel_gap = float(np.min(np.diff(ref.omega2) / ref.omega2[1:]))
    bound = 2 * eigen.MULTIGRID_TOLERANCE ** 2 / rel_gap + 0.5 * eigenvalue_rtol(
        beam.K, beam.M)
    err = float(np.abs(auto.frequencies_hz / ref.frequencies_hz - 1).max())
    record_tolerance("auto (multigrid from its size) vs Lanczos", err, bound)
    assert err <= bound
    assert solve_modes(beam.K, beam.M, COUNT, coarse=P,
                       precision="mixed").stats["precision"] == "mixed"
    assert solve_modes(beam.K, beam.M, COUNT, coarse=P,
                       tolerance=1e-9).stats["method"] == "block-lanczos"
    assert solve_modes(beam.K, beam.M, COUNT).stats["method"] == "block-lanczos"


@pytest.fixture(scope="module")
def soft_beam(tmp_path_factory):
    """The test beam in a nearly incompressible material (nu = 0.499), where the P1
    coarse space locks: the two-grid cycle converges slowly (41 sweeps projected after 5,
    measured; 84 sweeps on the 100k-DOF cantilever, against 12 at nu = 0.33)."""
    return build_model(tmp_path_factory.mktemp("mgsoft"), length=0.3, height=0.02,
                       depth=0.03, size=0.008,
                       material=dataclasses.replace(ALUMINIUM, nu=0.499))


def test_auto_gives_a_slow_multigrid_trial_up_for_the_factor(soft_beam, monkeypatch,
                                                             caplog):
    """A slowly converging two-grid trial under auto is given up after a few sweeps, with
    a warning naming the cause, and the factor path's answer is returned unchanged (the
    trial recorded in the statistics); when no factor fits, there is nothing to fall back
    to and the trial is not given up."""
    b = soft_beam
    P = p1_prolongation(b.space, b.free)
    ref = solve_modes(b.K, b.M, COUNT, method="factor")
    monkeypatch.setattr(plan, "MULTIGRID_AUTO_DOFS", b.K.shape[0])
    # a clock that ticks once per reading: the seconds below count readings, so the
    # check on them says what the total covers, whatever the machine's speed or load
    ticks = itertools.count()
    with caplog.at_level(logging.WARNING), monkeypatch.context() as clock:
        clock.setattr(time, "perf_counter", lambda: float(next(ticks)))
        auto = solve_modes(b.K, b.M, COUNT, coarse=P)
    assert auto.stats["method"] == "block-lanczos"
    trial = auto.stats["multigrid_trial"]
    assert PROJECT_FROM <= trial["sweeps"] < plan.MULTIGRID_AUTO_SWEEPS
    assert trial["projected_sweeps"] > plan.MULTIGRID_AUTO_SWEEPS
    assert "converges slowly" in caplog.text and "factor instead" in caplog.text
    np.testing.assert_allclose(auto.omega2, ref.omega2, rtol=eigenvalue_rtol(b.K, b.M))
    assert auto.seconds > trial["seconds"] > 0  # the total covers the trial and the factor
    # nothing fits: no budget, the trial runs on (stopped here by a small sweep cap)
    monkeypatch.setattr(eigen, "available_memory_bytes", lambda: 1)
    monkeypatch.setattr(eigen, "MULTIGRID_MAX_SWEEPS", trial["sweeps"] + 2)
    with pytest.raises(eigen.SolverError, match="did not converge"):
        solve_modes(b.K, b.M, COUNT, coarse=P)


def test_lobpcg_gives_up_when_the_projection_exceeds_its_budget():
    """With a poor preconditioner (identity) on diag(1..n), LOBPCG converges slowly: a
    budget stops it at PROJECT_FROM sweeps, marked abandoned and not converged; the
    same run without a budget goes on."""
    n = 2000
    K = sp.diags(np.arange(1.0, n + 1) ** 2).tocsr()
    M = sp.identity(n, format="csr")
    X0 = np.random.default_rng(5).standard_normal((n, 6))
    quick = lobpcg(K, M, X0, lambda R: R, 4, target=1e-8, budget=5)
    assert quick.abandoned and not quick.converged
    assert quick.sweeps == PROJECT_FROM
    assert projected_sweeps(quick.history, 1e-8) > 5
    long = lobpcg(K, M, X0, lambda R: R, 4, target=1e-8, max_sweeps=PROJECT_FROM + 3)
    assert not long.abandoned and long.sweeps == PROJECT_FROM + 3


def test_lobpcg_on_a_diagonal_pencil():
    """LOBPCG with an exact preconditioner on diag(1..n): the lowest eigenvalues to
    round-off of the Rayleigh-Ritz step, whatever the start block."""
    n = 400
    K = sp.diags(np.arange(1.0, n + 1)).tocsr()
    M = sp.identity(n, format="csr")
    X0 = np.random.default_rng(2).standard_normal((n, 7))
    r = lobpcg(K, M, X0, lambda R: R / K.diagonal()[:, None], 5, target=1e-10)
    assert r.converged
    assert np.allclose(r.omega2[:5], np.arange(1.0, 6.0), rtol=1e-12)


def test_method_key_is_validated():
    raw = {"name": "b", "geometry": {"kind": "box", "length": 0.3, "height": 0.02,
                                     "depth": 0.03},
           "mesh": {"order": 2, "size": 0.01},
           "material": {"E": 69e9, "nu": 0.33, "rho": 2700.0},
           "supports": [{"region": "root"}]}
    assert config_from_dict(raw).modes.method == "auto"
    raw["modes"] = {"method": "multigrid"}
    assert config_from_dict(raw).modes.method == "multigrid"
    raw["modes"] = {"method": "amg"}
    with pytest.raises(ConfigError, match="modes.method"):
        config_from_dict(raw)
    raw["modes"] = {"method": "multigrid"}
    raw["mesh"] = {"order": 1, "size": 0.01}
    with pytest.raises(ConfigError, match="modes.method.*mesh.order: 2"):
        config_from_dict(raw)
    raw["mesh"] = {"order": 2, "size": 0.01}
    raw["modes"] = {"method": "multigrid", "precision": "mixed"}
    with pytest.raises(ConfigError, match="modes.precision"):
        config_from_dict(raw)


def test_memory_estimate_knows_the_factor_free_path(monkeypatch):
    """At 3M DOFs neither factor fits in 24 GB; the estimate of the auto path is that of
    the multigrid solver, which does."""
    from pipeline._util import resources

    monkeypatch.setattr(resources, "available_memory_bytes", lambda: 24e9)
    n_nodes = 1_000_000  # 3M DOFs
    factor = resources.eigensolve_bytes(n_nodes, 2, 20, "factor")
    auto = resources.eigensolve_bytes(n_nodes, 2, 20, "auto")
    assert factor > 0.9 * 24e9 > auto
    assert resources.eigensolve_bytes(n_nodes, 1, 20, "auto") == pytest.approx(
        resources.eigensolve_bytes(n_nodes, 1, 20, "factor"))
    # from MULTIGRID_AUTO_DOFS, auto tries the factor-free solver first (its fallback
    # factor is checked against PARDISO's exact size when it is needed)
    n_nodes = resources.MULTIGRID_AUTO_DOFS // 3 + 1
    assert resources.eigensolve_bytes(n_nodes, 2, 20, "auto") == pytest.approx(
        resources.eigensolve_bytes(n_nodes, 2, 20, "multigrid"))
    assert resources.eigensolve_bytes(n_nodes, 2, 20, "auto") < \
        resources.eigensolve_bytes(n_nodes, 2, 20, "factor")
    assert resources.eigensolve_bytes(n_nodes - 2, 2, 20, "auto") == pytest.approx(
        resources.eigensolve_bytes(n_nodes - 2, 2, 20, "factor"))


def test_pipeline_under_multigrid_matches_the_factor_route(tmp_path):
    """End to end with values the validator accepts: the cantilever under
    ``modes.method: multigrid`` and ``factor`` gives the same frequencies, reduced
    state-space and modal stresses (shape bound of the module doc), and the file says
    which solver and how converged."""
    import h5py

    from pipeline.config import load_config
    from pipeline.run import run_pipeline
    from conftest import ROOT

    out = {}
    variants = {"factor": ["modes.method=factor", "modes.precision=double"],
                "multigrid": ["modes.method=multigrid"],
                # mixed precision: the static correction by PCG with the float32 factor
                "mixed": ["modes.method=factor", "modes.precision=mixed"]}
    for name, overrides in variants.items():
        cfg = load_config(ROOT / "configs" / "cantilever.yaml", ["mesh.size=0.008"] + overrides)
        out[name] = run_pipeline(cfg, tmp_path / f"{name}.h5").output
    for name in ("multigrid", "mixed"):
        with h5py.File(out["factor"]) as a, h5py.File(out[name]) as b:
            fa, fb = a["modes/frequencies_hz"][()], b["modes/frequencies_hz"][()]
            assert np.abs(fb / fa - 1).max() <= 1e-9
            if name == "multigrid":
                assert "multigrid" in b["modes"].attrs["solver"]
                assert b["modes"].attrs["preconditioned_residual"] <= \
                    eigen.MULTIGRID_TOLERANCE
            assert "preconditioned_residual" not in a["modes"].attrs
            for key in ("statespace/A", "statespace/B", "statespace/C", "statespace/D",
                        "stress_modes/stress"):
                x, y = a[key][()], b[key][()]
                d = float(np.abs(x - y).max() / np.abs(x).max())
                record_tolerance(f"{name} pipeline {key}", d, 1e-4)
                assert d <= 1e-4, (name, key)
