"""Exact linear multi-point constraints on the free DOFs: u = T q.

A constraint that ties the free DOFs u (n_free,) to fewer independent coordinates q
(n_q,) is one sparse matrix T (n_free x n_q): u = T q. The constrained body's stiffness
and mass are the congruent pair

    K_q = T^T K T,   M_q = T^T M T,

symmetric positive (semi-)definite when K and M are, so the eigensolver sees an ordinary
pencil; its shapes psi map back as phi = T psi, and a static load F deflects the body by

    X = T K_q^-1 T^T F

(the held directions carry the reaction, T^T F drops it). T = None is the unconstrained
body (u = q).

**Components held in a local frame** (:mod:`pipeline.fe.supports`): at a node i with held
unit directions e_1..e_h (rows of C, C u = 0) and globally fixed components c (removed
from the free DOFs already), the admissible displacements are the null space of the
3 x 3 matrix A_i = sum_j e_j e_j^T + sum_c e_c e_c^T; its orthonormal basis B_i (3 x k,
the eigenvectors of A_i at eigenvalue 0) are node i's columns of T, restricted to its
free components (zero on the fixed ones, so still orthonormal). Every other free DOF
keeps a unit column. T then has orthonormal columns, T^T T = I, and the rigid motions
and mode shapes that satisfy the constraint are mapped to q by q = T^T u exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

#: an eigenvalue of A_i below this is a free direction (A_i's held eigenvalues are >= ~1
#: for unit directions; round-off of an exact zero is ~1e-16)
NULL_TOL = 1e-8


@dataclass(frozen=True)
class Constraint:
    """u = T q on the free DOFs (module docstring).

    T: (n_free, n_q) CSR, dimensionless; orthonormal columns (T^T T = I).
    held: number of free DOFs the constraint removes, n_free - n_q.
    what: what the constraint holds, for the log and the run summary.
    """

    T: sp.csr_matrix
    held: int
    what: str

    @property
    def n_q(self) -> int:
        return self.T.shape[1]

    def project(self, A: sp.spmatrix) -> sp.csr_matrix:
        """T^T A T (n_q x n_q) of an (n_free x n_free) matrix ``A``."""
        return (self.T.T @ (A @ self.T)).tocsr()


def local_frame_constraint(rows: sp.spmatrix, free: np.ndarray, what: str) -> Constraint:
    """The :class:`Constraint` holding the unit directions ``rows`` ((n_c, n_dofs) CSR,
    one held direction of one node per row, on all DOFs 3 p + c) on the sorted ``free``
    DOFs (module docstring)."""
    rows = sp.csr_matrix(rows)
    n_dofs = rows.shape[1]
    node_of_row = rows.indices[rows.indptr[:-1]] // 3
    nodes, inverse = np.unique(node_of_row, return_inverse=True)
    A = np.zeros((nodes.size, 3, 3))
    dense = np.zeros((rows.shape[0], 3))
    for k in range(rows.shape[0]):  # each row lies on one node's three DOFs
        lo, hi = rows.indptr[k], rows.indptr[k + 1]
        dense[k, rows.indices[lo:hi] % 3] = rows.data[lo:hi]
    np.add.at(A, inverse, dense[:, :, None] * dense[:, None, :])
    is_free = np.zeros(n_dofs, dtype=bool)
    is_free[free] = True
    node_free = is_free[(3 * nodes[:, None] + np.arange(3))]  # (n, 3)
    A += np.einsum("nc,cd->ncd", (~node_free).astype(float), np.eye(3))
    lam, vec = np.linalg.eigh(A)
    keep = lam <= NULL_TOL  # (n, 3): the node's admissible directions
    position = np.full(n_dofs, -1, dtype=np.int64)
    position[free] = np.arange(free.size)
    constrained = np.zeros(free.size, dtype=bool)
    constrained[position[(3 * nodes[:, None] + np.arange(3))[node_free]]] = True
    # columns in DOF order: each unconstrained free DOF, and each node's kept directions
    # at the place of its DOFs (a small bandwidth for the factorisation)
    plain = np.flatnonzero(~constrained)
    pair_node, pair_dir = np.nonzero(keep)  # one column per (node, kept direction)
    sort_key = np.concatenate([free[plain].astype(float),
                               3.0 * nodes[pair_node] + pair_dir / 3.0])
    n_col = sort_key.size
    rank = np.empty(n_col, dtype=np.int64)
    rank[np.argsort(sort_key, kind="stable")] = np.arange(n_col)
    on = node_free[pair_node]  # (m, 3): the free components of each column's node
    pair, comp = np.nonzero(on)
    rows_T = np.concatenate([plain, position[3 * nodes[pair_node[pair]] + comp]])
    cols_T = rank[np.concatenate([np.arange(plain.size), plain.size + pair])]
    values = np.concatenate([np.ones(plain.size), vec[pair_node[pair], comp, pair_dir[pair]]])
    T = sp.csr_matrix((values, (rows_T, cols_T)), shape=(free.size, n_col))
    T.eliminate_zeros()
    return Constraint(T, int(free.size - n_col), what)
