"""The CAN link's driver on a real python-can bus (``virtual`` interface, in-process) against emulated ODrive 0.6
controllers: start-up, odometry, controller faults and the operator's clear, lost heartbeats, bus failures, garbage
(the frames, the DBC and the emulator's own contract: tests/integration/test_can_frames.py).

The expected values here are transcribed from ODrive's published 0.6 definitions, not from the driver:
``src/ODriveEnums.h`` of odriverobotics/ODriveArduino and ``odrive_base/include/can_simple_messages.hpp`` of
odriverobotics/ros_odrive (see drivers/odrive.py)."""

from __future__ import annotations

import math
import re
import struct
import threading
import time
import uuid
from collections.abc import Iterator

import can
import pytest

from drivers import open_driver
from drivers.base import Driver, LinkHealth, Pose
from drivers.can import CanDriver, CanHealthDetail, CanLinkConfig, database, decode, encode
from drivers.odrive import ODriveError
from sim_learner.can_ecu import DiffDriveEcus
from sim_learner.dynamics import mpc_learner
from sim_learner.vehicle import SimVehicle
from tests.fakeclock import FakeClock


def health(driver: Driver) -> LinkHealth:
    """The driver's health now (as the driver host asks for it each tick)."""
    return driver.health(time.monotonic())


# ------------------------------------------------------------------------------------------ the rig
class Rig:
    """Emulated controllers + driver + a third bus node (``spy``) on one fresh virtual channel."""

    def __init__(self, channel: str, driver: CanDriver, ecus: DiffDriveEcus, vehicle: SimVehicle,
                 spy: can.BusABC) -> None:
        self.channel, self.driver, self.ecus, self.vehicle, self.spy = channel, driver, ecus, vehicle, spy

    def body(self):
        return self.vehicle.advance(time.monotonic())

    def run(self, seconds: float, v: float = 0.0, w: float = 0.0, *, host: bool = False,
            co_located: bool = False) -> list[Pose]:
        """Call the driver for ``seconds`` at ~50 Hz: ``send(v, w)`` every tick (``host=True``: as the driver host
        does, ``send`` only while ``health().ok``, else ``stop``), then ``poll``. ``co_located``: first let the
        emulated controllers send what is due, as a driver host that emulates them in its own process does before
        each read of the bus (``DriverHost.co_located``)."""
        poses: list[Pose] = []
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            if co_located:
                self.ecus.emit_due()
            now = time.monotonic()
            if host and not health(self.driver).ok:
                self.driver.stop(now)
            else:
                self.driver.send(v, w, now)
            poses += self.driver.poll(now)
            time.sleep(max(0.0, now + 0.02 - time.monotonic()))  # pacing: a 50 Hz tick, as the driver host's
        return poses

    def wait(self, pred, timeout: float, v: float = 0.0, w: float = 0.0) -> bool:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            self.run(0.02, v, w, host=True)
            if pred():
                return True
        return False


@pytest.fixture
def rig() -> Iterator[Rig]:
    channel = f"test-{uuid.uuid4().hex[:8]}"
    vehicle = SimVehicle(mpc_learner(), (1.0, 2.0, 0.5), now=time.monotonic())
    ecus = DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle, watchdog=0.3).start()
    driver = open_driver("can", CanLinkConfig(interface="virtual", channel=channel, initial_pose=(1.0, 2.0, 0.5),
                                              heartbeat_timeout=0.3, reopen_backoff=0.05, reopen_backoff_max=0.2))
    spy = can.Bus(interface="virtual", channel=channel)
    try:
        driver.open(time.monotonic())
        driver.engage(time.monotonic())  # a person's act: both axes into closed loop
        yield Rig(channel, driver, ecus, vehicle, spy)
    finally:
        driver.close()
        ecus.stop()
        spy.shutdown()


def _master_frames(ecus: DiffDriveEcus, node: int, since: float) -> list[int]:
    """cmd ids the driver sent to ``node`` since ``since`` (emulator clock = time.monotonic)."""
    with ecus._lock:
        return [c for t, n, c, _ in ecus.received if n == node and t >= since]


