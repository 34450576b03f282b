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

__all__ = ["Terminated", "on_signal", "held", "raise_for", "raised_count"]

_state = {"depth": 0, "pending": 0, "raised": 0}


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
    if _state["depth"] > 0:
        _state["pending"] = _state["pending"] or signum
        return
    raise_for(signum)


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
