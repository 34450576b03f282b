"""Run the pipeline on every MPI rank and check what each rank holds (tests/test_mpi.py).

Usage: mpiexec -n N python tests/mpi_ranks.py OUTPUT [KEY=VALUE ...] (config overrides of
configs/cantilever.yaml). Writes OUTPUT like ``python -m pipeline run``, then asserts on
every rank that its mode shapes are its own rows only (a RowBlock of hi - lo rows; the
ranks' rows add up to the free DOFs, none holds them all), that the shapes dataset is
written from the ranks' own points (each rank's share smaller than the mesh), that
only rank 0 ran gmsh (none with ``mesh.parts``) and every other rank holds a part of
the mesh, not all of it, that no rank other than 0 received an array as long as the
mesh's points, its DOFs or its free DOFs (every message of the stage's communicator is inspected:
:class:`ReceivedArrays`), and prints one line
per rank: ``rank R rows N of F points P of Q gmsh G part H of Q
elements E of T`` (H, E: the points and elements of its part of the mesh).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


class ReceivedArrays:
    """A communicator that records the shape of every numpy array this rank receives
    (bcast, recv, scatter, allgather, alltoall, gather at the root, Allgatherv's buffer), found
    in tuples, lists, dicts and dataclasses, and passes everything else through."""

    def __init__(self, comm):
        self._comm, self.shapes = comm, []

    def __getattr__(self, name):
        return getattr(self._comm, name)

    def _record(self, obj, depth=0):
        import numpy as np

        if isinstance(obj, np.ndarray):
            self.shapes.append(obj.shape)
        elif depth > 6:
            return
        elif isinstance(obj, (tuple, list)):
            for item in obj:
                self._record(item, depth + 1)
        elif isinstance(obj, dict):
            for item in obj.values():
                self._record(item, depth + 1)
        elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            for f in dataclasses.fields(obj):
                self._record(getattr(obj, f.name), depth + 1)

    def _received(self, obj, mine: bool):
        if not mine:
            self._record(obj)
        return obj

    def bcast(self, obj, root=0):
        return self._received(self._comm.bcast(obj, root=root), self.rank == root)

    def recv(self, *args, **kwargs):
        return self._received(self._comm.recv(*args, **kwargs), False)

    def scatter(self, obj, root=0):
        return self._received(self._comm.scatter(obj, root=root), self.rank == root)

    def _pieces(self, got, mine: bool):
        """A gathered list: its items, and their concatenation if they are arrays."""
        import numpy as np

        if not mine and got and all(isinstance(g, np.ndarray) and g.ndim for g in got):
            self.shapes.append((sum(g.shape[0] for g in got),))
        return self._received(got, mine)

    def allgather(self, obj):
        return self._pieces(self._comm.allgather(obj), False)

    def gather(self, obj, root=0):
        return self._pieces(self._comm.gather(obj, root=root), self.rank != root)

    def alltoall(self, obj):
        return self._pieces(self._comm.alltoall(obj), False)

    def Allgatherv(self, send, recv):
        self._comm.Allgatherv(send, recv)
        self._record(recv[0])

    def whole_length(self, *lengths: int) -> list:
        """The received shapes with an axis of one of ``lengths``."""
        return [s for s in self.shapes if any(n in s for n in lengths)]


def main(argv: list[str]) -> None:
    from pipeline import run
    from pipeline.config import load_config
    from pipeline.distributed import stage
    from pipeline.distributed.blocks import PointBlocks, RowBlock
    from pipeline.fe import model

    cfg = load_config(ROOT / "configs" / "cantilever.yaml", ["modes.solver=slepc", *argv[1:]])
    seen = {"gmsh": 0}
    compute, mesh_body = stage.compute_modes, model.mesh_body

    def spy(fe, config):
        modes = compute(fe, config)
        part = fe.space.local
        seen.update(modes=modes, n_free=int(fe.free.size), n_points=int(fe.space.n_nodes),
                    part_points=int(part.points.size), n_elements=int(fe.n_elements),
                    part_elements=int(part.space.element_nodes.shape[0]))
        return modes

    def meshing(*args, **kwargs):
        seen["gmsh"] += 1
        return mesh_body(*args, **kwargs)

    comm = ReceivedArrays(stage.world())
    stage.compute_modes, model.mesh_body = spy, meshing  # mesh_config's gmsh call
    stage.world = lambda: comm  # every message of the stages passes through it
    run.run_pipeline(cfg, argv[0])
    modes, n_free, n_points = seen["modes"], seen["n_free"], seen["n_points"]
    shapes, blocks = modes.shapes, modes.shapes_full
    assert isinstance(shapes, RowBlock), type(shapes)
    rows = shapes.hi - shapes.lo
    assert shapes.local.shape == (rows, modes.omega2.size), shapes.local.shape
    assert comm.allreduce(rows) == n_free
    assert comm.size == 1 or rows < n_free
    assert isinstance(blocks, PointBlocks) and blocks.shape[0] == n_points
    assert comm.size == 1 or blocks.points.size < n_points
    # with a parts file (mesh.parts) no rank meshes
    assert seen["gmsh"] == (1 if comm.rank == 0 and not cfg.mesh.parts else 0), seen["gmsh"]
    assert comm.size == 1 or (seen["part_points"] < n_points
                              and seen["part_elements"] < seen["n_elements"])
    # whole-length arrays are rank 0's alone: the free DOFs, the PETSc row order, the
    # label step's points and weights, any (n_free, k) block
    whole = comm.whole_length(n_points, n_free, 3 * n_points)
    assert comm.rank == 0 or not whole, f"rank {comm.rank} received {whole}"
    print(f"rank {comm.rank} rows {rows} of {n_free} points {blocks.points.size} of "
          f"{n_points} gmsh {seen['gmsh']} part {seen['part_points']} of {n_points} "
          f"elements {seen['part_elements']} of {seen['n_elements']}", flush=True)


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main(sys.argv[1:])
