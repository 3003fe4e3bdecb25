"""drivers.mavlink.driver.MavlinkDriver without a vehicle: MAVLink messages framed by pymavlink are handed to the
driver as its connection would, on a fake clock, and what it makes of them (poses, health, counters) is checked.
Its behaviour against a vehicle (GUIDED, arming, set-points, close, reconnects) runs against the emulated rover in
tests/integration/test_mavlink_link.py and against ArduPilot's SITL in tests/integration/test_sitl.py."""

from __future__ import annotations

import math

import pytest
from pymavlink import mavutil

from drivers.mavlink import MavlinkLinkConfig
from drivers.mavlink.driver import MavlinkDriver
from tests.fakeclock import FakeClock

MAV = mavutil.mavlink
ENC = MAV.MAVLink(None, srcSystem=1, srcComponent=1)
STRANGER = MAV.MAVLink(None, srcSystem=7, srcComponent=1)


def _framed(enc, msg):
    """The message as the driver's connection hands it over: packed by the sender, parsed on arrival."""
    return MAV.MAVLink(None).parse_char(msg.pack(enc))


def feed(drv: MavlinkDriver, msg, enc=ENC) -> list:
    out: list = []
    drv._handle(_framed(enc, msg), out, drv.clock())  # received now, on the driver's clock
    return out


def heartbeat(armed: bool = True, mode: int = 15):
    flags = MAV.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
    return ENC.heartbeat_encode(MAV.MAV_TYPE_GROUND_ROVER, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                flags | MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode, MAV.MAV_STATE_ACTIVE)


def test_a_poses_heading_is_the_attitude_at_its_own_vehicle_time_in_either_order() -> None:
    """ArduPilot streams LOCAL_POSITION_NED and ATTITUDE on separate intervals: the ATTITUDE may come before the
    position, after it, or half a period away. The heading is taken at the position's time_boot_ms."""
    from drivers.mavlink import MavlinkDriver

    enc = MAV.MAVLink(None, srcSystem=1, srcComponent=1)
    dec = MAV.MAVLink(None)

    def yaw(ms: int) -> float:
        return 0.2 + 1.0 * ms / 1000.0  # turning clockwise at 1 rad/s

    def feed(drv: MavlinkDriver, kind: str, ms: int) -> list:
        m = (enc.attitude_encode(ms, 0.0, 0.0, yaw(ms), 0.0, 0.0, 1.0) if kind == "att"
             else enc.local_position_ned_encode(ms, 1.0, 2.0, 0.0, 0.0, 0.0, 0.0))
        out: list = []
        drv._handle(dec.parse_char(m.pack(enc)), out, drv.clock())  # received now, on the driver's clock
        return out

    for order in (("att", "pos"), ("pos", "att")):  # the same vehicle time, either order
        drv = MavlinkDriver(MavlinkLinkConfig())
        poses = [p for k in order for p in feed(drv, k, 1000)]
        assert len(poses) == 1 and poses[0].theta == pytest.approx(math.pi / 2 - yaw(1000), abs=1e-6), order
    drv = MavlinkDriver(MavlinkLinkConfig())  # streams half a period apart: interpolated
    poses = [p for k, ms in (("att", 1000), ("pos", 1025), ("att", 1050), ("pos", 1075), ("att", 1100))
             for p in feed(drv, k, ms)]
    assert [math.pi / 2 - p.theta for p in poses] == pytest.approx([yaw(1025), yaw(1075)], abs=1e-6)


def test_a_heartbeat_is_judged_on_the_clock_the_driver_was_given(clock: FakeClock) -> None:
    drv = MavlinkDriver(MavlinkLinkConfig(heartbeat_timeout=1.5), clock=clock)
    feed(drv, heartbeat(armed=True))
    assert drv.armed and drv.custom_mode == 15
    h = drv.health(clock.t)
    assert h.detail.heartbeat_age == 0.0 and h.detail.mode == "GUIDED"
    clock.advance(2.0)  # no heartbeat since: aged on the fake clock, nothing slept
    assert drv.health(clock.t).detail.heartbeat_age == 2.0


def test_another_systems_messages_are_counted_and_never_taken_for_the_vehicles(clock: FakeClock) -> None:
    drv = MavlinkDriver(MavlinkLinkConfig(), clock=clock)
    feed(drv, STRANGER.heartbeat_encode(MAV.MAV_TYPE_GROUND_ROVER, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                        MAV.MAV_MODE_FLAG_SAFETY_ARMED, 15, MAV.MAV_STATE_ACTIVE), enc=STRANGER)
    assert drv.custom_mode is None and not drv.armed
    d = drv.health(clock.t).detail
    assert d.foreign == 1 and d.foreign_ids == ((7, 1),)


def test_telemetry_with_a_non_finite_value_is_dropped_and_counted(clock: FakeClock) -> None:
    drv = MavlinkDriver(MavlinkLinkConfig(), clock=clock)
    feed(drv, ENC.attitude_encode(1000, 0.0, 0.0, 0.3, 0.0, 0.0, 0.0))
    assert feed(drv, ENC.local_position_ned_encode(1000, math.nan, 2.0, 0.0, 0.0, 0.0, 0.0)) == []
    assert drv.health(clock.t).detail.invalid_values == 1
    poses = feed(drv, ENC.local_position_ned_encode(1000, 1.0, 2.0, 0.0, 0.0, 0.0, 0.0))
    assert len(poses) == 1 and (poses[0].x, poses[0].y) == pytest.approx((2.0, 1.0))  # NED north/east -> ENU x/y


def test_a_pose_is_stamped_at_the_vehicles_time_on_this_hosts_clock(clock: FakeClock) -> None:
    drv = MavlinkDriver(MavlinkLinkConfig(), clock=clock)
    feed(drv, ENC.attitude_encode(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    first = feed(drv, ENC.local_position_ned_encode(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    clock.advance(0.13)  # this sample arrives 30 ms later than its vehicle time says: delivery jitter
    feed(drv, ENC.attitude_encode(1100, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    second = feed(drv, ENC.local_position_ned_encode(1100, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert second[0].stamp - first[0].stamp == pytest.approx(0.1, abs=1e-9)  # the vehicle's 100 ms, not 130
