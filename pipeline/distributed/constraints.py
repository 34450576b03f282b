"""The exact constraint u = T q (:mod:`pipeline.fe.constraints`) on MPI ranks: components
held in a local frame and rigid (RBE2) mass couplings, with no rank holding the whole T.

T (n_free, n_q) is a PETSc MPIAIJ matrix. Its rows are distributed as K's: rank r builds
the rows of its own free DOFs (PETSc rows lo:hi) from what rank 0 sends it
(:func:`constraint_sources`: the held local directions of the nodes with a row on r, and
of each rigid coupling the slave nodes with a row on r, their points and the master
point P), with the serial formulas (:func:`pipeline.fe.constraints.local_frame_triplets`,
:func:`~pipeline.fe.constraints.rigid_coupling_rows`). Its columns, the coordinates q,
are distributed too, each owned by one rank:

- a free DOF neither held nor coupled: its own unit column, on the rank of its row;
- the admissible directions of a node held in a local frame: on the rank of the node's
  lowest free DOF;
- the six motions [u_P; theta_P] of a coupling's master point: on the rank of its
  lowest slave node's x DOF.

Each column carries the serial path's sort key (its place in DOF order), so the PETSc
numbering of q maps to the serial one (``q_part.order``: the serial index of each PETSc
q row, which the sign convention's tie-break reads); the keys of all columns (8 bytes a
coordinate) are gathered on every rank, like the free DOFs themselves.

The eigensolver and the static solves run on the congruent pair

    K_q = T^T K T,   M_q = T^T M T        (PETSc's PtAP, distributed)

as :class:`~pipeline.distributed.operators.RowMatrix` stand-ins on q's partition; shapes
and static shapes map back as phi = T psi, X = T X_q (one MatMult a column), loads as
F_q = T^T F. A field u that satisfies the constraint has the coordinates
q = (T^T T)^-1 T^T u (:func:`pipeline.solve.blas.constraint_coordinates`): T^T T is block
diagonal (1 on a plain or local-frame column, whose columns are orthonormal; a 6 x 6
block per master, whose columns are all on one rank), so each rank solves its own rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pipeline._util.resources import release_free_heap
from pipeline.distributed.blocks import RowBlock
from pipeline.distributed.operators import RowMatrix
from pipeline.distributed.partition import RowPartition
from pipeline.fe.constraints import local_frame_triplets, master_keys, rigid_coupling_rows


@dataclass(frozen=True)
class ConstraintSource:
    """What rank r needs to build its rows of T (see the module).

    n_dofs: all DOFs of the body. frame_rows: (n_c, n_dofs) CSR, the held unit
    directions of the nodes with a free DOF among r's rows (one node's every row), or
    None. couplings: per rigid coupling (its lowest slave node, the slave nodes with a
    row on r (n_s,), their points (n_s, 3) m, the master point P (3,) m). what: what the
    whole constraint holds (the run summary).
    """

    n_dofs: int
    frame_rows: sp.csr_matrix | None
    couplings: tuple
    what: str


def dof_ranks(n_dofs: int, free: np.ndarray, part: RowPartition) -> np.ndarray:
    """(n_dofs,) the rank owning each DOF's PETSc row, -1 for a fixed DOF."""
    owner = np.full(n_dofs, -1, dtype=np.int64)
    for r in range(part.starts.size - 1):
        owner[np.asarray(free)[part.owned_free(r)]] = r
    return owner


