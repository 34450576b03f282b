"""Memory awareness: the estimate grows with the mesh and the modes, and a mesh that
does not fit is refused with both figures and a mesh size that would fit."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

import pytest

from pipeline._util import resources
from pipeline.config import Geometry, MeshSpec
from pipeline.errors import ResourceError
from pipeline.fe.space import build_space
from pipeline.fe.mesh import generate_mesh, read_mesh


@pytest.fixture(scope="module")
def space(tmp_path_factory):
    path = tmp_path_factory.mktemp("res") / "box.msh"
    generate_mesh(Geometry("box", 0.1, 0.02, 0.03), MeshSpec(order=2, size=0.01,
                                                             algorithm="delaunay"), path)
    # gmsh made it with mesh.size 0.01, as mesh_box records it
    return build_space(dataclasses.replace(read_mesh(path), element_size=0.01), 2)


def test_estimate_is_monotone_in_mesh_size_and_modes():
    sizes = [1_000, 10_000, 100_000, 333_000, 1_000_000]
    for order in (1, 2):
        est = [resources.estimate_memory_bytes(n, n, order, 20) for n in sizes]
        assert all(a < b for a, b in zip(est, est[1:]))
    by_modes = [resources.estimate_memory_bytes(100_000, 60_000, 2, m) for m in (1, 10, 50, 200)]
    assert all(a < b for a, b in zip(by_modes, by_modes[1:]))


def test_estimate_matches_the_measured_cantilever():
    # 977k DOFs (325,582 nodes, 217,000 tetrahedra), 20 modes: PARDISO factor 8.99 GB,
    # run peak 11.7 GB (make bench, docs/performance.md)
    assert resources.factor_bytes(976_746) == pytest.approx(8.99e9, rel=0.1)
    peak = resources.estimate_memory_bytes(325_582, 217_000, 2, 20, "factor",
                                           available=24 * 10**9)
    assert 11.0e9 < peak < 13.5e9
    # the same size under auto (factor-free from MULTIGRID_AUTO_DOFS): 999k DOFs
    # (333,081 nodes, 222,655 tetrahedra), 20 modes, run peak 5.16 GB (make bench,
    # 2026-11-23) and 5.36 GB (benchmarks/memory_trace.py, 2026-11-26); the model of
    # the factor-free path term by term (resources.multigrid_terms) says 5.36 GB
    peak = resources.estimate_memory_bytes(333_081, 222_655, 2, 20, available=24 * 10**9)
    assert peak == pytest.approx(5.36e9, rel=0.1)


def test_check_memory_passes_when_it_fits(space):
    need = resources.check_memory(space, 10, available=64 * 2**30)
    assert need == resources.estimate_memory_bytes(space.n_nodes, space.body.n_tetrahedra,
                                                   2, 10)


def test_check_memory_refuses_with_both_figures_and_a_size_that_fits(space):
    need = resources.estimate_memory_bytes(space.n_nodes, space.body.n_tetrahedra, 2, 10)
    have = need // 20
    with pytest.raises(ResourceError) as info:
        resources.check_memory(space, 10, available=have)
    msg = str(info.value)
    assert f"{space.n_dofs} DOFs" in msg
    assert f"{need / 1e9:.1f} GB" in msg
    assert (f"{resources.HEADROOM * have / 1e9:.2f} GB usable (90% of the "
            f"{have / 1e9:.2f} GB available)") in msg
    suggested = float(re.search(r"a mesh.size of about ([0-9.e-]+) m", msg).group(1))
    current = float(re.search(r"\(now ([0-9.e-]+) m", msg).group(1))
    assert current == 0.01 and suggested > current  # the mesh.size it was made with
    # memory scales like size^-4: the suggested size brings the estimate under the limit
    assert need * (current / suggested) ** 4 < resources.HEADROOM * have


def test_factor_check_refuses_before_factorising():
    with pytest.raises(ResourceError, match=r"needs 5\.0 GB, more than the 0\.90 GB usable "
                                            r"\(90% of the 1\.00 GB available\)"):
        resources.check_factor_memory(5.0e9, 1_000_000, available=int(1.0e9))
    resources.check_factor_memory(0.5e9, 1_000_000, available=int(1.0e9))
    # the factor does not know where the mesh came from: coarser, mesh.size where it applies
    with pytest.raises(ResourceError, match=r"; a mesh about 1\.57 times coarser would fit "
                                            r"\(mesh.size 1\.57 times larger where gmsh "
                                            r"makes the mesh\)$"):
        resources.check_factor_memory(4.5e9, 1_000_000, available=int(1.0e9))


def test_a_need_between_the_usable_share_and_all_of_it_reads_as_too_much():
    """A factor of 0.95 of the available memory is refused (HEADROOM 0.9): the message
    names the usable share below the need, not only the available figure above it (the
    bench's NGSolve case read "needs 12.0 GB, but only 13.3 GB is available")."""
    with pytest.raises(ResourceError) as caught:
        resources.check_factor_memory(12.0e9, 1_221_588, available=int(13.3e9))
    text = str(caught.value)
    assert "needs 12.0 GB, more than the 12.0 GB usable (90% of the 13.3 GB available)" in text
    usable = float(re.search(r"more than the ([\d.]+) GB usable", text).group(1))
    assert usable <= 12.0 < 13.3


def test_available_memory_is_positive():
    assert resources.available_memory_bytes() > 0


def test_pardiso_checks_the_exact_factor_size_before_factorising(monkeypatch):
    from pipeline.solve import factorization as solvers

    if "pardiso" not in solvers.available_backends():
        pytest.skip("needs MKL PARDISO")
    import scipy.sparse as sp

    n = 3000
    A = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n), format="csr")
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: 1000)
    with pytest.raises(ResourceError, match="sparse factorisation of the 3000-DOF"):
        solvers.factorize(A, "pardiso")
    monkeypatch.undo()
    fact = solvers.factorize(A, "pardiso")  # the refused handle was released cleanly
    assert np.allclose(A @ fact.solve(np.ones(n)), 1.0)


