"""Nothing replayed moves a UDP robot: the session of drivers/udp.py ("Session") against recordings.

Finding this answers (a hostile test, emulated links): keyed command datagrams recorded off the wire and replayed
into a UDP robot right after it rebooted drove it 1.74-1.80 m at 0.3 m/s in 4 of 5 reboots, while its driver host
said "estop latched": the robot forgot every sender at boot and never asked how old a command was.

The wire tap is a real man in the middle (``bench.attack_rigs.Tap``, which the attack bench's replay rows use too, as
they use its emulated robot, its recording of a drive and its distance): one
UDP socket on 127.0.0.1 that the driver takes for the robot and the robot takes for its peer; it forwards both ways
and records (or holds back) what the driver sends. A replay leaves from that socket, i.e. from the very address the
robot obeys. Real sockets, free ports, everything closed.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time

import pytest

from bench.attack import udp_record
from bench.attack_rigs import Tap, distance_from, drive_udp, position, tapped_driver, udp_robot, until
from bridge.core import wire as M
from bridge.core.auth import KeyFileError, load_key, make_key, open_session, seal
from bridge.tools.procs import free_udp_port
from drivers import open_driver
from drivers.udp import UdpLinkConfig
from sim_learner.dynamics import mpc_learner
from sim_learner.udp_robot import SESSION_FRESH_S, UdpRobot
from sim_learner.vehicle import SimVehicle

LOCAL = "127.0.0.1"



@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "udp.key"
    make_key(path)
    return path


def _record_a_drive(key_file, tap: Tap, robot: UdpRobot, vehicle: SimVehicle) -> list[tuple[float, bytes]]:
    """The driver drives the robot at 0.3 m/s for 1.5 s through the tap; what it sent, as recorded."""
    capture = udp_record(key_file, tap, 1.5)
    assert vehicle.distance > 0.2 and robot.counters["applied"] > 20  # the recording is potent
    return capture


@pytest.mark.parametrize("reboot", ["new instance", "reboot hook"])
@pytest.mark.parametrize("driver_host", ["none", "estop latched"])
def test_commands_recorded_before_a_reboot_do_not_move_the_robot_after_it(key_file, reboot, driver_host) -> None:
    key = load_key(key_file)
    bind = free_udp_port()
    with Tap(bind) as tap:
        robot, vehicle = udp_robot(key, tap.addr)
        tap.robot = (LOCAL, robot.port)
        try:
            capture = _record_a_drive(key_file, tap, robot, vehicle)
            if reboot == "new instance":  # a power cycle: a new process would be the same (nothing is kept)
                port = robot.port
                robot.stop()
                robot, vehicle = udp_robot(key, tap.addr, port)
            else:
                robot.reboot()
            start = position(vehicle)
            with contextlib.ExitStack() as stack:
                driver = None
                if driver_host == "estop latched":  # a driver host that only sends stops (its latch holds)
                    driver = stack.enter_context(tapped_driver(key_file, tap))
                applied = robot.counters["applied"]
                stopper_done = threading.Event()

                def stops() -> None:
                    while driver is not None and not stopper_done.is_set():
                        driver.stop(time.monotonic())
                        driver.poll(time.monotonic())
                        time.sleep(0.02)  # pacing: the host's 50 Hz stops

                t = threading.Thread(target=stops, daemon=True)
                t.start()
                try:
                    stale0 = robot.counters["stale_session"]
                    tap.replay(capture)
                    # the robot has judged the whole recording (a stale session each; a few may be lost)
                    until(lambda: robot.counters["stale_session"] >= stale0 + len(capture) - 5, 10.0)
                finally:
                    stopper_done.set()
                    t.join(timeout=2.0)
                assert distance_from(vehicle, start) < 0.01, robot.counters
                assert robot.counters["stale_session"] >= len(capture) - 5, robot.counters
                if driver is None:
                    assert robot.counters["applied"] == applied  # nothing of the recording was obeyed
        finally:
            robot.stop()


def test_commands_held_back_and_released_later_are_refused_as_stale(key_file) -> None:
    key = load_key(key_file)
    bind = free_udp_port()
    with Tap(bind) as tap:
        robot, vehicle = udp_robot(key, tap.addr)
        tap.robot = (LOCAL, robot.port)
        try:
            with tapped_driver(key_file, tap) as driver:
                tap.hold = True  # the robot's states still reach the driver; its commands are kept back
                n0 = len(tap.recorded)
                drive_udp(driver, 1.0, 0.3)
                held = tap.recorded[n0:]
                assert vehicle.distance == 0.0
                # a stall, the attack itself: the commands held back past their freshness
                time.sleep(SESSION_FRESH_S + 0.1)
                start = position(vehicle)
                stale = robot.counters["stale"]
                tap.replay(held, paced=False)
                assert until(lambda: robot.counters["stale"] >= stale + len(held), 10.0), robot.counters
                assert distance_from(vehicle, start) < 0.01 and not robot.moving
                tap.hold = False
        finally:
            robot.stop()


def test_a_keyed_link_follows_the_robot_into_its_new_session_after_a_reboot(key_file) -> None:
    key = load_key(key_file)
    bind = free_udp_port()
    robot, vehicle = udp_robot(key, (LOCAL, bind))
    driver = open_driver("udp", UdpLinkConfig(robot_port=robot.port, bind_port=bind, key_file=str(key_file)))
    try:
        driver.open(time.monotonic())
        drive_udp(driver, 0.3, 0.2)
        assert driver.session[0] == robot.epoch and robot.counters["applied"] > 5
        old = robot.epoch
        robot.reboot()
        applied = robot.counters["applied"]
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end and robot.counters["applied"] <= applied:
            drive_udp(driver, 0.05, 0.2)
        assert robot.counters["applied"] > applied and driver.session[0] == robot.epoch != old
        assert robot.counters["stale_session"] > 0  # the commands sealed for the old boot, until the new one was heard
        assert driver.health(time.monotonic()).detail.robot_restarts == 1
    finally:
        driver.close()
        robot.stop()


def test_a_command_sealed_the_old_way_or_for_no_session_is_refused(key_file) -> None:
    key = load_key(key_file)
    bind = free_udp_port()
    robot, vehicle = udp_robot(key, (LOCAL, bind))
    try:
        cmd = M.encode(M.Command(stamp=1.0, seq=1, v=0.3, omega=0.0, method="scm", sender="driver", epoch=7))
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind((LOCAL, bind))
            s.sendto(seal(key, cmd), (LOCAL, robot.port))  # a valid tag of the old format: no session
            assert until(lambda: robot.counters["unauthenticated"] == 1, 10.0)
            s.settimeout(1.0)
            data, _ = s.recvfrom(65536)  # the robot's state, sealed: no session datagram
            assert open_session(key, data) is None
        assert not robot.moving and vehicle.distance == 0.0
    finally:
        robot.stop()


def test_an_unkeyed_udp_link_refuses_to_open_unless_insecure(caplog) -> None:
    with pytest.raises(KeyFileError, match="insecure = true"):
        open_driver("udp", UdpLinkConfig(bind_port=0)).open(time.monotonic())
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with UdpRobot(vehicle, peer="first") as robot:
        driver = open_driver("udp", UdpLinkConfig(robot_port=robot.port, bind_port=0, insecure=True))
        try:
            with caplog.at_level("WARNING", logger="scmbridge.driver.udp"):
                driver.open(time.monotonic())
            assert "runs insecure" in caplog.text
        finally:
            driver.close()
