"""Tall blocks whose rows stay on their ranks, and the file datasets made from them.

:class:`RowBlock` is an (n_free, k) block (mode shapes, static shapes, a reduced basis)
of which rank r holds only the PETSc rows ``lo:hi`` it owns (``local``: (hi - lo, k)).
What the reduce stage needs from such blocks is small and made collectively:

    X^T Y = sum_r X_r^T Y_r                       (k, l): MPI_Allreduce
    T X   = sum_r T[:, rows_r] X_r                (n_y, k): a sparse T of a few rows
    A X   (A = K or M)                            PETSc's MatMatMult of the whole block
    X Q   (Q small, replicated)                   rows stay where they are

:class:`PointBlocks` turns per-rank rows into one dataset of the file,
(n_points, ...), written by rank 0 a block of ``BLOCK_POINTS`` points at a time: every
rank adds its contributions that fall in the block (zero elsewhere) and MPI_Reduce sums
them on rank 0, which writes the block and drops it. A point whose DOFs sit on several
ranks gets each component from its owner (the others add zero), so the sum is exact.
No rank ever holds more than its own rows plus one block.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from pipeline.distributed.mpi import allreduce_sum
from pipeline.distributed.partition import RowPartition

#: points per written block of a :class:`PointBlocks` dataset (16 MB for 10 modes)
BLOCK_POINTS = 1 << 16


class RowBlock:
    """An (n_free, k) block, this rank's rows ``lo:hi`` (PETSc order) in ``local``."""

    def __init__(self, comm, part: RowPartition, local: np.ndarray):
        self.comm, self.part = comm, part
        self.local = np.ascontiguousarray(local, dtype=np.float64)
        self.lo, self.hi = part.rows(comm.rank)
        if self.local.shape[0] != self.hi - self.lo:
            raise ValueError(f"RowBlock: {self.local.shape[0]} local rows, expected "
                             f"{self.hi - self.lo}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.part.n_free, int(self.local.shape[1])

    def like(self, local: np.ndarray) -> "RowBlock":
        """A block of the same rows holding ``local`` (hi - lo, k')."""
        return RowBlock(self.comm, self.part, local)

    def columns(self, sel) -> "RowBlock":
        return self.like(self.local[:, sel])

    def times(self, Q: np.ndarray) -> "RowBlock":
        """X Q for a replicated (k, l) Q."""
        return self.like(self.local @ np.asarray(Q, dtype=np.float64))

    def gram(self, other: "RowBlock") -> np.ndarray:
        """(k, l) X^T Y, the same on every rank."""
        return allreduce_sum(self.comm, self.local.T @ other.local)

    def column_norms(self) -> np.ndarray:
        """(k,) Euclidean norm of each column."""
        return np.sqrt(allreduce_sum(self.comm, np.einsum("ij,ij->j", self.local,
                                                          self.local)))

    def free_rows(self) -> np.ndarray:
        """(hi - lo,) the free-DOF index (serial order) of each local row."""
        return self.part.owned_free(self.comm.rank)

    def dofs(self) -> np.ndarray:
        """(hi - lo,) the DOF (3 p + c of point p) of each local row."""
        return self.part.owned_dofs(self.comm.rank)

    def dof_sensor_product(self, T) -> np.ndarray:
        """(n_y, k) T X for a replicated sparse (n_y, n_dofs) T on every DOF (its
        columns of the fixed DOFs never read): each rank its own rows' columns."""
        own = dof_rows(T.T, self.dofs())  # (hi - lo, n_y)
        return allreduce_sum(self.comm, np.asarray(own.T @ self.local))

    def sensor_product(self, T) -> np.ndarray:
        """(n_y, k) T X for a replicated sparse (n_y, n_free) T (free order)."""
        import scipy.sparse as sp

        T = sp.csc_matrix(T)
        return allreduce_sum(self.comm, np.asarray(T[:, self.free_rows()] @ self.local))

    def signs_of_largest(self) -> np.ndarray:
        """(k,) the sign of each column's largest-magnitude entry, the first one in free
        order among equals (as ``argmax`` over the whole column)."""
        k = self.local.shape[1]
        mag = np.abs(self.local)
        best = mag.max(axis=0, initial=0.0)
        free = self.free_rows()
        none = float(self.shape[0])  # no row: past the last free index (exact in float64)
        first = np.full(k, none)
        value = np.zeros(k)
        for j in range(k):
            hit = np.flatnonzero(mag[:, j] == best[j]) if self.local.shape[0] else []
            if len(hit):
                i = hit[np.argmin(free[hit])]
                first[j], value[j] = free[i], self.local[i, j]
        top = allreduce_sum(self.comm, best, "MAX")
        mine = np.where(best == top, first, none)
        winner = allreduce_sum(self.comm, mine, "MIN")
        signs = np.sign(np.where((mine == winner) & (mine < none), value, 0.0))
        signs = allreduce_sum(self.comm, signs)  # the winner's sign; the others add 0
        signs[signs == 0] = 1.0
        return signs

    def on_points(self) -> tuple[np.ndarray, np.ndarray]:
        """(points (p,), values (p, 3, k)): this rank's rows as displacements of the mesh
        points they belong to (:meth:`dofs`), zero in the components other ranks own or
        the supports hold; points ascending."""
        dofs = self.dofs()
        points, where = np.unique(dofs // 3, return_inverse=True)
        values = np.zeros((points.size, 3, self.local.shape[1]))
        values[where, dofs % 3] = self.local
        return points, values


def dof_rows(A, dofs: np.ndarray):
    """(len(dofs), n_cols) CSR: the rows ``dofs`` (any order, distinct) of the sparse
    (n_dofs, n_cols) ``A`` (a few stored entries: port loads, sensor rows), from its
    entries alone (no array of A's n_dofs rows is made, as row indexing a CSC or
    converting to CSR would)."""
    import scipy.sparse as sp

    B = sp.coo_matrix(A)
    by_dof = np.argsort(dofs, kind="stable")
    sorted_dofs = np.asarray(dofs)[by_dof]
    at = np.minimum(np.searchsorted(sorted_dofs, B.row), max(sorted_dofs.size - 1, 0))
    keep = (sorted_dofs[at] == B.row) if sorted_dofs.size else np.zeros(B.nnz, bool)
    return sp.csr_matrix((B.data[keep], (by_dof[at[keep]], B.col[keep])),
                         shape=(len(dofs), B.shape[1]))


class PointBlocks:
    """A (n_points, *tail) dataset summed over the ranks' contributions, written by
    rank 0 block by block (see the module): ``points`` (p,) ascending, ``values`` (p,
    *tail) this rank's share. ``blocks()`` is collective: every rank iterates it in
    the same order; on rank 0 it yields (first row, rows), elsewhere nothing."""

    dtype = np.dtype(np.float64)

    def __init__(self, comm, n_points: int, points: np.ndarray, values: np.ndarray):
        self.comm, self.points, self.values = comm, np.asarray(points), values
        self.shape = (int(n_points),) + tuple(values.shape[1:])

    def blocks(self) -> Iterator[tuple[int, np.ndarray]]:
        from mpi4py import MPI

        n = self.shape[0]
        for a in range(0, n, BLOCK_POINTS):
            b = min(n, a + BLOCK_POINTS)
            buf = np.zeros((b - a,) + self.shape[1:])
            i, j = np.searchsorted(self.points, [a, b])
            buf[self.points[i:j] - a] = self.values[i:j]
            out = np.empty_like(buf) if self.comm.rank == 0 else None
            self.comm.Reduce([buf, MPI.DOUBLE], [out, MPI.DOUBLE] if out is not None
                             else None, op=MPI.SUM, root=0)
            if out is not None:
                yield a, out

    def drain(self) -> None:
        """Take part in the writing without writing (ranks other than 0)."""
        for _ in self.blocks():
            pass
