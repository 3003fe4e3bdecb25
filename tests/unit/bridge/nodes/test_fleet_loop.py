"""The many-robot loop's bookkeeping (bridge/nodes/fleet_loop.py): each robot's deadlines counted as a loop of its
own counts them (``Deadlines``: ``FixedRate``'s rules) and its wake-up flag, which never loses a set. The loop itself
runs real stations over Zenoh in tests/integration/test_fleet_loop.py."""

from __future__ import annotations

import threading

import pytest

from bridge.nodes.fleet_loop import Deadlines, FleetWake

PERIOD = 0.1


def test_deadlines_count_a_miss_as_a_loop_of_its_own_does() -> None:
    d = Deadlines(PERIOD, 10.0)
    d.ticked(10.05, periodic=True)  # ended before the next deadline (10.1)
    assert (d.missed, d.t_next) == (0, pytest.approx(10.1))
    d.ticked(10.25, periodic=True)  # the tick due at 10.1 ended past 10.2: missed; next on its own phase after 10.25
    assert (d.missed, d.t_next) == (1, pytest.approx(10.3))
    d.ticked(10.32, periodic=True)
    assert (d.missed, d.t_next) == (1, pytest.approx(10.4))
    d.ticked(10.45, periodic=False)  # a woken tick past the deadline by less than a period: keeps the schedule
    assert (d.missed, d.t_next) == (1, pytest.approx(10.4))
    d.ticked(10.63, periodic=False)  # a whole period late: counted; the next deadline is its own after 10.63
    assert (d.missed, d.t_next) == (2, pytest.approx(10.7))
    d.ticked(10.71, periodic=True)  # a stall of several periods is one miss, and the phase is kept
    d.ticked(11.02, periodic=True)
    assert (d.missed, d.t_next) == (3, pytest.approx(11.1))


def test_a_wake_sets_the_shared_event_and_is_taken_once() -> None:
    shared = threading.Event()
    w = FleetWake(shared)
    assert not w.take() and not shared.is_set()
    w.set()
    assert shared.is_set() and w.is_set()
    assert w.take() and not w.is_set()
    assert not w.take()  # taken once
