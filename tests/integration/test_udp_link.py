"""The UDP shim link with real sockets on 127.0.0.1.

Two halves. The driver against a scripted robot (a bare socket the test drives datagram by datagram, so the
sequence numbers, epochs and timing are exact): the robot's address is pinned, its ``(epoch, seq)`` stream goes
through ``SeqGate`` (a forged seq cannot lock the robot out, a rebooted robot is taken after a silence), health is
ok only while the robot's state is fresh, commands carry the driver's epoch. The emulated robot against the real
driver: it obeys only its configured peer, applies its own hard limits, follows the driver's epoch (a restarted
driver host is taken after a silence, a replayed command is refused) and keeps its watchdog. Both sides are fuzzed
(seeded, ~2000 datagrams each). Every test binds port 0 (or a port the OS just said is free) and closes what it
opened.
"""

from __future__ import annotations

import contextlib
import math
import random
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import msgspec
import pytest

from bridge.core import wire as M
from bridge.tools.procs import free_udp_port, stop_group
from drivers import open_driver
from drivers.base import Driver, DriverError, LinkHealth
from drivers.udp import UdpLinkConfig
from sim_learner.dynamics import mpc_learner
from sim_learner.udp_robot import DEFAULT_PEER, UdpRobot
from sim_learner.vehicle import SimVehicle
from tests.wait import Pace, until


def health(driver: Driver) -> LinkHealth:
    """The driver's health now (as the driver host asks for it each tick)."""
    return driver.health(time.monotonic())

LOCAL = "127.0.0.1"


def udp_socket(port: int = 0) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((LOCAL, port))
    s.settimeout(0.2)
    return s


def wait_for(pred, timeout: float, step: float = 0.01) -> bool:
    return bool(until(pred, timeout, step))


def poll_first(driver: Driver, timeout: float = 10.0) -> list:
    """The poses of the driver's first poll that read any (the datagrams sent just before are on their way)."""
    return until(lambda: driver.poll(time.monotonic()), timeout)


# ============================================================================ the driver against a scripted robot
class ScriptedRobot:
    """A bare UDP socket standing in for the robot: the test decides every state datagram it sends."""

    def __init__(self) -> None:
        self.sock = udp_socket()
        self.port = int(self.sock.getsockname()[1])
        self.epoch = 0x5EED
        self.seq = 4999  # a robot that has been up for 100 s at 50 Hz
        self.commands: list[M.Command] = []
        self.driver_addr: tuple[str, int] | None = None

    def state(self, x: float = 0.0, *, seq: int | None = None, epoch: int | None = None,
              to: tuple[str, int] | None = None, via: socket.socket | None = None, stamp: float = 1.0) -> None:
        """Send one state; by default the next of this robot's stream (its epoch, seq + 1)."""
        if seq is None:
            self.seq += 1
            seq = self.seq
        msg = M.LearnerState(stamp=stamp, seq=seq, x=x, y=0.0, theta=0.0, v=0.0, omega=0.0, source="scripted",
                             epoch=self.epoch if epoch is None else epoch)
        (via or self.sock).sendto(M.encode(msg), to or self.driver_addr)

    @contextlib.contextmanager
    def answering(self) -> Iterator[None]:
        """While inside: answer every datagram (the driver's hello stops in ``open``) with the next state."""
        stop = threading.Event()

        def run() -> None:
            while not stop.is_set():
                try:
                    data, src = self.sock.recvfrom(65536)
                except (TimeoutError, OSError):
                    continue
                self.driver_addr = src
                self.commands.append(M.decode(data, M.Command))
                self.state()

        t = threading.Thread(target=run, name="scripted-robot", daemon=True)
        t.start()
        try:
            yield
        finally:
            stop.set()
            t.join(timeout=2.0)

    def read_commands(self) -> list[M.Command]:
        self.sock.settimeout(0.05)
        while True:
            try:
                data, _ = self.sock.recvfrom(65536)
            except (TimeoutError, OSError):
                return self.commands
            self.commands.append(M.decode(data, M.Command))

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def scripted():
    """An opened driver (state_timeout_s 0.3) and the scripted robot it is pinned to."""
    robot = ScriptedRobot()
    driver = open_driver("udp", UdpLinkConfig(insecure=True, robot_port=robot.port, bind_port=0, state_timeout_s=0.3,
                                              open_timeout=2.0))
    try:
        with robot.answering():
            driver.open(time.monotonic())
        yield driver, robot
    finally:
        driver.close()
        robot.close()


