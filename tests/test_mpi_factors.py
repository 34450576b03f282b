"""The MUMPS factors on MPI ranks (:mod:`pipeline.distributed`): what the per-rank memory
estimate counts and what the block products give.

The estimate before the run (:func:`pipeline.distributed.stage.check_rank_memory`)
counts one more factor of K's size, :func:`pipeline._util.resources.factor_bytes`,
divided among the ranks, exactly when a rotation sweep factorises K(Omega) beside the
run's factor (factor path, a speed other than 0); a sweep at rest only, or the
factor-free path, adds nothing. The connection models' and a free body's inertia
relief's factors are made after the run's is freed, so they add nothing either.
"""

from __future__ import annotations

import os
import subprocess

import pytest

from conftest import ROOT
from test_mpi import MPI_PYTHON, _mpiexec

_ESTIMATES = """
from pipeline.config import load_config
from pipeline.distributed.mpi import world
from pipeline.distributed.stage import check_rank_memory
from pipeline._util.resources import factor_bytes

spin = "rotation={axis: [0, 0, 1], point: [0, 0.01, 0.025], speeds_rad_s: [%s]}"
cases = [[], [spin % "0, 100"], [spin % "0"], [spin % "0, 100", "modes.method=multigrid"]]
comm = world()
n_nodes, n_el = 40000, 25000
plain, sweep, rest, factor_free = (
    check_rank_memory(n_nodes, n_el, load_config("configs/cantilever.yaml",
                                                 ["modes.solver=slepc", *extra]), comm)
    for extra in cases)
if comm.rank == 1:
    print(sweep - plain, factor_bytes(3 * n_nodes) / comm.size, rest - plain,
          factor_free - plain)
"""


@pytest.mark.mpi
def test_the_rank_memory_estimate_counts_the_rotation_sweeps_second_factor():
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMPI_ALLOW_RUN_AS_ROOT": "1",
           "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    proc = subprocess.run([*_mpiexec(2), str(MPI_PYTHON), "-c", _ESTIMATES], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    added, expected, at_rest, factor_free = map(float, proc.stdout.split())
    # int() of the per-rank bytes: the difference is exact to a byte
    assert abs(added - expected) <= 1.0 and expected > 0
    assert at_rest == 0.0
    assert factor_free == 0.0
