"""The signal handler of pipeline._util.interrupts, in this process (no subprocess)."""

from __future__ import annotations

import signal
import sys
import threading

from pipeline._util import interrupts


def test_a_signal_deferred_out_of_a_finaliser_is_delivered_again_by_a_daemon_timer():
    """A signal that arrives while a finaliser runs (where Python would print and swallow
    the exception its handler raises) is sent again 0.05 s later by a timer thread. That
    thread is a daemon: when the command completes meanwhile, the interpreter's exit
    does not wait for it (it waited before, and the signal then raised inside
    threading's shutdown: a traceback after a completed run)."""
    seen: list[int] = []
    old = signal.signal(signal.SIGUSR1, lambda signum, frame: seen.append(signum))
    try:
        before = set(threading.enumerate())

        class Finalised:
            def __del__(self):
                interrupts._on_signal(signal.SIGUSR1, sys._getframe())

        Finalised()  # its __del__ runs at once
        timers = [t for t in threading.enumerate() if t not in before]
        assert len(timers) == 1 and timers[0].daemon
        timers[0].join(timeout=5.0)
        assert seen == [signal.SIGUSR1]  # delivered again, to this process's handler
    finally:
        signal.signal(signal.SIGUSR1, old)
