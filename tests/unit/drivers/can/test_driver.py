"""drivers.can.driver.CanDriver, the bus supervisor, on a real python-can bus (``virtual``, in this process) and a fake
clock: two ODrive 0.6 controllers are played by the test (:class:`tests.odrive_play.Controllers`), answering what the
driver sent each time the driver reads its clock, so every step happens at a time the test chose and nothing sleeps.
The full emulated controllers on real time are tests/integration/test_can_link.py's."""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import can
import pytest

from drivers.can import CanDriver, CanLinkConfig, encode
from drivers.odrive import AxisState, ControlMode, InputMode, ODriveError
from tests.fakeclock import FakeClock
from tests.odrive_play import HEARTBEAT_PERIOD, Controllers

CLOSED, IDLE = AxisState.CLOSED_LOOP_CONTROL, AxisState.IDLE


class Rig:
    def __init__(self, clock: FakeClock) -> None:
        self.clock = clock
        self.channel = f"unit-{uuid.uuid4().hex[:8]}"
        self.controllers = Controllers(self.channel, clock)
        self.bus_fails = False
        self.opened_at: list[float] = []  # fake times the driver built its bus
        self.driver = CanDriver(CanLinkConfig(interface="virtual", channel=self.channel, heartbeat_timeout=0.3,
                                              reopen_backoff=0.05, reopen_backoff_max=0.2, open_timeout=1.0),
                                clock=clock, open_bus=self.open_bus)
        clock.on_read.append(self.controllers.step)

    def open_bus(self) -> can.BusABC:
        self.opened_at.append(self.clock.t)
        if self.bus_fails:
            raise can.CanInitializationError("interface gone")
        return can.Bus(interface="virtual", channel=self.channel)

    def estimates(self, pos: float, wall: float) -> None:
        """Both controllers' encoder estimates at ``pos`` turns (each wheel's sign), stamped ``wall`` on the bus."""
        for node, sign in ((0, 1.0), (1, -1.0)):
            f = encode(node, "Get_Encoder_Estimates", {"Pos_Estimate": sign * pos, "Vel_Estimate": 0.0})
            f.timestamp = wall
            self.controllers.bus.send(f)

    def tick(self, dt: float = 0.02, v: float = 0.0, w: float = 0.0) -> None:
        """One driver-host tick ``dt`` after the last: send (or stop while not ok), then poll."""
        now = self.clock.advance(dt)
        d = self.driver
        if d.health(now).ok:
            d.send(v, w, now)
        else:
            d.stop(now)
        d.poll(now)


@pytest.fixture
def rig(clock: FakeClock) -> Iterator[Rig]:
    r = Rig(clock)
    try:
        yield r
    finally:
        r.driver.close(stop_timeout=0.0)
        r.controllers.bus.shutdown()


def engaged(rig: Rig) -> CanDriver:
    d = rig.driver
    d.open(rig.clock.t)
    d.engage(rig.clock.t)
    return d


def test_open_only_listens_and_engage_arms_velocity_control_then_closed_loop(rig: Rig) -> None:
    d = rig.driver
    d.open(rig.clock.t)
    assert rig.controllers.received == []  # listening: not a frame to the controllers
    h = d.health(rig.clock.t)
    assert (h.ok, h.reason, h.text) == (False, "not_engaged", "axes idle: not engaged")
    d.engage(rig.clock.t)
    for node in (0, 1):
        names = [nm for n, nm, _ in rig.controllers.received if n == node]
        assert names.index("Set_Controller_Mode") < names.index("Set_Axis_State")
        assert rig.controllers.mode[node] == (ControlMode.VELOCITY_CONTROL, InputMode.PASSTHROUGH)
        assert rig.controllers.state[node] == CLOSED
    h = d.health(rig.clock.t)
    assert (h.ok, h.reason, h.text) == (True, "ok", "ready")


def test_commands_go_out_as_wheel_turn_rates(rig: Rig) -> None:
    engaged(rig)
    rig.tick(v=0.25, w=0.1)
    k = 1 / (2 * 3.141592653589793 * 0.1)
    assert rig.controllers.input_vel[0] == pytest.approx((0.25 - 0.1 * 0.2) * k, rel=1e-6)
    assert rig.controllers.input_vel[1] == pytest.approx(-(0.25 + 0.1 * 0.2) * k, rel=1e-6)


