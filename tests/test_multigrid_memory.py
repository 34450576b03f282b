"""The memory of the factor-free path (pipeline._util.resources.multigrid_terms) against
measured peaks, the LOBPCG layout chosen by memory, and LOBPCG in batches
(pipeline.solve.batched) against the factor route."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import build_model, cond_eps, eigenvalue_rtol
from pipeline._util import resources
from pipeline.fe.coarse import p1_prolongation
from pipeline.solve import eigen, multigrid, plan
from pipeline.solve.eigen import solve_modes

COUNT = 8

#: (P2 nodes, tetrahedra, ru_maxrss bytes) of `python -m pipeline run
#: configs/cantilever.yaml --set modes.count=20 --set modes.method=multigrid` with
#: mesh.size 0.003 and 0.00211 (benchmarks/memory_trace.py, 2026-11-26, LOBPCG the
#: peak) and 0.00146 (make bench, 2026-11-23, docs/performance.md)
MEASURED = ((124_400, 79_441, 2.02e9), (333_081, 222_655, 5.36e9),
            (945_641, 655_268, 15.12e9))


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    return build_model(tmp_path_factory.mktemp("mgb"), length=0.3, height=0.02, depth=0.03,
                       size=0.006)


@pytest.mark.parametrize("n_nodes,n_tets,peak", MEASURED)
def test_model_of_the_factor_free_path_matches_measured_peaks(n_nodes, n_tets, peak):
    """Within 10 % (the model gave +4 %, 0 % and +2 %); plenty of memory: one batch."""
    model = resources.estimate_memory_bytes(n_nodes, n_tets, 2, 20, "multigrid",
                                            available=10**12)
    assert model == pytest.approx(peak, rel=0.10)


def test_layout_keeps_one_batch_when_it_fits_and_batches_when_not():
    n = 5_000_000
    one = 8.0 * n * resources.LOBPCG_BLOCKS * 25
    assert resources.lobpcg_layout(n, 20, 5, one) == (20, 5)
    assert resources.lobpcg_layout(n, 20, 5, one - 1) == (20, 4)
    batch, guard = resources.lobpcg_layout(n, 20, 5, 0.5 * one)
    assert batch < 20 and guard >= 2
    need = 8.0 * n * (resources.LOBPCG_BLOCKS * (batch + guard) + 2 * (20 - batch))
    assert need <= 0.5 * one
    assert resources.lobpcg_layout(n, 20, 5, 0.0) == (1, 2)


def test_the_6m_cantilever_runs_factor_free_within_22_gb():
    """The cantilever at mesh.size 0.00116 (gmsh: 1,842,724 P2 nodes, 1,299,820
    tetrahedra) on the 24 GB machine: no factor fits, auto plans the factor-free path
    with no factor fallback, and the estimate of the whole run stays within the usable
    memory (LOBPCG in batches)."""
    available = 23.5e9
    n_nodes, n_tets = 1_842_724, 1_299_820
    need = resources.estimate_memory_bytes(n_nodes, n_tets, 2, 20, "auto",
                                           available=int(available))
    assert need <= resources.HEADROOM * available <= 22e9
    problem = plan.EigenProblem(n=3 * n_nodes - 5_000, count=20, precision="auto",
                                has_coarse=True)
    machine = plan.Machine(usable_bytes=resources.HEADROOM * available, backend="pardiso",
                           half_solves=True)
    chosen = plan.plan_modes(problem, machine)
    assert chosen.method == "multigrid" and chosen.fallback is None


def test_solver_budget_keeps_the_whole_process_within_headroom(monkeypatch):
    """The eigensolver may allocate HEADROOM of (held + available) less what the process
    holds: after any allocation the process stays within HEADROOM of what it could hold,
    and the budget falls as the process grows; none when it already holds more."""
    for held, available in ((16.7e9, 7.5e9), (1e9, 23e9), (23e9, 0.5e9)):
        monkeypatch.setattr(eigen, "resident_bytes", lambda: int(held))
        monkeypatch.setattr(eigen, "available_memory_bytes", lambda: int(available))
        budget = eigen._usable_bytes()
        assert budget == pytest.approx(max(0.0, resources.HEADROOM * (held + available)
                                           - held))
        if budget > 0:
            assert held + budget == pytest.approx(resources.HEADROOM * (held + available))
            assert budget < resources.HEADROOM * available
    assert budget == 0.0  # 23 GB held of 23.5: nothing more


def test_batched_lobpcg_finds_the_modes_of_one_block(beam, monkeypatch):
    """Three batches of 3, 3 and 2 modes (each deflated against the modes found before)
    give the frequencies of the factor route, within the bound of
    tests/test_multigrid.py (twice the squared tolerance over the relative gap, plus
    the round-off of the pencil)."""
    P = p1_prolongation(beam.space, beam.free)
    ref = solve_modes(beam.K, beam.M, COUNT, method="factor")
    monkeypatch.setattr(eigen, "lobpcg_layout", lambda n, count, guard, free: (3, 2))
    mg = solve_modes(beam.K, beam.M, COUNT, method="multigrid", coarse=P)
    assert mg.stats["batches"] == 3 and mg.stats["block"] == 5
    rel_gap = float(np.min(np.diff(ref.omega2) / ref.omega2[1:]))
    bound = 2 * eigen.MULTIGRID_TOLERANCE ** 2 / rel_gap + 0.5 * eigenvalue_rtol(
        beam.K, beam.M)
    assert np.abs(mg.frequencies_hz / ref.frequencies_hz - 1).max() <= bound
    # M-orthonormal across the batches, as the Rayleigh-Ritz step leaves them
    G = mg.shapes.T @ (beam.M @ mg.shapes)
    assert np.abs(G - np.eye(COUNT)).max() < 1e-10


def test_static_loads_ride_through_the_batches(beam, monkeypatch):
    """Where memory holds LOBPCG only in batches, and the riding solve's blocks beside
    the same batches, the static loads ride through all of them: one PCG iteration per
    cycle of every batch (sweeps + 1 cycles each), finished before the reduce stage asks
    (no iteration after), with the true residual of a PCG of its own
    (tests/test_multigrid.py); with no room for the rider, the same batches and no
    rider."""
    P = p1_prolongation(beam.space, beam.free)
    n = beam.K.shape[0]
    F = np.random.default_rng(14).standard_normal((n, 1))
    rider = multigrid.RIDER_BLOCKS * 8.0 * n
    batches = 8.0 * n * (resources.LOBPCG_BLOCKS * (3 + 2) + 2 * (COUNT - 3))
    monkeypatch.setattr(eigen, "_usable_bytes", lambda: batches + 1.5 * rider)
    modes = solve_modes(beam.K, beam.M, COUNT, method="multigrid", coarse=P, keep=True,
                        loads=F)
    try:
        stats = modes.stats
        assert stats["batches"] == 3 and stats["block"] == 5
        assert stats["riding_columns"] == 1
        tg = modes.factorization._solve.__self__  # the kept TwoGrid
        run = tg._riding[1]
        cycles = stats["sweeps"] + stats["batches"]
        assert run.finished and run.iterations < cycles  # done within the batches' cycles
        rode = run.iterations
        X = modes.factorization.solve(F)
        assert tg.iterations == rode  # nothing left for the reduce stage
    finally:
        modes.release_factorization()
    residual = float(np.linalg.norm(F - beam.K @ X) / np.linalg.norm(F))
    assert residual <= multigrid.PCG_RTOL + cond_eps(beam.K)
    monkeypatch.setattr(eigen, "_usable_bytes", lambda: batches + 0.5 * rider)
    tight = solve_modes(beam.K, beam.M, COUNT, method="multigrid", coarse=P, keep=True,
                        loads=F)
    tight.release_factorization()
    assert tight.stats["riding_columns"] == 0 and tight.stats["batches"] == 3
