"""Stand-ins for K, M and K^-1 whose rows live on different ranks.

The reduce stage runs on every rank with the same replicated small blocks (mode shapes,
port loads F, output rows T); it touches K and M only through products with such
blocks, their diagonals and solves with K. :class:`RowMatrix` computes its own rows of
A X and gathers the rest (MPI_Allgatherv): every rank gets the same (n_free, k) result;
its ``apply`` keeps a row block's rows on their ranks, one PETSc MatMatMult of the whole
block (:class:`BlockProduct`, shared with the factor-free path's products).
:class:`KspSolve` solves (K - sigma M) X = B with the distributed
factor that SLEPc's spectral transformation made (shift sigma 0: the operator is K
itself; below 0 for a body its supports leave free to move).
Every call is collective: all ranks make it, in the same order.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from pipeline._util.resources import release_free_heap
from pipeline.distributed.blocks import RowBlock
from pipeline.distributed.mpi import allgather_rows
from pipeline.distributed.partition import RowPartition


class BlockProduct:
    """A PETSc matrix (or its transpose) times blocks of this rank's rows: X (n_loc, k)
    -> A X (m_loc, k), one MatMatMult with a dense block (PETSc fetches the other ranks'
    rows it needs once for all k columns; a column at a time took 4.2 times as long for
    K times 25 vectors, 100k DOFs on 2 ranks). Collective: every rank calls it with the
    same k."""

    def __init__(self, PETSc, A, transpose: bool = False):
        self.PETSc, self.A, self.transpose = PETSc, A, transpose

    def __call__(self, X: np.ndarray) -> np.ndarray:
        PETSc = self.PETSc
        X = np.asfortranarray(X, dtype=np.float64)
        rows = self.A.getLocalSize()[1 if self.transpose else 0]
        if X.shape[1] == 0:  # no column (the same on every rank): nothing to fetch
            return np.zeros((rows, 0))
        Xd = PETSc.Mat().createDense(size=((X.shape[0], PETSc.DETERMINE),
                                           (PETSc.DECIDE, X.shape[1])),
                                     array=X, comm=self.A.getComm())
        Yd = self.A.transposeMatMult(Xd) if self.transpose else self.A.matMult(Xd)
        Y = np.array(Yd.getDenseArray(), dtype=np.float64, order="C")
        Xd.destroy()
        Yd.destroy()
        return Y


class RowMatrix:
    """A symmetric (n_free, n_free) matrix, rows ``lo:hi`` (PETSc order) on this rank.

    local: (hi - lo, n_free) CSR rows with PETSc's column numbers. Blocks going in and
    out are in the free-DOF order of the serial path."""

    ndim = 2
    dtype = np.dtype(np.float64)
    format = "distributed"
    #: the PETSc matrix of these rows, once made (:func:`~pipeline.distributed.stage.compute_modes`)
    petsc = None

    def __init__(self, comm, local: sp.csr_matrix, part: RowPartition):
        self.comm, self.local, self.part = comm, local, part
        n = part.n_free
        self.shape = (n, n)
        self.lo, self.hi = part.rows(comm.rank)

    @property
    def nnz(self) -> int:
        """Stored entries over all ranks."""
        return int(self.comm.allreduce(int(self.local.nnz)))

    def to_petsc_order(self, X: np.ndarray) -> np.ndarray:
        """A replicated (n_free, ...) X (free order) in PETSc's row order (collective:
        every row's order is gathered for it, as the replicated X is whole anyway)."""
        return np.asarray(X, dtype=np.float64)[self.part.whole(self.comm).order]

    def from_petsc_order(self, Y: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`to_petsc_order` (collective)."""
        out = np.empty_like(Y)
        out[self.part.whole(self.comm).order] = Y
        return out

    def own_rows(self, X: np.ndarray) -> np.ndarray:
        """This rank's rows (PETSc order) of a replicated (n_free, ...) X (free order)."""
        return np.asarray(X, dtype=np.float64)[self.part.owned_free(self.comm.rank)]

    def gather(self, local_rows: np.ndarray) -> np.ndarray:
        """Every rank's (n_i, ...) rows (PETSc order) -> the whole block in free order
        (collective)."""
        return self.from_petsc_order(allgather_rows(self.comm, local_rows))

    def __matmul__(self, X):
        X = np.asarray(X, dtype=np.float64)
        if X.shape[0] != self.shape[1]:
            raise ValueError(f"matmul: X has {X.shape[0]} rows, expected {self.shape[1]}")
        return self.gather(self.local @ self.to_petsc_order(X))

    dot = __matmul__

    def scaled_inf_norm(self, w: np.ndarray | None = None) -> float:
        """max_i w_i sum_j |A_ij| w_j over every rank's rows (w: (n_free,) free order;
        None: ones), see :func:`pipeline.solve.blas.scaled_inf_norm`."""
        from mpi4py import MPI

        absA = abs(self.local)
        if w is None:
            sums = np.asarray(absA.sum(axis=1)).ravel()
        else:
            wp = self.to_petsc_order(w)
            sums = wp[self.lo:self.hi] * (absA @ wp)
        return float(self.comm.allreduce(float(sums.max(initial=0.0)), op=MPI.MAX))

    def apply(self, X: RowBlock) -> RowBlock:
        """A X of a row block (its rows stay on their ranks): one PETSc MatMatMult of the
        whole block (:class:`BlockProduct`). On the cantilever at mesh.size 0.005
        (100,695 free DOFs, 2 ranks, one process measuring both): K times its 10 modes
        0.198 -> 0.062 s (3.2x), M 2.0x, 25 columns 2.4x, the same to round-off
        (1.8e-11 of the largest entry of K X, whose terms cancel). The reduce stage
        of cantilever_connection.yaml (Craig-Bampton, 20 modes; 30-50 s) is dominated
        by its clamped eigen solves: its products take a few seconds of it."""
        if self.petsc is None:
            raise RuntimeError("RowMatrix.apply: no PETSc matrix attached")
        from pipeline.distributed.mpi import petsc

        return X.like(BlockProduct(petsc()[0], self.petsc)(X.local))

    def diagonal(self) -> np.ndarray:
        """(n_free,) the diagonal, free order."""
        return self.gather(self.local.diagonal(k=self.lo))


def of_diagonals(fn, K: RowMatrix, M: RowMatrix):
    """``fn(K_d, M_d)`` of the diagonals of the distributed K and M, for the functions
    that read only them (:func:`pipeline.solve.thresholds.stiffness_scale`, a median of
    K_ii / M_ii; :func:`pipeline.solve.eigen.default_shift`): rank 0 gathers every
    rank's diagonal rows (in PETSc order: ``fn`` must not depend on the order) as sparse
    diagonal matrices, evaluates ``fn`` and sends the result; the other ranks hold their
    own rows only."""
    parts = K.comm.gather([A.local.diagonal(k=A.lo) for A in (K, M)], root=0)
    value = None
    if K.comm.rank == 0:
        value = fn(*(sp.diags(np.concatenate([p[i] for p in parts])).tocsr()
                     for i in (0, 1)))
    return K.comm.bcast(value, root=0)


class KspSolve:
    """X = (K - shift M)^-1 B for replicated (n_free,) or (n_free, k) B with a PETSc KSP
    whose operator is K - shift M (rows distributed as ``matrix``; ``shift`` rad^2/s^2,
    0: K itself). ``keep``: the solver's PETSc objects (MUMPS' factor among them), freed
    by ``release_solver`` once no solve is left to make (before another factor is made);
    ``matrices``: objects that outlive the solver (K's and M's PETSc matrices, the
    prolongation); ``release`` frees both."""

    #: the factor-free path's P2 -> P1 prolongation (a PETSc matrix, among ``matrices``),
    #: which the solves of related operators reuse (a spinning body's K(Omega)); None
    #: otherwise
    prolongation = None

    def __init__(self, ksp, matrix: RowMatrix, keep=(), shift: float = 0.0,
                 prolongation=None, matrices=()):
        self.ksp, self.matrix, self.keep = ksp, matrix, list(keep)
        self.matrices = list(matrices)
        self.shift = float(shift)
        self.prolongation = prolongation

    def solve(self, B: np.ndarray) -> np.ndarray:
        B = np.asarray(B, dtype=np.float64)
        cols = B.reshape(B.shape[0], -1)
        Bp = self.matrix.own_rows(cols)
        return self.matrix.gather(self.solve_rows(Bp)).reshape(B.shape)

    def solve_rows(self, Bp: np.ndarray) -> np.ndarray:
        """This rank's rows of (K - shift M)^-1 B from its rows of B ((hi - lo, k), PETSc
        order)."""
        if self.ksp is None:
            raise RuntimeError("the distributed factorisation was released")
        A, _ = self.ksp.getOperators()
        x, b = A.createVecs()
        X = np.empty_like(Bp)
        for c in range(Bp.shape[1]):
            b.getArray()[:] = Bp[:, c]
            self.ksp.solve(b, x)
            X[:, c] = x.getArray()
        x.destroy()
        b.destroy()
        return X

    def release_solver(self) -> None:
        """Free the solver's objects now (collective); the matrices stay. MUMPS' factor
        lives in the C heap, which keeps the freed pages (cantilever at 100k DOFs on 2
        ranks: a rank's resident memory stayed at 620 MB after the factor was freed,
        291 MB once given back), so they are given back to the system: the next factor
        then starts from the resident memory without it."""
        if not self.keep:
            return
        for obj in self.keep:
            obj.destroy()
        self.keep, self.ksp = [], None
        release_free_heap()

    def release(self) -> None:
        self.release_solver()
        for obj in self.matrices:
            obj.destroy()
        self.matrices, self.prolongation = [], None
