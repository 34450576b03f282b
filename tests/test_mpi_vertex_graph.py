"""The partitioner's graph on the mesh vertices (:mod:`pipeline.distributed.partition`).

Without MPI: the vertex graph's rows are the mesh's edges between the vertices that are
home to a free DOF, every point's home is a vertex of its own edge, and the vertex
weights add up to the free DOFs. With ``make mpi-env``:
PETSc's partitioner takes the vertex weights (a chain whose first tenth weighs ten times
the rest is cut where the weights balance, not at the middle), and on 3 ranks the rows
of every part are whole points, balanced in free DOFs within PT-Scotch's imbalance
tolerance plus one vertex's weight.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.sparse as sp

from conftest import build_model
from test_mpi import MPI_PYTHON, _mpiexec, _run


def test_the_vertex_graph_is_the_mesh_edges_weighted_by_the_free_dofs_at_home(tmp_path):
    from pipeline.distributed.partition import vertex_graph_rows, vertex_homes

    model = build_model(tmp_path, size=0.02)
    space, free, size = model.space, model.free, 3
    n_v, en = space.body.n_vertices, space.element_nodes
    edges = np.sort(space.edges, axis=1)  # midpoint n_v + k is edge k's (FESpace)
    home, far, n_v_found = vertex_homes(en, space.n_nodes)
    assert n_v_found == n_v
    assert np.array_equal(home[:n_v], np.arange(n_v))
    assert np.array_equal(home[n_v:], edges[:, 0]) and np.array_equal(far, edges[:, 1])

    home2, vertex, vorder, rows = vertex_graph_rows(en, space.node_points, free, size)
    assert np.array_equal(home2, home)
    per_point = np.bincount(free // 3, minlength=space.n_nodes)
    weight = np.bincount(home, weights=per_point, minlength=n_v).astype(np.int64)
    assert np.array_equal(np.flatnonzero(vertex >= 0), np.flatnonzero(weight > 0))
    assert (vertex[home[free // 3]] >= 0).all()  # every free DOF's home is in the graph
    # reference: the edges both ways, on the graph's vertices
    keep = (vertex[edges[:, 0]] >= 0) & (vertex[edges[:, 1]] >= 0)
    a, b = vertex[edges[keep, 0]], vertex[edges[keep, 1]]
    G = sp.csr_matrix((np.ones(2 * a.size), (np.concatenate([a, b]), np.concatenate([b, a]))),
                      shape=(vorder.size, vorder.size))
    G.sort_indices()
    vs = [(vorder.size * r) // size for r in range(size + 1)]
    total = 0
    for r in range(size):
        indptr, indices, vertex_weights = rows(r)
        ref = G[vs[r]:vs[r + 1]]
        assert indices.dtype == np.int32
        assert np.array_equal(indptr, ref.indptr) and np.array_equal(indices, ref.indices)
        assert np.array_equal(vertex_weights, weight[vorder[vs[r]:vs[r + 1]]])
        total += int(vertex_weights.sum())
    assert total == free.size


_WEIGHTS = """
import numpy as np
from petsc4py import PETSc
from pipeline.distributed.partition import set_weights
n = 100
ptr = [0]; idx = []
for i in range(n):
    idx += [j for j in (i - 1, i + 1) if 0 <= j < n]; ptr.append(len(idx))
G = PETSc.Mat().createAIJ(size=((n, n), (n, n)), comm=PETSc.COMM_SELF,
    csr=(np.array(ptr, dtype=PETSc.IntType), np.array(idx, dtype=PETSc.IntType),
         np.ones(len(idx))))
G.assemble()
PETSc.Options().setValue("weights_test_mat_partitioning_nparts", 2)
out = {}
for weighted in (False, True):
    mp = PETSc.MatPartitioning().create(comm=PETSc.COMM_SELF)
    mp.setOptionsPrefix("weights_test_")
    mp.setType("ptscotch"); mp.setAdjacency(G)
    if weighted:
        w = np.ones(n, dtype=int); w[:10] = 10
        set_weights(PETSc, mp, w)
    mp.setFromOptions()
    parts = PETSc.IS(); mp.apply(parts)
    out[str(weighted)] = parts.getIndices().tolist()
    parts.destroy(); mp.destroy()
print("PARTS " + __import__("json").dumps(out))
"""


@pytest.mark.mpi
def test_petscs_partitioner_takes_the_vertex_weights(tmp_path):
    """A chain of 100 vertices in 2 parts: 50 and 50 unweighted; with the first ten
    weighing 10 each (190 in all), the part holding them has about 95 of the weight:
    those ten and at most a vertex or two more."""
    _mpiexec(1)  # skips without the MPI environment
    proc = _run([str(MPI_PYTHON), "-c", _WEIGHTS], tmp_path, timeout=120)
    line = next(x for x in proc.stdout.splitlines() if x.startswith("PARTS "))
    parts = {k: np.array(v) for k, v in json.loads(line[6:]).items()}
    assert sorted(np.bincount(parts["False"]).tolist()) == [50, 50]
    heavy = parts["True"] == parts["True"][0]
    assert heavy[:10].all() and 10 <= heavy.sum() <= 12, parts["True"]


_PARTITION = """
import json, sys
import numpy as np
from mpi4py import MPI
from petsc4py import PETSc
sys.path.insert(0, "tests")
from conftest import build_model
from pathlib import Path
from pipeline.distributed.partition import graph_partition, vertex_graph_rows
comm = MPI.COMM_WORLD
model = build_model(Path(sys.argv[1]) / str(comm.rank), size=0.015) if comm.rank == 0 else None
space = model.space if model else None
part = graph_partition(PETSc, comm, space.element_nodes if model else None,
                       space.node_points if model else None, model.free if model else None)
if comm.rank == 0:
    home, vertex, vorder, rows = vertex_graph_rows(space.element_nodes, space.node_points,
                                                   model.free, comm.size)
    heaviest = max(int(rows(r)[2].max()) for r in range(comm.size))
    print("PARTITION " + json.dumps({"starts": part.starts.tolist(),
        "dofs": part.dofs.tolist(), "free": model.free.tolist(), "heaviest": heaviest}))
"""


@pytest.mark.mpi
def test_three_ranks_get_whole_points_balanced_in_free_dofs(tmp_path):
    """PT-Scotch's parts of the weighted vertex graph on 3 ranks: the rows are the free
    DOFs, each once; a point's three DOFs are consecutive rows of one rank; each rank's
    row count is within PT-Scotch's imbalance tolerance (PETSc's default, 1 %) plus one
    vertex's weight (its DOFs and its midpoints' move together) of the mean."""
    proc = _run([*_mpiexec(3), str(MPI_PYTHON), "-c", _PARTITION, str(tmp_path)], tmp_path,
                timeout=300)
    line = next(x for x in proc.stdout.splitlines() if x.startswith("PARTITION "))
    got = json.loads(line[10:])
    dofs, free, starts = np.array(got["dofs"]), np.array(got["free"]), np.array(got["starts"])
    assert np.array_equal(np.sort(dofs), free)
    counts = np.diff(starts)
    mean = free.size / 3
    assert counts.max() <= mean * 1.01 + got["heaviest"], counts
    for r in range(3):
        mine = dofs[starts[r]:starts[r + 1]]
        assert np.array_equal(mine[::3] // 3, mine[2::3] // 3)  # whole points, in order
        assert np.array_equal(mine % 3, np.tile([0, 1, 2], mine.size // 3))
    owner = np.repeat(np.arange(3), counts)
    point_owner = {}
    for d, o in zip(dofs // 3, owner):
        assert point_owner.setdefault(d, o) == o  # a point on one rank
