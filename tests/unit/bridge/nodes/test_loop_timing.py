"""The station's loops on a fake clock (tests/fakeclock.py; docs/ARCHITECTURE.md, "Threads and clocks"): the
scheduler's deadlines, wake-ups, missed deadlines and send budget (``FixedRate``); the station's own loop
(``Station._loop``) and the many-robot loop (``FleetLoop``) ticking on their deadlines, the status on a change and on
its cadence, a mission request settling on the driver host's next status, and the deadman on poses. Time moves only
when the loop waits on its clock: no test here sleeps, and each asserts the exact times.

The stations publish on a real Zenoh session (no endpoint: in process); what a callback would hand them (the driver
host's status, poses) is handed over as their callbacks do, at the time the fake clock says."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from bridge.core import wire as M
from bridge.core.acts import Address, stamped
from bridge.core.config import StationConfig, from_table, load_mission
from bridge.nodes.fleet_loop import FleetLoop
from bridge.nodes.mission_control import Fitness
from bridge.nodes.node import FixedRate
from bridge.nodes.station import Station
from bridge.nodes.station_status import STATUS_EVERY_S
from tests.fakeclock import FakeClock

RATE = 10.0
PERIOD = 1 / RATE


# ------------------------------------------------------------------------------------------------- the scheduler
def test_periodic_ticks_fall_on_their_deadlines_and_a_wake_comes_at_its_moment(clock: FakeClock) -> None:
    stop, wake = threading.Event(), threading.Event()
    t0 = clock.t
    ticker = FixedRate(RATE, stop, wake=wake, clock=clock)
    for k in range(1, 4):
        assert ticker.wait() is True and clock.t == pytest.approx(t0 + k * PERIOD) and ticker.late == 0.0
    clock.at(t0 + 3.25 * PERIOD, wake.set)  # an input between two deadlines: handled then, the deadline kept
    assert ticker.wait() is False and clock.t == pytest.approx(t0 + 3.25 * PERIOD) and not wake.is_set()
    assert ticker.wait() is True and clock.t == pytest.approx(t0 + 4 * PERIOD)
    clock.advance(2.5 * PERIOD)  # the tick overran two deadlines: one miss, a new schedule from now
    t_late = clock.t
    assert ticker.wait() is True and ticker.missed == 1 and clock.t == t_late
    assert ticker.late == pytest.approx(1.5 * PERIOD)
    assert ticker.wait() is True and clock.t == pytest.approx(t_late + PERIOD) and ticker.missed == 1


def test_a_rephased_wake_restarts_the_period_and_the_budget_holds_a_third_tick(clock: FakeClock) -> None:
    stop, wake = threading.Event(), threading.Event()
    t0 = clock.t
    ticker = FixedRate(20.0, stop, wake=wake, max_hz=40.0, rephase=True, clock=clock)  # the driver host's
    clock.at(t0 + 0.01, wake.set)
    assert ticker.wait() is False and clock.t == pytest.approx(t0 + 0.01) and ticker.t_next == clock.t
    wake.set()  # at once again: the budget's burst of two is spent, this one waits 1 / max_hz after the first
    assert ticker.wait() is False and clock.t == pytest.approx(t0 + 1 / 40.0)
    t3 = ticker.t_next
    assert ticker.wait() is True and clock.t == pytest.approx(t3 + 1 / 20.0)


# ------------------------------------------------------------------------------------------------- the station
@pytest.fixture(scope="module")
def session() -> Iterator[zenoh.Session]:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    s = zenoh.open(conf)
    yield s
    s.close()


class Heard:
    """What a station published on a robot's key, in order (a real subscriber on the session)."""

    def __init__(self, session: zenoh.Session, key: str, kind: type) -> None:
        self.kind, self.items, self.lock = kind, [], threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.items.append(M.decode(sample.payload.to_bytes(), self.kind))

    def wait(self, n: int, timeout: float = 10.0) -> list:
        """The first ``n`` messages, waited for up to ``timeout`` s (Zenoh delivers on its own threads)."""
        end = time.monotonic() + timeout
        while True:
            with self.lock:
                if len(self.items) >= n:
                    return list(self.items)
            assert time.monotonic() < end, f"{len(self.items)} of {n} messages on {self.kind.__name__}"
            time.sleep(0.005)


def _station(tmp_path, robot: str, session: zenoh.Session, clock: FakeClock, **cfg) -> Station:
    st = Station(from_table({"station": cfg}, StationConfig, "test"), robot, RATE,
                 tmp_path / f"{robot}.bin", load_mission(), clock=clock)
    keys = st.keys
    st.pubs = {t: session.declare_publisher(getattr(keys, t)) for t in ("cmd", "limits", "teacher")}
    st.pubs["status"] = session.declare_publisher(M.status_key(robot, "station"))
    st.core.latest.teacher_heard = False
    return st


def _driver(seq: int, ok: bool = True) -> M.Status:
    return M.Status(stamp=0.0, seq=seq, node="driver", ok=ok, text="link can: driving" if ok else "not engaged",
                    reason="ok" if ok else "not_engaged")


