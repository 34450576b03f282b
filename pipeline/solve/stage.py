"""The modes stage of the pipeline: the lowest modes of the supported (or free) body,
their shapes on every mesh point and their labels.

The stage is a function of two frozen records: :class:`ModesInput` (what it needs from
the FE stage's :class:`~pipeline.fe.model.FEModel`: plain arrays and sparse matrices, no
finite-element objects) and the config's :class:`~pipeline.config.schema.ModesConfig`;
it returns :class:`~pipeline.solve.modes.Modes`. DOF 3*p+c is component c of mesh point
p throughout.

Four points along x, point 0 clamped, its 9 free DOFs a spring chain (K =
tridiag(-1, 2, -1) * 1e4 N/m, unit masses):

>>> import numpy as np, scipy.sparse as sp
>>> from pipeline.config.schema import ModesConfig
>>> n = 9
>>> K = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n), format="csr") * 1e4
>>> body = ModesInput(K=K, M=sp.identity(n, format="csr"), free=np.arange(3, 12),
...                   node_points=np.c_[np.arange(4.0), np.zeros(4), np.zeros(4)])
>>> modes = compute_modes(body, ModesConfig(count=2, solver="superlu"), keep=False)
>>> modes.shapes_full.shape, len(modes.labels)
((4, 3, 2), 2)
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp

from pipeline.config.schema import ModesConfig
from pipeline.fe.body import node_volume_weights
from pipeline.fe.coarse import p1_prolongation
from pipeline.fe.model import FEModel
from pipeline.solve.eigen import factor_expected, solve_modes
from pipeline.solve.labels import label_modes
from pipeline.solve.modes import Modes

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ModesInput:
    """What the modes stage needs from the FE stage.

    K, M: (n_free, n_free) stiffness (N/m) and mass (kg) on the free DOFs.
    free: (n_free,) sorted free DOF indices into the 3 * n_points DOFs of the body.
    node_points: (n_points, 3) point coordinates, m.
    node_weights: (n_points,) positive point weights for the labels (m^3: the volume
    each point stands for), or None (equal weights).
    supported: False for a free body (the eigensolver then shifts below the rigid modes).
    coarse: (n_free, n_coarse) prolongation from a coarse space onto the free DOFs
    (:func:`pipeline.fe.coarse.p1_prolongation`), which the multigrid solver needs, or
    None.
    """

    K: sp.spmatrix
    M: sp.spmatrix
    free: np.ndarray
    node_points: np.ndarray
    node_weights: np.ndarray | None = None
    supported: bool = True
    coarse: sp.spmatrix | None = None

    @classmethod
    def from_fe(cls, fe: FEModel, config: ModesConfig, *, supported: bool) -> ModesInput:
        """The input of the modes stage for ``fe``: the volume weights of its points and,
        unless ``config.method`` is ``factor``, the P1 prolongation of a P2 space.

        ``supported``: whether the config names supports (``bool(cfg.supports)``).
        Hold the record no longer than the call it is built for: it keeps K alive.
        """
        return cls(K=fe.K, M=fe.M, free=fe.free, node_points=fe.space.node_points,
                   node_weights=node_volume_weights(fe.space), supported=supported,
                   coarse=None if config.method == "factor"
                   else p1_prolongation(fe.space, fe.free))


def expects_factor(n_free: int, config: ModesConfig, *, supported: bool) -> bool:
    """Whether :func:`compute_modes` will factorise K itself with PARDISO at shift 0 for
    ``n_free`` free DOFs under ``config`` (:func:`pipeline.solve.eigen.factor_expected`),
    so that a :class:`~pipeline.solve.backends.pardiso.PatternAnalysis` of K's pattern
    started during the assembly will be used."""
    return factor_expected(n_free, config.count, supported=supported, backend=config.solver,
                           method=config.method, precision=config.precision)


def full_shapes(shapes: np.ndarray, free: np.ndarray, n_points: int) -> np.ndarray:
    """(n_points, 3, n_m) shapes from (n_free, n_m) ones, zero on the fixed DOFs."""
    full = np.zeros((3 * n_points, shapes.shape[1]))
    full[free] = shapes
    return full.reshape(n_points, 3, -1)


def compute_modes(body: ModesInput, config: ModesConfig, *, keep: bool = True,
                  progress: Callable[[int], None] | None = None,
                  analysis=None) -> Modes:
    """The ``config.count`` lowest modes of (``body.K``, ``body.M``) with ``shapes_full``
    ((n_points, 3, n_m), zero on the fixed DOFs) and ``labels`` filled in.

    ``config`` picks the factorisation (``solver``), ``method``, ``precision`` and
    ``tolerance`` (see :func:`pipeline.solve.eigen.solve_modes`). The run-time handles:
    ``keep``: keep the factorisation of K in the result (supported bodies solved by
    factorisation), see :class:`pipeline.solve.modes.Modes` for who frees it;
    ``progress``, if given, is called with the number of right-hand sides of every solve;
    ``analysis``: a :class:`~pipeline.solve.backends.pardiso.PatternAnalysis` of K's
    pattern started during the assembly, or None.
    """
    modes = solve_modes(body.K, body.M, config.count, supported=body.supported,
                        backend=config.solver, tolerance=config.tolerance,
                        progress=progress, keep=keep, precision=config.precision,
                        method=config.method, coarse=body.coarse, analysis=analysis)
    try:
        shapes = full_shapes(modes.shapes, body.free, body.node_points.shape[0])
        labels = label_modes(body.node_points, shapes, modes.n_rigid, body.node_weights)
    except BaseException:
        modes.release_factorization()
        raise
    for f, lab in zip(modes.frequencies_hz, labels):
        log.info("mode %-14s %12.4f Hz", lab, f)
    return dataclasses.replace(modes, shapes_full=shapes, labels=tuple(labels))
