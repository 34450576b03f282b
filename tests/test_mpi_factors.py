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


@pytest.mark.mpi
def test_a_rotation_sweep_analyses_once_and_refactorises_per_speed(tmp_path):
    """MUMPS' analysis twice (the modes stage's K and the first speed's K(Omega): two
    logged analyses, each made by MatCholeskyFactorSymbolic before the memory check, and
    PCSetUp's own call, from which MUMPS returns at once for the analysed pattern: four
    calls in PETSc's event counts, ``-log_view``), the numeric factorisation once more
    per speed; the frequencies rise with the speed (the spin's stiffening dominates the
    bending modes of the cantilever spun about z)."""
    import h5py
    import numpy as np

    out = tmp_path / "spin.h5"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMPI_ALLOW_RUN_AS_ROOT": "1",
           "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1", "PETSC_OPTIONS": "-log_view"}
    proc = subprocess.run(
        [*_mpiexec(2), "-x", "PETSC_OPTIONS", str(MPI_PYTHON), "-m", "pipeline", "-v", "run",
         "configs/cantilever.yaml", "--set", "modes.solver=slepc", "--set", "mesh.size=0.02",
         "--set", "rotation={axis: [0, 0, 1], point: [0, 0.01, 0.025], "
         "speeds_rad_s: [0, 200, 400, 600]}", "-o", str(out)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    counts = {line.split()[0]: int(line.split()[1]) for line in proc.stdout.splitlines()
              if line.startswith(("MatCholFctrSym ", "MatCholFctrNum "))}
    assert counts == {"MatCholFctrSym": 4, "MatCholFctrNum": 4}, counts
    assert proc.stderr.count("MUMPS' analysis of K") == 2, proc.stderr[-3000:]
    with h5py.File(out) as f:
        first = f["rotation/frequencies_hz"][()][:, 0]
    assert np.all(np.diff(first) > 0), first


_REFRESH = """
import contextlib
import numpy as np
from mpi4py import MPI
from pipeline.config import load_config
from pipeline.distributed.eigen import petsc_matrix
from pipeline.distributed.mpi import petsc, world
from pipeline.distributed.multigrid import RankTwoGrid, prolongation
from pipeline.distributed.stage import build_fe_model

PETSc, _ = petsc()
comm = world()
cfg = load_config("configs/cantilever.yaml", ["modes.solver=slepc", "mesh.size=0.02"])
fe = build_fe_model(cfg, None, lambda name: contextlib.nullcontext())
A = petsc_matrix(PETSc, fe.K.local, fe.K.shape[0])
P = prolongation(PETSc, fe.space, fe.K.part, comm)
kept = RankTwoGrid(PETSc, A, P)
x = np.random.default_rng(comm.rank).standard_normal((fe.K.hi - fe.K.lo, 5))
before = kept.apply_double(x)
A.scale(1.5)  # the next speed: new values, the same pattern
kept.refresh(A)
fresh = RankTwoGrid(PETSc, A, P)
worst = comm.allreduce(float(np.abs(kept.apply_double(x) - fresh.apply_double(x)).max()),
                       op=MPI.MAX)
moved = comm.allreduce(float(np.abs(kept.apply_double(x) - before).max()), op=MPI.MAX)
same = comm.allreduce(kept.lambda_max == fresh.lambda_max, op=MPI.LAND)
if comm.rank == 0:
    print(worst, moved, same)
kept.release()
fresh.release()
"""


@pytest.mark.mpi
def test_a_refreshed_two_grid_cycle_is_a_new_one(tmp_path):
    """The factor-free rotation sweep keeps its two-grid cycle from speed to speed
    (:meth:`pipeline.distributed.multigrid.RankTwoGrid.refresh`: P, the coarse pattern
    and MUMPS' analysis kept; the smoother, lambda_max, P^T A P and the numeric factor
    made again): for an operator with the same pattern and new values (K scaled by 1.5:
    the cycle then applies (1/1.5) times the old one) it applies exactly as a cycle made
    from scratch, so the sweep's frequencies are those of a new cycle per speed."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMPI_ALLOW_RUN_AS_ROOT": "1",
           "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    proc = subprocess.run([*_mpiexec(2), str(MPI_PYTHON), "-c", _REFRESH], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    worst, moved, same = proc.stdout.split()
    assert float(worst) == 0.0 and same == "True"
    assert float(moved) > 0.0  # the refreshed cycle is not the old one
