"""The distributed bench's per-rank memory model (benchmarks/bench_mpi.py).

Synthetic rows made from known c, r0, r, w0, w and d (the model of the bench's
docstring, m(P, N) = c + r0 + r N / N0 + [rank 0, P > 1] (w0 + w N / N0) + d(N) / P, w
the whole mesh rank 0 keeps, which the worker counts) and rank 0's mesh phase
c + m0 + (m + mp / P) N / N0: the fit must give them back. The model is linear in what it fits, so
the checks are equalities to round-off (1e-9 MB)."""

import pytest

from conftest import bench_module

N0, N1 = 100_000, 20_000
C, R0, R, W0, W = 128.0, 17.0, 30.0, 18.0, 1.6
M0, M, MP = 20.0, 45.0, 60.0  # rank 0's mesh phase: the whole mesh and its graph share


@pytest.fixture(scope="module")
def bench():
    with bench_module("bench_mpi") as module:
        yield module


def _divided(n: int) -> float:
    return 800.0 * (n / N0) ** (4.0 / 3.0)


def _row(ranks: int, n: int) -> dict:
    """One case: every rank's peak from the model (rank 0 with w when P > 1), MUMPS'
    figures (half of d on 2 ranks, the larger rank 1.1 times the mean)."""
    s = n / N0
    others = C + R0 + R * s + _divided(n) / ranks
    peaks = [others + (W0 + W * s if ranks > 1 else 0.0)] + [others] * (ranks - 1)
    sent = [["parts sent", C + 10.0, C + M0 + (M + MP / ranks) * s]] + \
        [["parts sent", C, C + 5.0]] * (ranks - 1)
    total = 0.5 * _divided(n) * 2**20 / 1e6
    mumps = [{"of": "K", "entries": 1.0, "sum_mb": total, "max_mb": 0.55 * total,
              "max_used_mb": 0.0, "sum_used_mb": 0.0}]
    return {"ranks": ranks, "n_free": n, "peak_mb": peaks, "import_mb": [C] * ranks,
            "mumps": mumps, "kept_mb": W * s, "stages_mb": [[st] for st in sent]}


def test_the_fit_returns_what_made_the_peaks(bench):
    rows = [_row(1, N0), _row(2, N0), _row(4, N0), _row(2, N1), _row(4, N1), _row(2, 50_000)]
    model = bench.memory_model(rows)
    assert model["c"] == C
    assert model["r0"] == pytest.approx(R0, abs=1e-9)
    assert model["r"] == pytest.approx(R, abs=1e-9)
    assert model["w"] == pytest.approx(W, abs=1e-9)
    assert model["w0"] == pytest.approx(W0, abs=1e-9)
    assert model["mesh"]["m0"] == pytest.approx(M0, abs=1e-9)
    assert model["mesh"]["m"] == pytest.approx(M, abs=1e-9)
    assert model["mesh"]["mp"] == pytest.approx(MP, abs=1e-9)
    assert model["d"] == pytest.approx(_divided(N0), abs=1e-9)
    assert model["k"] == pytest.approx(1.1)
    # the 1-rank case is not used by the fit: it checks it (no w on one rank)
    assert model["one_mb"] == pytest.approx(model["one_measured_mb"], abs=1e-9)


def test_without_a_second_size_all_of_what_every_rank_holds_is_linear(bench):
    rows = [_row(1, N0), _row(2, N0), _row(4, N0), _row(2, N1), _row(2, 50_000)]
    model = bench.memory_model(rows)
    assert model["r0"] == 0.0
    assert model["r"] == pytest.approx(R0 + R, abs=1e-9)
