"""The two ODrive 0.6 axes of a differential-drive base as a pure state machine: what each controller last said (its
Heartbeat), the faults it latched, the arming phase a person's engage starts, lost Heartbeats, and the frames the
machine wants sent (as ``(node, message name, signals)``; the bus supervisor, :mod:`drivers.can.driver`, encodes and
sends them). Pure: every time is an argument (driver-host monotonic seconds), nothing here reads a clock or touches
the bus, so the whole supervision of the controllers is tested on a fake clock (tests/unit/drivers/can/test_axis.py).

The safety rules it implements are docs/ARCHITECTURE.md section 6 ("the operator always wins"): a fault is latched
and only an operator's clear (:meth:`Axes.arm` from ``clear_faults``, or :meth:`Axes.clear` while idle) lets it go;
the machine never asks for closed loop by itself.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

from drivers.base import LinkReason
from drivers.can.odometry import Wheel
from drivers.odrive import AxisState, ControlMode, InputMode, error_names, state_name

#: one CANSimple frame to send: (node id, message name in the DBC, its signals)
Frame = tuple[int, str, dict[str, float]]
#: closed (not opened) -> idle (listening, never armed by us) -> arming (a person engaged or cleared faults) ->
#: running (both axes confirmed, or the arming timed out) -> arming again on the operator's clear
Phase = Literal["closed", "idle", "arming", "running"]
#: a reason the base is not fit to drive, typed and in words
Reason = tuple[LinkReason, str]


def zero_input(node: int) -> Frame:
    """Set_Input_Vel 0 for ``node``: holds a healthy wheel in closed loop, harmless to an idle one."""
    return node, "Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}


@dataclass(frozen=True, slots=True)
class AxisHealth:
    """One wheel's controller as its last Heartbeat reported it."""

    node: int
    state: str  # the axis state's name: CLOSED_LOOP_CONTROL, IDLE, ...
    error: int  # the Axis_Error word
    errors: tuple[str, ...]  # its bits' names
    procedure_result: int
    heartbeat_age: float | None  # s since the last Heartbeat (None: none yet)
    fault: bool  # a latched fault (cleared only by clear_faults)


@dataclass
class Axis:
    """What is known of one wheel's controller. Stamps are driver-host monotonic seconds."""

    side: str  # "left" / "right": the word the status text uses
    node: int
    wheel: Wheel  # its odometry
    state: int = AxisState.UNDEFINED  # from the last Heartbeat
    error: int = 0  # ODriveError word of the last Heartbeat
    procedure_result: int = 0
    heartbeat_at: float | None = None
    fault: bool = False  # latched controller fault (cleared only by an operator's clear)
    fault_error: int = 0  # union of the error bits seen since the fault latched
    fault_state: int = AxisState.UNDEFINED  # the state the axis was in when it latched

    def ready(self, now: float, heartbeat_timeout: float) -> bool:
        """Heartbeat fresh, closed loop, no error: the axis executes velocity set-points."""
        return (not self.silent(now, heartbeat_timeout) and self.state == AxisState.CLOSED_LOOP_CONTROL
                and self.error == 0)

    def silent(self, now: float, heartbeat_timeout: float) -> bool:
        """No Heartbeat yet, or the last one older than ``heartbeat_timeout`` at ``now``."""
        return self.heartbeat_at is None or now - self.heartbeat_at > heartbeat_timeout

    def describe(self) -> str:
        """The controller's condition in words (for a latched fault)."""
        if self.fault_error:
            return f"{self.side} axis error: {', '.join(error_names(self.fault_error))}"
        return f"{self.side} axis not in closed loop ({state_name(self.fault_state)})"

    def health(self, now: float) -> AxisHealth:
        """Its report for :class:`drivers.can.driver.CanHealthDetail` at ``now``."""
        return AxisHealth(node=self.node, state=state_name(self.state), error=self.error,
                          errors=tuple(error_names(self.error)), procedure_result=self.procedure_result,
                          heartbeat_age=None if self.heartbeat_at is None else now - self.heartbeat_at,
                          fault=self.fault)


