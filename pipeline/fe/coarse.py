"""The linear (P1) space inside a quadratic (P2) one: the coarse space of the two-grid
solver (:mod:`pipeline.solve.multigrid`).

A P1 displacement field on the mesh vertices is exactly a P2 field whose edge-midpoint
values are the means of the edge's two vertex values. The prolongation P maps the free
vertex DOFs (the coarse DOFs) to the free DOFs of the P2 space:

    (P u_c)[3 v + c]       = u_c[3 v + c]                        vertex v
    (P u_c)[3 (n_v + e) + c] = (u_c[3 a + c] + u_c[3 b + c]) / 2  midpoint of edge e = (a, b)

with a fixed vertex DOF contributing zero (its value is held at zero). P^T K P and
P^T M P are then the P1 stiffness and mass of the same mesh (Galerkin, exact).
Shapes: P (n_free, n_coarse) CSR, at most 2 entries per row.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from pipeline.fe.space import FESpace


def p1_prolongation(space: FESpace, free: np.ndarray) -> sp.csr_matrix | None:
    """P (n_free x n_coarse) of the module doc, or None for a linear (order 1) space.

    ``free``: sorted free DOF indices of the space (3 * node + component). The coarse
    DOFs are the free vertex DOFs, in increasing order.
    """
    if space.order != 2:
        return None
    n_v = space.body.n_vertices
    edges = np.asarray(space.edges, dtype=np.int64)
    n_e = edges.shape[0]
    comp = np.arange(3)
    vert_rows = (3 * np.arange(n_v)[:, None] + comp).ravel()
    mid_nodes = n_v + np.arange(n_e)
    mid_rows = np.repeat((3 * mid_nodes[:, None] + comp).ravel(), 2)
    mid_cols = (3 * edges[:, None, :] + comp[None, :, None]).reshape(-1)  # (e, c, end)
    rows = np.concatenate([vert_rows, mid_rows])
    cols = np.concatenate([vert_rows, mid_cols])
    vals = np.concatenate([np.ones(vert_rows.size), np.full(mid_cols.size, 0.5)])
    free = np.asarray(free, dtype=np.int64)
    n_dofs = space.n_dofs
    row_of = np.full(n_dofs, -1, dtype=np.int64)
    row_of[free] = np.arange(free.size)
    coarse = free[free < 3 * n_v]
    col_of = np.full(3 * n_v, -1, dtype=np.int64)
    col_of[coarse] = np.arange(coarse.size)
    r, c = row_of[rows], col_of[cols]
    keep = (r >= 0) & (c >= 0)
    P = sp.csr_matrix((vals[keep], (r[keep], c[keep])), shape=(free.size, coarse.size))
    P.sum_duplicates()
    return P
