"""Row partition of the free DOFs over the ranks: contiguous slabs along the body's
longest extent.

The free DOFs are renumbered for PETSc: sorted by the coordinate of their mesh point
along the longest extent (stable, so a point's three DOFs stay together and in order),
then split into ``size`` ranges of (nearly) equal length. Rank r owns PETSc rows
``starts[r]:starts[r + 1]``; ``order[i]`` is the free-DOF index of PETSc row i. A slab
touches at most two neighbours, so the off-rank columns of a rank's rows are the
nodes of one element layer per neighbour (a graph partitioner such as ParMETIS would
cut less for a compact body; not used yet).

>>> import numpy as np
>>> points = np.array([[3.0, 0, 0], [0.0, 0, 0], [2.0, 0, 0], [1.0, 0, 0]])
>>> part = slab_partition(points, np.arange(12), 2)
>>> part.order.tolist()
[3, 4, 5, 9, 10, 11, 6, 7, 8, 0, 1, 2]
>>> part.starts.tolist()
[0, 6, 12]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RowPartition:
    """order: (n_free,) free-DOF index of each PETSc row; starts: (size + 1,) first row
    of each rank (starts[-1] = n_free); rank_of_row is implied by starts."""

    order: np.ndarray
    starts: np.ndarray

    def rows(self, rank: int) -> tuple[int, int]:
        """[lo, hi): the PETSc rows rank ``rank`` owns."""
        return int(self.starts[rank]), int(self.starts[rank + 1])

    def owned_free(self, rank: int) -> np.ndarray:
        """Free-DOF indices of the rows rank ``rank`` owns, in PETSc order."""
        lo, hi = self.rows(rank)
        return self.order[lo:hi]


def slab_partition(node_points: np.ndarray, free: np.ndarray, size: int) -> RowPartition:
    """The slab partition of the sorted ``free`` DOFs (DOF 3 p + c of point p) of a body
    with (n_points, 3) ``node_points`` over ``size`` ranks."""
    points = np.asarray(node_points, dtype=float)
    axis = int(np.argmax(np.ptp(points, axis=0))) if points.shape[0] else 0
    key = points[np.asarray(free) // 3, axis]
    order = np.argsort(key, kind="stable").astype(np.int64)
    n = order.size
    free = np.asarray(free)
    # whole points (every point's three DOFs free) stay on one rank: PETSc's rigid-body
    # near-null space needs a point's coordinates on the rank of its rows
    step = 3 if n % 3 == 0 and np.array_equal(free[order] % 3, np.tile(np.arange(3), n // 3)) \
        else 1
    starts = np.array([step * (((n // step) * r) // size) for r in range(size + 1)],
                      dtype=np.int64)
    return RowPartition(order=order, starts=starts)
