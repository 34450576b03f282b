"""Sparse-matrix helpers that every layer may use (the FE stage, the solvers and the
file readers' physics checks): no FE stack, only numpy and scipy.
"""

from __future__ import annotations

import threading

import numpy as np
import scipy.sparse as sp

from pipeline._util.resources import usable_cores

__all__ = ["DIAGONAL_HALVES_ROWS", "csr_diagonal"]

#: rows from which :func:`csr_diagonal` scans two row halves side by side
DIAGONAL_HALVES_ROWS = 200_000


def csr_diagonal(A: sp.spmatrix, threads: int | None = None) -> np.ndarray:
    """(n,) the main diagonal of the square sparse matrix A, as ``A.diagonal()``: the same
    values (per row, the sum of its entries in the diagonal column), for a float CSR
    matrix of :data:`DIAGONAL_HALVES_ROWS` rows or more by scipy's own scan run on two
    row halves side by side (the scan releases the GIL). K at 999k DOFs (80M entries,
    Intel Xeon 2 cores): 0.11-0.13 s against 0.21 s, where a run takes the diagonals of
    K and M six times. ``threads``: cores to use (default: the usable ones).

    >>> csr_diagonal(sp.csr_matrix([[2.0, 1.0], [1.0, 3.0]]))
    array([2., 3.])
    """
    n = A.shape[0]
    threads = usable_cores() if threads is None else threads
    if (getattr(A, "format", None) != "csr" or n != A.shape[1] or n < DIAGONAL_HALVES_ROWS
            or threads < 2 or A.dtype not in (np.float64, np.float32)):
        return A.diagonal()
    try:
        from scipy.sparse._sparsetools import csr_diagonal as scan
    except ImportError:  # private scipy API changed: one scan
        return A.diagonal()
    out = np.empty(n, dtype=A.dtype)
    failed: list[BaseException] = []

    def half(lo: int, hi: int) -> None:
        # rows lo:hi as a matrix whose diagonal starts at column lo (scipy's offset k);
        # indptr's values index the whole index and value arrays
        try:
            scan(lo, hi - lo, A.shape[1], A.indptr[lo:], A.indices, A.data, out[lo:hi])
        except BaseException as exc:  # raised by the caller's thread below
            failed.append(exc)

    h = n // 2
    worker = threading.Thread(target=half, args=(h, n), name="pipeline-diagonal")
    worker.start()
    half(0, h)
    worker.join()
    if failed:
        raise failed[0]
    return out
