"""The factorisation seam: a backend registered from outside works end to end, and MKL's
thread setting is scoped to the library's calls."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from pipeline.solve import factorization, mkl
from pipeline.solve.blas import is_csr, sparse_times_dense
from pipeline.solve.eigen import solve_modes


class DenseCholesky(factorization.Factorization):
    """A test backend: numpy's Cholesky A = L L^T, with half-solves."""

    backend = "dense-test"
    capabilities = factorization.Capabilities(half_solves=True)

    def __init__(self, A):
        super().__init__(A.shape[0], info={"format": "dense", "factor_nnz": A.shape[0] ** 2,
                                           "factor_bytes": 8 * A.shape[0] ** 2})
        self.L = np.linalg.cholesky(A.toarray())

    def solve(self, b):
        return self.backward(self.forward(b))

    def forward(self, b):
        from scipy.linalg import solve_triangular

        return solve_triangular(self.L, b, lower=True)

    def backward(self, y):
        from scipy.linalg import solve_triangular

        return solve_triangular(self.L.T, y, lower=False)


@pytest.fixture
def registered(monkeypatch):
    factorization.available_backends()  # the built-in ones first
    made = []

    def factor(A, **options):
        made.append(options)
        return DenseCholesky(A)

    monkeypatch.setitem(factorization._REGISTRY, "dense-test", factorization.Backend(
        name="dense-test", factor=factor, installed=lambda: True,
        capabilities=DenseCholesky.capabilities))
    return made


def _chain(n):
    K = sp.diags([np.full(n - 1, -1.0), np.full(n, 2.0), np.full(n - 1, -1.0)], [-1, 0, 1],
                 format="csr") * 1e4
    return K, sp.identity(n, format="csr")


def test_a_registered_backend_is_reached_by_name_end_to_end(registered):
    K, M = _chain(700)
    assert "dense-test" in factorization.available_backends()
    fact = factorization.factorize(K, "dense-test")  # with the singularity check
    assert isinstance(fact, DenseCholesky) and fact.memory_bytes == 8 * 700 ** 2
    assert fact.flops > 0
    np.testing.assert_allclose(K @ fact.solve(np.ones(700)), 1.0, rtol=1e-9)
    rows = fact.solve_rows(np.ones((3, 700)))  # the protocol's default block form
    assert rows.shape == (3, 700) and rows.flags.c_contiguous
    out = np.empty((3, 700))
    assert fact.solve_rows(np.ones((3, 700)), out=out) is out
    np.testing.assert_array_equal(out, rows)
    modes = solve_modes(K, M, 4, backend="dense-test")  # Lanczos on its half-solves
    exact = 2e4 * (1 - np.cos(np.arange(1, 5) * np.pi / 701))
    np.testing.assert_allclose(modes.omega2, exact, rtol=1e-9)
    assert modes.stats["method"] == "block-lanczos" and modes.backend == "dense-test"
    assert registered and not registered[0]["single"]


def test_an_unknown_backend_names_the_installed_ones(registered):
    with pytest.raises(Exception, match="installed backends: auto, .*dense-test"):
        factorization.resolve_backend("nowhere")


def test_csr_arrays_take_the_same_path_as_csr_matrices():
    K, _ = _chain(50)
    A = sp.csr_array(K)
    assert is_csr(A) and is_csr(K) and not is_csr(K.tocoo())
    X = np.ones((50, 3))
    np.testing.assert_allclose(sparse_times_dense(A, X), K @ X)


@pytest.mark.skipif(mkl.mkl_library() is None, reason="MKL is not installed (the 'fast' extra)")
def test_mkl_threads_are_the_same_before_and_after_a_factorisation(monkeypatch):
    """The host's own MKL setting (one thread here) survives a factorisation, its solves
    and a sparse product: the library scopes its thread count to its calls."""
    import ctypes

    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    lib = mkl.mkl_library()
    K, _ = _chain(2000)
    host = mkl.max_threads()
    lib.MKL_Set_Num_Threads(ctypes.c_int(1))  # the host process's choice
    try:
        with mkl.threads(2):
            assert mkl.max_threads() == 2
        assert mkl.max_threads() == 1
        fact = factorization.factorize(K, "pardiso")
        fact.solve(np.ones(2000))
        fact.release()
        sparse_times_dense(K, np.ones((2000, 4)))
        assert mkl.max_threads() == 1
    finally:
        lib.MKL_Set_Num_Threads(ctypes.c_int(host))
    assert mkl.interface_is_lp64(lib)


def test_factorising_leaves_the_environment_alone():
    """Loading MKL and factorising write nothing into os.environ (KMP_BLOCKTIME is the
    command-line entry point's to set, in its own process)."""
    import os
    import subprocess
    import sys

    code = ("import os, numpy as np, scipy.sparse as sp\n"
            "import pipeline\n"
            "before = dict(os.environ)\n"
            "from pipeline.solve.factorization import factorize\n"
            "K = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(500, 500), format='csr')\n"
            "factorize(K).solve(np.ones(500))\n"
            "assert dict(os.environ) == before, set(os.environ) ^ set(before)\n")
    env = {k: v for k, v in os.environ.items() if k != "KMP_BLOCKTIME"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=120)


def test_an_ilp64_mkl_is_recognised_and_refused():
    """Our ctypes signatures pass 32-bit integers: a runtime that reports the ILP64 layer
    (or cannot say) is not LP64."""
    class Layer:
        def __init__(self, value):
            self.value = value

        def __call__(self, requested):
            return self.value

    class FakeMKL:
        def __init__(self, value):
            self.MKL_Set_Interface_Layer = Layer(value)

    assert mkl.interface_is_lp64(FakeMKL(mkl.INTERFACE_LP64))
    assert not mkl.interface_is_lp64(FakeMKL(mkl.INTERFACE_ILP64))
    assert not mkl.interface_is_lp64(object())
