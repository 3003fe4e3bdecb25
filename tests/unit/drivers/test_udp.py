"""drivers.udp.UdpDriver on real UDP sockets (127.0.0.1, free ports) and a fake clock: the robot is played by the test
at each of the driver's sleeps (open and close wait with the ``sleep`` they were given), so its answers come at fake
times the test chose and nothing sleeps. The robot's own firmware behaviour is tests/integration/test_udp_link.py's."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest

from bridge.core import wire as M
from drivers.base import DriverError
from drivers.udp import GREET_PERIOD_S, UdpDriver, UdpLinkConfig
from tests.fakeclock import FakeClock


class Robot:
    """A robot's socket: each :meth:`answer` reads the commands the driver sent (waiting for the first, bounded) and
    sends one state from its own clock, which runs ``offset`` s from the driver's."""

    def __init__(self, clock: FakeClock, offset: float = -900.0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(2.0)
        self.port = self.sock.getsockname()[1]
        self.clock, self.offset = clock, offset
        self.epoch, self.seq = M.new_epoch(), 0
        self.commands: list[M.Command] = []
        self.peer: tuple[str, int] | None = None
        self.v = 0.3
        self.silent = False

    def answer(self) -> None:
        data, self.peer = self.sock.recvfrom(65536)  # the command the driver just sent (already in the buffer)
        self.commands.append(M.decode(data, M.Command))
        self.sock.setblocking(False)
        try:
            while True:
                data, _ = self.sock.recvfrom(65536)
                self.commands.append(M.decode(data, M.Command))
        except BlockingIOError:
            pass
        finally:
            self.sock.settimeout(2.0)
        if not self.silent:
            self.state(self.clock.t + self.offset)

    def state(self, stamp: float) -> None:
        assert self.peer is not None
        self.seq += 1
        st = M.LearnerState(stamp=stamp, seq=self.seq, x=1.0, y=2.0, theta=0.5, v=self.v, omega=0.0,
                            epoch=self.epoch)
        self.sock.sendto(M.encode(st), self.peer)


@pytest.fixture
def robot(clock: FakeClock) -> Iterator[Robot]:
    r = Robot(clock)
    clock.on_sleep.append(r.answer)
    yield r
    r.sock.close()


def driver(clock: FakeClock, robot: Robot, **cfg: object) -> UdpDriver:
    return UdpDriver(UdpLinkConfig(robot_port=robot.port, bind_port=0, insecure=True, **cfg),  # type: ignore[arg-type]
                     clock=clock)


def test_open_greets_with_a_stop_until_the_first_state_and_health_follows_the_fake_clock(clock: FakeClock,
                                                                                           robot: Robot) -> None:
    d = driver(clock, robot)
    t0 = clock.t
    d.open(t0)
    try:
        assert [c.method for c in robot.commands] == ["stop"] and robot.commands[0].v == 0.0
        assert clock.t == pytest.approx(t0 + GREET_PERIOD_S)  # one greeting period, on the fake clock
        h = d.health(clock.t)
        assert (h.ok, h.reason, h.text) == (True, "ok", "ready")
        late = d.health(clock.t + 0.51)  # state_timeout_s = 0.5
        assert (late.ok, late.reason, late.text) == (False, "no_telemetry", "no state from the robot for 0.5 s")
    finally:
        d.close(stop_timeout=0.0)


def test_open_gives_up_after_open_timeout_on_the_fake_clock(clock: FakeClock, robot: Robot) -> None:
    robot.silent = True
    d = driver(clock, robot, open_timeout=0.5)
    t0 = clock.t
    with pytest.raises(DriverError, match="no state from the UDP robot at 127.0.0.1:.* within 0.5 s"):
        d.open(t0)
    assert t0 + 0.5 <= clock.t <= t0 + 0.5 + GREET_PERIOD_S + 1e-9  # the deadline, on the fake clock
    assert len(robot.commands) == round((clock.t - t0) / GREET_PERIOD_S)  # a hello each period until then
    d.close(stop_timeout=0.0)


def test_poses_are_stamped_on_the_drivers_clock_from_the_robots_own_stamps(clock: FakeClock, robot: Robot) -> None:
    d = driver(clock, robot)
    d.open(clock.t)
    try:
        first = clock.t  # the first state was stamped at the robot's clock and received at once
        sample = clock.t + robot.offset
        for k in (1, 2, 3):  # sampled every 20 ms, received late by 0, 30 and 10 ms
            robot.state(sample + 0.02 * k)
        clock.advance(0.07)
        poses = d.poll(clock.t)
        assert [p.stamp for p in poses] == pytest.approx([first + 0.02, first + 0.04, first + 0.06])
        assert d.counters["clock_restarts"] == 0 and d.counters["stamp_fallbacks"] == 0
        robot.state(0.0)  # a stamp that does not advance: no clock, its receipt it is
        poses = d.poll(clock.t)
        assert [p.stamp for p in poses] == [clock.t] and d.counters["stamp_fallbacks"] == 1
    finally:
        d.close(stop_timeout=0.0)


def test_commands_carry_the_drivers_epoch_and_seq_and_close_stops_until_the_robot_has(clock: FakeClock,
                                                                                     robot: Robot) -> None:
    d = driver(clock, robot)
    d.open(clock.t)
    d.send(0.2, 0.1, clock.advance(0.02))
    d.send(0.2, 0.1, clock.advance(0.02))
    robot.answer()
    sent = robot.commands[-2:]
    assert [(c.method, c.v, c.omega, c.sender, c.epoch) for c in sent] == [("scm", 0.2, 0.1, "driver", d.epoch)] * 2
    assert sent[1].seq == sent[0].seq + 1 and sent[1].stamp == pytest.approx(sent[0].stamp + 0.02)
    robot.v = 0.2
    clock.on_sleep.append(lambda: setattr(robot, "v", robot.v - 0.1))  # the robot slows down on the stops
    t0 = clock.t
    d.close(stop_speed=0.05, stop_timeout=3.0)
    # it reports 0.2, 0.1, then 0.0 m/s: three stops, a period apart
    assert robot.commands[-1].method == "stop" and clock.t == pytest.approx(t0 + 3 * GREET_PERIOD_S)
    assert d.health(clock.t).reason == "closed"