def poll_until(driver, n_datagrams: int, timeout: float = 2.0) -> list:
    """Poll until the driver has received ``n_datagrams`` in all (bounded); the poses returned meanwhile."""
    poses: list = []
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        poses += driver.poll(time.monotonic())
        if health(driver).frames_received >= n_datagrams:
            break
        time.sleep(0.002)  # the poll step: until the datagrams counted have been read
    return poses


def test_a_forged_huge_seq_does_not_lock_the_robots_telemetry_out(scripted) -> None:
    driver, robot = scripted
    driver.poll(time.monotonic())
    n0 = health(driver).frames_received
    for i in range(3):
        robot.state(x=1.0 + i)
    # forged from the robot's own address (a spoofed source): the highest seq there is, and another epoch
    robot.state(x=99.0, seq=2**63 - 1)
    robot.state(x=98.0, seq=robot.seq + 1, epoch=0xBAD)
    for i in range(5):
        time.sleep(0.01)  # pacing: the robot's states apart in time, as a robot publishes them
        robot.state(x=10.0 + i)
    poses = poll_until(driver, n0 + 10)
    assert [p.x for p in poses] == [1.0, 2.0, 3.0, 10.0, 11.0, 12.0, 13.0, 14.0]  # the real robot, every state
    d = health(driver).detail
    assert d.state_seq_jump == 1 and d.state_foreign_epoch == 1


def test_state_datagrams_from_any_other_address_are_dropped_as_foreign(scripted) -> None:
    driver, robot = scripted
    driver.poll(time.monotonic())
    n0 = health(driver).frames_received
    with udp_socket() as spoofer:
        robot.state(x=1.0)
        robot.state(x=50.0, seq=robot.seq + 1, via=spoofer)  # the next seq of the right epoch, wrong sender
        robot.state(x=51.0, seq=robot.seq + 2, epoch=0xBAD, via=spoofer)
        robot.state(x=2.0)
        poses = poll_until(driver, n0 + 4)
    assert [p.x for p in poses] == [1.0, 2.0]
    h = health(driver)
    assert h.detail.foreign == 2 and h.malformed == 0


def test_datagrams_the_kernel_dropped_in_a_flood_are_counted(scripted) -> None:
    """Found by the fuzz bench: a burst larger than the socket's receive buffer between two polls was lost
    uncounted. Every datagram is now either received or counted as dropped by the kernel."""
    driver, robot = scripted
    driver.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a small buffer: the flood overflows it
    driver.poll(time.monotonic())
    n0, flood = health(driver).frames_received, 2000
    with udp_socket() as flooder:
        for _ in range(flood):
            flooder.sendto(b"\x00" * 64, ("127.0.0.1", driver.sock.getsockname()[1]))
    poll_until(driver, n0 + flood, timeout=1.0)
    robot.state(x=1.0)  # the kernel reports its drop count with the next datagram read
    poses = poll_until(driver, n0 + flood + 1 - health(driver).detail.dropped_by_kernel, timeout=1.0)
    poses += driver.poll(time.monotonic())
    h = health(driver)
    assert h.detail.dropped_by_kernel > 0
    assert h.frames_received - n0 + h.detail.dropped_by_kernel == flood + 1
    assert [p.x for p in poses] == [1.0]


