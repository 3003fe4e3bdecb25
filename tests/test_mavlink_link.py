"""The MAVLink link against the emulated ArduPilot Rover, real pymavlink framing over UDP on 127.0.0.1."""

from __future__ import annotations

import math
import socket
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridge.config import MavlinkLinkConfig
from drivers import open_driver
from drivers.mavlink import TYPE_MASK_VEL_YAWRATE
from sim_learner.dynamics import mpc_learner
from sim_learner.mavlink_rover import GUIDED, HOLD, MavlinkRover
from sim_learner.vehicle import SimVehicle


@pytest.fixture
def rig():
    vehicle = SimVehicle(mpc_learner(), (1.0, 2.0, 0.3), now=time.monotonic())
    rover = MavlinkRover(vehicle, init_s=0.3, target_timeout=0.6).start()
    cfg = MavlinkLinkConfig(url=f"udpout:127.0.0.1:{rover.port}", rate_hz=20, open_timeout=15)
    driver = open_driver("mavlink", cfg)
    try:
        driver.open(time.monotonic())
        yield driver, rover, vehicle
    finally:
        driver.close()
        rover.stop()


def test_open_reaches_guided_and_armed_even_if_the_first_mode_set_is_lost(rig) -> None:
    driver, rover, _ = rig
    assert driver.custom_mode == GUIDED and driver.armed and rover.armed
    assert rover.lost_mode_sets >= 1  # the first DO_SET_MODE arrived while the autopilot was initialising
    assert rover.intervals[32] == pytest.approx(0.05) and rover.intervals[30] == pytest.approx(0.05)


def test_velocity_set_points_follow_ardupilot_semantics_and_the_pose_comes_back_in_enu(rig) -> None:
    driver, rover, vehicle = rig
    poses = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.2:
        driver.send(0.25, 0.1, time.monotonic())
        poses += driver.poll(time.monotonic())
        time.sleep(0.03)
    sp = rover.setpoints[-1]
    assert sp["frame"] == 8 and sp["type_mask"] == TYPE_MASK_VEL_YAWRATE == 0x05E7
    assert sp["vx"] == pytest.approx(0.25) and sp["yaw_rate"] == pytest.approx(-0.1)  # NED is clockwise
    body = vehicle.advance(time.monotonic())
    last = poses[-1]
    assert math.hypot(last.x - body.x, last.y - body.y) < 0.03 and abs(last.theta - body.theta) < 0.02
    assert body.x > 1.1


def test_set_points_outside_guided_are_dropped_silently(rig) -> None:
    driver, rover, vehicle = rig
    rover.custom_mode = HOLD
    before = rover.dropped_setpoints
    driver._setpoint(0.3, 0.0)  # what an unguarded sender would do
    time.sleep(0.1)
    assert rover.dropped_setpoints == before + 1
    t_end = time.monotonic() + 4  # driving on, the driver sees the mode in the next HEARTBEAT and re-asserts GUIDED
    while rover.custom_mode != GUIDED and time.monotonic() < t_end:
        driver.send(0.3, 0.0, time.monotonic())
        driver.poll(time.monotonic())
        time.sleep(0.05)
    assert rover.custom_mode == GUIDED


def test_rover_stops_when_set_points_stop(rig) -> None:
    driver, rover, vehicle = rig
    for _ in range(10):
        driver.send(0.3, 0.0, time.monotonic())
        time.sleep(0.03)
    assert vehicle.advance(time.monotonic()).v > 0
    time.sleep(1.0)  # > target_timeout (0.6 s here; ArduPilot's 3 s by default)
    driver.poll(time.monotonic())
    assert vehicle.advance(time.monotonic()).v == 0.0
    assert "target not received last 3secs, stopping" in rover.statustexts
    assert MavlinkRover(vehicle).target_timeout == 3.0


@settings(max_examples=25, deadline=None)
@given(st.binary(min_size=1, max_size=80))
def test_random_bytes_on_the_link_are_counted_and_dropped(data: bytes) -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with MavlinkRover(vehicle) as rover, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(data, ("127.0.0.1", rover.port))
        s.sendto(b"\xfd" + data, ("127.0.0.1", rover.port))  # a MAVLink 2 start byte and garbage
        time.sleep(0.03)
        assert rover._thread is not None and rover._thread.is_alive()
        assert rover.setpoints == []
