"""Rank 0 lets the whole mesh go once the parts are sent (issue 38, rank 0's memory).

Rank 0 meshes the body and evaluates the whole mesh (regions, supports, ports, element
materials, the partition), cuts out and sends every rank its part, and from then on
holds, besides its own part, only what the writer stores, in a compact form
(:func:`pipeline.distributed.stage.handed_off`): the points, the elements as int32, the
regions, the held DOFs and, where ``/materials`` is written, the element materials.
The check runs the CLI on 2 ranks with a spy: on rank 0 it takes weak references to
the whole-mesh objects (the :class:`~pipeline.distributed.stage.WholeMesh`, its FE
space, scikit-fem mesh, gmsh body, int64 elements and edges, its element materials) as
:func:`~pipeline.distributed.stage.mesh_whole` returns them, and asserts, when rank 0
starts to assemble its rows (the FE stage's peak) and again when the modes stage
starts, without a garbage collection (reference counts free them at the hand-off, not
some later collection), that every one is dead, and that the whole-mesh
arrays left are the points (24 bytes a point) and the int32 elements (4 bytes a node
of an element). With the whole element materials in the file (a ``materials`` config)
they are kept, and nothing else. The memory gate before the assembly
(:func:`~pipeline.distributed.stage.check_rank_memory`) charges rank 0 those kept
arrays (or its hand-off phase where larger), not a whole mesh more.
"""

from __future__ import annotations

import os
import re
import subprocess

import numpy as np
import pytest

from conftest import ROOT
from test_mpi import MPI_PYTHON, _mpiexec