def test_a_robot_that_reboots_is_recognised_after_a_silence_and_its_old_epoch_refused(scripted) -> None:
    driver, robot = scripted
    old_epoch = robot.epoch
    for i in range(5):
        robot.state(x=float(i))
        time.sleep(0.01)  # pacing: the robot's states apart in time, as a robot publishes them
    t_last_old = time.monotonic()
    assert len(poll_until(driver, 0, timeout=0.05)) == 5
    robot.epoch, robot.seq = 0xB007, -1  # rebooted: a new epoch, seq from 0, and it keeps publishing
    poses: list = []
    t_end = time.monotonic() + 1.5
    while time.monotonic() < t_end and not poses:
        robot.state(x=100.0 + robot.seq + 1)
        time.sleep(0.02)  # pacing: the rebooted robot publishes at 50 Hz (the loop's deadline is the test)
        poses = driver.poll(time.monotonic())
    assert poses, "the rebooted robot's state was never taken"
    taken_after = time.monotonic() - t_last_old
    assert 0.3 <= taken_after < 0.3 + 0.25  # refused while the old stream may be alive, taken after the silence
    d = health(driver).detail
    assert d.state_foreign_epoch >= 1 and d.robot_restarts == 1
    # the old run's datagrams (a late one, a replay) are refused for good
    robot.state(x=-1.0, seq=1000, epoch=old_epoch)
    robot.state(x=200.0)
    assert [p.x for p in poll_first(driver)] == [200.0]  # the old run's, sent first, was read and refused
    assert health(driver).detail.state_old_epoch == 1


def test_health_is_ok_only_while_the_robots_state_is_fresh(scripted) -> None:
    driver, robot = scripted
    h = health(driver)
    assert h.ok and h.connected
    stale = r"no state from the robot for (0\.[4-9]|[1-9]\.\d) s"  # (its state_timeout_s is 0.3)
    assert until(lambda: (driver.poll(time.monotonic()), re.fullmatch(stale, health(driver).text))[1], 10)
    h = health(driver)
    assert not h.ok and h.connected
    assert re.fullmatch(stale, h.text), h.text
    robot.state(x=1.0)
    assert poll_first(driver)
    assert health(driver).ok


def test_health_is_not_ok_before_the_first_state() -> None:
    with udp_socket() as silent:  # a robot that never answers
        driver = open_driver("udp", UdpLinkConfig(insecure=True, robot_port=silent.getsockname()[1], bind_port=0,
                                                  open_timeout=0.2))
        assert not health(driver).ok
        with pytest.raises(DriverError, match="no state from the UDP robot"):
            driver.open(time.monotonic())
        h = health(driver)
        assert not h.ok and "no state from the robot yet" in h.text and h.reason == "no_telemetry"
        driver.close()


def test_poses_are_stamped_at_the_robots_clock_or_at_receipt_when_its_stamp_is_not_a_clock(scripted) -> None:
    """States read in one poll keep the robot's own spacing (about 0.02 s here), on the driver host's clock; a firmware
    whose stamp does not advance (this scripted robot's constant 1.0) gets receipt stamps, counted."""
    driver, robot = scripted
    for _ in range(3):  # the robot's clock (ours + 500 s) replaces the open's constant stamps: a step of the clock,
        robot.state(0.0, stamp=time.monotonic() + 500.0)  # followed once three in a row agree on it
        assert len(poll_first(driver)) == 1  # read at once: these set the offset
    assert driver.counters["clock_restarts"] == 3  # two samples held back, then the restart
    stamps = []
    for k in range(5):  # then five that wait in the socket for one poll
        stamps.append(time.monotonic() + 500.0)
        robot.state(0.01 * k, stamp=stamps[-1])
        time.sleep(0.02)  # pacing: the robot's own spacing, which its stamps must keep
    poses = driver.poll(time.monotonic())  # all five at once, one receipt time
    assert len(poses) == 5 and driver.counters["stamp_fallbacks"] == 0, driver.counters
    assert [b.stamp - a.stamp for a, b in zip(poses, poses[1:])] == pytest.approx(
        [b - a for a, b in zip(stamps, stamps[1:])], abs=1e-9)
    assert stamps[-1] - 500.0 <= poses[-1].stamp <= time.monotonic()
    for _ in range(3):
        robot.state(0.1, stamp=500.0)  # the clock stopped
        time.sleep(0.01)  # pacing: apart in time, so their receipt stamps differ
    poses = driver.poll(time.monotonic())
    assert len(poses) == 3 and driver.counters["stamp_fallbacks"] == 3
    assert poses[0].stamp < poses[1].stamp < poses[2].stamp  # their receipts


