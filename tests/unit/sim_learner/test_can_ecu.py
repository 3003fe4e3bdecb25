"""sim_learner/can_ecu.py: the emulated ODrive 0.6 controllers of a differential-drive learner, on a fake clock.

Their behaviour frame by frame on a live bus (arming, position-control default, Estop, Clear_Errors, the watchdog,
injected errors, unplugging, a short frame) is tested in tests/integration/test_can_link.py, with the driver
against them there too. Here the controllers are fed frames and times directly (no thread, no sleep): the wheel
kinematics and its signs, the velocity limit, the input modes, IDLE as a disarm, input_vel kept across a disarm,
what is ignored or counted as malformed, the encoder counts following the body, and a remote request answered."""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import uuid
from collections.abc import Callable, Iterator

import can
import pytest

from sim_learner import can_ecu as E
from sim_learner.dynamics import LearnerModel
from sim_learner.vehicle import SimVehicle

LINEAR = LearnerModel((-2.0, 2.0), (-4.0, 4.0), name="linear")  # the response is the command: speeds read back


def _frame(node: int, cmd: int, data: bytes = b"", **kw) -> can.Message:
    return can.Message(arbitration_id=(node << 5) | cmd, data=data, is_extended_id=False, **kw)


def _ecus(**kw) -> tuple[E.DiffDriveEcus, SimVehicle]:
    veh = SimVehicle(LINEAR, now=0.0)
    return E.DiffDriveEcus({"interface": "virtual", "channel": "unused"}, veh, clock=lambda: 0.0, **kw), veh


@contextlib.contextmanager
def _on_a_bus(t: list[float], wall: Callable[[], float]) -> Iterator[tuple[E.DiffDriveEcus, can.BusABC]]:
    """Controllers open on a virtual bus of their own, on the clock ``t[0]`` and the wall clock ``wall`` (a test's
    preemptions), and a spy on that bus; both closed after."""
    channel = f"ecu-{uuid.uuid4().hex[:8]}"
    ecus = E.DiffDriveEcus({"interface": "virtual", "channel": channel}, SimVehicle(LINEAR, now=0.0),
                           clock=lambda: t[0], wall=wall)
    spy = can.Bus(interface="virtual", channel=channel)
    try:
        ecus._open()
        yield ecus, spy
    finally:
        ecus._close()
        spy.shutdown()


def _arm(ecus: E.DiffDriveEcus, now: float, mode: int = E.INPUT_PASSTHROUGH) -> None:
    for node in (0, 1):
        ecus._handle(_frame(node, E.SET_CONTROLLER_MODE, struct.pack("<II", E.VELOCITY_CONTROL, mode)), now)
        ecus._handle(_frame(node, E.SET_AXIS_STATE, struct.pack("<I", E.CLOSED_LOOP_CONTROL)), now)


def _vel(ecus: E.DiffDriveEcus, node: int, rev_s: float, now: float) -> None:
    ecus._handle(_frame(node, E.SET_INPUT_VEL, struct.pack("<ff", rev_s, 0.0)), now)


def test_wheel_speeds_become_the_body_command_with_each_wheels_sign() -> None:
    ecus, veh = _ecus(wheel_radius=0.1, track_width=0.4)
    _arm(ecus, 0.0)
    circ = 2 * math.pi * 0.1
    _vel(ecus, 0, 1.0, 0.0)  # left forward: +1 rev/s
    _vel(ecus, 1, -1.0, 0.0)  # right is mounted mirrored (sign -1): -1 rev/s is forward
    assert veh.cmd == pytest.approx((circ, 0.0))
    _vel(ecus, 1, 0.0, 0.0)  # the left wheel alone pivots the body to the right
    assert veh.cmd == pytest.approx((0.5 * circ, -circ / 0.4))
    _vel(ecus, 0, 0.0, 0.0)  # both held: the body stops (wheels held, no creep)
    assert not veh.moving


def test_the_controller_clamps_the_set_point_to_vel_limit() -> None:
    ecus, veh = _ecus(vel_limit=1.5)
    _arm(ecus, 0.0)
    _vel(ecus, 0, 5.0, 0.0)
    _vel(ecus, 1, -5.0, 0.0)
    assert veh.cmd[0] == pytest.approx(1.5 * 2 * math.pi * 0.1)
    assert ecus.axis(0).input_vel == 5.0  # what was asked is kept; what is driven is clamped


@pytest.mark.parametrize("mode,drives", [(E.INPUT_PASSTHROUGH, True), (E.INPUT_VEL_RAMP, True), (5, False)])
def test_only_active_velocity_input_modes_turn_the_wheel(mode: int, drives: bool) -> None:
    ecus, veh = _ecus()
    _arm(ecus, 0.0, mode)
    _vel(ecus, 0, 1.0, 0.0)
    _vel(ecus, 1, -1.0, 0.0)
    assert veh.moving is drives


