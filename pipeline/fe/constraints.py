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
keeps a unit column.

**Rigid (RBE2) coupling** of a region to a point P: the region's nodes s (the slaves)
follow the six motions q_P = [u_P; theta_P] of P (new coordinates, the master),

    u_s = u_P + theta_P x (x_s - P) = [I, -skew(x_s - P)] q_P,

so the slaves' rows of T are those rigid-body rows on the master's six columns; the
slaves' own DOFs are no coordinates. An added mass's 6 x 6 rigid mass M6 at P sits on
q_P: the FE mass matrix carries it as G^T M6 G (:mod:`pipeline.fe.added_mass`, G any
rigid fit of the slaves with G R = I), and since the slaves move rigidly, u_s = R q_P,
T^T (G^T M6 G) T = M6 on q_P exactly: M on the free DOFs stays the one matrix the later
stages use (Phi^T M Phi = I), and the mass properties are exact.

T's columns are then orthogonal between groups but a master's columns are not unit ones;
a field u that satisfies the constraint has the coordinates q = (T^T T)^-1 T^T u
(:func:`pipeline.solve.blas.constraint_coordinates`; = T^T u without rigid couplings).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp

#: an eigenvalue of A_i below this is a free direction (A_i's held eigenvalues are >= ~1
#: for unit directions; round-off of an exact zero is ~1e-16)
NULL_TOL = 1e-8


@dataclass(frozen=True)
class Constraint:
    """u = T q on the free DOFs (module docstring).

    T: (n_free, n_q) CSR, dimensionless (m/rad on a master's rotation columns);
    orthonormal columns without rigid couplings.
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
    return build_constraint(free, rows.shape[1], rows, (), what)


def build_constraint(free: np.ndarray, n_dofs: int, rows: sp.spmatrix | None,
                     rigid: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                     what: str) -> Constraint:
    """The :class:`Constraint` on the sorted ``free`` DOFs (of ``n_dofs``) of the held
    unit directions ``rows`` ((n_c, n_dofs) CSR or None) and the rigid couplings
    ``rigid``: (slave nodes (n_s,), their points (n_s, 3) m, the master point P (3,) m)
    each (module docstring). A slave DOF must be free and in no other group: the caller
    checks (:func:`pipeline.fe.model.build_fe_model` names the config keys)."""
    position = np.full(n_dofs, -1, dtype=np.int64)
    position[free] = np.arange(free.size)
    constrained = np.zeros(free.size, dtype=bool)
    r_parts, c_parts, v_parts, keys = [], [], [], []  # c_parts: column within its group
    if rows is not None and rows.shape[0]:
        held, r, c, v, k = local_frame_triplets(sp.csr_matrix(rows), free, position, n_dofs)
        constrained[held] = True
        r_parts.append(r), c_parts.append(c), v_parts.append(v), keys.append(k)
    for nodes, points, P in rigid:
        dofs = position[3 * nodes[:, None] + np.arange(3)]  # (n_s, 3)
        constrained[dofs.ravel()] = True
        r_parts.append(np.repeat(dofs.ravel(), 6))
        c_parts.append(np.tile(np.arange(6), dofs.size))
        v_parts.append(rigid_coupling_rows(points, P).ravel())
        keys.append(master_keys(nodes.min()))
    plain = np.flatnonzero(~constrained)
    # columns in DOF order: each unconstrained free DOF, each group's columns at the place
    # of its first node (a small bandwidth for the factorisation)
    sort_key = np.concatenate([free[plain].astype(float), *keys])
    rank = np.empty(sort_key.size, dtype=np.int64)
    rank[np.argsort(sort_key, kind="stable")] = np.arange(sort_key.size)
    offsets = np.cumsum([plain.size] + [k.size for k in keys])
    cols = [rank[np.arange(plain.size)]] + [rank[o + c] for o, c in zip(offsets[:-1], c_parts)]
    T = sp.csr_matrix((np.concatenate([np.ones(plain.size), *v_parts]),
                       (np.concatenate([plain, *r_parts]), np.concatenate(cols))),
                      shape=(free.size, sort_key.size))
    T.eliminate_zeros()
    return Constraint(T, int(free.size - sort_key.size), what)


def rigid_coupling_rows(points: np.ndarray, P) -> np.ndarray:
    """(n_s, 3, 6) the rows of T of slave points ``points`` (n_s, 3) m on the six
    columns of the master point ``P`` (3,) m: u_s = u_P - skew(x_s - P) theta_P
    (module docstring; dimensionless on u_P, m/rad on theta_P)."""
    d = np.asarray(points, dtype=float) - np.asarray(P, dtype=float)
    block = np.zeros((d.shape[0], 3, 6))
    block[:, :, :3] = np.eye(3)
    block[:, 0, 4], block[:, 0, 5] = d[:, 2], -d[:, 1]
    block[:, 1, 3], block[:, 1, 5] = -d[:, 2], d[:, 0]
    block[:, 2, 3], block[:, 2, 4] = d[:, 1], -d[:, 0]
    return block


def master_keys(lowest_slave: int) -> np.ndarray:
    """(6,) the column sort keys of a rigid coupling's master whose lowest slave node is
    ``lowest_slave``: its columns sit at the place of that node's DOFs."""
    return 3.0 * lowest_slave + np.arange(6) / 6.0


def local_frame_triplets(rows: sp.csr_matrix, free: np.ndarray, position: np.ndarray,
                         n_dofs: int):
    """(the free DOFs of the held nodes, T rows, columns within the group, values, column
    sort keys) of the held local directions ``rows`` (module docstring); a node whose
    every component is held keeps no column (its DOFs are zero rows of T)."""
    node_of_row = rows.indices[rows.indptr[:-1]] // 3
    nodes, inverse = np.unique(node_of_row, return_inverse=True)
    dense = np.zeros((rows.shape[0], 3))
    # each row lies on one node's three DOFs
    dense[np.repeat(np.arange(rows.shape[0]), np.diff(rows.indptr)), rows.indices % 3] = rows.data
    A = np.zeros((nodes.size, 3, 3))
    np.add.at(A, inverse, dense[:, :, None] * dense[:, None, :])
    is_free = np.zeros(n_dofs, dtype=bool)
    is_free[free] = True
    node_free = is_free[(3 * nodes[:, None] + np.arange(3))]  # (n, 3)
    A += np.einsum("nc,cd->ncd", (~node_free).astype(float), np.eye(3))
    lam, vec = np.linalg.eigh(A)
    pair_node, pair_dir = np.nonzero(lam <= NULL_TOL)  # one column per kept direction
    pair, comp = np.nonzero(node_free[pair_node])  # its node's free components
    held_rows = position[(3 * nodes[:, None] + np.arange(3))[node_free]]
    T_rows = position[3 * nodes[pair_node[pair]] + comp]
    values = vec[pair_node[pair], comp, pair_dir[pair]]
    return held_rows, T_rows, pair, values, 3.0 * nodes[pair_node] + pair_dir / 3.0
