"""sim_learner/udp_robot.py: the emulated UDP-shim robot's firmware rules, one datagram at a time on a fake clock.

Over real sockets with the driver (its peer, limits, watchdog, reboots, fuzzing) it is tested in
tests/integration/test_udp_link.py and tests/integration/test_udp_replay.py. Here each rule of the module docstring is
fed datagrams and times directly (no thread, no socket, no sleep): the peer, the keyed session (nonce and the echo's
age), validation, the driver's stream, its own limits (refused, not clamped), stops, and that every datagram is counted
once as received and once as applied or refused."""

from __future__ import annotations

import math
import socket
import time

import pytest

from bridge.core import wire as M
from bridge.core.auth import seal, seal_session
from sim_learner.dynamics import LearnerModel
from sim_learner.udp_robot import DEFAULT_PEER, SESSION_FRESH_S, STALL_S, UdpRobot
from sim_learner.vehicle import SimVehicle

LINEAR = LearnerModel((-2.0, 2.0), (-4.0, 4.0), name="linear")
DRIVER = ("127.0.0.1", 47801)
KEY = bytes(range(32))
REFUSALS = ("malformed", "foreign", "unauthenticated", "stale_session", "stale", "out_of_order", "seq_jump",
            "old_epoch", "foreign_epoch", "over_limits")


def _robot(**kw) -> UdpRobot:
    r = UdpRobot(SimVehicle(LINEAR, now=0.0), peer=kw.pop("peer", DRIVER), epoch=kw.pop("epoch", 77), **kw)
    r.peer = None if r.peer_config == "first" else r.peer_config  # what _open resolves (numeric already)
    return r


def _cmd(seq: int, v: float = 0.2, w: float = 0.1, method: str = "scm", epoch: int = 5) -> bytes:
    return M.encode(M.Command(stamp=1.0, seq=seq, v=v, omega=w, method=method, epoch=epoch))


def _balanced(r: UdpRobot) -> bool:
    c = r.counters
    return c["received"] == c["applied"] + sum(c[k] for k in REFUSALS)