def test_a_controller_fault_zeroes_both_wheels_in_the_same_poll_and_waits_for_the_operator(rig: Rig) -> None:
    d = engaged(rig)
    for _ in range(5):
        rig.tick(v=0.3)
    assert rig.controllers.input_vel[1] != 0.0
    rig.controllers.fault(0, ODriveError.DRV_FAULT)
    rig.controllers.received.clear()
    now = rig.clock.advance(HEARTBEAT_PERIOD)
    d.poll(now)  # the Heartbeat that says so: both wheels get zero at once, not at the host's next tick
    assert rig.controllers.input_vel == {0: 0.0, 1: 0.0}
    h = d.health(now)
    assert (h.ok, h.reason, h.text) == (False, "fault", "left axis error: DRV_FAULT") and h.detail.counters.faults == 1
    for _ in range(50):  # a second of the host asking to drive: zero only, nothing cleared or re-armed
        d.send(0.3, 0.0, rig.clock.advance(0.02))
        d.poll(rig.clock.t)
    assert {s["Input_Vel"] for _, s in rig.controllers.sent("Set_Input_Vel")} == {0.0}
    assert rig.controllers.sent("Clear_Errors") == [] and rig.controllers.sent("Set_Axis_State") == []
    d.clear_faults(rig.clock.t)  # the operator
    for _ in range(3):
        rig.tick()
    assert d.health(rig.clock.t).ok and rig.controllers.state[0] == CLOSED


def test_a_silent_controller_is_named_after_heartbeat_timeout_on_the_fake_clock(rig: Rig) -> None:
    d = engaged(rig)
    rig.controllers.muted.add(1)
    rig.controllers.heartbeats()
    t0 = rig.clock.t
    for _ in range(15):  # 0.3 s: still within heartbeat_timeout of the last Heartbeat
        rig.tick(v=0.2)
    assert d.health(rig.clock.t).ok and rig.clock.t == pytest.approx(t0 + 0.3)
    rig.tick(v=0.2)
    h = d.health(rig.clock.t)
    assert (h.ok, h.reason, h.text) == (False, "no_heartbeat", "right controller (node 1): no heartbeat for 0.32 s")
    assert h.detail.counters.heartbeat_losses == 1


def test_a_failed_bus_is_reopened_with_a_backoff_that_doubles_up_to_its_bound(rig: Rig) -> None:
    """The waits between reopen attempts are reopen_backoff doubled per failed attempt, bounded by
    reopen_backoff_max (0.05 -> 0.1 -> 0.2 -> 0.2 ...), measured on the fake clock."""
    d = engaged(rig)
    rig.bus_fails = True
    attempts_before = len(rig.opened_at)
    assert d.bus is not None
    d.bus.shutdown()  # the bus dies under the driver: its next receive raises
    rig.tick()
    failed_at = rig.clock.t
    for _ in range(100):  # 1 s at 100 Hz
        rig.tick(0.01)
    h = d.health(rig.clock.t)
    assert (h.ok, h.connected, h.reason) == (False, False, "link_down")
    assert h.text.startswith("CAN bus down (reopen failed: interface gone); reopening in ")
    assert h.detail.counters.bus_failures == 1
    attempts = rig.opened_at[attempts_before:]
    assert attempts[0] - failed_at == pytest.approx(0.05, abs=0.011)
    gaps = [b - a for a, b in zip(attempts, attempts[1:])]
    assert gaps == pytest.approx([0.1] + [0.2] * (len(gaps) - 1), abs=0.011) and len(gaps) >= 4
    rig.bus_fails = False  # back: the controllers' frames flow again on the new bus
    for _ in range(30):
        rig.tick(0.01)
    h = d.health(rig.clock.t)
    assert h.connected and h.detail.counters.reopens == 1


