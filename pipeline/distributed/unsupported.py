"""The UNSUPPORTED body's K and M on MPI ranks, for the connection models whose clamped
pencil is not the run's (:mod:`pipeline.distributed.connection`): a distributing (RBE3)
parent, supports other than exactly the parent region held, springs, added masses.

Serially the connection model clamps the parent interface of the unsupported body,
K_c = T_c^T K T_c and M_c = T_c^T M T_c with K, M (n_dofs, n_dofs) before the supports
(the springs are supports; the added masses are in M). On the ranks the run's K and M
live on the free DOFs only, so a second pair is assembled on a partition of EVERY DOF
(:func:`held_partition`): rank r owns the run's rows of r first, in the same order,
then the held DOFs of its points (a held point without a free DOF goes to the lowest
rank owning a point of one of its elements, else rank 0), so every rank holds whole
points and a block of the run's rows becomes one of every DOF by zero rows appended on
the same rank (:func:`padded`: no communication). Rank 0 cuts the parts of this
partition from the whole mesh as it does the run's (:func:`~pipeline.distributed.submesh.split_mesh`,
with the added masses); each rank assembles its rows of K and M
(:func:`~pipeline.distributed.assemble.local_rows`) only when the connection stage
needs them (:func:`assemble_pair`), and frees them after the clamped solve.

A body with no DOF held and no spring has its unsupported pair already: the run's
(``Unsupported(None, None)``).

Memory per rank: the second part of the mesh from the FE stage on, and during the
connection stage the second K and M (what the run's rows cost, plus the held rows) and
the clamped pencil's MUMPS factor beside the run's (:func:`pair_bytes`, counted by the
FE stage's memory check).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.distributed.assemble import local_rows
from pipeline.distributed.blocks import RowBlock
from pipeline.distributed.eigen import petsc_matrix
from pipeline.distributed.mpi import petsc
from pipeline.distributed.operators import RowMatrix
from pipeline.distributed.partition import RowPartition
from pipeline.distributed.submesh import (
    RankMesh,
    point_ranks,
    scatter_parts,
    split_mesh,
)

__all__ = ["Unsupported", "held_partition", "unsupported_parts", "assemble_pair", "padded",
           "pair_bytes"]


@dataclass(frozen=True)
class Unsupported:
    """One rank's share of the unsupported body (module): ``mesh`` its part on the
    partition of every DOF and ``part`` its own rows of it (PETSc row -> DOF,
    :meth:`~pipeline.distributed.partition.RowPartition.local`), or both None when the
    run's matrices are the unsupported ones (no DOF held, no spring)."""

    mesh: RankMesh | None
    part: RowPartition | None


def held_partition(part: RowPartition, free: np.ndarray, n_dofs: int,
                   element_nodes: np.ndarray, size: int) -> RowPartition:
    """The partition of all ``n_dofs`` DOFs (module): rank r's run rows (``part`` of the
    sorted ``free`` DOFs) in their order, then the held DOFs of r's points, ascending.
    ``element_nodes`` (n_el, nb) place a held point without a free DOF."""
    free = np.asarray(free)
    n_nodes = n_dofs // 3
    owner = point_ranks(n_nodes, part, size)  # size: no free DOF
    alone = owner == size
    if alone.any() and element_nodes.size:  # the lowest rank among its elements' points
        nb = element_nodes.shape[1]
        near = np.full(n_nodes, size, dtype=np.int64)
        np.minimum.at(near, element_nodes.ravel(),
                      np.repeat(owner[element_nodes].min(axis=1), nb))
        owner[alone] = near[alone]
    owner[owner == size] = 0
    held = np.setdiff1d(np.arange(n_dofs), free)
    held_rank = owner[held // 3]
    order, starts = [], [0]
    for r in range(size):
        mine = np.concatenate([part.owned_dofs(r), held[held_rank == r]])
        order.append(mine)
        starts.append(starts[-1] + mine.size)
    order = np.concatenate(order).astype(np.int64)  # every DOF is a row: its own index
    return RowPartition(order=order, starts=np.asarray(starts, dtype=np.int64), dofs=order)


def unsupported_parts(comm, whole, part: RowPartition) -> Unsupported:
    """Every rank's :class:`Unsupported` (collective; ``whole``: the
    :class:`~pipeline.distributed.stage.WholeMesh` on rank 0, None elsewhere; ``part``
    the run's partition)."""
    reuse = None if whole is None else (whole.fixed.size == 0 and whole.springs is None)
    if comm.bcast(reuse, root=0):
        return Unsupported(None, None)
    parts = full = None
    if whole is not None:
        space = whole.space
        full = held_partition(part, whole.free, space.n_dofs, space.element_nodes,
                              comm.size)
        parts = split_mesh(space, whole.materials, np.arange(space.n_dofs), full,
                           comm.size, whole.added)
    mesh = scatter_parts(comm, parts)
    # each rank keeps its own rows of the partition (the whole one: O(n_dofs))
    own = comm.scatter(None if full is None else [full.local(r) for r in range(comm.size)],
                       root=0)
    return Unsupported(mesh, own)


def assemble_pair(comm, un: Unsupported) -> tuple[RowMatrix, RowMatrix]:
    """This rank's rows of the unsupported K (N/m) and M (kg) on ``un.part``, their
    PETSc matrices attached (collective; the caller destroys them)."""
    PETSc, _ = petsc()
    rows = local_rows(un.mesh)
    n = un.part.n_free
    K, M = RowMatrix(comm, rows.K, un.part), RowMatrix(comm, rows.M, un.part)
    K.petsc, M.petsc = petsc_matrix(PETSc, rows.K, n), petsc_matrix(PETSc, rows.M, n)
    return K, M


def padded(block: RowBlock, part: RowPartition) -> RowBlock:
    """The run's (n_free, k) rows ``block`` as (n_dofs, k) rows on ``part`` (the
    partition of :func:`held_partition`): zero on the held DOFs, no communication."""
    lo, hi = part.rows(block.comm.rank)
    local = np.zeros((hi - lo, block.local.shape[1]))
    local[:block.local.shape[0]] = block.local
    return RowBlock(block.comm, part, local)


def pair_bytes(n_nodes: int, order: int) -> float:
    """Bytes of the whole body's unsupported share (module) to divide by the ranks: the
    second part of the mesh, K and M on every DOF (the node-block estimate of
    :mod:`pipeline._util.resources`) and the clamped pencil's factor, which lives beside
    the run's."""
    from pipeline._util import resources as res

    return (res.MESH_BYTES_PER_NODE * n_nodes
            + res.BYTES_PER_BLOCK * res.BLOCKS_PER_NODE.get(order, 27.0) * n_nodes
            + res.factor_bytes(3 * n_nodes))
