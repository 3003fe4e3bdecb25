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
