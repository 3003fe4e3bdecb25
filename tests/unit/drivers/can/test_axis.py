"""drivers.can.axis: the two ODrive 0.6 controllers as a pure state machine, driven with Heartbeats at chosen times
(no bus, no clock). The enumerations' values are ODrive's own (drivers/odrive.py cites where they come from)."""

from __future__ import annotations

import pytest

from drivers.can.axis import Axes, Axis, verdict
from drivers.can.odometry import Wheel
from drivers.odrive import AxisState, ControlMode, InputMode, ODriveError

CLOSED, IDLE = AxisState.CLOSED_LOOP_CONTROL, AxisState.IDLE
OPEN_TIMEOUT, HB_TIMEOUT = 2.0, 0.5


def axes() -> Axes:
    a = Axes(Axis("left", 0, Wheel(1.0)), Axis("right", 1, Wheel(-1.0)), OPEN_TIMEOUT, HB_TIMEOUT)
    a.phase = "idle"  # the link opened
    return a


def beat(a: Axes, t: float, state: int = CLOSED, left_error: int = 0, right_error: int = 0) -> list[bool]:
    """A Heartbeat from each controller at ``t``; whether each latched a fault."""
    return [a.heartbeat(a.left, state, left_error, 0, t), a.heartbeat(a.right, state, right_error, 0, t)]


def running(t: float = 10.0) -> Axes:
    """Engaged: armed at ``t`` and both axes confirmed closed loop."""
    a = axes()
    beat(a, t, IDLE)
    a.arm(t, every_axis=True)
    beat(a, t + 0.1)
    a.advance(t + 0.1)
    assert a.phase == "running"
    return a


def test_an_idle_base_says_not_engaged_and_a_silent_controller_first() -> None:
    a = axes()
    assert not a.heard()
    ok, reason, text = verdict(a.reasons(1.0))
    assert not ok and reason == "no_heartbeat"
    assert text == ("left controller (node 0): no heartbeat; right controller (node 1): no heartbeat; "
                    "axes idle: not engaged")
    beat(a, 1.0, IDLE)
    assert a.heard() and verdict(a.reasons(1.2)) == (False, "not_engaged", "axes idle: not engaged")
    assert a.by_node(1) is a.right and a.by_node(5) is None and list(a) == [a.left, a.right]


def test_engage_is_refused_for_a_silent_controller_or_an_error_the_person_did_not_ask_to_clear() -> None:
    a = axes()
    assert a.engage_refusal(True) == "no heartbeat from the left controller (node 0) and the right controller (node 1)"
    beat(a, 1.0, IDLE, right_error=ODriveError.WATCHDOG_TIMER_EXPIRED)
    assert a.engage_refusal(False) == ("right axis error: WATCHDOG_TIMER_EXPIRED: check the robot, then engage with "
                                       "--clear-faults")
    assert a.engage_refusal(True) is None


