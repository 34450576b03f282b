"""Solvers: sparse factorisations behind one protocol, and the eigensolver of the modes
stage.

- :mod:`~pipeline.solve.factorization`: the
  :class:`~pipeline.solve.factorization.Factorization` protocol and the backend
  registry (``factorize``, ``register_backend``, ``available_backends``);
- :mod:`~pipeline.solve.backends`: one module per backend (PARDISO, SuperLU, CHOLMOD,
  cuDSS), each ending in its registry line;
- :mod:`~pipeline.solve.mkl`: finding MKL, its interface check and scoped threads;
  :mod:`~pipeline.solve.blas`: the products the solvers share;
- :mod:`~pipeline.solve.refine` (refined solves, backward errors) and
  :mod:`~pipeline.solve.thresholds` (stiffness scale, rigid-mode and singularity bounds);
- :mod:`~pipeline.solve.plan` (pure: which eigensolver) and :mod:`~pipeline.solve.eigen`
  (executes the plan: Lanczos, ARPACK, LOBPCG, Rayleigh-Ritz), :mod:`~pipeline.solve.stage`
  (the modes stage with labels).

The whole flow on a spring chain (K = tridiag(-1, 2, -1) * 1e4 N/m, unit masses):

>>> import numpy as np, scipy.sparse as sp
>>> from pipeline.solve.factorization import factorize
>>> from pipeline.solve.eigen import solve_modes
>>> n = 800
>>> K = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n), format="csr") * 1e4
>>> with factorize(K, "superlu") as fact:
...     bool(np.allclose(K @ fact.solve(np.ones(n)), 1.0))
True
>>> modes = solve_modes(K, sp.identity(n, format="csr"), 3, backend="superlu")
>>> exact = 2e4 * (1 - np.cos(np.arange(1, 4) * np.pi / (n + 1)))
>>> bool(np.allclose(modes.omega2, exact, rtol=1e-8)), modes.stats["method"]
(True, 'arpack')
"""

# the built-in factorisation backends register themselves with pipeline.solve.factorization
from pipeline.solve import backends  # noqa: E402,F401
