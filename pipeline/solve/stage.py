"""The modes stage of the pipeline: the lowest modes of the supported (or free) body,
their shapes on every mesh point and their labels.

Inputs are plain arrays and sparse matrices (no finite-element objects): K, M
(n_free x n_free, N/m and kg) on the free DOFs, the free DOF indices into the
3 * n_points DOFs of the body (DOF 3*p+c is component c of point p), the point
coordinates (n_points, 3) m and optional positive point weights for the labels.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import numpy as np
import scipy.sparse as sp

from pipeline.solve.eigen import solve_modes
from pipeline.solve.labels import label_modes
from pipeline.solve.modes import Modes

log = logging.getLogger(__name__)


def full_shapes(shapes: np.ndarray, free: np.ndarray, n_points: int) -> np.ndarray:
    """(n_points, 3, n_m) shapes from (n_free, n_m) ones, zero on the fixed DOFs."""
    full = np.zeros((3 * n_points, shapes.shape[1]))
    full[free] = shapes
    return full.reshape(n_points, 3, -1)


def compute_modes(K: sp.spmatrix, M: sp.spmatrix, count: int, free: np.ndarray,
                  node_points: np.ndarray, node_weights: np.ndarray | None = None, *,
                  supported: bool = True, backend: str = "auto", tolerance: float = 0.0,
                  progress: Callable[[int], None] | None = None, keep: bool = True,
                  precision: str = "double", method: str = "auto",
                  coarse: sp.spmatrix | None = None, analysis=None) -> Modes:
    """The ``count`` lowest modes of (K, M) with ``shapes_full`` and ``labels`` filled in.

    ``keep``: keep the factorisation of K in the result (supported bodies solved by
    factorisation), see :class:`pipeline.solve.modes.Modes` for who frees it.
    ``method``, ``coarse`` (the prolongation from a coarse space onto the free DOFs) and
    ``analysis``: see :func:`pipeline.solve.eigen.solve_modes`.
    """
    modes = solve_modes(K, M, count, supported=supported, backend=backend,
                        tolerance=tolerance, progress=progress, keep=keep,
                        precision=precision, method=method, coarse=coarse,
                        analysis=analysis)
    try:
        shapes = full_shapes(modes.shapes, free, node_points.shape[0])
        labels = label_modes(node_points, shapes, modes.n_rigid, node_weights)
    except BaseException:
        modes.release_factorization()
        raise
    for f, lab in zip(modes.frequencies_hz, labels):
        log.info("mode %-14s %12.4f Hz", lab, f)
    return dataclasses.replace(modes, shapes_full=shapes, labels=tuple(labels))