def test_arming_asks_velocity_control_and_passthrough_before_closed_loop_and_waits_for_both() -> None:
    a = axes()
    beat(a, 1.0, IDLE)
    frames = a.arm(1.0, every_axis=True)
    for node in (0, 1):
        assert [f for f in frames if f[0] == node] == [
            (node, "Clear_Errors", {"Identify": 0}),
            (node, "Set_Controller_Mode", {"Control_Mode": ControlMode.VELOCITY_CONTROL,
                                           "Input_Mode": InputMode.PASSTHROUGH}),
            (node, "Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}),
            (node, "Set_Axis_State", {"Axis_Requested_State": CLOSED}),
        ]
    assert a.phase == "arming" and a.arm_deadline == 1.0 + OPEN_TIMEOUT
    a.advance(1.1)
    assert verdict(a.reasons(1.1))[1] == "arming"
    a.heartbeat(a.left, CLOSED, 0, 0, 1.2)  # one axis up is not enough
    a.advance(1.2)
    assert a.phase == "arming"
    a.heartbeat(a.right, CLOSED, 0, 0, 1.3)
    a.advance(1.3)
    assert a.phase == "running" and verdict(a.reasons(1.3)) == (True, "ok", "ready") and a.faults == 0


def test_an_old_heartbeat_during_arming_latches_nothing() -> None:
    a = axes()
    beat(a, 1.0, IDLE, left_error=ODriveError.ESTOP_REQUESTED)
    a.arm(1.0, every_axis=True)
    assert beat(a, 1.05, IDLE, left_error=ODriveError.ESTOP_REQUESTED) == [False, False]
    assert not a.left.fault and a.faults == 0


def test_an_axis_that_does_not_come_up_within_open_timeout_is_a_latched_fault() -> None:
    a = axes()
    beat(a, 1.0, IDLE)
    a.arm(1.0, every_axis=True)
    for k in range(1, 21):  # up to the deadline, 1.0 + OPEN_TIMEOUT, included
        t = 1.0 + 0.1 * k
        a.heartbeat(a.left, CLOSED, 0, 0, t)
        a.heartbeat(a.right, IDLE, 0, 0, t)
        a.advance(t)
        assert a.phase == "arming"
    t = 1.0 + OPEN_TIMEOUT + 0.1
    a.heartbeat(a.left, CLOSED, 0, 0, t)
    a.heartbeat(a.right, IDLE, 0, 0, t)
    a.advance(t)
    assert a.phase == "running" and a.right.fault and not a.left.fault and a.faults == 1
    assert verdict(a.reasons(t)) == (False, "fault", "right axis not in closed loop (IDLE)")


def test_a_fault_while_running_latches_once_asks_for_a_stop_and_waits_for_the_operator() -> None:
    a = running()
    t = 11.0
    assert beat(a, t, left_error=ODriveError.DRV_FAULT) == [True, False]  # zero both wheels now
    assert beat(a, t + 0.1, IDLE, left_error=ODriveError.DRV_FAULT | ODriveError.MISSING_INPUT) == [False, True]
    assert a.faults == 2 and a.left.fault_error == ODriveError.DRV_FAULT | ODriveError.MISSING_INPUT
    ok, reason, text = verdict(a.reasons(t + 0.1))
    assert not ok and reason == "fault"
    assert text == "left axis error: DRV_FAULT, MISSING_INPUT; right axis not in closed loop (IDLE)"
    for k in range(1, 20):  # healthy Heartbeats again: still latched, time alone clears nothing
        beat(a, t + 0.1 * k)
        a.advance(t + 0.1 * k)
    assert a.left.fault and a.right.fault
    frames = a.arm(t + 2.0, every_axis=False)  # the operator's clear: both axes are in closed loop again
    assert not any(name == "Set_Axis_State" for _, name, _ in frames)
    assert not a.left.fault and not a.right.fault and a.phase == "arming"


def test_the_operators_clear_while_idle_clears_the_latches_and_never_arms() -> None:
    a = axes()
    a.left.fault, a.left.fault_error = True, int(ODriveError.DRV_FAULT)
    assert a.clear() == [(0, "Clear_Errors", {"Identify": 0}), (1, "Clear_Errors", {"Identify": 0})]
    assert not a.left.fault and a.phase == "idle"


def test_a_lost_heartbeat_is_reported_counted_once_per_loss_and_not_latched() -> None:
    a = running()
    t = 10.1
    a.heartbeat(a.left, CLOSED, 0, 0, t + 0.4)
    a.advance(t + 0.5)
    assert a.heartbeat_losses == 0
    a.advance(t + HB_TIMEOUT + 0.01)  # the right controller last spoke at 10.1
    a.advance(t + HB_TIMEOUT + 0.2)
    assert a.heartbeat_losses == 1 and a.lost == {"left": False, "right": True}
    ok, reason, text = verdict(a.reasons(t + HB_TIMEOUT + 0.2))
    assert (ok, reason) == (False, "no_heartbeat") and text == "right controller (node 1): no heartbeat for 0.70 s"
    beat(a, t + 1.0)  # back, still in closed loop: driving again, the loss not latched
    a.advance(t + 1.0)
    assert verdict(a.reasons(t + 1.0))[0] and a.lost == {"left": False, "right": False}
    a.advance(t + 2.0)  # both silent now: each controller's loss is counted
    assert a.heartbeat_losses == 3


def test_reasons_come_first_cause_first_with_the_bus_and_the_odometry_in_their_place() -> None:
    a = running()
    a.heartbeat(a.right, CLOSED, ODriveError.DRV_FAULT, 0, 10.2)
    reasons = a.reasons(10.3, down="CAN bus down (receive failed)", odometry="odometry: implausible")
    assert [r for r, _ in reasons] == ["link_down", "fault", "odometry"]
    assert [r for r, _ in a.reasons(12.0)] == ["fault", "no_heartbeat", "no_heartbeat"]


def test_zero_and_idle_frames_go_to_both_axes() -> None:
    a = axes()
    assert a.zero() == [(n, "Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}) for n in (0, 1)]
    assert a.idle() == [(n, "Set_Axis_State", {"Axis_Requested_State": IDLE}) for n in (0, 1)]


@pytest.mark.parametrize("phase", ["idle", "arming", "running"])
def test_reasons_and_verdict_are_pure(phase: str) -> None:
    a = running()
    a.phase = phase  # type: ignore[assignment]
    before = (a.phase, a.faults, a.heartbeat_losses, dict(a.lost), [(ax.fault, ax.heartbeat_at) for ax in a])
    verdict(a.reasons(99.0, down="x", odometry="y"))
    assert (a.phase, a.faults, a.heartbeat_losses, dict(a.lost), [(ax.fault, ax.heartbeat_at) for ax in a]) == before
