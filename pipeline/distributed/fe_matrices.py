"""The unsupported body's K and M (``/fe``, the matrices the Exudyn export reads) written
from MPI ranks, no rank holding the whole of either.

Every element is on exactly one rank's list (``mass_elements`` of its part), so

    A = sum_r A_r,   A_r = the upper triangle of rank r's elements' contributions

(:func:`~pipeline.distributed.assemble.element_share`, global DOF numbers, held DOFs
included). The file stores A's upper triangle as CSR arrays (``data``, ``indices``,
``indptr``: :func:`pipeline.store.schema_interfaces.csr_datasets`). Rank 0 writes them
a block of ``BLOCK_ROWS`` rows at a time: each rank sends its rows of the block, rank 0
sums them, drops exact zeros (as the serial writer does) and writes the block's part
of the array. A first pass counts each block's entries (the arrays' lengths and
offsets); each of the three arrays is then one more pass. Every pass is collective:
the ranks that do not write take part through ``drain``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from pipeline.distributed.blocks import BLOCK_POINTS

__all__ = ["BLOCK_ROWS", "SummedCsr"]

#: rows of the summed matrix that rank 0 holds at once
BLOCK_ROWS = 3 * BLOCK_POINTS


class SummedCsr:
    """A = sum over the ranks of ``local`` ((n, n) CSR upper triangles), written by rank 0
    block by block (module). ``csr_parts()``: the three block-written arrays, as the
    writer takes them. Making it is collective (the counting pass)."""

    def __init__(self, comm, local: sp.csr_matrix):
        self.comm, self.local = comm, sp.csr_matrix(local)
        self.shape = self.local.shape
        n = self.shape[0]
        self.ranges = [(a, min(n, a + BLOCK_ROWS)) for a in range(0, n, BLOCK_ROWS)] or [(0, 0)]
        counts = [None if block is None else block.nnz for block in self.summed()]
        counts = comm.bcast(counts, root=0)
        self.offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.nnz = int(self.offsets[-1])

    def summed(self):
        """Per block of rows: on rank 0 the summed rows (CSR, sorted, no zeros), None
        elsewhere (collective)."""
        for a, b in self.ranges:
            pieces = self.comm.gather(self.local[a:b], root=0)
            if self.comm.rank != 0:
                yield None
                continue
            block = sp.csr_matrix(sum(pieces[1:], pieces[0]))
            block.sum_duplicates()
            block.eliminate_zeros()
            block.sort_indices()
            yield block

    def csr_parts(self) -> tuple["CsrPart", "CsrPart", "CsrPart"]:
        """(data (nnz,) float64, indices (nnz,), indptr (n + 1,) int64), block-written."""
        itype = np.int32 if self.nnz < 2**31 - 1 else np.int64
        return (CsrPart(self, "data", np.float64), CsrPart(self, "indices", itype),
                CsrPart(self, "indptr", np.int64))


class CsrPart:
    """One CSR array of a :class:`SummedCsr`: ``shape``, ``dtype``, ``blocks()``
    (collective; rank 0 gets (first entry, entries)), ``drain()`` (the other ranks)."""

    def __init__(self, matrix: SummedCsr, name: str, dtype):
        self.matrix, self.name, self.dtype = matrix, name, np.dtype(dtype)
        n = matrix.shape[0]
        self.shape = (n + 1,) if name == "indptr" else (matrix.nnz,)

    def blocks(self):
        m = self.matrix
        for (a, _), offset, block in zip(m.ranges, m.offsets, m.summed()):
            if block is None:
                continue
            if self.name == "data":
                yield int(offset), block.data.astype(self.dtype)
            elif self.name == "indices":
                yield int(offset), block.indices.astype(self.dtype)
            else:
                yield a, (offset + block.indptr[:-1]).astype(self.dtype)
        if self.name == "indptr" and m.comm.rank == 0:
            yield m.shape[0], np.array([m.nnz], dtype=self.dtype)

    def drain(self) -> None:
        for _ in self.blocks():
            pass