def test_idle_disarms_and_input_vel_survives_the_disarm() -> None:
    ecus, veh = _ecus()
    _arm(ecus, 0.0)
    _vel(ecus, 0, 1.0, 0.0)
    _vel(ecus, 1, -1.0, 0.0)
    ecus._handle(_frame(0, E.SET_AXIS_STATE, struct.pack("<I", E.IDLE)), 0.1)
    ax = ecus.axis(0)
    assert (ax.state, ax.procedure_result, ax.error) == (E.IDLE, E.RESULT_CANCELLED, 0)
    assert ax.input_vel == 1.0  # kept: a master must zero it before arming again
    ecus._handle(_frame(0, E.SET_AXIS_STATE, struct.pack("<I", E.CLOSED_LOOP_CONTROL)), 0.2)
    assert ecus.axis(0).procedure_result == E.RESULT_BUSY and veh.cmd[0] > 0  # re-armed: it drives the old set-point


def test_the_watchdog_trips_only_after_its_time_without_a_feed(caplog) -> None:
    ecus, veh = _ecus(watchdog=0.5)
    _arm(ecus, 0.0)
    _vel(ecus, 0, 1.0, 0.0)
    _vel(ecus, 1, -1.0, 0.2)
    ecus._watchdog(0.5)  # exactly the watchdog's time since the left's feed: not yet
    assert ecus.axis(0).state == E.CLOSED_LOOP_CONTROL
    with caplog.at_level(logging.WARNING, logger="scmbridge.learner"):
        ecus._watchdog(0.51)
    assert ecus.axis(0).state == E.IDLE and ecus.axis(0).error == E.WATCHDOG_TIMER_EXPIRED
    # the trip says what the emulator saw: how long without a feed, and when the last feeds were placed
    said = [r.getMessage() for r in caplog.records if "watchdog tripped" in r.getMessage()]
    assert len(said) == 1 and "node 0" in said[0] and "no feed for 0.510 s" in said[0], said
    assert "the last feeds placed [" in said[0] and "0.31" in said[0], said  # the right's feed at 0.2
    assert ecus.axis(1).state == E.CLOSED_LOOP_CONTROL  # fed later: still armed, now pivoting the body alone
    assert veh.cmd[1] > 0


def test_what_is_ignored_and_what_is_malformed() -> None:
    ecus, veh = _ecus()
    _arm(ecus, 0.0)
    n = len(ecus.received)
    ecus._handle(can.Message(arbitration_id=(0 << 5) | E.SET_INPUT_VEL, data=struct.pack("<ff", 1, 0),
                             is_extended_id=True), 0.0)  # CANSimple is 11-bit
    ecus._handle(_frame(7, E.SET_INPUT_VEL, struct.pack("<ff", 1.0, 0.0)), 0.0)  # no such node
    ecus._handle(can.Message(is_error_frame=True), 0.0)
    assert len(ecus.received) == n and ecus.malformed == 0 and not veh.moving
    for cmd, data in ((E.SET_INPUT_VEL, struct.pack("<ff", math.nan, 0.0)), (E.SET_INPUT_VEL, b"\0" * 4),
                      (E.SET_AXIS_STATE, b"\x08"), (E.SET_CONTROLLER_MODE, b"\x02\0\0\0")):
        ecus._handle(_frame(0, cmd, data), 0.0)
    assert ecus.malformed == 4 and ecus.axis(0).input_vel == 0.0 and ecus.axis(0).control_mode == E.VELOCITY_CONTROL
    ecus.unplug(1)
    _vel(ecus, 1, -1.0, 0.0)  # an unplugged node hears nothing
    assert ecus.axis(1).input_vel == 0.0
    ecus.replug(1)
    _vel(ecus, 1, -1.0, 0.0)
    assert ecus.axis(1).input_vel == -1.0


def test_the_log_of_received_frames_keeps_the_last_thousand() -> None:
    ecus, _ = _ecus()
    for k in range(1200):
        ecus._handle(_frame(0, E.SET_INPUT_VEL, struct.pack("<ff", k, 0.0)), float(k))
    assert len(ecus.received) == 1000 and ecus.received[0][0] == 200.0 and ecus.received[-1][0] == 1199.0


def test_the_encoder_counts_follow_the_bodys_real_motion() -> None:
    ecus, veh = _ecus(wheel_radius=0.1, track_width=0.4)
    veh.roll(0.3, 0.5, 0.0)  # whatever moves the body (here a roll, not a set-point)
    ecus._integrate(2.0)
    circ = 2 * math.pi * 0.1
    turn = (veh.state.theta - veh.theta0) * 0.2
    assert ecus.left.pos == pytest.approx((0.6 - turn) / circ) and ecus.right.pos == pytest.approx(-(0.6 + turn) / circ)
    assert ecus.left.vel == pytest.approx((0.3 - 0.5 * 0.2) / circ)
    assert ecus.right.vel == pytest.approx(-(0.3 + 0.5 * 0.2) / circ)