def _feed(st: Station, clock: FakeClock, start: float, end: float, *, poses_until: float | None = None,
          ok_from: float | None = None, ok_until: float | None = None) -> None:
    """The robot's pose every 50 ms from ``start`` to ``end`` (until ``poses_until``) and the driver host's status
    as a host sends it (each second and on a change: ok from ``ok_from`` to ``ok_until``, else not engaged), each
    handed to ``st`` 0.1 ms after its moment as its callbacks do; the pose stands still (a robot parked on its
    path's start)."""
    x, y, theta = (float(v) for v in np.asarray(st.core.mission.start, dtype=float)[:3])
    seq = iter(range(1, 10**6))

    def ok_at(t: float) -> bool:
        return (ok_from is None or t >= ok_from - 1e-9) and (ok_until is None or t < ok_until - 1e-9)

    def pose(t: float) -> None:
        with st.rx.lock:
            st.rx.inbox.telemetry.append((M.LearnerState(stamp=t, seq=next(seq), x=x, y=y, theta=theta), t))

    for k in range(round((end - start) / 0.05) + 1):
        t = start + 0.05 * k
        if poses_until is None or t < poses_until - 1e-9:
            clock.at(t + 1e-4, lambda t=t + 1e-4: pose(t))
    changes = sorted({start + k for k in range(int(end - start) + 1)} | {t for t in (ok_from, ok_until)
                                                                          if t is not None and start <= t <= end})
    for n, t in enumerate(changes, 1):
        clock.at(t + 1e-4, lambda t=t + 1e-4, n=n: st.rx.on_driver_status(_driver(n, ok_at(t)), t))


def test_the_loop_ticks_on_its_deadlines_and_says_its_status_on_a_change_and_each_second(tmp_path, session,
                                                                                          clock: FakeClock) -> None:
    st = _station(tmp_path, "t1", session, clock)
    cmds = Heard(session, st.keys.cmd, M.Command)
    status = Heard(session, M.status_key("t1", "station"), M.Status)
    t0 = clock.t
    _feed(st, clock, t0, t0 + 2.6, ok_until=t0 + 1.32)  # the host stops being ok at 1.32 s: said at once
    st.begin()
    st._loop(threading.Event(), duration=2.45, exit_at_goal=False)
    st.end()
    got = cmds.wait(25)
    assert [c.stamp - t0 for c in got] == pytest.approx([k * PERIOD for k in range(25)])  # on the deadlines
    assert all(c.method == "stop" for c in got)  # idle: nobody started a mission
    said = [round(s.stamp - t0, 6) for s in status.wait(5)]
    # each second from the first tick, and at once when what it says changed: the host's first status (it came
    # after the first tick: said at 0.1 s), the host no longer ok at 1.32 s (said at 1.4 s); the cadence keeps its
    # grid
    assert said == pytest.approx([0.0, PERIOD, STATUS_EVERY_S, 1.4, 2 * STATUS_EVERY_S])
    assert clock.t - t0 == pytest.approx(2.5)  # it ended at the first deadline past its duration


def test_a_resume_waits_for_the_driver_hosts_next_status_at_most_settle_s(tmp_path, session,
                                                                           clock: FakeClock) -> None:
    st = _station(tmp_path, "t2", session, clock)
    answers: list[M.MissionState] = []
    got = threading.Event()
    q = session.declare_queryable(st.keys.control, st.rx.on_control_query)
    t0 = clock.t
    st.core.control.request(M.MissionRequest(stamp=0.0, action="start", source="test"), Fitness(""), 0.0)
    st.core.control.drove = True
    st.core.control.request(M.MissionRequest(stamp=0.0, action="pause", source="test"), Fitness(""), 0.0)
    # the host is not ok (not engaged) until 0.93 s, then ok: a resume at 0.71 s is answered on that status
    _feed(st, clock, t0, t0 + 3.0, ok_from=t0 + 0.93)

    def ask(action: str) -> None:
        req = stamped(M.MissionRequest(stamp=0.0, action=action, source="test"), Address(st.core.outbox.epoch, clock.t))

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                answers.append(M.decode(reply.ok.payload.to_bytes(), M.MissionState))
                got.set()

        n = len(st.rx.inbox.queries)
        session.get(st.keys.control, on_reply, payload=M.encode(req), timeout=10.0)
        end = time.monotonic() + 10  # the query reaches the station on Zenoh's thread: wait for it to be there
        while len(st.rx.inbox.queries) == n and time.monotonic() < end:
            time.sleep(0.002)
        assert len(st.rx.inbox.queries) > n

    clock.at(t0 + 0.71, lambda: ask("resume"))
    st.begin()
    st._loop(threading.Event(), duration=1.5, exit_at_goal=False)
    st.end()
    assert got.wait(10.0)
    ans = answers[0]
    assert ans.accepted and ans.stamp == pytest.approx(t0 + 0.93 + 1e-4), ans  # answered on that status
    q.undeclare()

    st2 = _station(tmp_path, "t3", session, clock)
    answers.clear()
    got.clear()
    q = session.declare_queryable(st2.keys.control, st2.rx.on_control_query)
    t0 = clock.t
    st2.core.control.request(M.MissionRequest(stamp=0.0, action="start", source="test"), Fitness(""), 0.0)
    st2.core.control.drove = True
    st2.core.control.request(M.MissionRequest(stamp=0.0, action="pause", source="test"), Fitness(""), 0.0)
    _feed(st2, clock, t0, t0 + 3.0, ok_from=t0 + 5.0)  # never ok: refused once SETTLE_S has passed
    st = st2
    clock.at(t0 + 0.51, lambda: ask("resume"))  # the host's next status comes at 1.0 s: after SETTLE_S
    st2.begin()
    st2._loop(threading.Event(), duration=1.5, exit_at_goal=False)
    st2.end()
    assert got.wait(10.0)
    ans = answers[0]
    assert not ans.accepted and "not engaged" in ans.text
    # at the first deadline after SETTLE_S, without the host's next status
    assert ans.stamp - t0 == pytest.approx(0.9), ans.stamp - t0
    q.undeclare()