_SPY = """
import sys, weakref
import numpy as np
from pipeline.distributed import stage

refs, seen = {}, {}
mesh_whole, compute_modes, local_rows = stage.mesh_whole, stage.compute_modes, stage.local_rows

def whole_refs(cfg, mesh_dir):
    whole = mesh_whole(cfg, mesh_dir)
    space = whole.space
    refs.update(whole=weakref.ref(whole), space=weakref.ref(space),
                skfem_mesh=weakref.ref(space.skfem_mesh), body=weakref.ref(space.body),
                element_nodes=weakref.ref(space.element_nodes), edges=weakref.ref(space.edges),
                materials=weakref.ref(whole.materials))
    seen.update(n_points=space.n_nodes, elements=space.element_nodes.shape)
    return whole

def at_assembly(mesh):
    seen["assembly"] = sorted(name for name, ref in refs.items() if ref() is not None)
    return local_rows(mesh)

def at_modes(fe, cfg):
    comm = stage.world()
    alive = sorted(set(seen.get("assembly", [])) |
                   {name for name, ref in refs.items() if ref() is not None})
    kept = expected = 0
    if comm.rank == 0:  # the whole-mesh arrays kept: the points and the elements
        space = fe.space
        kept = space.node_points.nbytes + space.element_nodes.nbytes
        expected = 24 * seen["n_points"] + 4 * int(np.prod(seen["elements"]))
        assert space.element_nodes.shape == seen["elements"]
        assert space.node_points.shape == (seen["n_points"], 3)
    print(f"rank {comm.rank} alive [{','.join(alive)}] kept {kept} compact {expected}",
          flush=True)
    return compute_modes(fe, cfg)

stage.mesh_whole, stage.compute_modes, stage.local_rows = whole_refs, at_modes, at_assembly
from pipeline.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _held_on_ranks(tmp_path, config: str, *overrides: str) -> dict[int, tuple]:
    """Run ``config`` on 2 ranks through the CLI with the spy; {rank: (the whole-mesh
    objects alive at the start of the modes stage, the bytes of the whole-mesh points and
    elements kept, those bytes in the compact form)}."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMPI_ALLOW_RUN_AS_ROOT": "1",
           "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    sets = [a for item in ("modes.solver=slepc", "mesh.size=0.02", *overrides)
            for a in ("--set", item)]
    out = tmp_path / "x.h5"
    proc = subprocess.run([*_mpiexec(2), str(MPI_PYTHON), "-c", _SPY, "run", config, *sets,
                           "-o", str(out)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert out.exists()
    # the ranks' lines may share one line of mpiexec's combined stdout
    found = re.findall(r"rank (\d) alive \[([a-z_,]*)\] kept (\d+) compact (\d+)",
                       proc.stdout)
    assert sorted(int(r) for r, *_ in found) == [0, 1], proc.stdout[-2000:]
    return {int(r): ([n for n in names.split(",") if n], int(kept), int(compact))
            for r, names, kept, compact in found}


@pytest.mark.mpi
@pytest.mark.parametrize("config", ["configs/cantilever.yaml",
                                    "configs/cantilever_connection.yaml"],
                         ids=["plain", "connection"])  # the second: a second split
def test_rank0_drops_the_whole_mesh_once_the_parts_are_sent(tmp_path, config):
    held = _held_on_ranks(tmp_path, config)
    assert {r: h[0] for r, h in held.items()} == {0: [], 1: []}, held
    assert held[0][1] == held[0][2] > 0 and held[1][1:] == (0, 0), held


@pytest.mark.mpi
def test_rank0_keeps_the_element_materials_it_writes_and_nothing_else(tmp_path):
    held = _held_on_ranks(tmp_path, "configs/cantilever_materials.yaml")
    assert {r: h[0] for r, h in held.items()} == {0: ["materials"], 1: []}, held
    assert held[0][1] == held[0][2] > 0, held


_ESTIMATES = """
from pipeline._util import resources as res
from pipeline.config import load_config
from pipeline.distributed.mpi import world
from pipeline.distributed.stage import check_rank_memory, handoff_meshes, kept_bytes

comm = world()
for n_nodes, n_el, extra in ((40000, 25000, []), (40000, 25000, ["mesh.size=0.02"]),
                             (40000, 25000, ["modes.method=multigrid"])):
    cfg = load_config("configs/cantilever.yaml", ["modes.solver=slepc", *extra])
    both = comm.gather(check_rank_memory(n_nodes, n_el, cfg, comm), root=0)
    if comm.rank == 0:
        share = both[1] - res.BASELINE_BYTES
        handoff = handoff_meshes(comm.size) * (res.MESH_BYTES_PER_NODE * n_nodes + 64 * n_el)
        print(both[0] - both[1], share + kept_bytes(n_nodes, n_el, cfg), handoff, share)
"""


@pytest.mark.mpi
def test_the_rank_memory_estimate_counts_rank0s_kept_mesh_not_a_whole_one():
    """check_rank_memory: rank 0's estimate is rank 1's plus the kept points and int32
    elements (24 bytes a point, 40 a quadratic element), or its hand-off phase where
    that is larger; no longer a whole mesh (600 bytes a point) on top of its share."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMPI_ALLOW_RUN_AS_ROOT": "1",
           "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    proc = subprocess.run([*_mpiexec(2), str(MPI_PYTHON), "-c", _ESTIMATES], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for line in proc.stdout.split("\n"):
        if not line.strip():
            continue
        more, solve, handoff, share = map(float, line.split())
        # int() of each rank's bytes: exact to a byte or two
        assert abs(more - (max(solve, handoff) - share)) <= 2.0, line
        assert more < 24 * 40000 + 40 * 25000 + 2.0 or handoff > solve, line


def test_rank0_judges_the_rigid_freedoms_without_an_array_over_every_dof(tmp_path):
    """rigid_freedoms(fields=False), as rank 0 judges the supports after the assembly
    (:func:`~pipeline.distributed.stage.supports_rigid_freedoms`): the same motions as
    the serial judgement less its (n_dofs, r) fields (names equal, twists to 1e-12 of
    their unit length: the springs' R^T S R summed over their DOFs alone differs by
    round-off), for held DOFs, held directions and springs, while it allocates
    (tracemalloc's peak) at most 2.5 times the points (the rms radius' (n, 3)
    temporaries and their (n,) sums: 56 bytes a point, 2.33 times the 24 of the points)
    plus 600 bytes a held or sprung DOF (R's rows of their points, 144 bytes a DOF, its
    rows picked, the springs' rows and columns), not R at every DOF (48 bytes a DOF,
    6 times the points, which the bound refuses)."""
    import tracemalloc

    import scipy.sparse as sp

    from conftest import build_model
    from pipeline.fe.space import region_nodes
    from pipeline.fe.supports import rigid_freedoms

    model = build_model(tmp_path, size=0.02)
    space, regions = model.space, model.regions
    x, n_dofs = space.node_points, space.n_dofs
    root, tip = region_nodes(space, regions["root"]), region_nodes(space, regions["tip"])
    held_x = 3 * root  # the root face held along x: three rigid motions left
    tip_y = sp.csr_matrix((np.ones(tip.size), (np.arange(tip.size), 3 * tip + 1)),
                          shape=(tip.size, n_dofs))  # the tip held along y, exactly
    k = np.linspace(1e6, 2e6, tip.size)  # springs along z at the tip, uneven
    springs = sp.csr_matrix((k, (3 * tip + 2, 3 * tip + 2)), shape=(n_dofs, n_dofs))
    center = x.mean(axis=0)
    mass = np.diag([7.0, 7.0, 7.0, 0.2, 0.3, 0.4])
    for fixed, held, spring, count in ((held_x, None, None, 3), (held_x, tip_y, None, 1),
                                       (held_x, None, springs, 1),
                                       (np.zeros(0, np.int64), None, springs, 4)):
        args = (x, center, fixed, spring, held, mass, 1.0)
        whole = rigid_freedoms(*args)
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            lean = rigid_freedoms(*args, fields=False)
            peak = tracemalloc.get_traced_memory()[1] - before
        finally:
            tracemalloc.stop()
        assert whole.count == count and whole.fields.shape == (n_dofs, count)
        assert lean.names == whole.names and lean.fields.shape == (0, count)
        assert np.abs(lean.twists - whole.twists).max() <= 1e-12
        assert lean.length == whole.length and np.array_equal(lean.center, whole.center)
        touched = fixed.size + (0 if spring is None else 2 * tip.size) + \
            (0 if held is None else tip.size)
        assert peak <= 2.5 * x.nbytes + 600 * touched, (peak, x.nbytes, touched)