def test_commands_carry_the_drivers_epoch_and_name_and_send_does_not_block(scripted) -> None:
    driver, robot = scripted
    t0 = time.perf_counter()
    for _ in range(50):
        driver.send(0.1, 0.0, time.monotonic())
    driver.stop(time.monotonic())
    assert time.perf_counter() - t0 < 0.5
    cmds = robot.read_commands()
    assert len(cmds) >= 51
    assert driver.epoch > 0 and {c.epoch for c in cmds} == {driver.epoch} and {c.sender for c in cmds} == {"driver"}
    seqs = [c.seq for c in cmds]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert cmds[-1].method == "stop" and (cmds[-1].v, cmds[-1].omega) == (0.0, 0.0)


def test_robot_host_is_resolved_once_at_open() -> None:
    robot = ScriptedRobot()
    driver = open_driver("udp", UdpLinkConfig(insecure=True, robot_host="localhost", robot_port=robot.port,
                                              bind_port=0))
    try:
        with robot.answering():
            driver.open(time.monotonic())
        assert driver.robot_addr == (LOCAL, robot.port)
    finally:
        driver.close()
        robot.close()


# ====================================================================== the emulated robot against the driver
@pytest.fixture
def rig():
    """The emulated robot pinned to the driver's port, and the driver, opened."""
    port = free_udp_port()
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    robot = UdpRobot(vehicle, peer=(LOCAL, port), watchdog=0.3).start()
    driver = open_driver("udp", UdpLinkConfig(insecure=True, robot_port=robot.port, bind_port=port))
    try:
        driver.open(time.monotonic())
        yield driver, robot, vehicle
    finally:
        driver.close()
        robot.stop()


def test_command_reaches_the_robot_and_state_comes_back(rig) -> None:
    driver, robot, vehicle = rig
    poses: list = []
    t0, pace = time.monotonic(), Pace(0.02)

    def tracked():
        """The vehicle now, if it has moved and the pose just read says where it is (a pose read before a stall of
        this process is as old as the stall: the vehicle has driven on since; the next one is fresh)."""
        body = vehicle.advance(time.monotonic())
        return body if poses and body.x > 0.05 and abs(poses[-1].x - body.x) < 0.02 else None

    # at least 1 s of commands, and on until the vehicle has moved and a fresh pose says where (a stalled robot
    # thread or test process takes longer, it does not fail the test)
    body = None
    while time.monotonic() - t0 < 1.0 or (time.monotonic() - t0 < 20.0 and body is None):
        driver.send(0.25, 0.1, time.monotonic())
        poses += driver.poll(time.monotonic())
        body = tracked()
        pace.wait()  # pacing: a driver host's 50 Hz
    assert robot.last_cmd is not None and (robot.last_cmd.v, robot.last_cmd.omega) == (0.25, 0.1)
    assert robot.last_cmd.seq == driver.seq and robot.last_cmd.epoch == driver.epoch
    body = body or vehicle.advance(time.monotonic())
    assert poses and body.x > 0.05 and abs(poses[-1].x - body.x) < 0.02
    assert health(driver).ok


