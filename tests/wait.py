"""Polling, bounded, for what no event announces (tests/integration/: another process's answers, an emulated
device's state, a Zenoh query's answer). Where an event can be awaited, tests await it instead."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def until(fn: Callable[[], T], timeout: float, step: float = 0.02) -> T:
    """``fn()`` once it is truthy, or its last value after ``timeout`` s, looked at every ``step`` s (a look that
    runs a process wants a longer step). For a state
    this process is told of by no event it could await: another process's answers (a ``scmbridge status`` run), an
    emulated device's or a Zenoh query's."""
    t_end = time.monotonic() + timeout
    while True:
        res = fn()
        if res or time.monotonic() > t_end:
            return res
        time.sleep(step)


class Pace:
    """The schedule of a simulated sender at a fixed rate (a mocap system, a robot's telemetry, a station's
    commands): ``wait()`` sleeps to the next slot of ``start + k * period``, so a late wake-up does not push every
    later send back (the rate holds on a loaded machine). After a stall longer than ``max_behind`` s it starts a new
    schedule from now instead of sending the missed slots in a burst."""

    def __init__(self, period: float, max_behind: float = 0.5) -> None:
        self.period = period
        self.max_behind = max_behind
        self.next = time.monotonic()

    def wait(self) -> None:
        """Sleep until the next slot."""
        self.next += self.period
        now = time.monotonic()
        if now - self.next > self.max_behind:
            self.next = now
        time.sleep(max(0.0, self.next - now))