def test_a_running_station_stops_within_max_pose_age_of_the_last_pose(tmp_path, session, clock: FakeClock) -> None:
    st = _station(tmp_path, "t4", session, clock, max_pose_age_s=0.3)
    cmds = Heard(session, st.keys.cmd, M.Command)
    t0 = clock.t
    st.core.control.request(M.MissionRequest(stamp=0.0, action="start", source="test"), Fitness(""), 0.0)
    last_pose = t0 + 1.0
    _feed(st, clock, t0, t0 + 2.0, poses_until=last_pose + 1e-6)  # the poses stop after 1.0 s
    st.begin()
    st._loop(threading.Event(), duration=1.95, exit_at_goal=False)
    st.end()
    got = cmds.wait(20)
    moving = [c for c in got if c.method != "stop"]
    assert moving, [c.method for c in got]  # it drove while poses came
    first_stop = next(c for c in got if c.stamp > moving[0].stamp and c.method == "stop")
    # the pose received at 1.0001 s is too old once 0.3 s have passed: the first tick after that publishes a stop
    assert last_pose + 1e-4 + 0.3 < first_stop.stamp <= last_pose + 1e-4 + 0.3 + PERIOD + 1e-9
    assert all(c.method != "stop" for c in got if moving[0].stamp <= c.stamp < first_stop.stamp)
    assert all(c.method == "stop" for c in got if c.stamp >= first_stop.stamp)


def test_the_fleet_loop_ticks_each_robot_on_its_own_phase(tmp_path, session, clock: FakeClock) -> None:
    robots = [_station(tmp_path, f"f{i}", session, clock) for i in range(2)]
    heard = [Heard(session, st.keys.cmd, M.Command) for st in robots]
    t0 = clock.t
    FleetLoop(robots, threading.Event(), duration=1.0, exit_at_goal=False, clock=clock).run()
    for i, h in enumerate(heard):
        got = h.wait(10)
        assert len(got) == 10
        # robot i's first tick at i * period / 2: spread over the period, each then on its own deadlines
        assert [c.stamp - t0 for c in got] == pytest.approx([i * PERIOD / 2 + k * PERIOD for k in range(10)])


def test_the_fleet_loop_answers_a_woken_robot_at_once_between_its_deadlines(tmp_path, session,
                                                                            clock: FakeClock) -> None:
    robots = [_station(tmp_path, f"w{i}", session, clock) for i in range(2)]
    queryables = [session.declare_queryable(st.keys.pairs, st.rx.on_pairs_query) for st in robots]
    answers: list[M.Pairs] = []
    got = threading.Event()
    t0 = clock.t

    def ask() -> None:  # robot w1's pairs asked 0.23 s in: between its deadlines (0.2 and 0.25 s after its phase)
        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                answers.append(M.decode(reply.ok.payload.to_bytes(), M.Pairs))
                got.set()

        session.get(robots[1].keys.pairs, on_reply, timeout=10.0)
        end = time.monotonic() + 10  # the query reaches the station on Zenoh's thread: wait for it to be there
        while not robots[1].rx.inbox.queries and time.monotonic() < end:
            time.sleep(0.002)
        assert robots[1].rx.inbox.queries

    clock.at(t0 + 0.23, ask)
    heard = Heard(session, robots[1].keys.cmd, M.Command)
    FleetLoop(robots, threading.Event(), duration=0.5, exit_at_goal=False, clock=clock).run()
    assert got.wait(10.0)
    assert answers[0].stamp == pytest.approx(t0 + 0.23)  # answered when it came, not at the next deadline
    # and its ticks kept their deadlines (phase: half a period)
    assert [c.stamp - t0 for c in heard.wait(5)] == pytest.approx([PERIOD / 2 + k * PERIOD for k in range(5)])
    for q in queryables:
        q.undeclare()
