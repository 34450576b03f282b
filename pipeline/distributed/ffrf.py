"""The floating-frame inertia invariants (:mod:`pipeline.reduce.ffrf`, ``/ffrf``) of a
basis of the run's modes on MPI ranks, for a body clamped on a region (every DOF of
its points held: the modes are zero there).

Each invariant is a bilinear form of nodal fields with M = N (x) I_3 (N the node-level
mass). The cross products are taken node by node, and the skew matrix is linear, so
M skew(Psi) = skew(M Psi) block by block: every form is a sum over the nodes j of
products of fields AT node j, which each rank sums over its own points (whole points
per rank, :func:`~pipeline.distributed.partition.slab_partition` and the graph
partition keep them) and MPI_Allreduce adds up:

    x~^T M Psi~   = sum_j skew((M x)_j)^T skew(psi_j)        (3, 3 n)
    Psi~^T M Psi~ = sum_j skew(psi_j)^T skew((M Psi)_j)      (3 n, 3 n)
    Psi~^T M Psi  = sum_j skew(psi_j)^T (M Psi)_j            (3 n, n)
    R_O^T M Psi   = sum_j ((M R_O)_j)^T psi_j                 (6, n)

Psi is zero on the held points, so (M Psi)_j at a free point is the supported M's
product (PETSc's), but (M x)_j and (M R_O)_j couple to the held points: they are summed
from the elements of the rank's part (:func:`~pipeline.distributed.assemble.full_mass_rows`).
On the unsupported pair (M on every DOF, :mod:`pipeline.distributed.unsupported`, the
added masses in it) they are M's own products.
D = R_O^T M R_O is the rigid mass the FE stage summed. The record is then the serial
:func:`~pipeline.reduce.ffrf.invariants_from_products`.
"""

from __future__ import annotations

import numpy as np

from pipeline.distributed.blocks import RowBlock
from pipeline.distributed.assemble import full_mass_rows
from pipeline.distributed.mpi import allreduce_sum
from pipeline.distributed.operators import RowMatrix
from pipeline.fe.body import rigid_body_modes
from pipeline.reduce.ffrf import (FFRFInvariants, invariants_from_products, modes_basis_labels,
                                 skew_columns)

__all__ = ["modes_invariants"]


def _node_major(block: RowBlock) -> np.ndarray:
    """(3 p, k) this rank's rows of ``block`` as node-major fields on its points."""
    _, values = block.on_points()
    return values.reshape(-1, values.shape[2])


def _field_rows(mesh, block: RowBlock, fields: np.ndarray) -> np.ndarray:
    """(hi - lo, k) this rank's rows (PETSc order) of nodal ``fields`` (n_loc, 3, k)
    given on the part's local nodes."""
    dofs = block.dofs()
    return fields[mesh.local_nodes(dofs // 3), dofs % 3]


def modes_invariants(space, K: RowMatrix, M: RowMatrix, shapes: RowBlock,
                     rigid_mass: np.ndarray, labels: tuple | None = None) -> FFRFInvariants:
    """The invariants about the origin of the basis ``shapes`` (the run's modes of a
    body clamped on a region, (n_free, n) rows on the ranks; module), as
    :func:`pipeline.reduce.ffrf.build_ffrf` makes them serially for a supported body
    without Craig-Bampton. ``space``: the DistributedSpace (its ``local`` part);
    ``K``, ``M``: the run's distributed matrices with
    their PETSc matrices; ``rigid_mass`` (6, 6) R_O^T M R_O; ``labels``: (basis kind,
    coordinate names, units) of another basis zero on the held points (default: the
    run's modes). ``basis`` of the record is the RowBlock itself. Collective."""
    mesh = space.local
    n = shapes.shape[1]
    comm = shapes.comm
    M_psi = M.apply(shapes)
    x = mesh.space.node_points[:, :, None]  # positions about the origin, (n_loc, 3, 1)
    R_O = rigid_body_modes(mesh.space.node_points).reshape(-1, 3, 6)
    if M.shape[0] == space.n_dofs:  # the unsupported M itself (added masses too)
        Mx, MR = (M.apply(shapes.like(_field_rows(mesh, shapes, f))) for f in (x, R_O))
    else:  # the rows of M that couple to the held points, from the part's elements
        Mx, MR = (shapes.like(full_mass_rows(mesh, f)) for f in (x, R_O))
    psi, m_psi = _node_major(shapes), _node_major(M_psi)
    psi_t = skew_columns(psi)
    coupling = MR.gram(shapes)
    x_psi = allreduce_sum(comm, skew_columns(_node_major(Mx)).T @ psi_t)
    psi_psi = allreduce_sum(comm, psi_t.T @ skew_columns(m_psi))
    psi_m_psi = allreduce_sum(comm, psi_t.T @ m_psi)
    return invariants_from_products(
        np.zeros(3), rigid_mass, coupling, shapes.gram(M_psi), shapes.gram(K.apply(shapes)),
        x_psi, psi_psi, psi_m_psi, shapes,
        *(labels or modes_basis_labels(np.arange(n), True)))
