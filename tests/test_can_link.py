"""The CAN link on a real python-can bus (``virtual`` interface, in-process): frames, odometry, watchdog, garbage."""

from __future__ import annotations

import math
import time
import uuid

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridge.config import CanLinkConfig
from drivers import open_driver
from drivers.can import AXIS_ERROR_WATCHDOG, AXIS_STATE_CLOSED_LOOP, AXIS_STATE_IDLE, decode, encode
from sim_learner.can_ecu import DiffDriveEcus
from sim_learner.dynamics import mpc_learner
from sim_learner.vehicle import SimVehicle


def test_cansimple_ids_and_layout_are_odrive_0_6() -> None:
    f = encode(3, "Set_Input_Vel", {"Input_Vel": 1.5, "Input_Torque_FF": -0.25})
    assert f.arbitration_id == (3 << 5) | 0x0D and not f.is_extended_id
    assert bytes(f.data) == bytes.fromhex("0000c03f000080be")  # two little-endian float32
    assert encode(1, "Heartbeat", {"Axis_Error": 0x800, "Axis_State": 8, "Procedure_Result": 0,
                                   "Trajectory_Done_Flag": 1}).arbitration_id == 0x21
    assert decode(encode(2, "Get_Encoder_Estimates", {"Pos_Estimate": 2.5, "Vel_Estimate": -1.0})) == (
        2, "Get_Encoder_Estimates", {"Pos_Estimate": 2.5, "Vel_Estimate": -1.0})
    with pytest.raises(ValueError, match="data bytes"):
        decode(can.Message(arbitration_id=0x0D, data=b"\x00\x00", is_extended_id=False))
    with pytest.raises(ValueError, match="not finite"):
        decode(can.Message(arbitration_id=0x09, data=bytes.fromhex("0000c07f00000000"), is_extended_id=False))


@pytest.fixture
def rig():
    channel = f"test-{uuid.uuid4().hex[:8]}"
    vehicle = SimVehicle(mpc_learner(), (1.0, 2.0, 0.5), now=time.monotonic())
    ecus = DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle, watchdog=0.3).start()
    driver = open_driver("can", CanLinkConfig(interface="virtual", channel=channel, initial_pose=(1.0, 2.0, 0.5)))
    spy = can.Bus(interface="virtual", channel=channel)
    try:
        driver.open(time.monotonic())
        yield driver, ecus, vehicle, spy
    finally:
        driver.close()
        ecus.stop()
        spy.shutdown()


def test_commands_reach_the_bus_as_wheel_speeds_and_odometry_returns_the_pose(rig) -> None:
    driver, ecus, vehicle, spy = rig
    v, w = 0.25, 0.1
    t0 = time.monotonic()
    poses = []
    while time.monotonic() - t0 < 1.5:
        driver.send(v, w, time.monotonic())
        poses += driver.poll(time.monotonic(), block=0.02)
    # the frames on the wire, read by a third bus: Input_Vel = sign * (v -/+ w b / 2) / (2 pi r)
    seen = {}
    while (f := spy.recv(timeout=0)) is not None:
        try:
            node, name, sig = decode(f)
        except ValueError:
            continue
        if name == "Set_Input_Vel":
            seen[node] = sig["Input_Vel"]
    k = 1 / (2 * math.pi * 0.1)
    assert seen[0] == pytest.approx((v - w * 0.2) * k, rel=1e-6)
    assert seen[1] == pytest.approx(-(v + w * 0.2) * k, rel=1e-6)
    # odometry follows the learner body (its degraded response, not the command)
    body = vehicle.advance(time.monotonic())
    last = poses[-1]
    assert math.hypot(last.x - body.x, last.y - body.y) < 0.01
    assert abs(last.theta - body.theta) < 0.01
    assert body.x > 1.1  # it moved


def test_controller_watchdog_stops_the_wheels_when_set_points_stop(rig) -> None:
    driver, ecus, vehicle, _ = rig
    for _ in range(10):
        driver.send(0.3, 0.0, time.monotonic())
        time.sleep(0.02)
    assert vehicle.advance(time.monotonic()).v > 0
    time.sleep(0.6)  # > watchdog (0.3 s)
    driver.poll(time.monotonic(), block=0.15)
    assert vehicle.advance(time.monotonic()).v == 0.0
    assert driver.left.state == AXIS_STATE_IDLE and driver.left.error & AXIS_ERROR_WATCHDOG
    # the next command re-arms the axes (clear errors, closed loop) and the vehicle drives again
    t0 = time.monotonic()
    while time.monotonic() - t0 < 0.5:
        driver.send(0.3, 0.0, time.monotonic())
        driver.poll(time.monotonic(), block=0.02)
    assert driver.left.state == AXIS_STATE_CLOSED_LOOP and vehicle.advance(time.monotonic()).v > 0


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_random_frames_never_crash_and_garbage_is_counted(arb: int, data: bytes) -> None:
    frame = can.Message(arbitration_id=arb, data=data, is_extended_id=False)
    try:
        node, name, sig = decode(frame)
    except ValueError:
        return
    assert 0 <= node < 64 and isinstance(sig, dict)


def test_driver_counts_malformed_frames_on_its_bus(rig) -> None:
    driver, _, _, spy = rig
    before = driver.health().malformed
    spy.send(can.Message(arbitration_id=(0 << 5) | 0x09, data=b"\x01\x02", is_extended_id=False))
    spy.send(can.Message(arbitration_id=(1 << 5) | 0x1F, data=b"", is_extended_id=False))
    driver.poll(time.monotonic(), block=0.1)
    assert driver.health().malformed >= before + 2
