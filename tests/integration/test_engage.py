"""A person is in charge of the vehicle: the driver host never arms it, changes its mode or closes an axis's loop by
itself (at start-up included, and after a restart), only on ``scmbridge engage`` (or ``engage_on_start``); the
estop latch survives a restart; closing stops the vehicle before disarming it; the vehicle's own failsafe is read
and reported; a dry run sends the vehicle nothing. Over real Zenoh against the emulated devices, which follow
ArduPilot Rover and ODrive 0.6, not our driver.

Findings this answers (against an ArduPilot SITL): a restarted driver host made the rover GUIDED within 0.5 s and
armed within 1.0 s and drove it at 0.8 m/s while the operator held it in HOLD, disarmed; an operator's estop was
forgotten by a restarted host; on SIGINT at 0.83 m/s the rover was disarmed 0.02 s later, still at 0.83 m/s."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import uuid

import can
import pytest
from pymavlink.dialects.v20 import ardupilotmega as MAV

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.estop import latch_states
from bridge.tools.procs import Children, free_udp_port, said
from drivers import open_driver
from drivers.base import DriverError
from drivers.can import CanLinkConfig
from drivers.mavlink import MavlinkLinkConfig
from sim_learner.can_ecu import DiffDriveEcus
from sim_learner.dynamics import mpc_learner
from sim_learner.mavlink_rover import MavlinkRover
from sim_learner.udp_robot import UdpRobot
from sim_learner.vehicle import SimVehicle
from tests.collect import Collector
from tests.wait import Pace, until

TAKE_OVER = (MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_CMD_COMPONENT_ARM_DISARM)


def _cli(port: int, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", *args, "--mode", "client", "--connect", tcp(port)],
                          capture_output=True, text=True, timeout=90)


@pytest.fixture
def rover_in_hold():
    """An emulated ArduPilot Rover, booted, that the operator has put in HOLD, disarmed."""
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    rover = MavlinkRover(vehicle, init_s=0.2, ekf_position_s=0.4).start()
    try:
        assert until(lambda: rover.mode_name == "MANUAL", 10)
        assert rover.rc_mode_switch("HOLD")
        yield rover
    finally:
        rover.stop()


def _mavlink_config(tmp_path, rover: MavlinkRover, extra: str = "") -> str:
    cfg = tmp_path / f"driver-{uuid.uuid4().hex[:6]}.toml"
    cfg.write_text(f'{extra}[link.mavlink]\nurl = "udpout:127.0.0.1:{rover.port}"\nrate_hz = 20\n')
    return str(cfg)


def _takeovers(rover: MavlinkRover, since: float = -1.0) -> list[dict]:
    return [c for c in rover.commands if c["command"] in TAKE_OVER and c["t"] > since]


@pytest.mark.timeout(150)
def test_a_driver_host_never_takes_the_vehicle_from_the_operator_not_even_after_a_restart(tmp_path,
                                                                                          rover_in_hold) -> None:
    rover, port, robot = rover_in_hold, free_port(), f"en{os.getpid()}"
    driver = ["driver", "--link", "mavlink", "--config", _mavlink_config(tmp_path, rover), "--robot", robot,
              "--mode", "client", "--connect", tcp(port), "--duration", "100"]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        status = col.listen(M.status_key(robot, "driver"), M.Status)
        host = kids.spawn(driver, out=subprocess.DEVNULL)
        assert col.wait(lambda: status and status[-1].state == "waiting", 60), [s.text for s in status[-2:]]
        assert "waiting for the operator: mode HOLD, disarmed" in status[-1].text and not status[-1].ok
        assert status[-1].latencies_ms.get("failsafe_drive_on") == 3000.0  # stock Rover: 3 s after the host dies
        # absence: the waiting host must not take the rover; watched while it runs on (two more of its statuses)
        n = len(status)
        assert col.wait(lambda: len(status) >= n + 2, 30)
        assert not _takeovers(rover) and rover.mode_name == "HOLD" and not rover.armed

        res = _cli(port, "engage", "--robot", robot)  # the person's act
        assert res.returncode == 0 and "engaged" in res.stdout, res.stdout + res.stderr
        assert rover.mode_name == "GUIDED" and rover.armed
        assert all(c["result"] == MAV.MAV_RESULT_ACCEPTED for c in _takeovers(rover))
        assert col.wait(lambda: status[-1].ok and status[-1].state == "driving", 10)
        assert _cli(port, "engage", "--robot", robot).stdout.strip().endswith("already engaged")

        os.killpg(host.pid, signal.SIGKILL)  # the host dies; the operator takes the rover back meanwhile
        host.wait(timeout=5)
        assert rover.rc_mode_switch("HOLD") and rover.rc_arm(False)
        t_restart = time.monotonic()
        n = len(status)
        kids.spawn(driver, out=subprocess.DEVNULL)  # as systemd's Restart=on-failure would
        assert col.wait(lambda: len(status) > n and status[-1].state == "waiting", 60)
        # absence: the restarted host must not take the rover back; watched while it runs on (two more statuses)
        n = len(status)
        assert col.wait(lambda: len(status) >= n + 2, 30)
        assert not _takeovers(rover, t_restart), _takeovers(rover, t_restart)
        assert rover.mode_name == "HOLD" and not rover.armed


@pytest.mark.timeout(90)
def test_engage_on_start_is_the_one_way_a_host_engages_by_itself(tmp_path, rover_in_hold) -> None:
    rover, port, robot = rover_in_hold, free_port(), f"eo{os.getpid()}"
    cfg = _mavlink_config(tmp_path, rover, "[driver]\nengage_on_start = true\n")
    with open_session(make_config(mode="router", listen=[tcp(port)])), Children() as kids:
        kids.spawn(["driver", "--link", "mavlink", "--config", cfg, "--robot", robot, "--mode", "client", "--connect",
                    tcp(port), "--duration", "60"], out=subprocess.DEVNULL)
        assert until(lambda: rover.mode_name == "GUIDED" and rover.armed, 60)


@pytest.mark.timeout(120)
def test_sigint_while_driving_disarms_only_once_the_rover_has_stopped(tmp_path) -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    rover = MavlinkRover(vehicle, init_s=0.2, ekf_position_s=0.4, wp_speed=2.0, decel_max=1.0).start()
    port, robot = free_port(), f"si{os.getpid()}"
    try:
        with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
            col = Collector(session)
            status = col.listen(M.status_key(robot, "driver"), M.Status)
            host = kids.spawn(["driver", "--engage", "--link", "mavlink", "--config", _mavlink_config(tmp_path, rover),
                               "--robot", robot, "--mode", "client", "--connect", tcp(port), "--duration", "90"])
            assert col.wait(lambda: status and status[-1].ok, 60), [s.text for s in status[-2:]]
            pub = session.declare_publisher(M.key(robot, "cmd"))
            seq, pace = 0, Pace(0.05)
            t_end = time.monotonic() + 20
            while time.monotonic() < t_end and vehicle.advance(time.monotonic()).v < 0.3:
                seq += 1
                pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=0.5, omega=0.0, method="scm",
                                           valid_ms=300)))
                pace.wait()  # pacing: the station's 20 Hz
            speed = vehicle.advance(time.monotonic()).v
            assert speed >= 0.3, speed
            os.killpg(host.pid, signal.SIGINT)  # while the commands still come: the closing host stops it first
            assert host.wait(timeout=20) == 0
            log = said(host)  # the host's own account of its close (why it disarmed when it did), for a failure
        assert rover.disarms, f"the rover was not disarmed at the end\n{log}"
        t_disarm, v_disarm = rover.disarms[-1]
        assert v_disarm < 0.1, f"disarmed at {v_disarm:.2f} m/s (it would coast)\n{log}"
        assert not rover.armed
    finally:
        rover.stop()


@pytest.mark.timeout(120)
def test_the_estop_latch_survives_a_driver_host_restart(tmp_path) -> None:
    port, robot = free_port(), f"la{os.getpid()}"
    driver = ["driver", "--link", "can", "--emulate", "--robot", robot, "--mode", "client", "--connect", tcp(port),
              "--duration", "100"]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        status = col.listen(M.status_key(robot, "driver"), M.Status)
        host = kids.spawn([*driver, "--engage"], out=subprocess.DEVNULL)
        assert col.wait(lambda: status and status[-1].ok, 60), [s.text for s in status[-2:]]
        assert _cli(port, "estop", "--robot", robot, "--reason", "person in the way").returncode == 0
        os.killpg(host.pid, signal.SIGKILL)
        host.wait(timeout=5)
        n = len(status)
        host = kids.spawn([*driver, "--engage"], out=subprocess.DEVNULL)  # even one told to engage at start
        assert col.wait(lambda: len(status) > n and status[-1].state not in ("", "starting"), 60)
        st = latch_states(session, M.key(robot, "estop"), 2.0)
        assert st and all(s.latched and s.source == "operator" and s.reason == "person in the way" for s in st.values())
        assert status[-1].state == "estop" and "estop latched by operator" in status[-1].text
        assert _cli(port, "estop", "--robot", robot, "--release").returncode == 0
        os.killpg(host.pid, signal.SIGKILL)
        host.wait(timeout=5)
        kids.spawn(driver, out=subprocess.DEVNULL)
        assert until(lambda: latch_states(session, M.key(robot, "estop"), 1.0), 60)
        assert not any(s.latched for s in latch_states(session, M.key(robot, "estop"), 1.0).values())


def test_no_axis_enters_closed_loop_before_engage_and_a_faulted_axis_needs_a_persons_clear() -> None:
    channel = f"en-{uuid.uuid4().hex[:8]}"
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    ecus = DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle, watchdog=0.5).start()
    spy = can.Bus(interface="virtual", channel=channel)
    driver = open_driver("can", CanLinkConfig(interface="virtual", channel=channel, open_timeout=3.0))
    closed_loop = []

    def watch(stop: threading.Event) -> None:
        while not stop.is_set():
            msg = spy.recv(0.05)
            if msg is not None and msg.arbitration_id & 0x1F == 0x07 and msg.data[:1] == b"\x08":
                closed_loop.append(time.monotonic())  # Set_Axis_State(CLOSED_LOOP_CONTROL) from the master

    stop = threading.Event()
    th = threading.Thread(target=watch, args=(stop,), daemon=True)
    th.start()
    try:
        driver.open(time.monotonic())
        for _ in range(50):  # the host's loop while nobody has engaged: stops only
            driver.stop(time.monotonic())
            driver.poll(time.monotonic())
            time.sleep(0.01)  # pacing the host's loop; absence: no closed loop without an engage (0.5 s of it)
        h = driver.health(time.monotonic())
        assert not closed_loop and not h.ok and "not engaged" in h.text
        assert all(ecus.axis(n).state == 1 for n in (0, 1))  # IDLE
        ecus.inject_error(0, 0x1000)  # the left controller reports an error (a DRV fault)
        assert until(lambda: (driver.poll(time.monotonic()), driver.left.error)[1] != 0, 3)
        with pytest.raises(DriverError, match="left axis error.*--clear-faults"):
            driver.engage(time.monotonic())
        assert not closed_loop
        driver.engage(time.monotonic(), clear_faults=True)  # the person looked at the robot and clears it
        assert closed_loop and driver.health(time.monotonic()).ok
    finally:
        stop.set()
        th.join(1)
        driver.close()
        spy.shutdown()
        ecus.stop()


@pytest.mark.timeout(120)
@pytest.mark.parametrize("dry_run", [False, True])
def test_the_udp_robot_gets_no_motion_before_engage_and_none_at_all_in_a_dry_run(tmp_path, dry_run: bool) -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    bind = free_udp_port()
    port, robot = free_port(), f"ud{os.getpid()}{int(dry_run)}"
    with UdpRobot(vehicle, peer=("127.0.0.1", bind)) as dev, \
            open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        cfg = tmp_path / "driver.toml"
        cfg.write_text(f"[link.udp]\ninsecure = true\nrobot_port = {dev.port}\nbind_port = {bind}\n")
        col = Collector(session)
        applied = col.listen(M.key(robot, "applied"), M.Applied)
        status = col.listen(M.status_key(robot, "driver"), M.Status)
        kids.spawn(["driver", "--link", "udp", "--config", str(cfg), "--robot", robot, "--mode", "client",
                    "--connect", tcp(port), "--duration", "90", *(["--dry-run"] if dry_run else [])],
                   out=subprocess.DEVNULL)
        assert col.wait(lambda: bool(status), 60)
        pub = session.declare_publisher(M.key(robot, "cmd"))
        seq = [0]

        def drive(seconds: float, done) -> None:
            """A station's commands for ``seconds``, and on until ``done()`` (a stalled host takes longer)."""
            t0, pace = time.monotonic(), Pace(0.05)
            while time.monotonic() - t0 < seconds or (time.monotonic() - t0 < 30 and not col.holds(done)):
                seq[0] += 1
                pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq[0], v=0.3, omega=0.0, method="scm",
                                           valid_ms=300)))
                pace.wait()  # pacing: the station's 20 Hz

        # absence: 1.5 s of commands before the engage move nothing; on until the host said why (it is live)
        drive(1.5, lambda: applied and applied[-1].reason == "disengaged")
        assert vehicle.distance == 0.0 and applied and applied[-1].reason == "disengaged"
        assert _cli(port, "engage", "--robot", robot).returncode == 0
        # in a dry run, absence again (on until the host applies the commands, on paper); else until it moved
        drive(1.5, (lambda: applied[-1].reason == "cmd" and applied[-1].v == 0.3) if dry_run
              else (lambda: vehicle.distance > 0.1))
        if dry_run:  # the whole loop runs and says what it would send; the robot gets nothing that moves it
            assert vehicle.distance == 0.0
            assert col.wait(lambda: applied[-1].reason == "cmd" and applied[-1].v == 0.3, 10)
            assert status[-1].state == "dry_run" and not status[-1].ok and "DRY RUN" in status[-1].text
        else:
            assert vehicle.distance > 0.1


