"""The many-robot loop's bookkeeping (bridge/nodes/fleet_loop.py): each robot's deadlines counted as a loop of its
own counts them (``Deadlines``: ``FixedRate``'s rules) and its wake-up flag, which never loses a set. The loop itself
runs real stations over Zenoh in tests/integration/test_fleet_loop.py."""

from __future__ import annotations

import threading

import pytest

from bridge.nodes.fleet_loop import Deadlines, FleetLoop, FleetWake, phases
from tests.fakeclock import FakeClock

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


def test_phases_spread_the_robots_over_the_period_and_share_instants_beyond_the_slots() -> None:
    assert phases(3, slots=5) == pytest.approx([0, 1 / 3, 2 / 3])  # few robots: an instant each
    assert phases(25, slots=5) == pytest.approx([k / 5 for k in range(5) for _ in range(5)])
    seven = phases(7, slots=5)
    assert seven == sorted(seven) and set(seven) == {k / 5 for k in range(5)}
    assert max(seven.count(p) for p in seven) - min(seven.count(p) for p in seven) <= 1  # as evenly as they go
    assert phases(1, slots=5) == [0.0] and phases(4, slots=1) == [0.0] * 4


class _Robot:
    """What the loop ticks (:class:`bridge.nodes.fleet_loop.Ticked`), recording when it was ticked."""

    def __init__(self, name: str, clock: FakeClock | None = None, work_s: float = 0.0) -> None:
        self.robot, self.period, self.ticker, self.wake = name, PERIOD, None, None
        self.core = type("Core", (), {"finished": False})()
        self.pubs: dict = {}
        self.ticks: list[float] = []
        #: each tick leaves work for later that takes ``work_s`` of the clock (when a clock is given)
        self.clock, self.work_s = clock, work_s
        self.left = False
        self.done: list[float] = []  # when the loop did it

    def tick(self, now: float, periodic: bool = True) -> None:
        self.ticks.append(now)
        self.left = self.clock is not None

    def between_ticks(self) -> bool:
        return False

    def background(self) -> bool:
        if not self.left:
            return False
        assert self.clock is not None
        self.left = False
        self.done.append(self.clock.t)
        self.clock.advance(self.work_s)
        return True

    def begin(self) -> None: ...

    def end(self) -> None: ...

    def undeclare(self) -> int:
        return 0


def test_the_robots_of_one_instant_are_ticked_on_one_wake_up() -> None:
    clock = FakeClock()
    waits: list[float] = []
    wait = clock.wait

    def counted(event: threading.Event, timeout: float | None) -> bool:
        waits.append(clock.t)
        return wait(event, timeout)

    clock.wait = counted  # type: ignore[method-assign]
    robots = [_Robot(f"r{i}") for i in range(6)]
    t0 = clock.t
    FleetLoop(robots, threading.Event(), duration=5 * PERIOD - 1e-6, exit_at_goal=False, clock=clock, slots=2).run()
    for i, r in enumerate(robots):  # two instants half a period apart, three robots each, every period
        assert r.ticks == pytest.approx([t0 + (i // 3) * PERIOD / 2 + k * PERIOD for k in range(5)])
    assert len(waits) <= 2 * 5 + 1  # one wake-up per instant (and the last one, to the end), not one per robot


def test_the_work_ticks_leave_for_later_is_done_while_no_robot_is_due_and_delays_no_tick() -> None:
    clock = FakeClock()
    robots = [_Robot(f"r{i}", clock, work_s=0.003) for i in range(6)]
    t0 = clock.t
    FleetLoop(robots, threading.Event(), duration=5 * PERIOD - 1e-6, exit_at_goal=False, clock=clock, slots=2).run()
    for i, r in enumerate(robots):
        due = [t0 + (i // 3) * PERIOD / 2 + k * PERIOD for k in range(5)]
        assert r.ticks == pytest.approx(due)  # on time: the work waited for the instant's ticks
        # each tick's work done once, after the robots of its instant were ticked and before its next tick
        assert len(r.done) == 5
        assert all(a <= d < b for a, d, b in zip(r.ticks, r.done, r.ticks[1:] + [float("inf")]))
    # the first instant's work began once its three robots were ticked: the third robot's work came 6 ms after the
    # instant (the two others' before it), and the next instant's ticks were still on time
    assert [robots[i].done[0] - t0 for i in range(3)] == pytest.approx([0.0, 0.003, 0.006])


def test_no_left_work_is_begun_when_the_next_deadline_is_near() -> None:
    from bridge.nodes.fleet_loop import BACKGROUND_LEAD_S

    clock = FakeClock()
    n = 40  # instants 2.5 ms apart, nearer than the lead: each robot's next tick does its own work
    assert PERIOD / n < BACKGROUND_LEAD_S
    robots = [_Robot(f"r{i}", clock, work_s=0.003) for i in range(n)]
    FleetLoop(robots, threading.Event(), duration=3 * PERIOD - 1e-6, exit_at_goal=False, clock=clock, slots=n).run()
    assert all(len(r.ticks) == 3 for r in robots) and not any(r.done for r in robots)
