"""Progress of long steps, with an end in sight: one mechanism for bars and log lines.

Library code marks a step with :func:`stage` and says what it knows about its length::

    with progress.stage("Lanczos", total=68, unit="vec") as st:
        ...
        st.update(4)                       # 4 more of the 68 vectors

    with progress.stage("factorise") as st:
        st.expect_work(3.1e12, "flop")     # a known amount of work: the time follows
        ...                                # from the measured rate (below)

What is shown depends on the :class:`Reporter` the caller installed with :func:`use`
(the CLI does; library calls without one stay silent and cost one attribute look-up):

- :class:`BarReporter` (stderr is a terminal): a tqdm bar per stage; a stage whose length
  is known only as a duration (a factorisation, one blocking call into MKL) gets a bar
  over its expected seconds that a background thread advances twice a second;
- :class:`LogReporter` (output piped to a file): one log line when the stage starts (with
  its expected duration where known), one when it ends (elapsed vs expected), and for a
  long stage one line every ``every_s`` seconds in between with the time left.

Expected durations: a stage with a ``total`` extrapolates from its own rate (elapsed /
done * left). A stage with a known amount of floating-point work ``W`` (flop) expects
``W / R`` seconds, with ``R`` the rate (flop/s) of the last stage of that unit measured in
this process, or before any, :func:`dense_rate`: the rate of a dense Cholesky
factorisation on this machine (numpy's LAPACK, ~0.05 s to measure, once per process),
scaled by :data:`SPARSE_EFFICIENCY`. Every finished stage with known work records its
measured rate, which the next estimate uses.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import Iterator

log = logging.getLogger("pipeline.progress")

#: sparse supernodal factorisation rate / dense Cholesky rate (n = 1500) on the same
#: cores, for the first estimate of a process: MKL PARDISO on the 2-core shared reference
#: machine ran at 15 Gflop/s against a dense rate of 15.8 (0.95, 101k DOFs, quiet machine)
#: and at 5.5 against 2.5 (267k DOFs, other jobs running: the 0.05 s dense measurement
#: then catches the machine at its busiest); later estimates use the measured rate
SPARSE_EFFICIENCY = 1.0

#: flop below which a stage gets no first estimate from :func:`dense_rate`: under 1e11
#: flop is seconds on any machine this runs on (>= 20 Gflop/s on two cores), and the
#: measurement itself costs 0.2 s (3 % of a 100k-DOF run; its factorisation is 34 Gflop)
QUICK_WORK_FLOP = 1e11

#: the clock of every stage's times (s): read through this module attribute, so that a
#: test can drive it (``monkeypatch.setattr(progress, "clock", fake)``)
clock = time.perf_counter

#: measured rates (unit -> units per second) of finished stages in this process
_rates: dict[str, float] = {}
_reporter: "Reporter | None" = None


def dense_rate(n: int = 1500) -> float:
    """Floating-point rate (flop/s) of a dense Cholesky factorisation of order ``n`` here
    (n^3 / 3 flop), measured once per process (best of three)."""
    if "dense_flop" not in _rates:
        import numpy as np

        # symmetric and diagonally dominant, so positive definite: built in O(n^2) (the
        # Gram matrix a a^T used before cost 6 x the Cholesky it was built for: 0.2 s)
        a = np.random.default_rng(0).random((n, n))
        a += a.T
        a[np.diag_indices(n)] += 2.0 * n
        best = float("inf")
        for _ in range(3):
            t0 = time.perf_counter()
            np.linalg.cholesky(a)
            best = min(best, time.perf_counter() - t0)
        _rates["dense_flop"] = n ** 3 / 3.0 / max(best, 1e-6)
    return _rates["dense_flop"]


def cholesky_flops(factor_nnz: float, n: int) -> float:
    """Estimated flop count of a sparse Cholesky factorisation with ``factor_nnz``
    non-zeros in its factor of order ``n``.

    The count is sum_j c_j^2 over the column counts c_j of the factor, at least
    (sum_j c_j)^2 / n = nnz(L)^2 / n (Cauchy-Schwarz). PARDISO's own count (iparm[18];
    reported in its classic one-level mode only, and the pipeline factorises in the
    two-level mode, which leaves it at -1) on the cantilever's nested-dissection factors
    is 1.93 x that bound at 101k DOFs and 2.29 x at 267k: the ratio grows like n^0.17
    (for 3D nested dissection, flops ~ n^2 and nnz(L)^2 / n ~ n^(5/3), so n^(1/3) at
    most), which is the factor used here.
    """
    n = max(n, 1)
    return max(1.0, 1.93 * (n / 1e5) ** 0.17) * factor_nnz ** 2 / n


def rate(unit: str) -> float | None:
    """Units per second measured by the last finished stage of ``unit`` (None: none yet)."""
    return _rates.get(unit)


def fmt_seconds(s: float) -> str:
    """'42 s', '3 min 05 s', '1 h 02 min'."""
    if s < 100:
        return f"{s:.1f} s" if s < 10 else f"{s:.0f} s"
    m, sec = divmod(int(round(s)), 60)
    if m < 60:
        return f"{m} min {sec:02d} s"
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min"


def fmt_amount(x: float, unit: str) -> str:
    """3.1e12, 'flop' -> '3.1 Tflop'."""
    for factor, prefix in ((1e15, "P"), (1e12, "T"), (1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(x) >= factor:
            return f"{x / factor:.3g} {prefix}{unit}"
    return f"{x:.3g} {unit}"


class Stage:
    """One step being watched: counts (``done`` of ``total`` ``unit``) and/or an expected
    duration ``expected_s``. ``note`` says where the expectation comes from."""

    def __init__(self, name: str, total: float | None = None, unit: str = "it",
                 reporter: "Reporter | None" = None):
        self.name, self.total, self.unit = name, total, unit
        self.done = 0.0
        self.work: float | None = None          # amount of work, in work_unit
        self.work_unit = ""
        self.expected_s: float | None = None
        self.note = ""
        self.t0 = clock()
        self.finished_s: float | None = None
        self._reporter = reporter

    @property
    def elapsed(self) -> float:
        return (self.finished_s if self.finished_s is not None
                else clock() - self.t0)

    def remaining(self) -> float | None:
        """Seconds left (None when unknown)."""
        if self.expected_s is not None:
            return max(self.expected_s - self.elapsed, 0.0)
        if self.total and self.done > 0:
            return self.elapsed * max(self.total - self.done, 0.0) / self.done
        return None

    def expected_total(self) -> float | None:
        left = self.remaining()
        return None if left is None else self.elapsed + left

    def update(self, n: float = 1) -> None:
        self.done += n
        if self.total is not None and self.done > self.total:
            self.total = self.done  # an estimate of the total was low: never show > 100 %
        if self._reporter is not None:
            self._reporter.refresh(self)

    def set_total(self, total: float) -> None:
        self.total = total
        if self._reporter is not None:
            self._reporter.refresh(self)

    def expect_work(self, work: float, unit: str = "flop") -> None:
        """This stage does ``work`` ``unit`` in all: expect work / rate seconds, with the
        rate measured by the last stage of that unit (else :func:`dense_rate` times
        :data:`SPARSE_EFFICIENCY` for flop, from :data:`QUICK_WORK_FLOP` on)."""
        self.work, self.work_unit = float(work), unit
        measured = _rates.get(unit)
        if measured is None and unit == "flop" and self.work < QUICK_WORK_FLOP:
            return  # seconds of work: not worth measuring the machine for
        if measured is None and unit == "flop":
            r = SPARSE_EFFICIENCY * dense_rate()
            source = f"dense rate here {fmt_amount(dense_rate(), 'flop/s')} x {SPARSE_EFFICIENCY:g}"
        elif measured is None:
            return
        else:
            r, source = measured, "rate of the last one"
        self.expected_s = self.elapsed + self.work / r  # the work starts now
        self.note = f"{fmt_amount(self.work, unit)} at ~{fmt_amount(r, unit + '/s')} ({source})"
        if self._reporter is not None:
            self._reporter.expected(self)

    def _finish(self) -> None:
        self.finished_s = clock() - self.t0
        if self.work and self.finished_s > 0:
            _rates[self.work_unit] = self.work / self.finished_s


class Reporter:
    """Shows stages; the base class shows nothing."""

    def start(self, st: Stage) -> None: ...

    def refresh(self, st: Stage) -> None: ...

    def expected(self, st: Stage) -> None: ...

    def finish(self, st: Stage, failed: bool) -> None: ...


class LogReporter(Reporter):
    """Log lines (logger ``pipeline.progress``, INFO): start, every ``every_s``, end."""

    def __init__(self, every_s: float = 15.0, min_s: float = 0.0):
        self.every_s, self.min_s = every_s, min_s
        self._last: dict[int, float] = {}
        self._timers: dict[int, threading.Event] = {}

    def start(self, st: Stage) -> None:
        total = f" ({fmt_amount(st.total, st.unit)})" if st.total else ""
        log.info("%s started%s", st.name, total)
        self._last[id(st)] = st.t0
        stop = threading.Event()
        self._timers[id(st)] = stop
        # a blocking call (one MKL factorisation) never calls update(): a timer speaks
        threading.Thread(target=self._tick, args=(st, stop), daemon=True,
                         name=f"progress-{st.name}").start()

    def _tick(self, st: Stage, stop: threading.Event) -> None:
        while not stop.wait(self.every_s):
            self._line(st)

    def _line(self, st: Stage) -> None:
        self._last[id(st)] = clock()
        left = st.remaining()
        count = (f"{st.done:.0f}/{st.total:.0f} {st.unit}, " if st.total else "")
        end = f", about {fmt_seconds(left)} left" if left is not None else ""
        log.info("%s: %s%s elapsed%s", st.name, count, fmt_seconds(st.elapsed), end)

    def expected(self, st: Stage) -> None:
        log.info("%s: expected %s (%s)", st.name, fmt_seconds(st.expected_s), st.note)

    def finish(self, st: Stage, failed: bool) -> None:
        stop = self._timers.pop(id(st), None)
        if stop is not None:
            stop.set()
        self._last.pop(id(st), None)
        if failed:
            log.info("%s stopped after %s", st.name, fmt_seconds(st.elapsed))
            return
        exp = f" (expected {fmt_seconds(st.expected_s)})" if st.expected_s else ""
        measured = (f"; {fmt_amount(st.work / st.elapsed, st.work_unit + '/s')} measured"
                    if st.work and st.elapsed > 0 else "")
        log.info("%s done in %s%s%s", st.name, fmt_seconds(st.elapsed), exp, measured)


class BarReporter(Reporter):
    """tqdm bars on stderr: counted stages advance with update(); a stage with an
    expected duration is a bar over seconds advanced by a background thread."""

    def __init__(self, stream=None):
        import sys

        self.stream = stream or sys.stderr
        self._bars: dict[int, object] = {}
        self._stops: dict[int, threading.Event] = {}

    def start(self, st: Stage) -> None:
        from tqdm import tqdm

        self._bars[id(st)] = tqdm(total=st.total, desc=st.name, unit=st.unit, leave=False,
                                  file=self.stream, dynamic_ncols=True)

    def refresh(self, st: Stage) -> None:
        bar = self._bars.get(id(st))
        if bar is not None and st.expected_s is None:
            if st.total is not None and bar.total != st.total:
                bar.total = st.total
            bar.update(int(st.done) - bar.n if float(st.done).is_integer() else st.done - bar.n)

    def expected(self, st: Stage) -> None:
        from tqdm import tqdm

        old = self._bars.pop(id(st), None)
        if old is not None:
            old.close()
        bar = tqdm(total=round(st.expected_s, 1), desc=f"{st.name} (~{fmt_seconds(st.expected_s)}"
                   f", {fmt_amount(st.work, st.work_unit)})", unit="s", leave=False,
                   file=self.stream, dynamic_ncols=True, mininterval=0.2, miniters=0,
                   bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f} of ~{total:.0f} s")
        self._bars[id(st)] = bar
        stop = threading.Event()
        self._stops[id(st)] = stop

        def tick() -> None:
            while not stop.wait(0.5):
                target = min(st.elapsed, bar.total * 0.99)  # never 100 % before it is done
                if target > bar.n:
                    bar.update(target - bar.n)

        threading.Thread(target=tick, daemon=True, name=f"progress-{st.name}").start()

    def finish(self, st: Stage, failed: bool) -> None:
        stop = self._stops.pop(id(st), None)
        if stop is not None:
            stop.set()
        bar = self._bars.pop(id(st), None)
        if bar is not None:
            bar.close()


def use(reporter: Reporter | None):
    """Install ``reporter`` for this process (None: silent); returns the previous one."""
    global _reporter
    previous, _reporter = _reporter, reporter
    return previous


@contextlib.contextmanager
def using(reporter: Reporter | None) -> Iterator[Reporter | None]:
    """``with using(LogReporter()): ...``: ``reporter`` for the duration of the block."""
    previous = use(reporter)
    try:
        yield reporter
    finally:
        use(previous)


@contextlib.contextmanager
def stage(name: str, total: float | None = None, unit: str = "it") -> Iterator[Stage]:
    """Watch one step (see the module docstring); yields its :class:`Stage`."""
    reporter = _reporter
    st = Stage(name, total, unit, reporter)
    if reporter is not None:
        reporter.start(st)
    failed = True
    try:
        yield st
        failed = False
    finally:
        st._finish()
        if reporter is not None:
            reporter.finish(st, failed)


@contextlib.contextmanager
def counter(desc: str, total: int | None, unit: str):
    """The ``progress(desc, total, unit)`` factory the pipeline's stages take (a context
    manager yielding ``update(n)``), on top of :func:`stage`."""
    with stage(desc, total, unit) as st:
        yield st.update