def test_poses_carry_the_robots_own_stamps_so_the_pairs_are_its_true_response() -> None:
    """``scmbridge bench pairing --link udp`` for 4 s: the station's pairing on this link's poses as the driver host
    feeds them. Finding: poses stamped when the host's 50 Hz tick read them put 0.0096 m/s (median) of error into the
    pairs; at the robot's own stamps it is below a micrometre per second here."""
    from bench.pairing import measure

    res = measure("udp", 4.0, seed=3)
    assert res["formed"] >= 0.75 * res["commands"] and res["rejected"] <= 0.1 * res["commands"], res  # load margin
    assert res["error_v_mps"]["median"] < 0.002 and res["error_omega_radps"]["median"] < 0.002, res


def test_robot_watchdog_stops_it_when_commands_stop(rig) -> None:
    driver, robot, vehicle = rig
    t_end, pace = time.monotonic() + 10.0, Pace(0.02)
    for _ in range(10):
        driver.send(0.3, 0.0, time.monotonic())
        pace.wait()  # pacing: a driver host's 50 Hz
    while vehicle.advance(time.monotonic()).v <= 0 and time.monotonic() < t_end:  # until the robot took them
        driver.send(0.3, 0.0, time.monotonic())
        pace.wait()
    assert vehicle.advance(time.monotonic()).v > 0
    assert until(lambda: vehicle.advance(time.monotonic()).v == 0.0, 10.0)  # the commands stopped: its watchdog
    assert vehicle.advance(time.monotonic()).v == 0.0
    assert robot.counters["watchdog_stops"] >= 1


def test_replayed_commands_and_garbage_are_dropped_and_counted(rig) -> None:
    driver, robot, vehicle = rig
    driver.send(0.2, 0.0, time.monotonic())
    assert wait_for(lambda: robot.last_cmd is not None and robot.last_cmd.v == 0.2, 10.0)
    to = (LOCAL, robot.port)
    old = M.Command(stamp=1.0, seq=1, v=0.3, omega=0.2, method="scm", epoch=driver.epoch)  # a replay
    driver.sock.sendto(M.encode(old), to)
    driver.sock.sendto(msgspec.msgpack.encode({"stamp": 1.0, "seq": 10**6, "v": float("nan"), "omega": 0.0,
                                               "method": "scm"}), to)
    driver.sock.sendto(b"\x00garbage", to)
    assert wait_for(lambda: robot.counters["out_of_order"] >= 1 and robot.counters["malformed"] >= 2, 10.0)
    assert (robot.last_cmd.v, robot.last_cmd.omega) == (0.2, 0.0)


def test_the_robot_obeys_and_answers_only_its_configured_peer(rig) -> None:
    driver, robot, vehicle = rig
    driver.stop(time.monotonic())
    with udp_socket() as stranger:
        for seq in range(1, 6):  # a well-formed command stream of its own, and the next seq of the driver's
            stranger.sendto(M.encode(M.Command(stamp=1.0, seq=seq, v=0.3, omega=0.0, method="scm", epoch=77)),
                            (LOCAL, robot.port))
        stranger.sendto(M.encode(M.Command(stamp=1.0, seq=driver.seq + 1, v=0.3, omega=0.0, method="scm",
                                           epoch=driver.epoch)), (LOCAL, robot.port))
        assert wait_for(lambda: robot.counters["foreign"] >= 6, 10.0)
        time.sleep(0.1)  # absence: the stranger's commands, all counted, must not drive it meanwhile
        assert vehicle.advance(time.monotonic()).v == 0.0 and robot.last_cmd.v == 0.0
        stranger.settimeout(0.1)
        with pytest.raises(TimeoutError):  # the robot's telemetry goes to its peer only
            stranger.recvfrom(65536)
    assert driver.poll(time.monotonic())  # ... which still gets it


