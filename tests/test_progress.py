"""Progress with an end in sight (pipeline._util.progress): stages with totals and expected
durations, log lines when the output is not a terminal, the solver hooks."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
import scipy.sparse as sp

from pipeline._util import progress


class FakeClock:
    """A clock that moves only when told (seconds); stands in for progress.clock, so that
    the durations these tests check do not depend on how busy the machine is."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def clock(monkeypatch) -> FakeClock:
    fake = FakeClock()
    monkeypatch.setattr(progress, "clock", fake)
    return fake


def _wait_for_record(caplog, predicate, what: str, timeout: float = 30.0) -> None:
    """Wait for the reporter's timer thread to log a line that ``predicate`` accepts
    (a bounded wait for a thread, not a measure of speed)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(predicate(r.getMessage()) for r in caplog.records):
            return
        time.sleep(0.01)
    raise AssertionError(f"no log line {what} within {timeout:g} s")


def test_log_reporter_says_when_a_stage_starts_ends_and_how_long_it_should_take(caplog,
                                                                                clock):
    caplog.set_level(logging.INFO, logger="pipeline.progress")
    fmt = progress.fmt_seconds
    with progress.using(progress.LogReporter(every_s=0.01)):
        with progress.stage("first") as st:
            st.expect_work(1e9, "widget")  # no rate measured yet: no expectation
            clock.advance(2.0)
        measured = progress.rate("widget")
        assert measured == 1e9 / 2.0  # the rate the first stage took
        with progress.stage("second") as st:
            st.expect_work(2e9, "widget")  # 4 s at the first stage's rate
            clock.advance(1.0)
            # the reporter's timer thread speaks every every_s (real) seconds
            _wait_for_record(caplog, lambda m: m == f"second: {fmt(1.0)} elapsed, about "
                             f"{fmt(3.0)} left", "with the time elapsed and left")
            clock.advance(2.0)
    lines = [r.getMessage() for r in caplog.records]
    # the timer's lines may fall anywhere between a stage's start and end
    second = lines[lines.index("second started"):]
    assert f"second: expected {fmt(4.0)} (2 Gwidget at " \
        f"~{progress.fmt_amount(measured, 'widget/s')} (rate of the last one))" in second
    assert f"second done in {fmt(3.0)} (expected {fmt(4.0)}); " \
        f"{progress.fmt_amount(2e9 / 3.0, 'widget/s')} measured" in second


def test_counted_stage_extrapolates_its_remaining_time(clock):
    st = progress.Stage("Lanczos", total=10, unit="step")
    clock.advance(4.0)
    st.update(4)
    assert st.remaining() == 6.0  # 4 of 10 steps in 4 s: 6 s left
    st.update(8)  # a restart: more steps than estimated -> the total follows
    assert st.total == 12 and st.remaining() == 0.0


def test_without_a_reporter_stages_are_silent(caplog):
    caplog.set_level(logging.DEBUG)
    with progress.using(None), progress.stage("quiet", total=3) as st:
        st.update()
    assert not caplog.records


def test_cholesky_flop_estimate_is_above_its_lower_bound():
    # sum_j c_j^2 >= nnz^2 / n: a dense factor (c_j = n - j) is the equality-free check
    n = 300
    c = np.arange(n, 0, -1, dtype=float)
    exact_bound = c.sum() ** 2 / n
    assert progress.cholesky_flops(c.sum(), n) >= exact_bound
    assert (c ** 2).sum() >= exact_bound


def test_factorisation_and_lanczos_report_their_stages(caplog, monkeypatch):
    from pipeline.solve.eigen import solve_modes
    from pipeline.solve.factorization import available_backends

    n = 2000
    K = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    M = sp.identity(n, format="csr")
    caplog.set_level(logging.INFO, logger="pipeline.progress")
    monkeypatch.setattr(progress, "QUICK_WORK_FLOP", 0.0)  # this tiny factor gets one too
    with progress.using(progress.LogReporter()):
        solve_modes(K, M, 4)
    text = "\n".join(r.getMessage() for r in caplog.records)
    if "pardiso" in available_backends():
        assert "factorise (PARDISO): expected" in text and "Lanczos started (" in text
    else:
        assert "factorise (SuperLU) done" in text and "ARPACK done" in text


def test_the_cli_leaves_no_reporter_behind(tmp_path):
    from pipeline.cli import main

    before = progress.use(None)
    try:
        assert main(["inspect", str(tmp_path / "missing.h5")]) != 0
        assert progress.use(None) is None  # main's reporter was its own, not left behind
    finally:
        progress.use(before)


def test_first_flop_estimate_measures_the_machine_only_for_long_work(monkeypatch, clock):
    """Before any flop stage has finished, the estimate comes from the dense rate, which
    costs 0.2 s to measure: not for work under QUICK_WORK_FLOP (seconds anywhere)."""
    monkeypatch.setattr(progress, "_rates", {})
    calls = []

    def dense_rate(n: int = 1500) -> float:
        calls.append(n)
        return 2e10

    monkeypatch.setattr(progress, "dense_rate", dense_rate)
    st = progress.Stage("factorise", total=None, unit="flop")
    st.expect_work(0.5 * progress.QUICK_WORK_FLOP)
    assert st.expected_s is None and not calls
    st.expect_work(2.0 * progress.QUICK_WORK_FLOP)
    assert calls and st.expected_s == st.elapsed + 2.0 * progress.QUICK_WORK_FLOP / 2e10


def test_dense_rate_is_a_positive_definite_cholesky(monkeypatch):
    monkeypatch.setattr(progress, "_rates", {})
    assert progress.dense_rate(200) > 0  # raises LinAlgError if the matrix were not SPD
