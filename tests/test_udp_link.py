"""The UDP shim link with real sockets on 127.0.0.1.

Two halves. The driver against a scripted robot (a bare socket the test drives datagram by datagram, so the
sequence numbers, epochs and timing are exact): the robot's address is pinned, its ``(epoch, seq)`` stream goes
through ``SeqGate`` (a forged seq cannot lock the robot out, a rebooted robot is taken after a silence), health is
ok only while the robot's state is fresh, commands carry the driver's epoch. The driver is fuzzed (seeded, ~2000
datagrams). Every test binds port 0 (or a port the OS just said is free) and closes what it
opened.
"""

from __future__ import annotations

import contextlib
import math
import random
import re
import socket
import threading
import time
from collections.abc import Iterator

import msgspec
import pytest

from bridge import wire as M
from bridge.config import UdpLinkConfig
from drivers import open_driver
from drivers.base import DriverError

LOCAL = "127.0.0.1"


def free_udp_port() -> int:
    """A UDP port the OS says is free right now (the robot must know the driver's port before the driver binds)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((LOCAL, 0))
        return int(s.getsockname()[1])


def udp_socket(port: int = 0) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((LOCAL, port))
    s.settimeout(0.2)
    return s


def wait_for(pred, timeout: float, step: float = 0.01) -> bool:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(step)
    return pred()


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
              to: tuple[str, int] | None = None, via: socket.socket | None = None) -> None:
        """Send one state; by default the next of this robot's stream (its epoch, seq + 1)."""
        if seq is None:
            self.seq += 1
            seq = self.seq
        msg = M.LearnerState(stamp=1.0, seq=seq, x=x, y=0.0, theta=0.0, v=0.0, omega=0.0, source="scripted",
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
    driver = open_driver("udp", UdpLinkConfig(robot_port=robot.port, bind_port=0, state_timeout_s=0.3,
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
        if driver.health().frames_received >= n_datagrams:
            break
        time.sleep(0.002)
    return poses


def test_a_forged_huge_seq_does_not_lock_the_robots_telemetry_out(scripted) -> None:
    driver, robot = scripted
    driver.poll(time.monotonic())
    n0 = driver.health().frames_received
    for i in range(3):
        robot.state(x=1.0 + i)
    # forged from the robot's own address (a spoofed source): the highest seq there is, and another epoch
    robot.state(x=99.0, seq=2**63 - 1)
    robot.state(x=98.0, seq=robot.seq + 1, epoch=0xBAD)
    for i in range(5):
        time.sleep(0.01)
        robot.state(x=10.0 + i)
    poses = poll_until(driver, n0 + 10)
    assert [p.x for p in poses] == [1.0, 2.0, 3.0, 10.0, 11.0, 12.0, 13.0, 14.0]  # the real robot, every state
    d = driver.health().detail
    assert d["state_seq_jump"] == 1 and d["state_foreign_epoch"] == 1


def test_state_datagrams_from_any_other_address_are_dropped_as_foreign(scripted) -> None:
    driver, robot = scripted
    driver.poll(time.monotonic())
    n0 = driver.health().frames_received
    with udp_socket() as spoofer:
        robot.state(x=1.0)
        robot.state(x=50.0, seq=robot.seq + 1, via=spoofer)  # the next seq of the right epoch, wrong sender
        robot.state(x=51.0, seq=robot.seq + 2, epoch=0xBAD, via=spoofer)
        robot.state(x=2.0)
        poses = poll_until(driver, n0 + 4)
    assert [p.x for p in poses] == [1.0, 2.0]
    h = driver.health()
    assert h.detail["foreign"] == 2 and h.malformed == 0


def test_a_robot_that_reboots_is_recognised_after_a_silence_and_its_old_epoch_refused(scripted) -> None:
    driver, robot = scripted
    old_epoch = robot.epoch
    for i in range(5):
        robot.state(x=float(i))
        time.sleep(0.01)
    t_last_old = time.monotonic()
    assert len(poll_until(driver, 0, timeout=0.05)) == 5
    robot.epoch, robot.seq = 0xB007, -1  # rebooted: a new epoch, seq from 0, and it keeps publishing
    poses: list = []
    t_end = time.monotonic() + 1.5
    while time.monotonic() < t_end and not poses:
        robot.state(x=100.0 + robot.seq + 1)
        time.sleep(0.02)
        poses = driver.poll(time.monotonic())
    assert poses, "the rebooted robot's state was never taken"
    taken_after = time.monotonic() - t_last_old
    assert 0.3 <= taken_after < 0.3 + 0.25  # refused while the old stream may be alive, taken after the silence
    d = driver.health().detail
    assert d["state_foreign_epoch"] >= 1 and d["robot_restarts"] == 1
    # the old run's datagrams (a late one, a replay) are refused for good
    robot.state(x=-1.0, seq=1000, epoch=old_epoch)
    robot.state(x=200.0)
    time.sleep(0.05)
    assert [p.x for p in driver.poll(time.monotonic())] == [200.0]
    assert driver.health().detail["state_old_epoch"] == 1


def test_health_is_ok_only_while_the_robots_state_is_fresh(scripted) -> None:
    driver, robot = scripted
    h = driver.health()
    assert h.ok and h.connected
    time.sleep(0.45)
    driver.poll(time.monotonic())
    h = driver.health()
    assert not h.ok and h.connected
    assert re.fullmatch(r"no state from the robot for 0\.[4-9] s", h.text), h.text
    robot.state(x=1.0)
    time.sleep(0.02)
    driver.poll(time.monotonic())
    assert driver.health().ok


def test_health_is_not_ok_before_the_first_state() -> None:
    with udp_socket() as silent:  # a robot that never answers
        driver = open_driver("udp", UdpLinkConfig(robot_port=silent.getsockname()[1], bind_port=0,
                                                  open_timeout=0.2))
        assert not driver.health().ok
        with pytest.raises(DriverError, match="no state from the UDP robot"):
            driver.open(time.monotonic())
        h = driver.health()
        assert not h.ok and "no state from the robot yet" in h.text
        driver.close()


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
    driver = open_driver("udp", UdpLinkConfig(robot_host="localhost", robot_port=robot.port, bind_port=0))
    try:
        with robot.answering():
            driver.open(time.monotonic())
        assert driver.robot_addr == (LOCAL, robot.port)
    finally:
        driver.close()
        robot.close()


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
    h0 = driver.health()
    base = (h0.frames_received, h0.malformed, h0.detail["foreign"])
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
    h = driver.health()
    d = h.detail
    assert h.frames_received - base[0] == sent
    refused = sum(d[k] for k in ("state_out_of_order", "state_seq_jump", "state_old_epoch", "state_foreign_epoch"))
    assert len(poses) + (h.malformed - base[1]) + (d["foreign"] - base[2]) + refused == sent
    assert d["foreign"] - base[2] > 200 and h.malformed - base[1] > 500 and len(poses) > 300
    assert all(math.isfinite(v) for p in poses for v in (p.x, p.y, p.theta, p.v or 0.0, p.omega or 0.0))
