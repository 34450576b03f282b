"""Run the pipeline on every MPI rank and check what each rank holds (tests/test_mpi.py).

Usage: mpiexec -n N python tests/mpi_ranks.py OUTPUT [KEY=VALUE ...] (config overrides of
configs/cantilever.yaml). Writes OUTPUT like ``python -m pipeline run``, then asserts on
every rank that its mode shapes are its own rows only (a RowBlock of hi - lo rows; the
ranks' rows add up to the free DOFs, none holds them all), that the shapes dataset is
written from the ranks' own points (each rank's share smaller than the mesh), and
prints one line per rank: ``rank R rows N of F points P of Q``.
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

    cfg = load_config(ROOT / "configs" / "cantilever.yaml", ["modes.solver=slepc", *argv[1:]])
    seen = {}
    compute = stage.compute_modes

    def spy(fe, config):
        modes = compute(fe, config)
        seen.update(modes=modes, n_free=int(fe.free.size), n_points=int(fe.space.n_nodes))
        return modes

    stage.compute_modes = spy
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
    print(f"rank {comm.rank} rows {rows} of {n_free} points {blocks.points.size} of "
          f"{n_points}", flush=True)


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main(sys.argv[1:])
