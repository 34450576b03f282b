"""Memory awareness: the estimate grows with the mesh and the modes, and a mesh that
does not fit is refused with both figures and a mesh size that would fit."""

from __future__ import annotations

import re

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
    return build_space(read_mesh(path), 2)


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
    # (333,081 nodes, 222,655 tetrahedra), 20 modes, run peak 6.38 GB (2026-11-23)
    peak = resources.estimate_memory_bytes(333_081, 222_655, 2, 20, available=24 * 10**9)
    assert peak == pytest.approx(6.38e9, rel=0.1)


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
    assert f"{need / 1e9:.1f} GB" in msg and f"{have / 1e9:.1f} GB" in msg
    sizes = [float(x) for x in re.findall(r"about ([0-9.e-]+) m", msg)]
    suggested, current = sizes
    assert suggested > current
    # memory scales like size^-4: the suggested size brings the estimate under the limit
    assert need * (current / suggested) ** 4 < resources.HEADROOM * have


def test_factor_check_refuses_before_factorising():
    with pytest.raises(ResourceError, match=r"needs 5\.0 GB, but only 1\.0 GB"):
        resources.check_factor_memory(5.0e9, 1_000_000, available=int(1.0e9))
    resources.check_factor_memory(0.5e9, 1_000_000, available=int(1.0e9))


def test_available_memory_is_positive():
    assert resources.available_memory_bytes() > 0


def test_pardiso_checks_the_exact_factor_size_before_factorising(monkeypatch):
    from pipeline.solve import factorize as solvers

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
    return lib is not None and hasattr(lib, "mallopt") and hasattr(lib, "malloc_trim")


@pytest.mark.skipif(not _glibc_mallopt(), reason="needs glibc's mallopt")
def test_retained_heap_keeps_freed_blocks_inside_and_gives_them_back_after():
    """Inside the block a freed 64 MB array stays resident (the heap keeps it); after the
    block the pages go back to the system, and a freed array is returned at once. Nested
    use and a block whose growth would not fit leave the allocator alone. Measured as
    resident memory while the array is held against after it is freed, so whatever
    free heap earlier tests left behind does not matter."""
    mb = 64 * 2**20

    def held_and_freed() -> tuple[int, int]:
        a = np.ones(mb // 8)  # written: resident
        held = resources.resident_bytes()
        del a
        return held, resources.resident_bytes()

    before = resources.resident_bytes()
    with resources.retained_heap(mb) as kept:
        assert kept
        held, freed = held_and_freed()
        assert held - freed < mb // 2  # kept in the heap
        with resources.retained_heap(mb) as nested:
            assert not nested
    assert resources.resident_bytes() - before < mb // 2
    held, freed = held_and_freed()
    assert held - freed > mb // 2  # mmap again: returned on free
    with resources.retained_heap(10.0 * resources.available_memory_bytes()) as kept:
        assert not kept