def test_poses_carry_the_frames_own_stamp_on_the_drivers_clock(rig: Rig) -> None:
    d = engaged(rig)
    estimates = rig.estimates

    estimates(0.0, rig.clock.wall() - 0.40)  # the anchor
    estimates(0.001, rig.clock.wall() - 0.30)  # received by the bus 0.3 s before this poll
    poses = d.poll(rig.clock.t)
    assert len(poses) == 1 and poses[0].stamp == pytest.approx(rig.clock.t - 0.30, abs=1e-6)
    fallbacks = d.counters["stamp_fallbacks"]
    estimates(0.002, 0.0)  # no stamp
    estimates(0.003, rig.clock.wall() + 30.0)  # from a wall clock that stepped
    poses = d.poll(rig.clock.t)
    assert [p.stamp for p in poses] == [rig.clock.t, rig.clock.t] and d.counters["stamp_fallbacks"] == fallbacks + 4


def test_a_preemption_between_the_clock_reads_does_not_move_a_polls_stamps(rig: Rig) -> None:
    """The wall clock's offset read with the thread held up (80 ms) between the two reads: the poll's poses keep
    their frames' own stamps (read one after the other, they were stamped 80 ms early, which a station can drop as
    moving too fast for its stamp)."""
    d = engaged(rig)
    estimates = rig.estimates

    estimates(0.0, rig.clock.wall() - 0.02)  # the anchor
    estimates(0.001, rig.clock.wall() - 0.01)
    clock, real_wall = rig.clock, rig.clock.wall
    preempted = []

    def wall_after_a_preemption() -> float:
        if not preempted:  # the thread loses the core just before its first wall read of this poll
            preempted.append(clock.advance(0.08))
        return real_wall()

    clock.wall = wall_after_a_preemption  # type: ignore[method-assign]
    try:
        poses = d.poll(clock.t)
    finally:
        clock.wall = real_wall  # type: ignore[method-assign]
    sent_at = preempted[0] - 0.08 - 0.01  # the frame's wall stamp on the driver's clock
    assert preempted and len(poses) == 1 and poses[0].stamp == pytest.approx(sent_at, abs=1e-6)


def test_health_reads_no_clock_and_changes_nothing(rig: Rig) -> None:
    d = engaged(rig)
    rig.tick()
    reads: list[float] = []
    rig.clock.on_read.append(lambda: reads.append(rig.clock.t))
    now = rig.clock.t
    before = (d.axes.phase, d.counters, dict(d.axes.lost))
    later, h = d.health(now + 5.0), d.health(now)
    assert reads == [] and not later.ok and h.ok and h == d.health(now)
    assert (d.axes.phase, d.counters, dict(d.axes.lost)) == before


def test_close_stops_the_wheels_and_idles_the_axes_only_when_told(rig: Rig) -> None:
    d = engaged(rig)
    rig.tick(v=0.3)
    rig.controllers.sent("Set_Input_Vel")
    d.close(disarm=True, stop_timeout=0.0)
    assert rig.controllers.sent("Set_Input_Vel") == [(0, {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}),
                                                   (1, {"Input_Vel": 0.0, "Input_Torque_FF": 0.0})]
    rig.controllers.step()
    assert rig.controllers.state == {0: IDLE, 1: IDLE}
    assert d.health(rig.clock.t).reason == "closed"


def test_close_stops_at_the_hosts_now(rig: Rig) -> None:
    """The driver host gives ``close`` its tick's ``now``: the zero set-points of closing are decided at it (the
    odometry counts the stop from then), not at a time the link read itself."""
    d = engaged(rig)
    rig.tick(v=0.3)
    given = rig.clock.t - 0.3  # a time the link's own clock does not read now
    d.close(disarm=True, stop_timeout=0.0, now=given)
    assert given in [at for at, _ in d.left.wheel.history] and given in [at for at, _ in d.right.wheel.history]
    assert rig.controllers.sent("Set_Input_Vel")[-2:] == [(0, {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}),
                                                         (1, {"Input_Vel": 0.0, "Input_Torque_FF": 0.0})]
    rig.controllers.step()
    assert rig.controllers.state == {0: IDLE, 1: IDLE}
