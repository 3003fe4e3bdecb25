"""The MAVLink link's pure decisions (drivers.mavlink.state) and its driver and client on a fake clock: messages are
real pymavlink frames (encoded, then parsed back), the command protocol runs over a real pymavlink UDP connection on
127.0.0.1, and every time is the fake clock's. The driver against an emulated rover on real time is
tests/integration/test_mavlink_link.py's."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import pytest
from pymavlink import mavutil

from drivers.base import LinkHealth
from drivers.mavlink import MavlinkDriver, MavlinkLinkConfig, load_pymavlink
from drivers.mavlink.client import NO_ACK, Command, MavlinkClient
from drivers.mavlink.state import (
    GUIDED_TIMEOUT_S,
    Change,
    SetpointPacer,
    Vehicle,
    Verdict,
    change,
    failsafe_report,
)
from tests.fakeclock import FakeClock

MAV = mavutil.mavlink
GUIDED, HOLD = 15, 4  # ArduPilot Rover's custom modes


# ------------------------------------------------------------------------------------------ pure decisions
def test_an_unchanged_set_point_repeats_at_its_rate_a_changed_one_goes_at_once_within_the_radios_budget() -> None:
    p = SetpointPacer(period=0.1, min_gap=0.04)
    assert p.due((0.2, 0.0), 0.0)
    p.sent((0.2, 0.0), 0.0)
    assert not p.due((0.2, 0.0), 0.09) and p.due((0.2, 0.0), 0.1)  # the same command: each period
    assert not p.due((0.3, 0.0), 0.03) and p.deferred == 1  # changed, but the last went 30 ms ago
    assert p.due((0.3, 0.0), 0.04)
    assert p.due((0.0, 0.0), 0.001)  # a stop after motion: always at once
    p.sent((0.0, 0.0), 0.001)
    assert not p.due((0.0, 0.0), 0.002)  # a stop repeated is an unchanged command
    assert p.deferred == 1


def test_a_new_verdict_says_a_change_counts_a_lost_link_once_and_asks_for_the_streams_when_it_is_back() -> None:
    ok = Verdict(True, True, "driving: GUIDED, armed", "ok")
    down = Verdict(False, False, "no heartbeat for 3.1 s", "link_down")
    hold = Verdict(True, False, "operator took control: mode HOLD", "operator")
    assert change(ok, down, link_up=True) == Change(said=True, lost=True, back=False)
    assert change(down, down, link_up=False) == Change(said=False, lost=False, back=False)
    assert change(down, hold, link_up=False) == Change(said=True, lost=False, back=True)
    assert change(hold, ok, link_up=True) == Change(said=True, lost=False, back=False)


def test_the_failsafe_report_names_how_long_the_vehicle_drives_on_without_this_host() -> None:
    assert failsafe_report({}).drive_on_s == GUIDED_TIMEOUT_S
    assert "no failsafe parameter answered" in failsafe_report({}).text
    r = failsafe_report({"FS_GCS_ENABLE": 1.0, "FS_GCS_TIMEOUT": 1.0, "FS_ACTION": 2.0, "FS_TIMEOUT": 0.5})
    assert r.drive_on_s == 1.5 and "FS_GCS_ENABLE=1, FS_GCS_TIMEOUT=1, FS_ACTION=2, FS_TIMEOUT=0.5" in r.text
    assert failsafe_report({"FS_GCS_ENABLE": 1.0, "FS_GCS_TIMEOUT": 1.0, "FS_ACTION": 0.0}).drive_on_s == 3.0


def test_the_vehicle_remembers_guided_once_seen_and_a_clock_gone_back_is_a_reboot() -> None:
    v = Vehicle()
    v.heard(HOLD, False, 5.0, GUIDED)
    assert (v.custom_mode, v.armed, v.hb_time, v.guided_seen) == (HOLD, False, 5.0, False)
    v.heard(GUIDED, True, 6.0, GUIDED)
    v.heard(HOLD, True, 7.0, GUIDED)
    assert v.guided_seen and v.hb_time == 7.0
    assert not v.boot(10_000) and not v.boot(9_500) and not v.rebooted  # jitter within a second
    assert v.boot(800) and v.rebooted and v.boot_ms == 800


# ------------------------------------------------------------------------------------------ the driver's messages
class Sender:
    """The vehicle's side of the framing: pymavlink messages encoded and parsed back, as the link would deliver."""

    def __init__(self) -> None:
        self.enc = MAV.MAVLink(None, srcSystem=1, srcComponent=1)
        self.dec = MAV.MAVLink(None)

    def __call__(self, drv: MavlinkDriver, msg: Any) -> list:
        out: list = []
        drv._handle(self.dec.parse_char(msg.pack(self.enc)), out, drv.clock())  # received now, on the driver's clock
        return out