def _glibc_mallopt() -> bool:
    lib = resources._libc()
    return lib is not None and all(hasattr(lib, name)
                                   for name in ("mallopt", "malloc_trim", "mallinfo2"))


_RETAINED_HEAP_CHECK = """
import ctypes
import numpy as np
from pipeline._util import resources
mb = 64 * 2**20

def held_and_freed(nbytes):
    a = np.ones(nbytes // 8)  # written: resident
    held = resources.resident_bytes()
    del a
    return held, resources.resident_bytes()

class _Mallinfo2(ctypes.Structure):  # glibc >= 2.33
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = _Mallinfo2

def mapped_during(nbytes):
    # bytes glibc holds in mmapped chunks while an nbytes array is alive, over before
    base = libc.mallinfo2().hblkhd
    a = np.ones(nbytes // 8)
    mapped = libc.mallinfo2().hblkhd - base
    del a
    return mapped

before = resources.resident_bytes()
with resources.retained_heap(mb) as kept:
    assert kept
    assert mapped_during(2 * mb) == 0, "no mmap inside the block"
    held, freed = held_and_freed(mb)
    assert held - freed < mb // 2, ("freed inside the block", held - freed)
    with resources.retained_heap(mb) as nested:
        assert not nested
assert resources.resident_bytes() - before < mb // 2, ("trimmed after the block",
                                                       resources.resident_bytes() - before)
# twice the block's array: larger than any hole the block left in the heap, so glibc
# maps it (mmap was allowed again) and unmaps it on free
held, freed = held_and_freed(2 * mb)
assert held - freed > mb, ("returned on free after the block", held - freed)
assert mapped_during(2 * mb) >= 2 * mb, "mmap allowed again after the block"
# below the mmap threshold, from the heap: its free top is trimmed on free (trim threshold
# back to 128 kB); keepcost is that free top, whether or not the array came from it
a = np.ones(mb // 4 // 8)
del a
assert libc.mallinfo2().keepcost < mb // 8, ("heap top trimmed", libc.mallinfo2().keepcost)
print("ok")
"""


@pytest.mark.skipif(not _glibc_mallopt(), reason="needs glibc >= 2.33 (mallopt, mallinfo2)")
def test_retained_heap_keeps_freed_blocks_inside_and_gives_them_back_after():
    """Inside the block a freed 64 MB array stays resident (the heap keeps it); after the
    block the pages go back to the system, and a freed array is returned at once. Nested
    use and a block whose growth would not fit leave the allocator alone.

    The allocator part runs in a fresh interpreter: the state of glibc's heap is global to
    the process, and free chunks that earlier tests left in it (a retained block's holes
    below live objects) can serve a later large array from the heap instead of mmap, which
    made this check depend on test order (it failed once in CI that way)."""
    env = {**os.environ, resources.RETAIN_HEAP_VARIABLE: "1"}  # the opt-in the CLI sets
    proc = subprocess.run([sys.executable, "-c", _RETAINED_HEAP_CHECK], capture_output=True,
                          text=True, timeout=120, cwd=Path(__file__).resolve().parents[1],
                          env=env)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]
    with resources.retained_heap(10.0 * resources.available_memory_bytes()) as kept:
        assert not kept


