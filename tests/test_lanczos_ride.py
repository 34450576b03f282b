"""Solves that ride along in block Lanczos' first passes over the factor
(pipeline.solve.eigen._run_factor, _lanczos_modes) and PARDISO's remembered solves.

The tolerances: a ridden solve is a forward and a backward substitution with the same
factor as a direct one, so both are backward stable and their difference is bounded by
c eps cond(K) ||x|| (conftest.cond_eps); the modes with and without riders come from
the same Krylov steps, so the frequencies agree to the Lanczos tolerance squared, far
below 1e-10 relative."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.linalg import eigh

from conftest import build_model, cond_eps
from pipeline.errors import SolverError
from pipeline.solve import factorization as solvers
from pipeline.solve.eigen import _lanczos_modes, solve_modes

pytestmark = pytest.mark.skipif("pardiso" not in solvers.available_backends(),
                                reason="riding needs PARDISO's half-solves")


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    """A clamped P2 beam of about 3k free DOFs."""
    return build_model(tmp_path_factory.mktemp("ride"), length=0.1, height=0.02,
                       depth=0.03, size=0.01)


def test_ridden_solves_equal_direct_ones_and_leave_the_modes_alone(beam):
    K, M = beam.K, beam.M
    n = K.shape[0]
    B = np.random.default_rng(5).standard_normal((2, n))
    fact = solvers.factorize(K, "pardiso")
    try:
        X = np.empty_like(B)
        v_ride, _ = _lanczos_modes(fact, M, 8, 0.0, 4, None, None, (B, X))
        v_plain, _ = _lanczos_modes(fact, M, 8, 0.0, 4, None, None)
        direct = fact.solve(B.T).T
        bound = 2 * cond_eps(K) * np.abs(direct).max()
        assert np.abs(X - direct).max() <= bound
        # the remembered columns come back without a solve of their own, others solve
        fact.remember(B.T, X.T)
        assert np.array_equal(fact.solve(B[1]), X[1])
        assert np.array_equal(fact.solve(B[::-1].T), X[::-1].T)
        other = B[0] + 1.0
        assert np.abs(K @ fact.solve(other) - other).max() <= 1e-8 * np.abs(other).max()
    finally:
        fact.release()

    def omega2(v):  # the Rayleigh-Ritz values of span(v)
        return eigh(v.T @ (K @ v), v.T @ (M @ v), eigvals_only=True)

    assert np.allclose(omega2(v_ride), omega2(v_plain), rtol=1e-10, atol=0)


def test_the_static_loads_and_the_check_ride_along_on_the_kept_factor(beam, monkeypatch):
    """solve_modes with ``loads`` and ``keep``: the kept factor solves K X = loads and the
    singularity check's probe from memory (no pass over the factor of their own)."""
    from pipeline.solve.backends import pardiso

    K, M = beam.K, beam.M
    loads = np.zeros((K.shape[0], 1))
    loads[-3:, 0] = 1.0
    passes = []
    apply = pardiso.PardisoFactorization._apply
    monkeypatch.setattr(pardiso.PardisoFactorization, "_apply",
                        lambda self, phase, b: passes.append(phase) or apply(self, phase, b))
    modes = solve_modes(K, M, 6, backend="pardiso", keep=True, loads=loads)
    try:
        assert passes == []  # the check's solve came from memory
        X = modes.solve(np.asfortranarray(loads))
        assert passes == []
        assert np.abs(K @ X - loads).max() <= 1e-10 * np.abs(loads).max()
    finally:
        modes.release_factorization()


def test_a_singular_stiffness_is_still_reported_as_such(beam):
    """A body held at one point only (K singular): the check after Lanczos refuses it."""
    K, M = beam.K_full, beam.M_full
    n = K.shape[0]
    keep = np.arange(3, n)  # one node held: rigid rotations remain
    Ks, Ms = K[keep][:, keep].tocsr(), M[keep][:, keep].tocsr()
    with pytest.raises(SolverError, match="singular to working precision"):
        solve_modes(sp.csr_matrix(Ks), Ms, 6, backend="pardiso", keep=False)