def test_messages_are_timed_on_the_drivers_clock_and_poses_at_the_vehicles_own_time(clock: FakeClock) -> None:
    drv = MavlinkDriver(MavlinkLinkConfig(), clock=clock)
    send, enc = Sender(), Sender().enc
    send(drv, enc.heartbeat_encode(MAV.MAV_TYPE_GROUND_ROVER, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                   MAV.MAV_MODE_FLAG_SAFETY_ARMED | MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED, 0))
    assert drv.vehicle.hb_time == clock.t and drv.armed and drv.custom_mode == GUIDED
    t0 = clock.t
    poses = []
    for k, late in enumerate((0.004, 0.030, 0.002)):  # each sample 50 ms after the last, delivered this late
        clock.t = t0 + 0.05 * k + late
        ms = 2000 + 50 * k
        send(drv, enc.attitude_encode(ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        poses += send(drv, enc.local_position_ned_encode(ms, 1.0, 2.0, 0.0, 0.5, 0.0, 0.0))
    # on the driver's clock by the least delivery delay seen (the window's minimum), not by each delivery's
    assert [p.stamp for p in poses] == pytest.approx([t0 + 0.004, t0 + 0.054, t0 + 0.102])
    assert (poses[0].x, poses[0].y, poses[0].theta, poses[0].v) == pytest.approx((2.0, 1.0, math.pi / 2, 0.5))
    d = drv.health(clock.t + 0.25).detail
    assert d.heartbeat_age == pytest.approx(clock.t + 0.25 - t0) and d.position_age == pytest.approx(0.25)
    send(drv, enc.attitude_encode(100, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))  # its clock went back: it rebooted
    assert drv.vehicle.rebooted and drv.poses.att is not None and drv.poses.att.ms == 100


def test_statustexts_are_kept_with_their_receipt_on_the_fake_clock(clock: FakeClock) -> None:
    drv = MavlinkDriver(MavlinkLinkConfig(statustext_keep=2), clock=clock)
    send, enc = Sender(), Sender().enc
    for k, text in enumerate((b"PreArm: one", b"PreArm: two", b"PreArm: three")):
        clock.t = 1000.0 + k
        send(drv, enc.statustext_encode(MAV.MAV_SEVERITY_WARNING, text))
    assert drv.statustexts == ["PreArm: two", "PreArm: three"]
    assert drv.vehicle.said_since(1002.0) == ["PreArm: three"]


# ------------------------------------------------------------------------------------------ the command protocol
@pytest.fixture
def link(clock: FakeClock) -> Iterator[tuple[MavlinkClient, Any]]:
    """A MavlinkClient on a real pymavlink UDP connection to a vehicle end played by the test."""
    vehicle = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1)
    port = vehicle.port.getsockname()[1]
    cfg = MavlinkLinkConfig(url=f"udpout:127.0.0.1:{port}", ack_timeout=1.0, command_retries=2)
    counts = {"stray_acks": 0, "reconnects": 0}
    client = MavlinkClient(cfg, load_pymavlink(), LinkHealth(), counts, on_message=lambda m: None, clock=clock)
    client.on_message = lambda m: client.ack(m) if m.get_type() == "COMMAND_ACK" else None
    client.connect(clock.t)
    try:
        yield client, vehicle
    finally:
        client.close()
        vehicle.close()


def command_long(vehicle: Any) -> Any:
    """The next COMMAND_LONG the vehicle gets (waiting for it, bounded)."""
    msg = vehicle.recv_match(type="COMMAND_LONG", blocking=True, timeout=2.0)
    assert msg is not None, "no COMMAND_LONG"
    return msg


def test_a_command_is_sent_again_each_ack_timeout_with_its_confirmation_counted_until_acked(
        clock: FakeClock, link: tuple[MavlinkClient, Any]) -> None:
    client, vehicle = link
    done: list[Command] = []
    c = client.submit(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (1, 0), "arming", done.append)
    assert c.tries == 1 and c.first_sent == clock.t
    assert command_long(vehicle).command == MAV.MAV_CMD_COMPONENT_ARM_DISARM
    client.service(clock.advance(0.99))
    assert c.tries == 1  # within ack_timeout: not again
    client.service(clock.advance(0.01))
    again = command_long(vehicle)
    assert c.tries == 2 and again.confirmation == 1
    stray = vehicle.mav.command_ack_encode(MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_RESULT_ACCEPTED, 0, 0, 255,
                                           client.dialect.source_component)
    vehicle.mav.send(stray)  # an ACK for a command not in flight
    vehicle.mav.command_ack_send(MAV.MAV_CMD_COMPONENT_ARM_DISARM, MAV.MAV_RESULT_ACCEPTED, 0, 0, 255,
                                 client.dialect.source_component)
    client.wait(lambda: c.result is not None, clock.t + 1.0)  # real reads, the deadline on the fake clock
    client.service(clock.t)
    assert c.result == MAV.MAV_RESULT_ACCEPTED and done == [c] and client.counts["stray_acks"] == 1


def test_a_command_never_acked_ends_with_no_ack_after_its_retries(clock: FakeClock,
                                                                   link: tuple[MavlinkClient, Any]) -> None:
    client, vehicle = link
    c = client.submit(MAV.MAV_CMD_DO_SET_MODE, (1, GUIDED), "mode change to GUIDED")
    for k in range(1, 4):  # command_retries = 2: sent 3 times, a second apart
        assert c.tries == k and c.result is None
        assert command_long(vehicle).confirmation == k - 1
        client.service(clock.advance(1.0))
    assert c.result == NO_ACK and not client.in_flight(MAV.MAV_CMD_DO_SET_MODE, 1)
