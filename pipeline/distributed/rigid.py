"""A partly held body on MPI ranks: the rigid-body motions its supports leave, each rank
holding its own rows, in place of the eigensolver's zero-frequency modes.

The serial modes stage (:func:`pipeline.solve.stage.with_rigid_motions`) replaces the
first r modes of a body whose supports leave r rigid-body motions R (n_free, r; exact
null vectors of K, :func:`pipeline.fe.supports.rigid_freedoms`) by R itself,
M-orthonormalised in its order, and makes the elastic modes M-orthogonal to it:

    G = R^T M R = L L^T (Cholesky),   R <- R L^-T          (Gram-Schmidt order)
    Phi_e <- Phi_e - R (R^T M Phi_e),  phi <- phi / sqrt(phi^T M phi)  (each column)

Here R is a :class:`~pipeline.distributed.blocks.RowBlock`: each rank evaluates the
motions' twists on the points of its own rows
(:meth:`~pipeline.fe.supports.RigidFreedoms.fields_at`, 24 r bytes a row), and the
products above are the row blocks' collective ones (M R and M Phi by PETSc, the (r, r)
and (r, m) Gram matrices by MPI_Allreduce): no rank holds a whole column.
"""

from __future__ import annotations

import numpy as np

from pipeline.distributed.blocks import RowBlock
from pipeline.distributed.mpi import allreduce_sum
from pipeline.solve.stage import check_rigid_found


def rigid_rows(rigid, mesh, like: RowBlock) -> RowBlock:
    """(n_free, r) the rigid motions ``rigid`` (a
    :class:`~pipeline.fe.supports.RigidFreedoms`, m per unit twist) on the rows of
    ``like``: this rank's rows, from the coordinates of its own points (``mesh``: its
    :class:`~pipeline.distributed.submesh.RankMesh`; the DOF 3 p + c of each row: its
    partition's)."""
    dofs = like.dofs()
    points, where = np.unique(dofs // 3, return_inverse=True)
    x = mesh.space.node_points[mesh.local_nodes(points)]
    fields = rigid.fields_at(x).reshape(points.size, 3, rigid.count)
    return like.like(fields[where, dofs % 3])


def with_rigid_rows(omega2: np.ndarray, Phi: RowBlock, M, R: RowBlock, n_found: int,
                    names: tuple[str, ...]) -> tuple[np.ndarray, RowBlock]:
    """(omega2 (m,) with the first r = R.shape[1] zero, the shapes (n_free, m)): the
    distributed twin of :func:`pipeline.solve.stage.with_rigid_motions` (module) for the
    Ritz pairs ``omega2``, ``Phi`` of which ``n_found`` are at zero frequency, ``M`` the
    distributed mass (:class:`~pipeline.distributed.operators.RowMatrix`) and ``names``
    the motions'; refuses (SolverError) as that function does."""
    r = R.shape[1]
    check_rigid_found(n_found, omega2, r, names)
    G = R.gram(M.apply(R))
    L = np.linalg.cholesky(0.5 * (G + G.T))
    R = R.like(np.linalg.solve(L, R.local.T).T)  # R L^-T
    phi = Phi.columns(slice(r, None))
    phi = phi.like(phi.local - R.local @ R.gram(M.apply(phi)))
    norms = np.sqrt(allreduce_sum(Phi.comm, np.einsum("ij,ij->j", phi.local,
                                                      M.apply(phi).local)))
    omega2 = np.concatenate([np.zeros(r), omega2[r:]])
    return omega2, Phi.like(np.hstack([R.local, phi.local / norms]))