def test_a_remote_request_for_the_encoder_estimates_is_answered_on_the_bus() -> None:
    channel = f"ecu-{uuid.uuid4().hex[:8]}"
    veh = SimVehicle(LINEAR, now=0.0)
    ecus = E.DiffDriveEcus({"interface": "virtual", "channel": channel}, veh, clock=lambda: 1.0)
    spy = can.Bus(interface="virtual", channel=channel)
    try:
        ecus._open()
        veh.roll(0.2, 0.0, 0.0)
        ecus._handle(_frame(0, E.GET_ENCODER_ESTIMATES, is_remote_frame=True, dlc=8), 1.0)
        f = spy.recv(timeout=2.0)
        assert f is not None and f.arbitration_id == (0 << 5) | E.GET_ENCODER_ESTIMATES
        pos, vel = struct.unpack("<ff", bytes(f.data))
        turns = 0.2 / (2 * math.pi * 0.1)  # 1 s at 0.2 m/s; and 0.2 m/s, in wheel turns
        assert pos == pytest.approx(turns, rel=1e-6) and vel == pytest.approx(turns, rel=1e-6)
    finally:
        ecus._close()
        spy.shutdown()


def test_a_stall_of_the_emulator_itself_is_not_counted_by_the_watchdog() -> None:
    # the process hosting the emulated controllers was not scheduled for 0.7 s (a loaded test machine): the driver
    # host beside them could not feed them either, so the watchdog counts from when they run again; a master that
    # hangs while they run still trips it at its time
    ecus, _ = _ecus(watchdog=0.5)
    _arm(ecus, 0.0)
    _vel(ecus, 0, 1.0, 0.0)
    _vel(ecus, 1, -1.0, 0.0)
    ecus._stalled(0.05)  # a late turn of the loop, not a stall: nothing moves
    ecus._stalled(0.7)
    ecus._watchdog(0.75)
    assert ecus.axis(0).state == ecus.axis(1).state == E.CLOSED_LOOP_CONTROL
    ecus._watchdog(0.76 + 0.5)  # no feed for the watchdog's time after the stall: tripped, as without one
    assert ecus.axis(0).state == E.IDLE and ecus.axis(0).error == E.WATCHDOG_TIMER_EXPIRED


def test_a_preemption_between_the_clock_reads_moves_no_frame_in_time() -> None:
    """The controllers' own frames carry the moment they measured, and a command is applied at its bus stamp, even
    when the thread lost the core (80 ms) between reading its clock and the wall clock: read one after the other, the
    two clocks' offset was off by the preemption, and every frame of that turn with it."""
    t = [1.0]
    preempt = [0.08]

    def wall() -> float:
        if preempt:  # once: the thread loses the core just before this read
            t[0] += preempt.pop()
        return t[0] + 1000.0

    with _on_a_bus(t, wall) as (ecus, spy):
        ecus._send_encoder(ecus.axis(0), 1.0)  # measured at 1.0 on the emulator's clock
        f = spy.recv(timeout=2.0)
        assert f is not None and f.timestamp == pytest.approx(1001.0, abs=1e-6)
        preempt.append(0.08)
        stop = _frame(0, E.SET_INPUT_VEL, struct.pack("<ff", 0.0, 0.0), timestamp=1000.95 + 0.08)  # at 1.03
        assert ecus._arrival(stop, t[0], ecus._wall_to_mono()) == pytest.approx(1.03, abs=1e-6)


def test_frames_sent_while_every_clock_read_is_preempted_keep_the_last_tight_offset() -> None:
    """Under sustained load every bracket of a read can be wide (here 30 ms, the thread preempted before each second
    wall read): a frame stamped through such a read would claim its measurement 15 ms late, and the motion between
    two estimates would look that much faster. The emulator keeps its last tight offset instead, as a controller's
    hardware stamps its frames whatever a thread waits for."""
    t, wide, reads = [1.0], [0.0], [0]

    def wall() -> float:
        reads[0] += 1
        if wide[0] and reads[0] % 2 == 0:
            t[0] += wide[0]
        return t[0] + 1000.0

    with _on_a_bus(t, wall) as (ecus, spy):
        ecus._send_encoder(ecus.axis(0), 1.0)  # a tight read first
        wide[0] = 0.03
        ecus._send_encoder(ecus.axis(0), 1.01)
        stamps = [spy.recv(timeout=2.0), spy.recv(timeout=2.0)]
        assert all(f is not None for f in stamps)
        assert [f.timestamp for f in stamps] == pytest.approx([1001.0, 1001.01], abs=1e-6)