# ------------------------------------------------------------------------------------------ start-up, driving
def test_open_sets_velocity_control_and_passthrough_before_closed_loop(rig: Rig) -> None:
    for node in (0, 1):
        with rig.ecus._lock:
            seq = [(c, d) for _, n, c, d in rig.ecus.received if n == node]
        modes = [i for i, (c, d) in enumerate(seq) if c == 0x0B and struct.unpack("<II", d) == (2, 1)]
        arm = [i for i, (c, d) in enumerate(seq) if c == 0x07 and struct.unpack_from("<I", d)[0] == 8]
        assert modes and arm and modes[0] < arm[0], seq
        ax = rig.ecus.axis(node)
        assert (ax.state, ax.control_mode, ax.input_mode) == (8, 2, 1)
    h = health(rig.driver)
    assert h.ok and h.text == "ready" and h.reason == "ok"


def test_commands_reach_the_bus_as_wheel_speeds_and_odometry_returns_the_pose(rig: Rig) -> None:
    v, w = 0.25, 0.1
    poses = rig.run(1.5, v, w)
    # the frames on the wire, read by a third bus: Input_Vel = sign * (v -/+ w b / 2) / (2 pi r)
    seen = {}
    while (f := rig.spy.recv(timeout=0)) is not None:
        try:
            node, name, sig = decode(f)
        except ValueError:
            continue
        if name == "Set_Input_Vel":
            seen[node] = sig["Input_Vel"]
    k = 1 / (2 * math.pi * 0.1)
    assert seen[0] == pytest.approx((v - w * 0.2) * k, rel=1e-6)
    assert seen[1] == pytest.approx(-(v + w * 0.2) * k, rel=1e-6)
    # odometry follows the learner body (its degraded response, not the command), up to the motion since the
    # last pose's own stamp
    body = rig.body()
    last = poses[-1]
    lag = max(0.0, time.monotonic() - last.stamp)
    assert math.hypot(last.x - body.x, last.y - body.y) < 0.01 + abs(body.v) * lag
    assert abs(last.theta - body.theta) < 0.01 + abs(body.omega) * lag
    assert body.x > 1.1  # it moved
    assert all(b.stamp >= a.stamp for a, b in zip(poses, poses[1:]))


# ------------------------------------------------------------------------------------------ controller faults
def _assert_held_while_sending(rig: Rig, seconds: float = 1.0) -> None:
    """Keep calling send(0.3, 0) for ``seconds``: the body must not move and no driving set-point may reach a
    wheel; the driver must not clear or re-arm anything by itself."""
    t_end = time.monotonic() + 10.0
    while rig.body().v != 0.0 and time.monotonic() < t_end:  # the stop takes effect (braking): waited for
        rig.run(0.02, 0.3, 0.0)
    t0 = time.monotonic()
    b0 = rig.body()
    x0, y0, th0 = b0.x, b0.y, b0.theta
    rig.run(seconds, 0.3, 0.0)
    b1 = rig.body()
    assert math.hypot(b1.x - x0, b1.y - y0) < 1e-6 and abs(b1.theta - th0) < 1e-6 and b1.v == 0.0
    for node in (0, 1):
        sent = _master_frames(rig.ecus, node, t0)
        assert 0x18 not in sent and 0x07 not in sent, f"driver cleared or re-armed node {node} by itself"
        ax = rig.ecus.axis(node)
        assert ax.input_vel == 0.0 or not ax.plugged  # a wheel that hears the driver got zero, not the command


def _cleared_and_driving(rig: Rig) -> None:
    rig.driver.clear_faults(time.monotonic())
    assert rig.wait(lambda: health(rig.driver).ok, 10.0), health(rig.driver).text
    x0 = rig.body().x
    rig.run(0.6, 0.3, 0.0, host=True)
    assert rig.body().v > 0.0 and rig.body().x != x0


def test_an_axis_error_stops_both_wheels_is_named_and_waits_for_the_operator(rig: Rig) -> None:
    rig.run(0.4, 0.3, 0.0)
    assert rig.body().v > 0.0
    rig.ecus.inject_error(0, ODriveError.DRV_FAULT)
    assert rig.wait(lambda: not health(rig.driver).ok, 10.0, 0.3)
    h = health(rig.driver)
    assert "left axis error: DRV_FAULT" in h.text and h.reason == "fault"
    _assert_held_while_sending(rig)
    assert rig.ecus.axis(0).state == 1 and rig.ecus.axis(1).state == 8  # left idle, right held in closed loop
    assert not health(rig.driver).ok and health(rig.driver).detail.counters.faults == 1
    _cleared_and_driving(rig)


