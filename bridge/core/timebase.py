"""The one place the control path reads the time or waits on it (docs/ARCHITECTURE.md section 4, "Threads and
clocks").

A loop (the driver host's, the drivers' bounded waits in ``open``, ``engage`` and ``close``) is given a :data:`Clock`
and a :data:`Wait` when it is built, reads the clock once per tick and passes that ``now`` down; nothing below it
reads the time again. The defaults here are the machine's monotonic clock and a real wait on an event; a test gives
a fake clock whose waits move the time at once (``tests/fakeclock.py``), so the loops' timing (wake-ups, the
deadman, the send budget, the status cadence) is tested without sleeping and without depending on the machine's
load.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol


class Event(Protocol):
    """What a clock waits on: a ``threading.Event`` (named by its methods: the pure station core, which reaches
    this module through :mod:`bridge.core.clock`, imports no threading)."""

    def wait(self, timeout: float | None = None) -> bool: ...

    def is_set(self) -> bool: ...


#: a monotonic clock in seconds (:func:`monotonic`, or a test's fake)
Clock = Callable[[], float]
#: wait on ``event`` at most ``timeout`` seconds of that clock; True if the event was set (``event.wait``'s contract)
Wait = Callable[[Event, float], bool]
#: a wait of so many seconds on that clock, with nothing to wake it (``time.sleep``'s contract)
Sleep = Callable[[float], None]


def monotonic() -> float:
    """The machine's monotonic clock: every stamp of a driver host and of its link. (Looked up at each call, so a
    test that replaces ``time.monotonic`` to catch a read catches this one too.)"""
    return time.monotonic()


def wall() -> float:
    """The machine's wall clock (only python-can's frame stamps and MAVLink signing's timestamps are on it)."""
    return time.time()


def sleep(dt: float) -> None:
    """A real sleep of ``dt`` s."""
    time.sleep(dt)


def perf() -> float:
    """A high-resolution counter, for a duration's measurement only."""
    return time.perf_counter()


def wait(event: Event, timeout: float | None) -> bool:
    """Block until ``event`` is set or ``timeout`` seconds have passed (a negative timeout does not wait; None waits
    until it is set)."""
    return event.wait(None if timeout is None else max(0.0, timeout))
