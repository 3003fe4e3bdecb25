"""bridge/core/timebase.py: the one module of the control path that reads the time (docs/ARCHITECTURE.md section 4),
and the fake clock's stand-in for its wait (``tests/fakeclock.py``) keeping the same contract."""

from __future__ import annotations

import threading
import time

import pytest

from bridge.core import timebase
from tests.fakeclock import FakeClock


def test_the_clock_is_looked_up_at_each_call_so_a_test_that_replaces_it_sees_every_read(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(time, "monotonic", lambda: 42.0)
    monkeypatch.setattr(time, "time", lambda: 1.7e9)
    assert timebase.monotonic() == 42.0 and timebase.wall() == 1.7e9


def test_a_wait_returns_true_at_once_on_a_set_event_and_false_after_its_timeout() -> None:
    ev = threading.Event()
    ev.set()
    assert timebase.wait(ev, 10.0) is True
    ev.clear()
    t0 = time.monotonic()
    assert timebase.wait(ev, 0.01) is False and time.monotonic() - t0 >= 0.005
    assert timebase.wait(ev, -1.0) is False  # a deadline already passed does not wait


def test_the_fake_wait_moves_the_clock_to_what_is_due_and_ends_when_the_event_is_set() -> None:
    clock, ev = FakeClock(t=10.0), threading.Event()
    clock.at(10.3, ev.set)
    assert clock.wait(ev, 1.0) is True and clock.t == 10.3  # woken at the moment the input came
    ev.clear()
    assert clock.wait(ev, 0.5) is False and clock.t == pytest.approx(10.8)
    clock.at(20.0, ev.set)  # beyond the timeout: not yet
    assert clock.wait(ev, 1.0) is False and clock.t == pytest.approx(11.8) and not ev.is_set()
