"""Interrupts (SIGINT, SIGTERM, SIGHUP) as exceptions, and regions where they wait.

The CLI routes these signals to :func:`on_signal` (``pipeline.cli.guard``): SIGINT raises
:class:`KeyboardInterrupt`, SIGTERM and SIGHUP raise :class:`Terminated` (a
KeyboardInterrupt too, so every ``finally`` and cleanup that handles Ctrl-C handles them).

:func:`held` marks a region where an interrupt must not land: creating a temporary folder
and taking charge of its removal, removing a temporary file, HDF5 writing (an exception
raised inside HDF5 crashed the interpreter at exit). A signal that arrives there is
recorded and raised when the outermost region ends. A flag is used rather than the
thread's signal mask: with numeric libraries' threads running, the kernel delivers a
process signal to any thread that does not block it, and Python then runs the handler in
the main thread all the same.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

__all__ = ["Terminated", "on_signal", "held", "raise_for", "raised_count", "received",
           "handle_signals"]

_state = {"depth": 0, "pending": 0, "raised": 0, "received": 0}


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP arrived (handled like Ctrl-C); ``signum`` says which."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def raise_for(signum: int) -> None:
    """Raise the exception of ``signum``: KeyboardInterrupt or Terminated."""
    _state["raised"] += 1
    if signum == signal.SIGINT:
        raise KeyboardInterrupt("SIGINT")
    raise Terminated(signum)


def on_signal(signum: int) -> None:
    """Raise for ``signum`` now, or when the current :func:`held` region ends."""
    _state["received"] = _state["received"] or signum
    if _state["depth"] > 0:
        _state["pending"] = _state["pending"] or signum
        return
    raise_for(signum)


def received() -> int:
    """The first interrupt signal received (0: none). A library may turn the exception
    into another one (numpy turns it into an ImportError while it is imported): the CLI
    then reports the interrupt, not that error."""
    return _state["received"]


def raised_count() -> int:
    """How many interrupts were raised so far (to tell whether one was swallowed)."""
    return _state["raised"]


@contextlib.contextmanager
def held() -> Iterator[None]:
    """Interrupts wait until the outermost held region ends (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _state["depth"] += 1
    try:
        yield
    finally:
        _state["depth"] -= 1
        if _state["depth"] == 0 and _state["pending"]:
            signum, _state["pending"] = _state["pending"], 0
            raise_for(signum)


#: code where an exception raised by a signal handler is printed and swallowed by Python
#: (weakref callbacks, finalisers): the signal is delivered again a moment later instead
_SWALLOWING = ("weakref.py", "_weakrefset.py")


def _would_be_swallowed(frame) -> bool:
    for _ in range(3):
        if frame is None:
            return False
        code = frame.f_code
        if code.co_name == "__del__" or code.co_filename.endswith(_SWALLOWING):
            return True
        frame = frame.f_back
    return False


def _on_signal(signum, frame) -> None:
    if _would_be_swallowed(frame):
        import os
        import threading

        seen = raised_count()

        def again() -> None:  # only if no interrupt was raised meanwhile
            if raised_count() == seen:
                os.kill(os.getpid(), signum)

        # a daemon: a process that ends meanwhile (the run completed) does not wait for
        # it at exit, where the signal would be raised inside threading's shutdown
        timer = threading.Timer(0.05, again)
        timer.daemon = True
        timer.start()
        return
    on_signal(signum)  # raises now, or when a region that must not be cut short ends


def handle_signals() -> None:
    """SIGINT, SIGTERM and SIGHUP raise KeyboardInterrupt (a :class:`Terminated` for the
    latter two) in the main thread; a signal this process was started ignoring (``nohup``,
    a background job of a script) stays ignored."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(sig) is not signal.SIG_IGN:  # nohup, a background job: kept
            signal.signal(sig, _on_signal)
