"""The UDP shim link with real sockets on 127.0.0.1: commands reach the robot, state comes back, bad datagrams and
replays are dropped and counted, the robot's own watchdog stops it."""

from __future__ import annotations

import socket
import time

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridge import wire as M
from bridge.config import UdpLinkConfig
from drivers import open_driver
from sim_learner.dynamics import mpc_learner
from sim_learner.udp_robot import UdpRobot
from sim_learner.vehicle import SimVehicle


@pytest.fixture
def rig():
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    robot = UdpRobot(vehicle, watchdog=0.3).start()
    driver = open_driver("udp", UdpLinkConfig(robot_port=robot.port))
    try:
        driver.open(time.monotonic())
        yield driver, robot, vehicle
    finally:
        driver.close()
        robot.stop()


def test_command_reaches_the_robot_and_state_comes_back(rig) -> None:
    driver, robot, vehicle = rig
    poses = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.0:
        driver.send(0.25, 0.1, time.monotonic())
        poses += driver.poll(time.monotonic())
        time.sleep(0.02)
    assert robot.last_cmd is not None and (robot.last_cmd.v, robot.last_cmd.omega) == (0.25, 0.1)
    assert robot.last_cmd.seq == driver.seq
    body = vehicle.advance(time.monotonic())
    assert poses and body.x > 0.05 and abs(poses[-1].x - body.x) < 0.02


def test_robot_watchdog_stops_it_when_commands_stop(rig) -> None:
    driver, robot, vehicle = rig
    for _ in range(10):
        driver.send(0.3, 0.0, time.monotonic())
        time.sleep(0.02)
    assert vehicle.advance(time.monotonic()).v > 0
    time.sleep(0.6)
    assert vehicle.advance(time.monotonic()).v == 0.0


def test_replayed_commands_and_garbage_are_dropped_and_counted(rig) -> None:
    driver, robot, vehicle = rig
    driver.send(0.2, 0.0, time.monotonic())
    time.sleep(0.05)
    old = M.Command(stamp=1.0, seq=1, v=0.3, omega=0.2, method="scm")  # seq below the driver's: a replay
    driver.sock.sendto(M.encode(old), ("127.0.0.1", robot.port))
    driver.sock.sendto(msgspec.msgpack.encode({"stamp": 1.0, "seq": 10**6, "v": float("nan"), "omega": 0.0,
                                               "method": "scm"}), ("127.0.0.1", robot.port))
    driver.sock.sendto(b"\x00garbage", ("127.0.0.1", robot.port))
    time.sleep(0.1)
    assert robot.dropped_old >= 1 and robot.malformed >= 2
    assert (robot.last_cmd.v, robot.last_cmd.omega) == (0.2, 0.0)


@settings(max_examples=40, deadline=None)
@given(st.binary(min_size=1, max_size=64))
def test_random_state_datagrams_never_crash_the_driver(data: bytes) -> None:
    driver = open_driver("udp", UdpLinkConfig(robot_port=9))
    driver.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    driver.sock.bind(("127.0.0.1", 0))
    driver.sock.setblocking(False)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(data, driver.sock.getsockname())
        time.sleep(0.002)
        poses = driver.poll(time.monotonic())
        h = driver.health()
        assert h.frames_received <= 1 and len(poses) + h.malformed == h.frames_received
    finally:
        driver.sock.close()
