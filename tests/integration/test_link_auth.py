"""Authenticated links: the UDP shim's keyed datagram tags and MAVLink 2 signing, against the emulated devices.

Findings this answers: a spoofed UDP datagram with v = 0.95 (within the robot's own limit) drove the robot at its
body maximum for 0.6 s: pinning an address and port is not authentication. The forged datagram is bench.attack's
(``unsealed_command``, ``spoof_from``: the attack bench's ``udp_spoof`` row sends the same)."""

from __future__ import annotations

import os
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as MAV

from bench.attack import drive_udp, spoof_from, unsealed_command
from bridge.core.auth import load_key, make_key
from bridge.tools.procs import free_udp_port
from drivers import open_driver
from drivers.base import DriverError
from drivers.mavlink import MavlinkLinkConfig
from drivers.udp import UdpLinkConfig
from sim_learner.dynamics import mpc_learner
from sim_learner.mavlink_rover import MavlinkRover
from sim_learner.udp_robot import UdpRobot
from sim_learner.vehicle import SimVehicle


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "link.key"
    make_key(path)
    return path


def test_only_datagrams_sealed_with_the_key_move_the_udp_robot(key_file) -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    bind = free_udp_port()
    with UdpRobot(vehicle, peer=("127.0.0.1", bind), key=load_key(key_file)) as robot:
        driver = open_driver("udp", UdpLinkConfig(robot_port=robot.port, bind_port=bind, key_file=str(key_file)))
        try:
            driver.open(time.monotonic())
            # a forger who knows the driver's epoch and seq and sends from the driver's own address, unsealed
            spoof_from(robot, unsealed_command(driver), ("127.0.0.1", bind))
            assert robot.counters["unauthenticated"] == 1 and not robot.moving and vehicle.distance == 0.0
            drive_udp(driver, 0.5, 0.3)  # the driver's own, sealed: they drive it
            assert vehicle.distance > 0.05 and robot.counters["applied"] > 0
            assert driver.counters["unauthenticated"] == 0 and driver.health(time.monotonic()).ok
        finally:
            driver.close()


def test_a_driver_without_the_key_cannot_move_a_robot_that_has_one(key_file) -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    bind = free_udp_port()
    with UdpRobot(vehicle, peer=("127.0.0.1", bind), key=load_key(key_file)) as robot:
        driver = open_driver("udp", UdpLinkConfig(robot_port=robot.port, bind_port=bind, open_timeout=0.5,
                                                  insecure=True))  # no key: an insecure driver
        try:
            with pytest.raises(DriverError, match="no state"):  # its states are sealed: not decodable without it
                driver.open(time.monotonic())
            assert robot.counters["unauthenticated"] > 0 and vehicle.distance == 0.0
        finally:
            driver.close()


def test_mavlink_signing_refuses_every_unsigned_or_foreign_signed_message(tmp_path, key_file) -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    rover = MavlinkRover(vehicle, init_s=0.2, ekf_position_s=0.4, signing_key=load_key(key_file)).start()
    url = f"udpout:127.0.0.1:{rover.port}"
    try:
        other = tmp_path / "other.key"
        make_key(other)
        for wrong in (None, other):  # no signing, and another lab's key
            cfg = MavlinkLinkConfig(url=url, open_timeout=3.0, ack_timeout=0.2, command_retries=1,
                                    signing_key_file=str(wrong) if wrong else "")
            driver = open_driver("mavlink", cfg)
            try:
                if wrong is not None:  # its own check refuses the rover's signed messages: nothing heard
                    with pytest.raises(DriverError, match="no HEARTBEAT"):
                        driver.open(time.monotonic())
                    assert driver.health(time.monotonic()).detail.bad_signatures > 0
                else:  # it hears the rover, but the rover refuses what it says
                    driver.open(time.monotonic())
                    with pytest.raises(DriverError):
                        driver.engage(time.monotonic())
            finally:
                driver.close(disarm=False, stop_timeout=0.0)
            assert not rover.armed and rover.mode_name == "MANUAL"
        refused = rover.bad_signatures
        assert refused > 0
        driver = open_driver("mavlink", MavlinkLinkConfig(url=url, open_timeout=10.0, signing_key_file=str(key_file)))
        try:
            driver.open(time.monotonic())
            driver.engage(time.monotonic())
            assert rover.armed and rover.mode_name == "GUIDED"
            drive_udp(driver, 0.6, 0.4)
            assert vehicle.distance > 0.05
        finally:
            driver.close()
        assert not rover.armed
        assert not [c for c in rover.commands if c["command"] == MAV.MAV_CMD_COMPONENT_ARM_DISARM
                    and c["result"] != MAV.MAV_RESULT_ACCEPTED]  # every command it handled was the signed driver's
    finally:
        rover.stop()
    assert os.stat(key_file).st_mode & 0o077 == 0


def test_a_driver_host_with_a_missing_or_unsafe_key_says_so_in_one_line(tmp_path, key_file) -> None:
    import subprocess
    import sys

    cfg = tmp_path / "driver.toml"
    for key, why in ((tmp_path / "missing.key", "not found (make one: scmbridge keys udp"),
                     (key_file, "readable by others")):
        if key == key_file:
            key.chmod(0o644)
        cfg.write_text(f'[link.udp]\nkey_file = "{key}"\n')
        res = subprocess.run([sys.executable, "-m", "bridge", "driver", "--link", "udp", "--config", str(cfg),
                              "--duration", "1"], capture_output=True, text=True, timeout=60)
        assert res.returncode == 2 and why in res.stderr and "Traceback" not in res.stderr, res.stderr