def test_the_vehicles_failsafe_is_read_at_open_and_the_gcs_failsafe_acts_as_rovers() -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    rover = MavlinkRover(vehicle, init_s=0.2, ekf_position_s=0.4,
                         params={"FS_GCS_ENABLE": 1, "FS_GCS_TIMEOUT": 1.0, "FS_TIMEOUT": 0.5}).start()
    driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:127.0.0.1:{rover.port}", open_timeout=10.0))
    try:
        driver.open(time.monotonic())
        fs = driver.failsafe()
        assert fs.params == {"FS_GCS_ENABLE": 1.0, "FS_GCS_TIMEOUT": 1.0, "FS_ACTION": 2.0, "FS_TIMEOUT": 0.5}
        assert fs.drive_on_s == 1.5 and "FS_GCS_ENABLE=1" in fs.text
        driver.engage(time.monotonic())
        # the host "dies": no more heartbeats nor set-points from it; FS_GCS_TIMEOUT + FS_TIMEOUT after the last one
        assert until(lambda: rover.mode_name == "HOLD", 5)
        assert 1.5 - 0.05 <= time.monotonic() - rover.gcs_seen <= 2.5 and "Failsafe: GCS" in rover.statustexts
    finally:
        driver.close()
        rover.stop()


@pytest.mark.timeout(120)
def test_a_driver_host_started_before_its_vehicle_waits_for_it_and_says_so(tmp_path) -> None:
    """Start in any order: no vehicle yet is not an exit with a traceback but a wait, on status and in the log."""
    port, robot, bind = free_port(), f"wv{os.getpid()}", free_udp_port()
    robot_port = free_udp_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        cfg = tmp_path / "driver.toml"
        cfg.write_text(f"[link.udp]\ninsecure = true\nrobot_port = {robot_port}\nbind_port = {bind}\n"
                       "open_timeout = 0.5\n")
        col = Collector(session)
        status = col.listen(M.status_key(robot, "driver"), M.Status)
        host = kids.spawn(["driver", "--link", "udp", "--config", str(cfg), "--robot", robot, "--mode", "client",
                           "--connect", tcp(port), "--duration", "60"])
        assert col.wait(lambda: status and "waiting for the vehicle" in status[-1].text, 30), status[-1:]
        assert host.poll() is None and status[-1].state == "starting"
        vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
        with UdpRobot(vehicle, port=robot_port, peer=("127.0.0.1", bind)):
            assert col.wait(lambda: status[-1].state == "waiting" and "waiting for engage" in status[-1].text, 30)
