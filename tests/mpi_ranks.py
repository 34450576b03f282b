"""Run the pipeline on every MPI rank and check what each rank holds (tests/test_mpi.py).

Usage: mpiexec -n N python tests/mpi_ranks.py OUTPUT [KEY=VALUE ...] (config overrides of
configs/cantilever.yaml). Writes OUTPUT like ``python -m pipeline run``, then asserts on
every rank that its mode shapes are its own rows only (a RowBlock of hi - lo rows; the
ranks' rows add up to the free DOFs, none holds them all), that the shapes dataset is
written from the ranks' own points (each rank's share smaller than the mesh), that
only rank 0 ran gmsh and every other rank holds a part of the mesh, not all of it,
and prints one line per rank: ``rank R rows N of F points P of Q gmsh G part H of Q
elements E of T`` (H, E: the points and elements of its part of the mesh).
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


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

    stage.compute_modes, model.mesh_body = spy, meshing  # mesh_config's gmsh call
    run.run_pipeline(cfg, argv[0])
    comm = stage.world()
    modes, n_free, n_points = seen["modes"], seen["n_free"], seen["n_points"]
    shapes, blocks = modes.shapes, modes.shapes_full
    assert isinstance(shapes, RowBlock), type(shapes)
    rows = shapes.hi - shapes.lo
    assert shapes.local.shape == (rows, modes.omega2.size), shapes.local.shape
    assert comm.allreduce(rows) == n_free
    assert comm.size == 1 or rows < n_free
    assert isinstance(blocks, PointBlocks) and blocks.shape[0] == n_points
    assert comm.size == 1 or blocks.points.size < n_points
    assert seen["gmsh"] == (1 if comm.rank == 0 else 0), seen["gmsh"]
    assert comm.size == 1 or (seen["part_points"] < n_points
                              and seen["part_elements"] < seen["n_elements"])
    print(f"rank {comm.rank} rows {rows} of {n_free} points {blocks.points.size} of "
          f"{n_points} gmsh {seen['gmsh']} part {seen['part_points']} of {n_points} "
          f"elements {seen['part_elements']} of {seen['n_elements']}", flush=True)


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main(sys.argv[1:])
