"""The per-node memory check of MUMPS' factorisation under a cgroup memory limit
(:func:`pipeline.distributed.factor_memory.check_factor_estimate`).

The check adds what the node's ranks hold now to what the node can still give them.
Under a cgroup limit what it can still give is the limit less the cgroup's usage
(:func:`pipeline._util.resources.cgroup_left_bytes`); the limit itself, which the check
read before, already contains the ranks' memory, so it was counted twice. Here 2 ranks
read a faked cgroup (a 10 GB limit, 9.7 GB of it used, on every rank: 300 MB left)
while the machine has more available: a factorisation of 2 x 200 MB more is refused on
every rank, one of 2 x 50 MB passes. With the limit taken for what is left, the first
passed (the machine had GBs available).
"""

from __future__ import annotations

import os
import re
import subprocess

import pytest

from conftest import ROOT
from test_mpi import MPI_PYTHON, _mpiexec

_CHECK = """
import sys
import pipeline._util.resources as res
root, rank_mb = sys.argv[1], float(sys.argv[2])
res.CGROUP_MEMORY = ((f"{root}/memory.max", f"{root}/memory.current",
                      f"{root}/memory.stat", "inactive_file"),)
from pipeline.distributed.factor_memory import MumpsEstimate, check_factor_estimate
from pipeline.distributed.mpi import world
from pipeline.errors import ResourceError
comm = world()
estimate = MumpsEstimate(rank_mb * 1e6, rank_mb * 1e6, comm.size * rank_mb * 1e6, 1e6, 20)
try:
    check_factor_estimate(comm, estimate, "K", 1000)
    print(f"rank {comm.rank} fits", flush=True)
except ResourceError as exc:
    print(f"rank {comm.rank} refused: {exc}", flush=True)
"""


@pytest.mark.mpi
@pytest.mark.parametrize("rank_mb, verdict", [(200, "refused"), (50, "fits")])
def test_the_node_check_counts_what_a_cgroup_limit_leaves(tmp_path, rank_mb, verdict):
    mb = 1 << 20
    (tmp_path / "memory.max").write_text(f"{10_000 * mb}\n")
    (tmp_path / "memory.current").write_text(f"{9_700 * mb}\n")
    (tmp_path / "memory.stat").write_text("inactive_file 0\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMPI_ALLOW_RUN_AS_ROOT": "1",
           "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    proc = subprocess.run([*_mpiexec(2), str(MPI_PYTHON), "-c", _CHECK, str(tmp_path),
                           str(rank_mb)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # the ranks' lines may share one line of mpiexec's combined stdout
    said = sorted(re.findall(r"rank (\d) (refused|fits)", proc.stdout))
    assert said == [("0", verdict), ("1", verdict)], proc.stdout
    if verdict == "refused":  # what they hold + 0.31 GB left, not + 10 GB
        have = [float(g) for g in re.findall(r"of the ([\d.]+) GB available", proc.stdout)]
        assert have and all(g < 1.0 for g in have), proc.stdout
