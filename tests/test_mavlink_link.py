"""The MAVLink link against the emulated ArduPilot Rover: real pymavlink framing over UDP or TCP on 127.0.0.1.

The emulator (:mod:`sim_learner.mavlink_rover`) follows ArduPilot's source, so each test here states something the
real vehicle does and checks the driver copes with it: the operator's RC switch wins, commands are acknowledged or
refused with a reason, a disarm can be lost on close, the EKF origin comes late, the radio drops out, the vehicle
reboots, other systems share the link.
"""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink import mavutil

from bridge.config import MavlinkLinkConfig
from drivers import open_driver
from drivers.mavlink import TYPE_MASK_VEL_YAWRATE
from sim_learner.dynamics import LearnerModel, mpc_learner
from sim_learner.mavlink_rover import GUIDED, MavlinkRover
from sim_learner.vehicle import SimVehicle

MAV = mavutil.mavlink
MODE_OR_ARM = (MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_CMD_COMPONENT_ARM_DISARM)
REVERSIBLE = LearnerModel((-0.5, 0.5), (-1.0, 1.0), name="reversible")


@contextmanager
def rig(transport: str = "udp", *, model: LearnerModel | None = None, open_link: bool = True,
        rover_kw: dict[str, Any] | None = None, **cfg_kw: Any) -> Iterator[tuple[Any, MavlinkRover, SimVehicle]]:
    """A rover (fast boot: 0.2 s, EKF ready at 0.4 s, GUID_TIMEOUT 0.6 s) and a driver on it; both cleaned up."""
    vehicle = SimVehicle(model or mpc_learner(), (1.0, 2.0, 0.3), now=time.monotonic())
    rover = MavlinkRover(vehicle, transport=transport,
                         **({"init_s": 0.2, "ekf_position_s": 0.4, "guid_timeout": 0.6} | (rover_kw or {}))).start()
    url = f"udpout:127.0.0.1:{rover.port}" if transport == "udp" else f"tcp:127.0.0.1:{rover.port}"
    cfg = MavlinkLinkConfig(url=url, **({"open_timeout": 10.0, "ack_timeout": 0.3, "heartbeat_timeout": 1.5}
                                        | cfg_kw))
    driver = open_driver("mavlink", cfg)
    try:
        if open_link:
            driver.open(time.monotonic())
        yield driver, rover, vehicle
    finally:
        driver.close()
        rover.stop()


def drive(driver: Any, seconds: float, v: float, w: float, poses: list | None = None) -> None:
    """What the driver host does at 50 Hz: send, then poll."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        driver.send(v, w, time.monotonic())
        got = driver.poll(time.monotonic())
        if poses is not None:
            poses += got
        time.sleep(0.02)


def wait_for(driver: Any, pred: Callable[[], bool], timeout: float) -> bool:
    """Poll the driver (as the host does) until ``pred()``."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        driver.poll(time.monotonic())
        if pred():
            return True
        time.sleep(0.02)
    return False


def commands_after(rover: MavlinkRover, t: float, kinds: tuple[int, ...] = MODE_OR_ARM) -> list[dict]:
    return [c for c in rover.commands if c["t"] > t and c["command"] in kinds]


def test_velocity_set_points_follow_ardupilot_semantics_and_the_pose_comes_back_in_enu() -> None:
    with rig() as (driver, rover, vehicle):
        poses: list = []
        drive(driver, 1.2, 0.25, 0.1, poses)
        sp = rover.setpoints[-1]
        assert sp["frame"] == MAV.MAV_FRAME_BODY_NED and sp["type_mask"] == TYPE_MASK_VEL_YAWRATE == 0x05E7
        assert sp["vx"] == pytest.approx(0.25) and sp["yaw_rate"] == pytest.approx(-0.1)  # NED is clockwise
        body = vehicle.advance(time.monotonic())
        last = poses[-1]
        assert math.hypot(last.x - body.x, last.y - body.y) < 0.03 and abs(last.theta - body.theta) < 0.02
        assert body.x > 1.1 and last.v == pytest.approx(body.v, abs=1e-3)


def test_rover_stops_when_set_points_stop() -> None:
    with rig() as (driver, rover, vehicle):
        drive(driver, 0.3, 0.3, 0.0)
        assert vehicle.advance(time.monotonic()).v > 0
        wait_for(driver, lambda: False, 1.0)  # > GUID_TIMEOUT (0.6 s here; ArduPilot's 3 s by default)
        assert vehicle.advance(time.monotonic()).v == 0.0
        assert "target not received last 0.6 secs, stopping" in rover.statustexts
        assert MavlinkRover(vehicle).guid_timeout == 3.0


def test_the_emulated_rover_answers_like_ardupilot() -> None:
    """The emulator itself (raw pymavlink, no driver): ACKs addressed to the sender, refusals with their texts,
    set-points ignored silently outside GUIDED and without an EKF origin."""
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with MavlinkRover(vehicle, init_s=0.1, ekf_position_s=60.0) as rover:
        c = mavutil.mavlink_connection(f"udpout:127.0.0.1:{rover.port}", source_system=250, source_component=190)
        try:
            c.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)

            def ask(command: int, *p: float) -> tuple[Any, list[str]]:
                c.mav.command_long_send(1, 1, command, 0, *p, *([0.0] * (7 - len(p))))
                ack, texts, t_end = None, [], time.monotonic() + 1.0
                while time.monotonic() < t_end:
                    m = c.recv_match(type=["COMMAND_ACK", "STATUSTEXT"], blocking=True, timeout=0.1)
                    if m is not None and m.get_type() == "COMMAND_ACK":
                        ack = m
                    elif m is not None:
                        texts.append(m.text)
                        if ack is not None:
                            break
                return ack, texts

            assert c.recv_match(type="HEARTBEAT", blocking=True, timeout=2.0) is not None
            time.sleep(0.2)  # boot over: INITIAL_MODE
            ack, texts = ask(MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 99)
            assert ack.result == MAV.MAV_RESULT_FAILED and "No such mode 99" in texts
            assert (ack.target_system, ack.target_component) == (250, 190)
            c.mav.set_position_target_local_ned_send(0, 1, 1, MAV.MAV_FRAME_BODY_NED, 0x05E7, 0, 0, 0, 0.3, 0, 0,
                                                     0, 0, 0, 0, 0)
            ack, _ = ask(MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED)  # disarmed: ok
            assert ack.result == MAV.MAV_RESULT_ACCEPTED and rover.ignored_setpoints == {"not GUIDED": 1}
            ack, texts = ask(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            assert ack.result == MAV.MAV_RESULT_FAILED and "PreArm: Need Position Estimate" in texts
            ack, _ = ask(MAV.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 1e5)
            assert ack.result == MAV.MAV_RESULT_FAILED
            ack, _ = ask(MAV.MAV_CMD_SET_MESSAGE_INTERVAL, MAV.MAVLINK_MSG_ID_ATTITUDE, 1e5)
            assert ack.result == MAV.MAV_RESULT_ACCEPTED and rover.intervals[30] == pytest.approx(0.1)
            c.mav.set_position_target_local_ned_send(0, 1, 1, MAV.MAV_FRAME_BODY_NED, 0x05E7, 0, 0, 0, 0.3, 0, 0,
                                                     0, 0, 0, 0, 0)
            time.sleep(0.05)
            assert rover.ignored_setpoints.get("no EKF origin") == 1 and rover.setpoints == []
        finally:
            c.close()


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
