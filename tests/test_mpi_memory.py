"""MUMPS' own memory estimate on MPI ranks (:mod:`pipeline.distributed.factor_memory`).

After MUMPS' analysis and before its numeric factorisation, every rank's estimate plus
what it holds is checked against what its node has. A run whose node has too little is
refused there: one line on every rank, the ResourceError's exit code 6, no file, no
numeric factorisation. The memory available to the ranks is faked in the subprocess by
replacing :func:`pipeline.distributed.factor_memory.available_bytes` (the early gate,
:func:`pipeline.distributed.stage.check_rank_memory`, still reads the machine's memory
and passes: the case of a model that underestimates what MUMPS will need).

MUMPS' estimate against the factor it then makes, for the cantilever at 16.6k DOFs
(2 ranks): its estimated factor entries INFOG(20) against the actual INFOG(29), and its
in-core estimate INFOG(17) (MB, all ranks) against the factor's 8 INFOG(29) bytes.
"""

from __future__ import annotations

import os
import re
import subprocess

import pytest

from conftest import ROOT, rank_error_lines
from test_mpi import MPI_PYTHON, _mpiexec

_FAKED = """
import sys
import pipeline.distributed.factor_memory as factor_memory
factor_memory.available_bytes = lambda: 1
from pipeline.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT), "OMPI_ALLOW_RUN_AS_ROOT": "1",
            "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}


@pytest.mark.mpi
def test_a_factor_that_does_not_fit_is_refused_after_the_analysis(tmp_path):
    out = tmp_path / "x.h5"
    proc = subprocess.run(
        [*_mpiexec(2), str(MPI_PYTHON), "-c", _FAKED, "-v", "run", "configs/cantilever.yaml",
         "--set", "modes.solver=slepc", "--set", "mesh.size=0.02", "-o", str(out)],
        cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 6, proc.stderr[-2000:]
    assert "memory estimate" in proc.stderr  # the early gate ran and passed
    assert "MUMPS' analysis of K" in proc.stderr  # the analysis ran ...
    assert "MUMPS' factor of" not in proc.stderr  # ... the numeric factorisation did not
    # every rank raises it; the first MPI_Abort may stop the other before it prints
    lines = rank_error_lines(proc.stderr)
    assert 1 <= len(lines) <= 2, proc.stderr[-2000:]
    for line in lines:
        assert re.search(r"MUMPS' analysis of K \(\d+ rows\) on 2 ranks: the numeric "
                         r"factorisation needs [\d.]+ GB more on a rank, [\d.]+ GB with what "
                         r"the 2 ranks of one node hold, more than the [\d.]+ GB usable "
                         r"\(90% of the [\d.]+ GB available to them\); expected about \d+ "
                         r"nodes like it or a mesh about [\d.]+ times coarser \(mesh.size "
                         r"[\d.]+ times larger where gmsh makes the mesh\)$", line), line
    assert "Traceback" not in proc.stderr
    assert not out.exists()


_FIGURES = re.compile(
    r"MUMPS' analysis of K \(\d+ rows\): (\d+) MB on the largest rank, (\d+) MB on all "
    r"\(ICNTL\(14\) (\d+) %.*\n.*MUMPS' factor of K: (\d+) entries \(analysis: (\d+)\), "
    r"(\d+) MB allocated on the largest rank \(estimate (\d+) MB, used (\d+) MB\), (\d+) "
    r"MB on all \(estimate (\d+) MB, used (\d+) MB\)")


@pytest.mark.mpi
def test_mumps_estimate_bounds_the_factor_it_makes(tmp_path):
    """MUMPS' analysis counts the factor of the symbolic structure; only pivots delayed
    by LDL^T's numerical pivoting add entries, and MUMPS stops (INFOG(1) = -9) where
    they outgrow ICNTL(14)'s margin m: a factorisation that completes has
    INFOG(20) <= INFOG(29) <= (1 + m) INFOG(20) (K is positive definite: no pivot is
    delayed, measured equal). The in-core estimate is the factor, the stack of
    contribution blocks and the integer data, their working part increased by m: it
    holds the factor (8 bytes an entry), 8 INFOG(29) <= INFOG(17) * 1e6, and what MUMPS
    used is at most what it allocated, which is its estimate (INFOG(19) = INFOG(17)).
    Above: the stack and integer data grow more slowly than the factor with N (the
    largest front ~ N^(2/3) against N^(4/3) factor entries): the estimate on 2 ranks was
    2.7, 1.9, 1.6 and 1.5 times the factor's bytes at 16.6k, 44k, 101k and 173k DOFs
    (benchmarks/bench_mpi.py), so 3 (1 + m) factors bound it at this size, the smallest
    of them, and above."""
    out = tmp_path / "x.h5"
    proc = subprocess.run(
        [*_mpiexec(2), str(MPI_PYTHON), "-m", "pipeline", "-v", "run",
         "configs/cantilever.yaml", "--set", "modes.solver=slepc", "--set",
         "mesh.size=0.01", "-o", str(out)],
        cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    found = _FIGURES.search(proc.stderr)
    assert found, proc.stderr[-3000:]
    (est_max, est_sum, margin, entries, est_entries, alloc_max, est_max2, used_max,
     alloc_sum, est_sum2, used_sum) = map(int, found.groups())
    m = margin / 100
    assert est_entries <= entries <= (1 + m) * est_entries
    assert (est_max, est_sum) == (est_max2, est_sum2)
    assert alloc_max == est_max and alloc_sum == est_sum
    assert used_max <= alloc_max and used_sum <= alloc_sum
    factor_mb = 8 * entries / 1e6
    assert factor_mb <= used_sum <= est_sum <= 3 * (1 + m) * factor_mb, \
        (factor_mb, used_sum, est_sum)


def test_rank_error_lines_are_cut_where_mpiexecs_own_output_begins():
    """The rank lines the MPI tests read, from stderr as mpiexec interleaves it (seen in
    CI: OpenMPI's log line glued to a rank's error without a newline)."""
    stderr = ("12:00:01 INFO memory estimate ...\n"
              "error on rank 0 of 2: the factor needs 0.31 GB[vm:13632] [[22974,0],0] "
              "ORTE_ERROR_LOG: Data unpack would read past end of buffer\n"
              "error on rank 1 of 2: SIGTERM----------------------------------------\n"
              "mpiexec noticed ...\n")
    assert rank_error_lines(stderr) == ["error on rank 0 of 2: the factor needs 0.31 GB",
                                        "error on rank 1 of 2: SIGTERM"]
    assert rank_error_lines("error on rank 0 of 2: a (b) error on rank 1 of 2: c\n") == \
        ["error on rank 0 of 2: a (b) ", "error on rank 1 of 2: c"]