class Axes:
    """Both wheels' controllers: the phase, the latched faults, the lost Heartbeats and the typed reasons the base is
    not fit to drive (the verdict :func:`verdict` turns into ``ok``, ``reason`` and ``text``). Iterating gives the
    two :class:`Axis` (left, right)."""

    def __init__(self, left: Axis, right: Axis, open_timeout: float, heartbeat_timeout: float) -> None:
        self.left, self.right = left, right
        self.open_timeout, self.heartbeat_timeout = open_timeout, heartbeat_timeout
        self.phase: Phase = "closed"
        self.arm_deadline = 0.0
        self.faults = 0  # controller faults latched (only grows)
        self.heartbeat_losses = 0  # a controller silent for heartbeat_timeout while running, once per loss
        self.lost = {left.side: False, right.side: False}  # the loss counted and not over yet, per side

    def __iter__(self) -> Iterator[Axis]:
        return iter((self.left, self.right))

    def by_node(self, node: int) -> Axis | None:
        """The axis of CANSimple ``node`` (None: another device on the bus)."""
        return self.left if node == self.left.node else self.right if node == self.right.node else None

    def heard(self) -> bool:
        """Both controllers have sent a Heartbeat since the link opened."""
        return all(ax.heartbeat_at is not None for ax in self)

    # ----------------------------------------------------------------------------------------------- inputs
    def heartbeat(self, ax: Axis, state: int, error: int, procedure_result: int, stamp: float) -> bool:
        """A Heartbeat of ``ax`` received at ``stamp``. While running, an error or an axis out of closed loop (its
        watchdog, an Estop from another bus node, an operator's tool) latches a fault; returns True when one latched
        now: both wheels must get zero set-points at once (the healthy wheel alone would pivot the robot)."""
        ax.state, ax.error, ax.procedure_result = int(state), int(error), int(procedure_result)
        ax.heartbeat_at = stamp if ax.heartbeat_at is None else max(ax.heartbeat_at, stamp)
        if self.phase != "running":
            return False  # arming: old Heartbeats (from before the request) still report the fault being cleared
        latched = False
        if ax.error or ax.state != AxisState.CLOSED_LOOP_CONTROL:
            if not ax.fault:
                ax.fault, ax.fault_state = True, ax.state
                self.faults += 1
                latched = True
            ax.fault_error |= ax.error
        return latched

    def advance(self, now: float) -> bool:
        """What time changes: arming ends once both axes confirm closed loop, or when ``open_timeout`` has passed (an
        axis that did not come up is then a latched fault); a controller whose Heartbeats stop while running is
        counted once per loss. True if anything changed."""
        changed = False
        if self.phase == "arming":
            if all(ax.ready(now, self.heartbeat_timeout) for ax in self):
                self.phase, changed = "running", True
            elif now > self.arm_deadline:
                self.phase, changed = "running", True
                for ax in self:  # (an axis that is silent is reported as a lost heartbeat)
                    if ax.heartbeat_at is not None and (ax.error or ax.state != AxisState.CLOSED_LOOP_CONTROL):
                        ax.fault, ax.fault_error, ax.fault_state = True, ax.error, ax.state
                        self.faults += 1
        for ax in self:
            lost = self.phase == "running" and ax.silent(now, self.heartbeat_timeout)
            if lost != self.lost[ax.side]:
                changed = True
                if lost:
                    self.heartbeat_losses += 1
            self.lost[ax.side] = lost
        return changed

    # ----------------------------------------------------------------------------------------------- a person's acts
    def engage_refusal(self, clear_faults: bool) -> str | None:
        """Why a person's engage cannot arm the axes now (None: it can): a controller never heard from, or one that
        reports an error the person did not ask to clear."""
        silent = [f"{ax.side} controller (node {ax.node})" for ax in self if ax.heartbeat_at is None]
        if silent:
            return f"no heartbeat from the {' and the '.join(silent)}"
        faulted = [ax for ax in self if ax.error or ax.fault]
        if faulted and not clear_faults:
            what = "; ".join(f"{ax.side} axis error: {', '.join(error_names(ax.error or ax.fault_error))}"
                             for ax in faulted)
            return f"{what}: check the robot, then engage with --clear-faults"
        return None

    def arm(self, now: float, every_axis: bool) -> list[Frame]:
        """The frames that arm: per axis Clear_Errors, velocity control + passthrough, zero set-point, and closed
        loop (every axis: a person's engage; only an axis not in it: an operator's clear while running); the phase
        becomes arming until both Heartbeats confirm or ``open_timeout`` passes. Only a person's act calls this
        (``CanDriver.engage`` and ``CanDriver.clear_faults``), never the supervision."""
        out: list[Frame] = []
        for ax in self:
            out.append((ax.node, "Clear_Errors", {"Identify": 0}))
            out.append((ax.node, "Set_Controller_Mode", {"Control_Mode": ControlMode.VELOCITY_CONTROL,
                                                         "Input_Mode": InputMode.PASSTHROUGH}))
            out.append(zero_input(ax.node))
            if every_axis or ax.state != AxisState.CLOSED_LOOP_CONTROL or ax.error:
                out.append((ax.node, "Set_Axis_State", {"Axis_Requested_State": AxisState.CLOSED_LOOP_CONTROL}))
            ax.fault, ax.fault_error = False, 0
        self.phase = "arming"
        self.arm_deadline = now + self.open_timeout
        return out

    def clear(self) -> list[Frame]:
        """An operator's clear while not engaged: Clear_Errors to both controllers and the latches dropped; never
        arms (engaging does)."""
        out: list[Frame] = []
        for ax in self:
            out.append((ax.node, "Clear_Errors", {"Identify": 0}))
            ax.fault, ax.fault_error = False, 0
        return out

    def zero(self) -> list[Frame]:
        """Zero set-points to both axes."""
        return [zero_input(ax.node) for ax in self]

    def idle(self) -> list[Frame]:
        """Both axes to IDLE (closing a link this host armed, when told to disarm)."""
        return [(ax.node, "Set_Axis_State", {"Axis_Requested_State": AxisState.IDLE}) for ax in self]

    # ----------------------------------------------------------------------------------------------- verdict
    def reasons(self, now: float, down: str | None = None, odometry: str | None = None) -> list[Reason]:
        """Why the base is not fit to drive at ``now`` (none: it is), first cause first: a silent controller before
        "not engaged" (a controller that does not answer is what is wrong; not engaged is what a person does next),
        then the bus (``down``: why the supervisor's bus is down), arming, the latched faults, the odometry's alarm
        (``odometry``) and, while running, the silent controllers. Pure."""
        reasons: list[Reason] = []
        if self.phase == "idle":
            reasons += self._silent(now)
            reasons.append(("not_engaged", "axes idle: not engaged"))
        if down is not None:
            reasons.append(("link_down", down))
        if self.phase == "arming":
            reasons.append(("arming", "arming: waiting for both axes in closed loop"))
        reasons += [("fault", ax.describe()) for ax in self if ax.fault]
        if odometry is not None:
            reasons.append(("odometry", odometry))
        if self.phase == "running":
            reasons += self._silent(now)
        return reasons

    def _silent(self, now: float) -> list[Reason]:
        out: list[Reason] = []
        for ax in self:
            if ax.silent(now, self.heartbeat_timeout):
                age = "" if ax.heartbeat_at is None else f" for {now - ax.heartbeat_at:.2f} s"
                out.append(("no_heartbeat", f"{ax.side} controller (node {ax.node}): no heartbeat{age}"))
        return out


def verdict(reasons: list[Reason]) -> tuple[bool, LinkReason, str]:
    """``ok``, the first reason typed, and every reason in words (``"ready"`` when there is none)."""
    if not reasons:
        return True, "ok", "ready"
    return False, reasons[0][0], "; ".join(text for _, text in reasons)


__all__ = ["Axes", "Axis", "AxisHealth", "Frame", "Phase", "verdict", "zero_input"]
