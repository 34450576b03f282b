"""What a rank holds of the free-DOF numbering (:mod:`pipeline.distributed.partition`)
and the port rows it reads (:func:`pipeline.distributed.blocks.dof_rows`), without MPI:
each emulated rank's own partition holds its rows only, and gathering the ranks' own
partitions gives the whole one back; the rows of a sparse port matrix at a rank's
DOFs are the matrix's rows, made from its stored entries alone."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp

from pipeline.distributed.blocks import RowBlock, dof_rows
from pipeline.distributed.partition import FreeDofs, slab_partition
from conftest import ROOT
from test_mpi import MPI_PYTHON, _mpiexec


class _Gathered:
    """An emulated communicator whose successive allgathers return ``gathers`` (every
    rank's contributions, as MPI would)."""

    def __init__(self, rank: int, gathers: list):
        self.rank, self._gathers = rank, iter(gathers)

    def allgather(self, obj):
        return next(self._gathers)


def test_each_rank_holds_its_own_rows_and_the_whole_partition_gathers_back():
    rng = np.random.default_rng(3)
    points = rng.uniform(0, 1, size=(40, 3)) * [1.0, 0.1, 0.1]
    free = np.setdiff1d(np.arange(120), [0, 1, 2, 7, 50])  # a few held DOFs
    size = 3
    whole = slab_partition(points, free, size)
    assert np.array_equal(whole.dofs, free[whole.order])
    locals_ = [whole.local(r) for r in range(size)]
    for r, own in enumerate(locals_):
        lo, hi = whole.rows(r)
        assert own.order.size == own.dofs.size == hi - lo < free.size
        assert np.array_equal(own.owned_dofs(r), free[whole.owned_free(r)])
        assert own.n_free == free.size and own.rows(r) == (lo, hi)
        with pytest.raises(ValueError, match="own rows only"):
            own.owned_free((r + 1) % size)
        block = RowBlock(SimpleNamespace(rank=r), own, np.zeros((hi - lo, 2)))
        assert block.shape == (free.size, 2) and np.array_equal(block.dofs(), own.dofs)
    comm = _Gathered(1, [[p.order for p in locals_], [p.dofs for p in locals_]])
    back = locals_[1].whole(comm)
    assert np.array_equal(back.order, whole.order) and np.array_equal(back.dofs, whole.dofs)
    assert np.array_equal(back.free_dofs(), free)
    assert FreeDofs(free.size).size == free.size
    with pytest.raises(TypeError, match="not held on every rank"):
        np.asarray(FreeDofs(free.size))


def _point_graph(space, free, size):
    """Reference: the point graph of ``space`` as scipy's product E^T E of the
    element-node incidence, its columns mapped to the vertices of
    :func:`~pipeline.distributed.partition.slab_graph_rows` (the points with a free DOF,
    along the longest extent), without self loops, cut into the slabs' rows."""
    from pipeline.distributed.partition import slab_graph_rows

    vertex, vorder, _ = slab_graph_rows(space.element_nodes, space.node_points, free, size)
    n_el, nb = space.element_nodes.shape
    E = sp.csr_matrix((np.ones(n_el * nb), space.element_nodes.ravel(),
                       np.arange(0, n_el * nb + 1, nb)), shape=(n_el, space.n_nodes))
    A = (E.T @ E).tocoo()
    keep = (vertex[A.row] >= 0) & (vertex[A.col] >= 0) & (A.row != A.col)
    G = sp.csr_matrix((np.ones(int(keep.sum())), (vertex[A.row[keep]], vertex[A.col[keep]])),
                      shape=(vorder.size, vorder.size))
    G.sort_indices()
    vs = [(vorder.size * r) // size for r in range(size + 1)]
    return vertex, vorder, [G[vs[r]:vs[r + 1]] for r in range(size)]


def test_the_graph_rows_made_chunk_by_chunk_are_the_point_graph_and_stay_small(tmp_path):
    """slab_graph_rows (rank 0's rows of the partitioner's graph, issue 38): each slab's
    rows, made a chunk of points at a time (down to one point a chunk), are those of the
    whole point graph E^T E (two points with a free DOF adjacent when an element holds
    both), and making a slab's rows allocates (tracemalloc's peak) at most twice the
    indices they keep (the chunks' pieces and their concatenation), four times their
    indptr (the points' pair counts, the chunks' row counts, their concatenation, the
    indptr) and 150 bytes an element-node pair of one chunk (its elements, product rows,
    keys and their sort: about 60 measured), not a product of the whole slab at once
    (about 15 times the indices it keeps, which this bound refuses)."""
    import tracemalloc

    from conftest import build_model
    from pipeline.distributed.partition import slab_graph_rows

    model = build_model(tmp_path, size=0.02)
    space, free, size = model.space, model.free, 3
    vertex, vorder, ref = _point_graph(space, free, size)
    assert vorder.size == np.unique(free // 3).size < space.n_nodes  # the held face: no vertex
    for chunk in (1, 2000, 1 << 19):
        v, o, rows = slab_graph_rows(space.element_nodes, space.node_points, free, size,
                                     chunk_pairs=chunk)
        assert np.array_equal(v, vertex) and np.array_equal(o, vorder)
        for r in range(size):
            indptr, indices = rows(r)
            assert indices.dtype == np.int32
            assert np.array_equal(indptr, ref[r].indptr), (chunk, r)
            assert np.array_equal(indices, ref[r].indices), (chunk, r)
    chunk = 1000
    _, _, rows = slab_graph_rows(space.element_nodes, space.node_points, free, 1,
                                 chunk_pairs=chunk)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        indptr, indices = rows(0)
        peak = tracemalloc.get_traced_memory()[1] - before
    finally:
        tracemalloc.stop()
    assert indices.size > 10 * chunk  # dozens of chunks: the bound is not the whole slab's
    assert peak <= 2 * indices.nbytes + 4 * indptr.nbytes + 150 * chunk, peak


def test_port_rows_at_a_ranks_dofs_are_the_matrix_rows():
    rng = np.random.default_rng(0)
    F = sp.random(300, 4, density=0.05, format="csc", random_state=1)  # loads, CSC
    T = sp.random(3, 300, density=0.05, format="csr", random_state=2)  # sensors, CSR
    dofs = rng.permutation(300)[:80]  # a rank's rows: any order
    assert (dof_rows(F, dofs) != sp.csr_matrix(F)[dofs]).nnz == 0
    assert (dof_rows(T.T, dofs).T != T[:, dofs]).nnz == 0
    assert dof_rows(F, dofs[:0]).shape == (0, 4)


class _Exchange:
    """What emulated ranks (threads) hand each other in one collective."""

    def __init__(self, size: int):
        import threading

        self.slots, self.barrier = [None] * size, threading.Barrier(size)

    def swap(self, rank: int, obj) -> list:
        self.slots[rank] = obj
        self.barrier.wait()
        out = list(self.slots)
        self.barrier.wait()
        return out


class _ThreadComm:
    """An emulated rank's communicator (allgather, alltoall) over an :class:`_Exchange`."""

    def __init__(self, rank: int, exchange: _Exchange):
        self.rank, self.size, self._x = rank, len(exchange.slots), exchange

    def allgather(self, obj):
        return self._x.swap(self.rank, obj)

    def alltoall(self, objs):
        return [sent[self.rank] for sent in self._x.swap(self.rank, objs)]


def test_each_ranks_coarse_numbers_are_the_whole_numbering(tmp_path):
    """The factor-free path's coarse DOFs: each emulated rank numbers its own vertex rows
    after the ranks before it and asks the owners for the other vertex rows its
    midpoint rows read; its numbers are coarse_numbering of every row (the serial
    definition), and it asked for few rows (its neighbours' boundary layer)."""
    import threading

    from conftest import ALUMINIUM, build_model
    from pipeline.distributed.multigrid import coarse_numbering, coarse_rows
    from pipeline.distributed.submesh import split_mesh
    from pipeline.fe.materials import assign_materials

    model = build_model(tmp_path, size=0.02)
    space, free, size = model.space, model.free, 3
    n_vertices = space.body.n_vertices
    part = slab_partition(space.node_points, free, size)
    meshes = list(split_mesh(space, assign_materials(space, ALUMINIUM), free, part, size))
    exchange, found = _Exchange(size), [None] * size

    def rank(r: int) -> None:
        found[r] = coarse_rows(_ThreadComm(r, exchange), part.local(r), meshes[r],
                               n_vertices)

    threads = [threading.Thread(target=rank, args=(r,)) for r in range(size)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    whole = coarse_numbering(part.dofs // 3 < n_vertices)
    for r, coarse in enumerate(found):
        lo, hi = part.rows(r)
        assert np.array_equal(coarse.own, whole[lo:hi])
        assert coarse.others.size and np.array_equal(coarse[coarse.others],
                                                     whole[coarse.others])
        assert coarse.others.size < (hi - lo) // 4  # a layer, not the neighbours' rows
        assert coarse.n_coarse == int(whole.max()) + 1


_CONNECTIONS = ("connections=[{name: root, region: root, point: [0.0, 0.01, 0.025], "
                "coupling: distributing}, {name: tip, region: tip, point: [0.5, 0.01, "
                "0.025], coupling: rigid}]")


@pytest.mark.mpi
@pytest.mark.parametrize("overrides", [
    ("supports=[{region: root, fix: [x]}]", "modes.method=multigrid", "mesh.size=0.03"),
    (_CONNECTIONS, "craig_bampton={modes: 5}", "mesh.size=0.02",
     "supports=[{region: tip, fix: [x]}, {region: root, bushing: {stiffness: [0, 2.0e9, "
     "2.0e9, 1.0e6, 1.0e6, 1.0e6]}}]"),
], ids=["partly-held-factor-free", "unsupported-pair-craig-bampton"])
def test_no_rank_but_zero_receives_a_whole_length_array(tmp_path, overrides):
    """Beyond the plain cantilever (tests/test_mpi.py): a partly held body on the
    factor-free path (its rigid motions on each rank's own points, the coarse numbering
    from each rank's rows) and a connection model on the unsupported pair with
    Craig-Bampton (the partition of every DOF held per rank, the clamped entries made
    on rank 0): tests/mpi_ranks.py asserts on every rank that no message brought it an
    array as long as the points, DOFs or free DOFs."""
    from test_mpi import _run

    proc = _run([*_mpiexec(2), str(MPI_PYTHON), str(ROOT / "tests" / "mpi_ranks.py"),
                 str(tmp_path / "mpi.h5"), *overrides], tmp_path, timeout=300)
    assert len(re.findall(r"rank \d+ rows \d+ of \d+", proc.stdout)) == 2, proc.stdout