@pytest.mark.parametrize(
    "kw,match",
    [({"v_max": 0.0}, "limits must be finite and > 0"), ({"omega_max": math.inf}, "limits must be finite"),
     ({"peer": "any"}, "peer must be \\(host, port\\) or 'first'"), ({"peer": ("h", 1, 2)}, "peer must be")],
)
def test_bad_limits_and_peers_are_refused(kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        UdpRobot(SimVehicle(LINEAR, now=0.0), **kw)


def test_defaults_are_the_drivers_address_and_the_watchdogs_silence() -> None:
    r = UdpRobot(SimVehicle(LINEAR, now=0.0))
    assert r.peer_config == DEFAULT_PEER == ("127.0.0.1", 47801)
    assert r.silence == r.watchdog == 0.5 and r.fresh_us == int(SESSION_FRESH_S * 1e6)
    assert 0 <= r.epoch < 2**63


def test_it_obeys_its_peer_only_and_counts_everything_once() -> None:
    r = _robot()
    r._handle(_cmd(1), ("127.0.0.1", 40000), 1.0)  # another port: foreign, not decoded
    assert r.counters["foreign"] == 1 and not r.vehicle.moving
    r._handle(b"\x00garbage", DRIVER, 1.0)
    r._handle(_cmd(1), DRIVER, 1.0)
    assert r.counters["malformed"] == 1 and r.counters["applied"] == 1
    assert r.vehicle.cmd == (0.2, 0.1) and r.last_cmd is not None and r.last_cmd.seq == 1
    r._handle(_cmd(1), DRIVER, 1.1)  # a replay of the same seq
    r._handle(_cmd(2, epoch=6), DRIVER, 1.2)  # a second driver while the first is alive
    assert r.counters["out_of_order"] == 1 and r.counters["foreign_epoch"] == 1
    r._handle(_cmd(1, epoch=6), DRIVER, 1.2 + 0.51)  # the first silent for the silence time: the new one is taken
    assert r.counters["applied"] == 2
    assert _balanced(r) and r.counters["received"] == 6


def test_beyond_its_own_limits_a_command_is_refused_and_the_wheels_held() -> None:
    r = _robot(v_max=0.5, omega_max=1.0)
    r._handle(_cmd(1, v=0.4, w=0.0), DRIVER, 1.0)
    assert r.vehicle.moving
    r._handle(_cmd(2, v=0.6, w=0.0), DRIVER, 1.1)  # never clamped to 0.5: refused, and stopped
    assert r.counters["over_limits"] == 1 and not r.vehicle.moving and r.last_cmd.seq == 1
    r._handle(_cmd(3, v=0.1, w=-1.5), DRIVER, 1.2)
    assert r.counters["over_limits"] == 2 and _balanced(r)


def test_a_stop_or_an_exact_zero_holds_the_wheels() -> None:
    r = _robot()
    r._handle(_cmd(1), DRIVER, 1.0)
    r._handle(_cmd(2, v=0.3, w=0.3, method="stop"), DRIVER, 1.1)  # a stop whatever v and omega say
    assert not r.vehicle.moving and r.counters["applied"] == 2
    r._handle(_cmd(3), DRIVER, 1.2)
    r._handle(_cmd(4, v=0.0, w=0.0), DRIVER, 1.3)
    assert not r.vehicle.moving and not r.moving


def test_a_first_peer_is_the_first_valid_sender() -> None:
    r = _robot(peer="first")
    r._handle(b"junk", ("127.0.0.1", 1111), 1.0)  # not valid: pins nobody
    assert r.peer is None
    r._handle(_cmd(1), ("127.0.0.1", 2222), 1.0)
    assert r.peer == ("127.0.0.1", 2222)
    r._handle(_cmd(2), ("127.0.0.1", 1111), 1.1)
    assert r.counters["foreign"] == 1


def test_keyed_commands_must_carry_this_boots_nonce_and_a_fresh_echo_of_its_clock() -> None:
    r = _robot(key=KEY, epoch=1234)
    now = 50.0
    us = int(now * 1e6)
    r._handle(_cmd(1), DRIVER, now)  # not sealed
    r._handle(seal(KEY, _cmd(1)), DRIVER, now)  # sealed the old way, for no session
    r._handle(seal_session(bytes(32), 1234, us, _cmd(1)), DRIVER, now)  # another key
    assert r.counters["unauthenticated"] == 3
    r._handle(seal_session(KEY, 999, us, _cmd(1)), DRIVER, now)  # recorded in another boot
    assert r.counters["stale_session"] == 1
    r._handle(seal_session(KEY, 1234, us + 1, _cmd(1)), DRIVER, now)  # echoes a reading from the robot's future
    r._handle(seal_session(KEY, 1234, us - r.fresh_us - 1, _cmd(1)), DRIVER, now)  # held back too long
    assert r.counters["stale"] == 2 and not r.vehicle.moving
    r._handle(seal_session(KEY, 1234, us - r.fresh_us, _cmd(1)), DRIVER, now)  # at the edge of fresh: obeyed
    assert r.counters["applied"] == 1 and r.vehicle.moving and _balanced(r)


def test_reboot_holds_the_wheels_draws_a_new_nonce_and_forgets_the_stream() -> None:
    t = time.monotonic()  # reboot() is a test hook on the real clock: this test's times are on it too
    r = UdpRobot(SimVehicle(LINEAR, now=t), peer="first", epoch=77)
    r._handle(_cmd(9), ("127.0.0.1", 2222), t)
    assert r.vehicle.moving
    r.reboot(epoch=4242)
    assert r.epoch == 4242 and r._seq == 0 and not r.vehicle.moving and r.peer is None and r.last_cmd is None
    assert r.counters["reboots"] == 1
    r._handle(_cmd(1), ("127.0.0.1", 3333), time.monotonic())  # the driver's epoch at a lower seq: a fresh gate
    assert r.counters["applied"] == 2 and r.peer == ("127.0.0.1", 3333)


def test_a_stall_of_the_emulator_is_said_in_its_log_with_why(caplog) -> None:
    """A real robot on loopback streaming states to a socket of the test's: held for 0.3 s (its loop waits for the
    lock the test hooks take), it sends no state meanwhile, and its log says so with the stall watch's line (how long,
    why, its CPU): the driver host beside it, which sees only the silence, stops the robot for it, and this line
    tells the emulator's stall from the driver's fault. Only a gap over the threshold is said (a loaded machine may
    add a stall of its own before the hold; it is said the same way)."""
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.settimeout(2.0)
    try:
        with caplog.at_level("WARNING", logger="scmbridge.learner"), \
                UdpRobot(SimVehicle(LINEAR, now=time.monotonic()), peer=sink.getsockname()) as robot:
            for _ in range(10):  # states at their rate
                sink.recvfrom(65536)
            with robot._lock:
                time.sleep(0.3)
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline and not [g for g in _stalls_said(caplog) if g >= 0.25]:
                sink.recvfrom(65536)
    finally:
        sink.close()
    gaps = _stalls_said(caplog)
    assert [g for g in gaps if 0.25 <= g < 2.0], gaps  # the 0.3 s it was held (a loaded machine may add to it)
    assert all(g > STALL_S for g in gaps), gaps  # nothing shorter than the threshold is said


def _stalls_said(caplog) -> list[float]:
    """The gaps the robot's log said it sent no state for, s (each line also says why and its CPU)."""
    out = []
    for r in caplog.records:
        text = r.getMessage()
        if "sent no state" in text:
            assert "loop stalled" in text and "s CPU" in text, text
            out.append(float(text.split("loop stalled ")[1].split(" s")[0]))
    return out
