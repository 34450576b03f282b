"""The solver comparison of issue 39 (benchmarks/bench_solvers.py) and the accuracy
measures of the bench (:mod:`pipeline.solve.accuracy`): correctness only (speed and
memory live in the bench).

Tolerances:
- the accuracy functions against direct dense computations of the same formula:
  round-off of a few products of O(n) terms, 1e-12 relative;
- subspace angles against scipy.linalg.subspace_angles (Euclidean) for an angle of
  1e-3, where its cosine-free formula is exact to ~1e-16 / 1e-3 relative: 1e-9;
- frequencies of every LOBPCG (ours, scipy's) with every preconditioner (two-grid,
  PyAMG smoothed aggregation) against dense eigh: for an M-normalised Ritz pair with
  residual r, |theta - lambda| <= ||r||^2_{M^-1} / gap (the gap between theta and the
  nearest other eigenvalue; Kato-Temple), computed from the pair's own residual, plus
  the round-off of the two routes (conftest.eigenvalue_rtol); and the bound itself must
  be small (<= 1e-8 relative): a solver that stopped early fails.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from conftest import build_model, eigenvalue_rtol
from pipeline.fe.coarse import p1_prolongation
from pipeline.solve import accuracy

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

COUNT = 6


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    model = build_model(tmp_path_factory.mktemp("cmp"), length=0.3, height=0.02, depth=0.03,
                        size=0.015)  # 2.8k DOFs: dense eigh in a second
    Kd, Md = model.K.toarray(), model.M.toarray()
    w = la.eigh(Kd, Md, eigvals_only=True, subset_by_index=[0, COUNT])
    return model, w


def test_relative_residuals_equal_the_direct_formula(beam):
    model, _ = beam
    K, M = model.K, model.M
    rng = np.random.default_rng(1)
    X = rng.standard_normal((K.shape[0], 3))
    w = np.array([1e3, 2e5, 7e6])
    Kd, Md = K.toarray(), M.toarray()
    direct = np.array([np.linalg.norm(Kd @ X[:, k] - w[k] * Md @ X[:, k])
                       / np.linalg.norm(Kd @ X[:, k]) for k in range(3)])
    assert np.allclose(accuracy.relative_residuals(K, M, X, w), direct, rtol=1e-12, atol=0)
    inf = lambda A: np.abs(A).sum(axis=1).max()  # noqa: E731
    backward = np.array([np.abs(Kd @ X[:, k] - w[k] * Md @ X[:, k]).max()
                         / ((inf(Kd) + w[k] * inf(Md)) * np.abs(X[:, k]).max())
                         for k in range(3)])
    assert np.allclose(accuracy.backward_errors(K, M, X, w), backward, rtol=1e-12, atol=0)


def test_subspace_angle_matches_scipy_and_the_m_inner_product(beam):
    model, _ = beam
    rng = np.random.default_rng(2)
    n = model.K.shape[0]
    X = rng.standard_normal((n, 4))
    Y = X + 1e-3 * np.linalg.norm(X, axis=0) / np.sqrt(n) * rng.standard_normal((n, 4))
    assert np.isclose(accuracy.largest_subspace_angle(X, Y),
                      la.subspace_angles(X, Y).max(), rtol=1e-9, atol=0)
    # in the M inner product: the Euclidean angle of L^T X, L^T Y (M = L L^T)
    L = la.cholesky(model.M.toarray(), lower=True)
    assert np.isclose(accuracy.largest_subspace_angle(X, Y, model.M),
                      la.subspace_angles(L.T @ X, L.T @ Y).max(), rtol=1e-9, atol=0)
    assert accuracy.largest_subspace_angle(X, X @ rng.standard_normal((4, 4))) < 1e-7


def _preconditioned(beam, precond: str):
    """(the bench module, the model, P, apply) for ``precond`` (two-grid or sa; sa skips
    without PyAMG)."""
    if precond == "sa":
        pytest.importorskip("pyamg")
    import bench_solvers

    model = beam[0]
    P = p1_prolongation(model.space, model.free)
    apply, _, _ = bench_solvers._preconditioner(precond, model.K, P, model.free,
                                                model.space.node_points)
    return bench_solvers, model, P, apply


@pytest.mark.parametrize("solver", ["ours", "scipy"])
@pytest.mark.parametrize("precond", ["two-grid", "sa"])
def test_every_lobpcg_and_preconditioner_give_the_dense_frequencies(beam, solver, precond):
    from pipeline.solve.lobpcg import lobpcg

    bench_solvers, model, P, apply = _preconditioned(beam, precond)
    w_dense = beam[1]
    K, M = model.K, model.M
    X0 = bench_solvers._start_block(K, M, P, COUNT + 3)
    if solver == "ours":
        res = lobpcg(K, M, X0, apply, COUNT, target=1e-7)
        assert res.converged
        w, X = res.omega2[:COUNT], res.X[:, :COUNT]
    else:
        n = K.shape[0]
        T = sla.LinearOperator((n, n), matvec=apply, matmat=apply, dtype=np.float64)
        tol = 1e-6 * w_dense[0] * np.linalg.norm(M @ X0[:, 0]) / np.sqrt(
            X0[:, 0] @ (M @ X0[:, 0]))
        w, X = sla.lobpcg(K, X0, B=M, M=T, tol=tol, maxiter=200, largest=False)
        order = np.argsort(w)[:COUNT]
        w, X = w[order], X[:, order]
    X = X / np.sqrt(np.einsum("ij,ij->j", X, M @ X))
    R = K @ X - (M @ X) * w
    r2 = np.einsum("ij,ij->j", R, sp.linalg.splu(M.tocsc()).solve(R))  # ||r||^2_{M^-1}
    gaps = np.array([np.delete(np.abs(w_dense - w_dense[k]), k).min() for k in range(COUNT)])
    bound = r2 / gaps / w_dense[:COUNT]
    assert bound.max() <= 1e-8, bound
    rtol = bound + eigenvalue_rtol(K, M)
    assert np.all(np.abs(w / w_dense[:COUNT] - 1) <= rtol), (w / w_dense[:COUNT] - 1, rtol)


@pytest.mark.parametrize("precond", ["two-grid", "sa"])
def test_pcg_with_either_preconditioner_solves_the_static_problem(beam, precond):
    """Static solves to 1e-10 with ours PCG: the answer equals a direct solve within
    1e-10 cond(K) (the recursive residual's bound) plus round-off."""
    from conftest import cond_eps, condition_number
    from pipeline.solve.pcg import pcg

    bench_solvers, model, _, apply = _preconditioned(beam, precond)
    K, M = model.K, model.M
    F = M @ bench_solvers.rigid_body_modes(model.space.node_points, model.free)[:, :4]
    X, _ = pcg(K, F, apply, rtol=1e-10)
    exact = sla.spsolve(K.tocsc(), F)
    cond = condition_number(K)
    err = np.abs(X - exact).max(axis=0) / np.abs(exact).max(axis=0)
    assert np.all(err <= 10 * 1e-10 * cond + 2 * cond_eps(K)), err


def test_rigid_body_modes_are_the_null_space_of_the_free_stiffness(tmp_path):
    """K (no supports) times each of the six rigid-body modes vanishes to round-off."""
    import bench_solvers

    model = build_model(tmp_path, length=0.1, height=0.02, depth=0.02, size=0.01,
                        supports=())
    B = bench_solvers.rigid_body_modes(model.space.node_points, model.free)
    KB = model.K @ B
    scale = abs(model.K).max() * np.abs(B).max(axis=0)
    assert np.all(np.abs(KB).max(axis=0) <= 1e-12 * scale * model.K.shape[0] ** 0.5)