def test_first_sender_mode_pins_the_first_valid_sender() -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with UdpRobot(vehicle, peer="first", watchdog=0.3) as robot:
        driver = open_driver("udp", UdpLinkConfig(insecure=True, robot_port=robot.port, bind_port=0))
        try:
            with udp_socket() as stranger:
                stranger.sendto(b"\x01not a command", (LOCAL, robot.port))  # garbage does not pin anyone
                assert wait_for(lambda: robot.counters["malformed"] == 1, 10.0) and robot.peer is None
                driver.open(time.monotonic())
                assert robot.peer == driver.sock.getsockname()
                stranger.sendto(M.encode(M.Command(stamp=1.0, seq=1, v=0.3, omega=0.0, method="scm", epoch=5)),
                                (LOCAL, robot.port))
                assert wait_for(lambda: robot.counters["foreign"] == 1, 10.0)
                assert robot.last_cmd.epoch == driver.epoch
        finally:
            driver.close()


def test_the_robot_refuses_commands_beyond_its_own_limits_and_holds_still(rig) -> None:
    driver, robot, vehicle = rig
    assert (robot.v_max, robot.omega_max) == (1.0, 2.0)
    calls: list[tuple[float, float]] = []
    real = vehicle.command
    vehicle.command = lambda v, w, now: (calls.append((v, w)), real(v, w, now))  # type: ignore[method-assign]
    for _ in range(5):
        driver.send(0.3, 0.0, time.monotonic())
        time.sleep(0.01)  # pacing: a stream of valid commands before the two beyond the limits
    driver.send(100.0, 0.0, time.monotonic())  # the link does not clamp (the driver host does): the robot must
    driver.send(0.5, -2.5, time.monotonic())
    assert wait_for(lambda: robot.counters["over_limits"] == 2, 10.0)
    assert all(abs(v) <= 1.0 and abs(w) <= 2.0 for v, w in calls) and (0.3, 0.0) in calls
    assert vehicle.advance(time.monotonic()).v == 0.0  # refused means stopped, not "keep the last one"
    assert robot.last_cmd.v == 0.3


def test_a_restarted_driver_host_is_recognised_after_a_silence_and_old_commands_are_refused() -> None:
    port = free_udp_port()
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with UdpRobot(vehicle, peer=(LOCAL, port), watchdog=0.3) as robot:
        cfg = UdpLinkConfig(insecure=True, robot_port=robot.port, bind_port=port)
        first = open_driver("udp", cfg)
        first.open(time.monotonic())
        for _ in range(20):
            first.send(0.2, 0.0, time.monotonic())
            time.sleep(0.01)  # pacing: the first run's command stream
        replay = M.Command(stamp=1.0, seq=first.seq + 1, v=0.4, omega=0.0, method="scm", epoch=first.epoch)
        first.close()
        second = open_driver("udp", cfg)  # a restarted driver host: the same address, a new epoch, seq from 1
        try:
            second.open(time.monotonic())
            assert second.epoch != first.epoch
            t0 = time.monotonic()
            while time.monotonic() - t0 < 1.5 and not (robot.last_cmd and robot.last_cmd.epoch == second.epoch
                                                       and robot.last_cmd.v == 0.25):
                second.send(0.25, 0.0, time.monotonic())
                time.sleep(0.01)  # pacing: the restarted host's stream (the loop's deadline is the test)
            assert robot.last_cmd.epoch == second.epoch and robot.last_cmd.v == 0.25
            assert time.monotonic() - t0 < 0.3 + 0.3  # the robot's silence (its watchdog), then at once
            second.sock.sendto(M.encode(replay), (LOCAL, robot.port))  # the old run's next command, replayed
            assert wait_for(lambda: robot.counters["old_epoch"] == 1, 10.0)
            assert robot.last_cmd.epoch == second.epoch
        finally:
            second.close()