def constraint_sources(frame_rows, couplings, what: str, n_dofs: int, free: np.ndarray,
                       part: RowPartition) -> list[ConstraintSource]:
    """Rank 0: each rank's :class:`ConstraintSource` from the whole constraint's inputs
    (:func:`pipeline.fe.model.constraint_inputs`: the held directions (n_c, n_dofs) CSR
    or None, the rigid couplings (slave nodes, their points, P))."""
    owner = dof_ranks(n_dofs, free, part).reshape(-1, 3)
    frame = None if frame_rows is None else sp.csr_matrix(frame_rows)
    row_owners = None
    if frame is not None:
        row_owners = owner[frame.indices[frame.indptr[:-1]] // 3]  # (n_c, 3)
    out = []
    for r in range(part.starts.size - 1):
        mine = None
        if frame is not None:
            mine = frame[np.flatnonzero((row_owners == r).any(axis=1))]
        groups = []
        for nodes, points, P in couplings:
            on = (owner[nodes] == r).any(axis=1)
            groups.append((int(nodes.min()), nodes[on], points[on], np.asarray(P, float)))
        out.append(ConstraintSource(n_dofs, mine, tuple(groups), what))
    return out


class DistributedConstraint:
    """u = T q on the ranks (module): this rank's rows of T, the partitions of u and q,
    and, once :meth:`project` ran, PETSc's T, K_q, M_q and T^T T.

    T_local: (hi - lo, n_q) CSR, T's rows of this rank's free DOFs (PETSc order) with
    PETSc's q column numbers. u_part, q_part: the row partitions of u (K's) and q.
    held: free DOFs the constraint removes, n_free - n_q. what: what it holds.
    """

    def __init__(self, comm, u_part: RowPartition, q_part: RowPartition,
                 T_local: sp.csr_matrix, what: str):
        self.comm, self.u_part, self.q_part = comm, u_part, q_part
        self.T_local, self.what = T_local, what
        self.held = u_part.n_free - q_part.n_free
        self.T = self.TtT = self.K = self.M = None
        self._gram_lu = None

    @property
    def n_q(self) -> int:
        return self.q_part.n_free

    def project(self, PETSc, K: RowMatrix, M: RowMatrix) -> tuple[RowMatrix, RowMatrix]:
        """(K_q, M_q) = (T^T K T, T^T M T) as row matrices on q's partition with their
        PETSc matrices attached (``K``, ``M``: the distributed ones, theirs attached);
        made once, kept here (collective)."""
        q_lo, q_hi = self.q_part.rows(self.comm.rank)
        u_lo, u_hi = self.u_part.rows(self.comm.rank)
        T = self.T_local
        self.T = PETSc.Mat().createAIJ(
            size=((u_hi - u_lo, self.u_part.n_free), (q_hi - q_lo, self.n_q)),
            csr=(T.indptr.astype(PETSc.IntType), T.indices.astype(PETSc.IntType), T.data),
            comm=PETSc.COMM_WORLD)
        self.T.assemble()
        self.K, self.M = (self._row_matrix(PETSc, A.petsc.ptap(self.T)) for A in (K, M))
        self.TtT = self.T.transposeMatMult(self.T)
        indptr, indices, data = self.TtT.getValuesCSR()
        gram = sp.csr_matrix((data, indices, indptr), shape=(q_hi - q_lo, self.n_q))
        from scipy.sparse.linalg import splu

        # a rank may own no coordinate (all its rows a coupling's slaves)
        self._gram_lu = splu(sp.csc_matrix(gram[:, q_lo:q_hi])) if q_hi > q_lo else None
        return self.K, self.M

    def _row_matrix(self, PETSc, A) -> RowMatrix:
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        indptr, indices, data = A.getValuesCSR()
        lo, hi = self.q_part.rows(self.comm.rank)
        out = RowMatrix(self.comm, sp.csr_matrix((data, indices, indptr),
                                                 shape=(hi - lo, self.n_q)), self.q_part)
        out.petsc = A
        return out

    def _apply(self, X: np.ndarray, transpose: bool, part: RowPartition) -> RowBlock:
        x, y = self.T.createVecs()  # x: q, y: u
        src, dst = (y, x) if transpose else (x, y)
        out = np.empty((dst.getLocalSize(), X.shape[1]))
        for c in range(X.shape[1]):
            src.getArray()[:] = X[:, c]
            (self.T.multTranspose if transpose else self.T.mult)(src, dst)
            out[:, c] = dst.getArray()
        x.destroy()
        y.destroy()
        return RowBlock(self.comm, part, out)

    def to_q(self, F: RowBlock) -> RowBlock:
        """T^T F (n_q, k) of an (n_free, k) row block (loads)."""
        return self._apply(F.local, True, self.q_part)

    def from_q(self, Y: RowBlock) -> RowBlock:
        """T Y (n_free, k) of an (n_q, k) row block (shapes)."""
        return self._apply(Y.local, False, self.u_part)

    def coordinates(self, U: RowBlock) -> RowBlock:
        """q = (T^T T)^-1 T^T U (n_q, k) of fields U (n_free, k) that satisfy the
        constraint (module)."""
        y = self.to_q(U)
        q = self._gram_lu.solve(y.local) if y.local.size else y.local
        return y.like(np.asarray(q).reshape(y.local.shape))

    def destroy(self) -> None:
        """Free the PETSc objects (collective; KspSolve.release calls it)."""
        for A in (self.T, self.TtT) + tuple(B.petsc for B in (self.K, self.M)
                                            if B is not None):
            if A is not None:
                A.destroy()
        self.T = self.TtT = self.K = self.M = None
        release_free_heap()  # the projected pencil's (and its factor's) pages, as KspSolve


class Unconstrained:
    """The identity constraint u = q (the same methods as :class:`DistributedConstraint`)
    on the distributed ``K`` and ``M``."""

    def __init__(self, K: RowMatrix, M: RowMatrix):
        self.K, self.M = K, M

    @staticmethod
    def to_q(F: RowBlock) -> RowBlock:
        return F

    from_q = coordinates = to_q


def rank_entries(source: ConstraintSource, free: np.ndarray, part: RowPartition, rank: int):
    """(rows (k,), keys (k,), values (k,), anchored (c,)): the entries of T in the rows
    of rank ``rank``'s free DOFs (rows: free-DOF indices; keys: their columns' sort keys)
    and the sorted keys of the columns this rank owns (module), from its ``source``."""
    free = np.asarray(free)
    position = np.full(source.n_dofs, -1, dtype=np.int64)
    position[free] = np.arange(free.size)
    owner = np.empty(free.size, dtype=np.int64)  # the rank of each free DOF's row
    for r in range(part.starts.size - 1):
        owner[part.owned_free(r)] = r
    constrained = np.zeros(free.size, dtype=bool)
    rows, keys, values, anchored = [], [], [], []
    if source.frame_rows is not None and source.frame_rows.shape[0]:
        held, r_free, pair, v, col_keys = local_frame_triplets(
            source.frame_rows, free, position, source.n_dofs)
        constrained[held] = True
        rows.append(r_free), keys.append(col_keys[pair]), values.append(v)
        nodes = (col_keys // 3).astype(np.int64)
        node_dofs = position[3 * nodes[:, None] + np.arange(3)]
        lowest = np.where(node_dofs >= 0, node_dofs, free.size).min(axis=1)
        anchored.append(col_keys[owner[lowest] == rank])
    for lowest_slave, nodes, points, P in source.couplings:
        dofs = position[3 * np.asarray(nodes, dtype=np.int64)[:, None] + np.arange(3)]
        constrained[dofs.ravel()] = True
        rows.append(np.repeat(dofs.ravel(), 6))
        keys.append(np.tile(master_keys(lowest_slave), dofs.size))
        values.append(rigid_coupling_rows(points, P).ravel())
        if owner[position[3 * lowest_slave]] == rank:
            anchored.append(master_keys(lowest_slave))
    own = part.owned_free(rank)
    plain = own[~constrained[own]]
    rows.append(plain), keys.append(free[plain].astype(float)), values.append(np.ones(plain.size))
    anchored.append(free[plain].astype(float))
    rows = np.concatenate(rows).astype(np.int64)
    mine = np.isin(rows, own)
    return (rows[mine], np.concatenate(keys)[mine], np.concatenate(values)[mine],
            np.sort(np.concatenate(anchored)))


def rows_of_T(rows: np.ndarray, keys: np.ndarray, values: np.ndarray, own: np.ndarray,
              all_keys: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """(T's rows (len(own), n_q) CSR on PETSc's q columns, q's order: the serial index
    of each PETSc q row) from :func:`rank_entries`' entries, the rank's free DOFs
    ``own`` (PETSc order) and every rank's anchored keys in rank order ``all_keys``."""
    sorter = np.argsort(all_keys, kind="stable")
    order = np.empty(all_keys.size, dtype=np.int64)
    order[sorter] = np.arange(all_keys.size)
    by_free = np.argsort(own)
    local_rows = by_free[np.searchsorted(own[by_free], rows)]
    cols = sorter[np.searchsorted(all_keys[sorter], keys)]
    T = sp.csr_matrix((values, (local_rows, cols)), shape=(own.size, all_keys.size))
    T.eliminate_zeros()
    T.sort_indices()
    return T, order


def build_rows(comm, source: ConstraintSource, whole: RowPartition) -> DistributedConstraint:
    """This rank's rows of T and q's partition (collective: the column keys are gathered
    on every rank) from its ``source`` (:func:`constraint_sources`) and u's ``whole``
    partition (the constraint keeps this rank's own, :meth:`RowPartition.local`)."""
    entries = rank_entries(source, whole.free_dofs(), whole, comm.rank)
    return from_entries(comm, entries, whole.local(comm.rank), source.what)


def from_entries(comm, entries, part: RowPartition, what: str) -> DistributedConstraint:
    """The :class:`DistributedConstraint` of this rank's ``entries`` (rows, keys, values,
    anchored keys: :func:`rank_entries`' answer) on u's partition ``part`` (collective:
    the anchored keys are gathered on every rank)."""
    rows, keys, values, mine = entries
    gathered = comm.allgather(mine)
    T, order = rows_of_T(rows, keys, values, part.owned_free(comm.rank),
                         np.concatenate(gathered))
    starts = np.concatenate([[0], np.cumsum([g.size for g in gathered])]).astype(np.int64)
    return DistributedConstraint(comm, part, RowPartition(order, starts), T, what)


def distribute_constraint(comm, inputs, n_dofs: int, part: RowPartition
                          ) -> DistributedConstraint | None:
    """Every rank's :class:`DistributedConstraint`, or None without one (collective;
    ``inputs``: :func:`pipeline.fe.model.constraint_inputs` on rank 0, ignored
    elsewhere; ``part``: this rank's partition): rank 0 cuts each rank's source and
    sends it; while each rank builds its rows, it holds u's whole partition (gathered:
    the owner of every free DOF)."""
    if not comm.bcast(comm.rank == 0 and inputs is not None, root=0):
        return None
    whole = part.whole(comm)
    sources = None
    if comm.rank == 0:
        sources = constraint_sources(*inputs, n_dofs, whole.free_dofs(), whole)
    return build_rows(comm, comm.scatter(sources, root=0), whole)