def test_retained_heap_is_an_opt_in(monkeypatch):
    """Without ``PIPELINE_RETAIN_HEAP=1`` a library call leaves glibc's thresholds alone."""
    monkeypatch.delenv(resources.RETAIN_HEAP_VARIABLE, raising=False)
    assert not resources.heap_tuning_allowed()
    with resources.retained_heap(1.0) as kept:
        assert not kept


_TUNING_CHECK = """
import os, sys
before = dict(os.environ)
import pipeline, pipeline.cli
assert dict(os.environ) == before, "import changed the environment"
assert "numpy" not in sys.modules, "numpy loaded before the CLI's tuning"
pipeline.cli.tune_process()
import numpy
print(os.environ["OPENBLAS_THREAD_TIMEOUT"], os.environ["KMP_BLOCKTIME"],
      os.environ["PIPELINE_RETAIN_HEAP"])
"""


def test_cli_tunes_its_process_before_numpy_and_import_does_not():
    """``import pipeline`` and ``import pipeline.cli`` change nothing and load no numpy; the
    CLI's entry point sets OpenBLAS's and MKL's spin times and the heap opt-in, and a value
    already in the environment wins."""
    from pipeline.cli.process import PROCESS_SETTINGS

    env = {k: v for k, v in os.environ.items() if k not in PROCESS_SETTINGS}
    out = subprocess.run([sys.executable, "-c", _TUNING_CHECK], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == ["4", "0", "1"]
    env["OPENBLAS_THREAD_TIMEOUT"] = "12"
    out = subprocess.run([sys.executable, "-c", _TUNING_CHECK], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == ["12", "0", "1"]


def test_console_script_entry_point_tunes_before_running(monkeypatch):
    """``pipeline.cli:main`` (the console script and ``python -m pipeline``) tunes the
    process first (conftest undoes it after the test)."""
    import pipeline.cli
    from pipeline.cli.process import PROCESS_SETTINGS

    for name in PROCESS_SETTINGS:
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(SystemExit):
        pipeline.cli.main(["--help"])
    assert {name: os.environ.get(name) for name in PROCESS_SETTINGS} == PROCESS_SETTINGS
    assert "from pipeline.cli import main" in (Path(pipeline.cli.__file__).parents[1]
                                               / "__main__.py").read_text()


def _fake_cgroup(tmp_path, monkeypatch, limit: str, current: int, inactive: int) -> None:
    """A cgroup v2 memory.max / memory.current / memory.stat under tmp_path, read by
    available_memory_bytes instead of the machine's."""
    (tmp_path / "memory.max").write_text(limit + "\n")
    (tmp_path / "memory.current").write_text(f"{current}\n")
    (tmp_path / "memory.stat").write_text(f"anon {current - inactive}\n"
                                          f"inactive_file {inactive}\nactive_file 0\n")
    monkeypatch.setattr(resources, "CGROUP_MEMORY", (
        (str(tmp_path / "memory.max"), str(tmp_path / "memory.current"),
         str(tmp_path / "memory.stat"), "inactive_file"),))


def test_a_cgroup_limit_leaves_the_limit_less_what_the_cgroup_uses(tmp_path, monkeypatch):
    """Under a cgroup limit the memory still available is the limit less the cgroup's
    usage (its reclaimable inactive file pages not counted), not the limit: a caller
    adding what its processes hold to it counted that memory twice."""
    free_now = resources.available_memory_bytes()
    mb = 1 << 20
    _fake_cgroup(tmp_path, monkeypatch, str(10_000 * mb), 9_800 * mb, 50 * mb)
    assert resources.cgroup_left_bytes() == 250 * mb
    assert resources.available_memory_bytes() == min(free_now, 250 * mb)
    _fake_cgroup(tmp_path, monkeypatch, str(10_000 * mb), 10_100 * mb, 0)  # over it
    assert resources.available_memory_bytes() == 0
    _fake_cgroup(tmp_path, monkeypatch, "max", 9_800 * mb, 0)  # no limit
    assert resources.cgroup_left_bytes() is None