def test_a_robot_reboot_and_a_telemetry_pause_do_not_lock_the_link(rig) -> None:
    driver, robot, vehicle = rig
    old_epoch = robot.epoch
    robot.pause_telemetry(0.8)  # the driver's state_timeout_s is 0.5
    assert wait_for(lambda: (driver.poll(time.monotonic()), not health(driver).ok)[1], 1.0)
    assert "no state from the robot" in health(driver).text
    assert wait_for(lambda: len(driver.poll(time.monotonic())) > 0, 10.0) and health(driver).ok
    robot.reboot()
    assert robot.epoch != old_epoch
    wait_for(lambda: (driver.poll(time.monotonic()), health(driver).detail.robot_restarts)[1] > 0, 10.0)
    assert health(driver).detail.robot_restarts == 1
    assert wait_for(lambda: len(driver.poll(time.monotonic())) > 0, 10.0) and health(driver).ok


def test_the_learner_command_serves_its_peer_only_and_refuses_a_bad_peer(tmp_path) -> None:
    """``scmbridge learner --link udp --peer HOST:PORT``: a real process the driver reaches from that port."""
    port = free_udp_port()
    with udp_socket() as s:
        robot_port = s.getsockname()[1]
    py = [sys.executable, "-m", "bridge", "learner", "--link", "udp"]
    bad = subprocess.run(py + ["--peer", "nowhere", "--duration", "1"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "expected HOST:PORT" in bad.stderr
    proc = subprocess.Popen(py + ["--port", str(robot_port), "--peer", f"{LOCAL}:{port}", "--v-max", "0.5",
                                  "--duration", "30"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    driver = open_driver("udp", UdpLinkConfig(insecure=True, robot_port=robot_port, bind_port=port, open_timeout=20.0))
    try:
        driver.open(time.monotonic())
        assert health(driver).ok
    finally:
        driver.close()
        stop_group(proc)


def test_the_robot_default_peer_is_the_drivers_default_port() -> None:
    cfg = UdpLinkConfig()
    assert (cfg.bind_host, cfg.bind_port) == DEFAULT_PEER and cfg.bind_port != cfg.robot_port


# ================================================================================================ fuzzing
def _mutations(rng: random.Random, valid: dict, kind: type) -> bytes:
    """One datagram: random bytes, a valid message with one field made wrong, or a valid one with flipped bytes."""
    roll = rng.random()
    if roll < 0.25:
        return rng.randbytes(rng.randint(1, 80))
    msg = dict(valid)
    if roll < 0.7:
        field = rng.choice([*msg, "extra"])
        msg[field] = rng.choice([float("nan"), float("inf"), -float("inf"), 1e300, -1e9, 2**64, -1, "x", None,
                                 [1.0], rng.uniform(-200, 200), rng.randint(0, 2**63 - 1)])
        try:
            return msgspec.msgpack.encode(msg)
        except OverflowError:
            return b"\xcf" + rng.randbytes(8)
    raw = bytearray(M.encode(msgspec.convert(msg, kind)))
    for _ in range(rng.randint(1, 3)):
        raw[rng.randrange(len(raw))] = rng.randrange(256)
    return bytes(raw)


def test_fuzzing_the_driver_with_2000_datagrams(scripted) -> None:
    driver, robot = scripted
    rng = random.Random(20240610)
    driver.poll(time.monotonic())
    h0 = health(driver)
    base = (h0.frames_received, h0.malformed, h0.detail.foreign)
    poses: list = []
    sent = 0
    with udp_socket() as stranger:
        for _ in range(40):
            for _ in range(50):
                valid = {"stamp": 1.0, "seq": robot.seq + 1, "x": rng.uniform(-10, 10), "y": 0.0, "theta": 0.0,
                         "epoch": robot.epoch}
                via = stranger if rng.random() < 0.2 else robot.sock
                if rng.random() < 0.2:  # the robot's real next state (its seq counts only what it really sends)
                    data = M.encode(msgspec.convert(valid, M.LearnerState))
                    robot.seq += via is robot.sock
                else:
                    data = _mutations(rng, valid, M.LearnerState)
                via.sendto(data, robot.driver_addr)
                sent += 1
            poses += poll_until(driver, base[0] + sent)
    h = health(driver)
    d = h.detail
    assert h.frames_received - base[0] == sent
    refused = d.state_out_of_order + d.state_seq_jump + d.state_old_epoch + d.state_foreign_epoch
    assert len(poses) + (h.malformed - base[1]) + (d.foreign - base[2]) + refused == sent
    assert d.foreign - base[2] > 200 and h.malformed - base[1] > 500 and len(poses) > 300
    assert all(math.isfinite(v) for p in poses for v in (p.x, p.y, p.theta, p.v or 0.0, p.omega or 0.0))


def test_fuzzing_the_robot_with_2000_datagrams() -> None:
    rng = random.Random(77)
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    calls: list[tuple[float, float]] = []
    real = vehicle.command
    vehicle.command = lambda v, w, now: (calls.append((v, w)), real(v, w, now))  # type: ignore[method-assign]
    with udp_socket() as peer, udp_socket() as stranger, \
            UdpRobot(vehicle, peer=peer.getsockname(), watchdog=0.3, v_max=1.0, omega_max=2.0) as robot:
        to = (LOCAL, robot.port)
        epoch, seq, sent = 0xD21, 0, 0
        for _ in range(40):
            for _ in range(50):
                seq += 1
                valid = {"stamp": 1.0, "seq": seq, "v": rng.uniform(-3, 3), "omega": rng.uniform(-5, 5),
                         "method": rng.choice(["scm", "direct", "stop", "perturb"]), "epoch": epoch,
                         "sender": "driver"}
                data = M.encode(msgspec.convert(valid, M.Command)) if rng.random() < 0.4 else \
                    _mutations(rng, valid, M.Command)
                (stranger if rng.random() < 0.2 else peer).sendto(data, to)
                sent += 1
            assert wait_for(lambda n=sent: robot.counters["received"] >= n, 10.0, step=0.002)
        c = dict(robot.counters)
    assert c["received"] == sent
    refused = sum(c[k] for k in ("malformed", "foreign", "out_of_order", "seq_jump", "old_epoch", "foreign_epoch",
                                 "over_limits"))
    assert c["applied"] + refused == sent
    assert c["foreign"] > 200 and c["malformed"] > 500 and c["over_limits"] > 50 and c["applied"] > 100
    assert calls and all(math.isfinite(v) and math.isfinite(w) and abs(v) <= 1.0 and abs(w) <= 2.0
                         for v, w in calls)


def test_the_robot_stops_by_itself_when_a_commands_valid_ms_is_over() -> None:
    """Finding: the reference UDP robot ignored a command's ``valid_ms``: a man in the middle dropping the stops
    moved it 0.20 m (0.66 s) after an estop, until its watchdog. Here its watchdog is long (5 s) and one command
    valid 150 ms comes, with nothing after it: the robot holds its wheels on its own (``expired_stops``), long
    before the watchdog would."""
    import socket

    from tests.wait import until

    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sender.bind((LOCAL, 0))
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    robot = UdpRobot(vehicle, peer=sender.getsockname(), watchdog=5.0).start()
    try:
        cmd = M.Command(stamp=1.0, seq=1, v=0.3, omega=0.0, method="scm", epoch=M.new_epoch(), valid_ms=150)
        sender.sendto(M.encode(cmd), (LOCAL, robot.port))
        assert until(lambda: robot.counters["applied"] == 1, 5.0)
        assert until(lambda: robot.counters["expired_stops"] == 1, 4.0), robot.counters
        assert robot.counters["watchdog_stops"] == 0 and not robot.moving
        assert vehicle.advance(time.monotonic()).v == 0.0 or vehicle.state.v < 0.3
    finally:
        robot.stop()
        sender.close()
