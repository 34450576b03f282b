"""Physics thresholds the solvers and the reduction share: the stiffness scale of a mesh,
when a matrix is singular to working precision, and when a mode is a rigid-body mode.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from pipeline._util.sparse import csr_diagonal

#: A matrix whose estimated condition number times eps exceeds this is singular to
#: working precision: its solutions may be wrong by 100 % in the direction of the
#: (near-)null space, however small the residual.
SINGULAR_COND_EPS = 1e-2


def stiffness_scale(K: sp.spmatrix, M: sp.spmatrix) -> float:
    """The stiffness scale of the mesh (rad^2/s^2): the median diagonal ratio K_ii / M_ii,
    the squared frequency of a typical element (as :func:`pipeline.solve.eigen.default_shift`
    uses). Median, not max: a Cholesky/LDL^T solve is insensitive to symmetric diagonal
    scaling (van der Sluis), so a few stiff sliver elements (a 0.5 mm strip meshed at 5 mm
    has max/median ~1e2) do not make K harder to solve. With the lowest eigenvalue
    lambda_1 it estimates the condition number that governs solves with K."""
    d_k = np.abs(csr_diagonal(K))
    d_m = np.abs(csr_diagonal(M))
    ok = d_m > 0
    return float(np.median(d_k[ok] / d_m[ok])) if ok.any() else float(d_k.max(initial=0.0))


def rigid_omega2_threshold(scale: float) -> float:
    """omega^2 (rad^2/s^2) below which a mode of a body with stiffness scale ``scale`` (see
    :func:`stiffness_scale`) is a rigid-body mode: zero to round-off, 100 eps of the scale.
    Relative, so a soft body (E = 500 Pa, f1 = 0.007 Hz) or a 0.2 mm strip keeps its
    elastic modes elastic (a supported K that is singular was refused by the
    factorisation check already), while the eigenvalues of a free body's rigid modes
    (set to 0 by the eigensolver, round-off ~eps scale otherwise) stay below it."""
    return float(scale) * 100.0 * np.finfo(float).eps