@pytest.mark.parametrize("trip", ["watchdog", "estop from another node"])
def test_a_controllers_own_stop_is_never_overridden(rig: Rig, trip: str) -> None:
    rig.run(0.4, 0.3, 0.0)
    assert rig.body().v > 0.0
    if trip == "watchdog":
        time.sleep(0.6)  # a simulated stall: the driver host hangs, no set-point for > the controllers' watchdog
        node, name = 0, "left axis error: WATCHDOG_TIMER_EXPIRED"
    else:
        rig.spy.send(encode(1, "Estop"))
        node, name = 1, "right axis error: ESTOP_REQUESTED"
    assert rig.wait(lambda: not health(rig.driver).ok, 10.0, 0.3)
    _assert_held_while_sending(rig)
    assert rig.ecus.axis(node).state == 1
    assert name in health(rig.driver).text
    _cleared_and_driving(rig)


def test_health_is_pure_asking_changes_nothing_and_reads_no_clock(rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    """``health(now)`` reports the state at ``now`` as the last poll left it: asking about a moment when both
    controllers would have been silent for 5 s neither latches nor counts anything, and no clock is read."""
    d = rig.driver
    assert rig.wait(lambda: health(d).ok, 10.0), health(d).text
    now = time.monotonic()
    before = (d.axes.phase, dict(d.counters), dict(d.axes.lost), [(ax.fault, ax.heartbeat_at) for ax in d.axes])

    def no_clock() -> float:
        raise AssertionError("health() read the clock")

    with monkeypatch.context() as m:
        m.setattr(time, "monotonic", no_clock)
        m.setattr(time, "time", no_clock)
        later, h = d.health(now + 5.0), d.health(now)
    assert not later.ok and re.search(r"left controller \(node 0\): no heartbeat for 5\.\d\d s", later.text), later.text
    assert h.ok and h.text == "ready" and h == d.health(now)
    assert (d.axes.phase, dict(d.counters), dict(d.axes.lost), [(ax.fault, ax.heartbeat_at) for ax in d.axes]) == before
    assert isinstance(h.detail, CanHealthDetail) and h.detail.left.state == "CLOSED_LOOP_CONTROL"
    assert h.detail.right.node == 1 and not h.detail.right.fault and h.detail.counters.heartbeat_losses == 0
    rig.run(0.1, 0.2, 0.0, host=True)
    assert health(d).ok and d.counters["heartbeat_losses"] == 0


def test_a_lost_heartbeat_stops_the_base_and_names_the_node(rig: Rig) -> None:
    rig.run(0.4, 0.3, 0.0)
    rig.ecus.unplug(1)  # the right controller's cable
    t0 = time.monotonic()
    assert rig.wait(lambda: not health(rig.driver).ok and "node 1" in health(rig.driver).text, 10.0, 0.3)
    assert time.monotonic() - t0 < 0.3 + 0.25  # heartbeat_timeout + one heartbeat period + slack
    assert "right controller (node 1): no heartbeat" in health(rig.driver).text
    assert health(rig.driver).reason == "no_heartbeat"
    _assert_held_while_sending(rig, 0.8)
    # plugged back: its own watchdog tripped meanwhile, which is a latched fault for the operator
    rig.ecus.replug(1)
    assert rig.wait(lambda: "right axis error: WATCHDOG_TIMER_EXPIRED" in health(rig.driver).text, 10.0)
    rig.run(0.3, 0.3, 0.0)
    assert not health(rig.driver).ok and rig.ecus.axis(1).state == 1
    assert health(rig.driver).detail.counters.heartbeat_losses >= 1
    _cleared_and_driving(rig)


def test_controllers_emulated_in_the_hosts_process_speak_on_time_though_their_thread_is_starved(rig: Rig) -> None:
    """Finding (the fleet demo beside two busy loops): the controllers emulated inside a driver host (``--emulate``)
    ran on a thread the loaded interpreter did not schedule for 0.9 s; their Heartbeats stopped where real
    controllers' would not, and the station rightly paused that robot for a lost link. The host now lets them send
    what is due before each read of the bus (``DriverHost.co_located``)."""
    rig.run(0.4, 0.3, 0.0)
    rig.ecus._stop.set()  # the controllers' own thread is never scheduled again (their bus stays open)
    rig.ecus._thread.join(timeout=2.0)
    # a window in which the link must NOT be lost (> 3 heartbeat_timeout): absence is watched over time
    rig.run(1.0, 0.3, 0.0, co_located=True)
    h = health(rig.driver)
    assert h.ok and h.detail.counters.heartbeat_losses == 0, h.text
    # without it, as before: the link is lost (waited for, while the host keeps calling)
    assert rig.wait(lambda: health(rig.driver).detail.counters.heartbeat_losses >= 1, 10.0, 0.3)


def test_controllers_whose_thread_is_starved_apply_a_stop_when_it_arrives_not_when_they_run_again(rig: Rig) -> None:
    """Finding (the fleet demo under six test workers): the controllers emulated inside a driver host took a stop
    off the bus only when their starved thread ran again, so the wheels ran on at the old speed after it; the host,
    which sends estimates on their behalf before each read, then measured travel no real wheel makes after a stop
    and its odometry rightly rejected it ("implausible encoder estimates"): the station paused the robot. A real
    ODrive applies a Set_Input_Vel when the frame arrives; the emulator now applies each frame at its bus stamp."""
    rig.ecus.watchdog = 2.0  # controllers whose watchdog outlasts this test's starvation of their thread
    rig.run(0.5, 0.3, 0.26)  # a bend: the outer wheel at its fastest
    rig.ecus._stop.set()  # the controllers' own thread is never scheduled again (their bus stays open)
    rig.ecus._thread.join(timeout=2.0)
    t_a = time.monotonic()
    rig.vehicle.advance(t_a)
    d0 = rig.vehicle.distance
    rig.driver.send(0.0, 0.0, time.monotonic())  # the stop: on the bus now
    t_b = time.monotonic()
    time.sleep(0.3)  # a simulated stall: the host's thread too, after its write
    rig.ecus.emit_due()  # the host lets the controllers speak before it reads
    assert not rig.vehicle.moving
    assert rig.vehicle.distance - d0 <= 0.3 * (t_b - t_a) + 1e-9  # held from the stop's arrival, not from now
    rig.run(0.5, co_located=True)  # the host ticks on, stopped: its odometry judges what the wheels reported
    h = health(rig.driver)
    assert h.ok and h.detail.counters.rejected_estimates == 0, h.text


def test_a_driver_host_that_stalled_reads_the_heartbeats_waiting_on_the_bus_before_it_judges_the_link(
        rig: Rig) -> None:
    """Finding (the shard test beside two busy loops): a driver host that was not scheduled for 0.6 s judged the
    link's health before reading the bus, so the controllers' Heartbeats waiting there unread counted as lost, its
    status said "no heartbeat" and the station paused the mission. The host now reads the link first."""
    from bridge.nodes.driver_config import DriverConfig
    from bridge.nodes.driver_host import DriverHost

    class Pub:
        def put(self, data: bytes) -> None:
            pass

    rig.ecus.watchdog = 1.0  # controllers whose watchdog outlasts the stall (else they fault, as they must)
    host = DriverHost(DriverConfig(), "can", rig.driver, "r1", 50.0)
    host.pubs = {"state": Pub(), "applied": Pub()}
    host.engaged = True
    t_end = time.monotonic() + 10.0
    while time.monotonic() < t_end and not host.health.ok:  # ticking at 50 Hz until the link is fit
        host.tick(time.monotonic())
        time.sleep(0.02)  # the poll step of this deadline loop (a 50 Hz tick)
    assert host.health.ok, host.health.text
    time.sleep(0.6)  # a simulated stall: the host stalls for twice heartbeat_timeout; the controllers keep sending
    host.tick(time.monotonic())
    assert host.health.ok, host.health.text
    assert health(rig.driver).detail.counters.heartbeat_losses == 0


# ------------------------------------------------------------------------------------------ bus failures
def test_a_failed_bus_is_reported_and_reopened_with_bounded_backoff(rig: Rig, monkeypatch) -> None:
    d = rig.driver
    rig.run(0.2, 0.2, 0.0, host=True)
    attempts: list[float] = []
    real_open = d._open_bus

    def failing_open():
        attempts.append(time.monotonic())
        raise can.CanInitializationError("interface gone")

    monkeypatch.setattr(d, "_open_bus", failing_open)
    assert d.bus is not None
    d.bus.shutdown()  # the bus dies under the driver: recv/send raise can.CanOperationError
    rig.run(1.0, 0.2, 0.0, host=True)
    h = health(d)
    assert not h.ok and not h.connected and "CAN bus down" in h.text and "interface gone" in h.text
    assert h.reason == "link_down"
    assert h.detail.counters.bus_failures == 1
    # the waits between the attempts are test_reopen_attempts_wait_a_backoff_that_doubles_up_to_its_bound's (on a
    # fake clock); here, that it was retried and the wait reached its bound
    assert len(attempts) >= 2 and d._backoff.delay == 0.2, attempts
    monkeypatch.setattr(d, "_open_bus", real_open)
    # back: the controllers' frames flow again; their watchdogs (0.3 s) tripped during the 1 s outage, which
    # the driver reports and leaves to the operator
    assert rig.wait(lambda: health(d).connected and "WATCHDOG_TIMER_EXPIRED" in health(d).text, 10.0), (
        health(d).text)
    assert health(d).detail.counters.reopens == 1 and not health(d).ok
    n = health(d).frames_received
    rig.run(0.3, 0.2, 0.0, host=True)
    assert health(d).frames_received > n
    _cleared_and_driving(rig)


def test_reopen_attempts_wait_a_backoff_that_doubles_up_to_its_bound() -> None:
    """The waits between the attempts to reopen a failed bus: reopen_backoff, doubled after each failed attempt up to
    reopen_backoff_max (0.05, 0.1, 0.2, 0.2, ... s), on the driver's fake clock polled every 10 ms."""
    clock = FakeClock()
    channel = f"test-{uuid.uuid4().hex[:8]}"
    peer = can.Bus(interface="virtual", channel=channel)
    attempts: list[float] = []
    failing = False

    def open_bus() -> can.BusABC:
        attempts.append(clock.t)
        if failing:
            raise can.CanInitializationError("interface gone")
        bus = can.Bus(interface="virtual", channel=channel)
        for node in (0, 1):  # the controllers' Heartbeats, waiting for the driver's first poll
            peer.send(encode(node, "Heartbeat", {"Axis_Error": 0, "Axis_State": 1, "Procedure_Result": 0,
                                                 "Trajectory_Done_Flag": 0}))
        return bus

    d = CanDriver(CanLinkConfig(interface="virtual", channel=channel, reopen_backoff=0.05, reopen_backoff_max=0.2),
                  clock=clock, open_bus=open_bus)
    try:
        d.open(clock.t)
        failing = True
        assert d.bus is not None
        d.bus.shutdown()
        d.poll(clock.advance(0.01))  # the receive fails: the bus is released, a reopen scheduled
        failed_at, attempts[:] = clock.t, []
        for _ in range(100):
            d.poll(clock.advance(0.01))
        gaps = [b - a for a, b in zip(attempts, attempts[1:])]
        assert attempts[0] - failed_at == pytest.approx(0.05, abs=0.011), attempts
        assert gaps == pytest.approx([0.1] + [0.2] * (len(gaps) - 1), abs=0.011) and len(gaps) >= 4, gaps
        assert d.counters["bus_failures"] == 1 and not d.health(clock.t).connected
    finally:
        d.close(stop_timeout=0.0)
        peer.shutdown()


def test_error_frames_are_counted_apart_from_garbage_and_bus_off_reopens(rig: Rig) -> None:
    d = rig.driver
    h0 = health(d)
    malformed0, errors0 = h0.malformed, h0.errors
    rig.spy.send(can.Message(arbitration_id=0x004, is_error_frame=True, data=bytes(8)))  # controller problem
    rig.run(0.1)
    h = health(d)
    assert h.detail.counters.error_frames == 1 and h.errors == errors0 + 1 and h.malformed == malformed0
    assert h.ok and h.detail.counters.bus_failures == 0
    rig.spy.send(can.Message(arbitration_id=0x040, is_error_frame=True, data=bytes(8)))  # CAN_ERR_BUSOFF
    rig.run(0.05)
    h = health(d)
    assert h.detail.counters.bus_failures == 1 and h.malformed == malformed0
    assert rig.wait(lambda: health(d).ok, 10.0), health(d).text
    assert health(d).detail.counters.reopens == 1


def test_driver_counts_malformed_frames_on_its_bus(rig: Rig) -> None:
    before = health(rig.driver).malformed
    rig.spy.send(can.Message(arbitration_id=(0 << 5) | 0x09, data=b"\x01\x02", is_extended_id=False))
    rig.spy.send(can.Message(arbitration_id=(1 << 5) | 0x1F, data=b"", is_extended_id=False))
    rig.driver.poll(time.monotonic())  # (a virtual bus delivers at once)
    assert health(rig.driver).malformed >= before + 2


# ------------------------------------------------------------------------------------------ odometry
def test_implausible_encoder_estimates_never_reach_the_pose(rig: Rig) -> None:
    d = rig.driver
    poses = rig.run(0.3, 0.25, 0.0)
    garbage = [(3.0e38, 0.0), (2000.0, 0.0), (0.0, 1e6), (-1e8, 0.0)]
    for pos, vel in garbage:
        for node in (0, 1):
            rig.spy.send(encode(node, "Get_Encoder_Estimates", {"Pos_Estimate": pos, "Vel_Estimate": vel}))
        poses += rig.run(0.05, 0.25, 0.0)
    for data in (struct.pack("<ff", math.nan, 0.0), struct.pack("<ff", 0.0, math.inf)):
        rig.spy.send(can.Message(arbitration_id=0x09, data=data, is_extended_id=False))
    poses += rig.run(0.5, 0.25, 0.0)
    assert all(math.isfinite(p.x) and math.isfinite(p.y) and abs(p.x - 1.0) < 2.0 for p in poses)
    body = rig.body()
    lag = max(0.0, time.monotonic() - poses[-1].stamp)
    assert math.hypot(poses[-1].x - body.x, poses[-1].y - body.y) < 0.01 + abs(body.v) * lag
    assert health(d).detail.counters.rejected_estimates >= 2 * len(garbage)
    assert health(d).malformed >= 2 * len(garbage) + 2


def test_a_real_encoder_jump_resyncs_the_reference_without_moving_the_pose() -> None:
    d = CanDriver(CanLinkConfig(max_wheel_speed=5.0))
    t = 0.0
    for step in range(5):  # driving straight: left +0.01 rev, right -0.01 rev per 10 ms
        t = step * 0.01
        d._encoder(d.left, 0.01 * step, 1.0, t, t)
        d._encoder(d.right, -0.01 * step, -1.0, t, t)
    x_before = d.pose[0]
    assert x_before > 0.0
    for k in range(1, 4):  # the left controller rebooted: its position starts again near 500 rev
        t += 0.01
        d._encoder(d.left, 500.0 + 0.01 * k, 1.0, t, t)
        d._encoder(d.right, -0.04 - 0.01 * k, -1.0, t, t)
    assert d.counters["resyncs"] == 1 and d.counters["rejected_estimates"] == 3
    assert d.pose[0] == pytest.approx(x_before, abs=1e-9)  # the jump was not integrated
    for k in range(4, 8):
        t += 0.01
        d._encoder(d.left, 500.0 + 0.01 * k, 1.0, t, t)
        d._encoder(d.right, -0.04 - 0.01 * k, -1.0, t, t)
    assert d.pose[0] > x_before + 3 * 0.01 * 2 * math.pi * 0.1 * 0.99  # it integrates again from the new anchor


class FakeControllers:
    """Heartbeats (closed loop, no error) for nodes 0 and 1 from a thread; ``tx`` sends crafted frames with the
    wall-clock stamp they carry (``preserve_timestamps``: the stamp a receiving interface would have set)."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, daemon=True)
        self._lock = threading.Lock()

    def _beat(self) -> None:
        while not self._stop.wait(0.05):
            for node in (0, 1):
                f = encode(node, "Heartbeat", {"Axis_Error": 0, "Axis_State": 8, "Procedure_Result": 1,
                                               "Trajectory_Done_Flag": 1})
                f.timestamp = time.time()
                self.tx(f)

    def tx(self, frame: can.Message) -> None:
        with self._lock:
            self.bus.send(frame)

    def __enter__(self) -> FakeControllers:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.bus.shutdown()


def test_poses_carry_the_frames_own_receive_time_on_the_monotonic_clock() -> None:
    channel = f"test-{uuid.uuid4().hex[:8]}"
    driver = open_driver("can", CanLinkConfig(interface="virtual", channel=channel))
    with FakeControllers(channel) as fake:
        try:
            driver.open(time.monotonic())

            def pair(pos: float, wall: float) -> None:
                for node, sign in ((0, 1.0), (1, -1.0)):
                    f = encode(node, "Get_Encoder_Estimates", {"Pos_Estimate": sign * pos, "Vel_Estimate": 0.0})
                    f.timestamp = wall
                    fake.tx(f)

            pair(0.0, time.time() - 0.40)  # the anchor
            mono_expected = time.monotonic() - 0.30
            pair(0.01, time.time() - 0.30)  # received (by the bus) 0.3 s before now: the pose's time, not the poll's
            # (the virtual bus delivers at once; the poll comes whenever the loaded host gets to it)
            poses = driver.poll(time.monotonic())
            assert len(poses) == 1 and poses[0].stamp == pytest.approx(mono_expected, abs=0.03)
            # no stamp, or one from a wall clock that stepped: the receive time, counted
            fallbacks = driver.counters["stamp_fallbacks"]
            pair(0.02, 0.0)
            pair(0.03, time.time() + 30.0)
            t_poll = time.monotonic()
            poses = driver.poll(t_poll)
            assert len(poses) == 2 and all(t_poll - 0.05 <= p.stamp <= time.monotonic() for p in poses)
            assert driver.counters["stamp_fallbacks"] >= fallbacks + 4
        finally:
            driver.close()


def test_many_small_crafted_encoder_steps_cannot_add_up_to_more_than_the_wheel_can_do() -> None:
    """Finding: crafted encoder frames, each a small plausible step, gave 101 m of odometry error in 2 s (status
    ok). Each wheel's travel now has a budget refilled at what it can really turn; the link says so when tampered."""
    clock = FakeClock()
    d = CanDriver(CanLinkConfig(max_wheel_speed=10.0), clock=clock)
    d.axes.phase = "running"
    t = 0.0
    d._encoder(d.left, 0.0, 0.0, t, clock.t)  # (stamped t, read by the poll at the driver's clock.t)
    d._encoder(d.right, 0.0, 0.0, t, clock.t)
    for k in range(1, 4001):  # 2 s of frames at 2 kHz, each 0.02 rev ahead (40 rev/s if believed): standing still
        t = k * 0.0005
        d._encoder(d.left, 0.02 * k, 0.0, t, clock.t)
        d._encoder(d.right, -0.02 * k, 0.0, t, clock.t)
    assert abs(d.pose[0]) < 0.7, d.pose  # at most what a wheel told to stand still may roll (not 100 m)
    assert d.counters["rejected_estimates"] > 1000
    h = d.health(clock.t)
    assert not h.ok and "odometry: implausible encoder estimates" in h.text


@pytest.mark.parametrize("engage,disarm", [(False, False), (False, True), (True, False), (True, True)])
def test_close_sends_nothing_to_axes_it_never_armed_and_idles_them_only_when_told(engage: bool, disarm: bool) -> None:
    """Found: close ignored ``disarm`` and always sent IDLE, also on ``--dry-run`` (which promises that nothing is
    sent to the vehicle) and for a host that was never engaged. The emulated ODrives record every frame they got."""
    channel = f"test-{uuid.uuid4().hex[:8]}"
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle, watchdog=0.3) as ecus:
        driver = open_driver("can", CanLinkConfig(interface="virtual", channel=channel, heartbeat_timeout=0.3))
        driver.open(time.monotonic())
        if engage:
            driver.engage(time.monotonic())
        spy = can.Bus(interface="virtual", channel=channel)  # sees every frame put on the bus from now on
        try:
            driver.close(disarm=disarm, stop_timeout=1.0)
            frames, t_end = [], time.monotonic() + 0.3  # the controllers' Heartbeats never stop: a bounded look
            while time.monotonic() < t_end:
                if (f := spy.recv(timeout=0.05)) is not None:
                    frames.append(f.arbitration_id)
        finally:
            spy.shutdown()
    cmd = database().get_message_by_name
    idle = cmd("Set_Axis_State").frame_id & 0x1F
    vel = cmd("Set_Input_Vel").frame_id & 0x1F
    nodes = (ecus.left.node, ecus.right.node)
    # what the driver sent (the controllers' own frames, Heartbeats and encoder estimates, are theirs)
    sent = [a & 0x1F for a in frames if a >> 5 in nodes and a & 0x1F in (idle, vel, cmd("Set_Controller_Mode").frame_id
                                                                          & 0x1F)]
    if not engage:
        assert sent == [], sent  # never armed by this link: nothing at all
    else:
        assert vel in sent  # armed by this link: stopped first
        assert (idle in sent) == disarm
