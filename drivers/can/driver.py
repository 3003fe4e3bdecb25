"""The CAN driver: a differential-drive base with one ODrive 0.6 controller per wheel behind the
:class:`drivers.base.Driver` protocol. It supervises the bus and the controllers, arms the axes only when a person
engages, and wires the frame codec (:mod:`.codec`) and the odometry (:mod:`.odometry`)."""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from bridge.core.backoff import Backoff
from drivers.base import DriverError, FailsafeReport, LinkHealth, LinkReason, Pose, whole_numbers
from drivers.can.codec import decode, encode
from drivers.can.config import CanLinkConfig
from drivers.can.odometry import Odometry, Wheel
from drivers.odrive import AxisState, ControlMode, InputMode, error_names, state_name

if TYPE_CHECKING:
    import can

#: error class bit of a bus-off error frame (Linux ``include/uapi/linux/can/error.h``: ``CAN_ERR_BUSOFF``); python-can's
#: socketcan interface puts the error class into the error frame's ``arbitration_id``.
CAN_ERR_BUSOFF = 0x40
#: implausible encoder estimates keep the link's health not ok this long, s
ODOMETRY_ALARM_S = 2.0
#: s a frame's stamp may lie after its receipt (clock granularity) and still be believed.
STAMP_SLACK = 0.05
#: s a frame's stamp may lie before its receipt (it waited in the socket buffer) and still be believed.
STAMP_MAX_AGE = 1.0
#: consecutive send failures that mean the bus is down (one can be a full transmit queue).
SEND_FAILURES_DOWN = 3
#: frames read in one ``poll`` at most, so a flooded bus cannot hold the driver host's loop.
MAX_FRAMES_PER_POLL = 2000


@dataclass(frozen=True, slots=True)
class CanCounters:
    """The CAN link's own counts (only grow)."""

    error_frames: int = 0  # error frames on the bus
    bus_failures: int = 0  # the bus shut down after a failure (receive, three sends, bus-off)
    reopens: int = 0  # the bus reopened after a failure
    send_failures: int = 0
    faults: int = 0  # controller faults latched
    heartbeat_losses: int = 0  # a controller silent for heartbeat_timeout while running
    rejected_estimates: int = 0  # implausible encoder estimates, never integrated
    resyncs: int = 0  # the encoder reference re-anchored after agreeing rejected steps
    stamp_fallbacks: int = 0  # frames stamped at their receipt (no usable bus stamp)


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


@dataclass(frozen=True, slots=True)
class CanHealthDetail:
    """The CAN link's detail in :class:`drivers.base.LinkHealth`."""

    counters: CanCounters
    left: AxisHealth
    right: AxisHealth

    def status_counters(self) -> dict[str, int]:
        return whole_numbers(self.counters)


@dataclass
class _Axis:
    """What the driver knows of one wheel's controller. Stamps are driver-host monotonic seconds."""

    side: str  # "left" / "right": the word the status text uses
    node: int
    wheel: Wheel  # its odometry
    state: int = AxisState.UNDEFINED  # from the last Heartbeat
    error: int = 0  # ODriveError word of the last Heartbeat
    procedure_result: int = 0
    heartbeat_at: float | None = None
    fault: bool = False  # latched controller fault (cleared only by clear_faults)
    fault_error: int = 0  # union of the error bits seen since the fault latched
    fault_state: int = AxisState.UNDEFINED  # the state the axis was in when it latched

    def ready(self, now: float, heartbeat_timeout: float) -> bool:
        """Heartbeat fresh, closed loop, no error: the axis executes velocity set-points."""
        return (self.heartbeat_at is not None and now - self.heartbeat_at <= heartbeat_timeout
                and self.state == AxisState.CLOSED_LOOP_CONTROL and self.error == 0)

    def describe(self) -> str:
        """The controller's condition in words (for a latched fault)."""
        if self.fault_error:
            return f"{self.side} axis error: {', '.join(error_names(self.fault_error))}"
        return f"{self.side} axis not in closed loop ({state_name(self.fault_state)})"


class CanDriver:
    """The CAN link (python-can).

    **Start-up** (``open``) only opens the bus and listens: no axis enters closed loop until a person engages
    (``scmbridge engage``, or ``engage_on_start``), since a restarted driver host must not take the robot back.
    **Engage** (:meth:`engage`) refuses, naming the axis and its errors, while an axis reports an error (the watchdog
    error a killed session left, an ODrive's own estop) unless the person also asks to clear it (``--clear-faults``);
    then per axis Clear_Errors, Set_Controller_Mode(VELOCITY_CONTROL, PASSTHROUGH), Set_Input_Vel(0),
    Set_Axis_State(CLOSED_LOOP_CONTROL), and it waits, at most ``open_timeout``, feeding the watchdogs with zero
    set-points, until both Heartbeats report closed loop without error. **Close**: zero set-points until both axes
    report less than ``stop_speed`` (at most ``stop_timeout``), then IDLE. Velocity control must be set explicitly: an
    ODrive's factory control mode is POSITION_CONTROL, in which Set_Input_Vel is only a feed-forward and the wheel
    holds its position. The input mode is PASSTHROUGH, not VEL_RAMP: the set-point the driver host applies is the one
    it echoes on ``applied`` and the one the station's learner model is identified on; a ramp inside the controller
    would add a lag nothing upstream models.

    **Supervision** (in ``poll`` and ``send``; ``health`` reports it and changes nothing):

    - *controller fault*, latched: a Heartbeat with a non-zero ``Axis_Error``, or an axis that left closed loop (its
      watchdog, an Estop frame from another bus node, an operator's tool). Both axes get zero set-points at once (the
      healthy wheel must not keep driving: the robot would pivot), ``ok`` is False and ``text`` names the axis and
      the errors (``"left axis error: WATCHDOG_TIMER_EXPIRED"``). Only :meth:`clear_faults` (the operator) clears and
      re-arms; the driver never does it by itself.
    - *heartbeat lost*: no Heartbeat from a controller for ``heartbeat_timeout`` -> ``ok`` False, ``text`` names the
      node. Not latched: when Heartbeats return, what they report decides (a controller whose own watchdog tripped
      meanwhile reports WATCHDOG_TIMER_EXPIRED, which is a latched fault).
    - *bus failure*: a python-can error on receive, three send failures in a row, or a bus-off error frame -> the bus
      is shut down and reopened with a backoff that doubles from ``reopen_backoff`` up to ``reopen_backoff_max``;
      ``ok`` is False while it is down. Error frames are counted apart from malformed frames. On SocketCAN the
      controller itself leaves bus-off only if the interface restarts it: ``ip link set can0 type can bitrate 500000
      restart-ms 100``.
    - *odometry*: an implausible encoder estimate (:class:`drivers.can.odometry.Odometry`) is counted
      (``malformed``, ``rejected_estimates``), never integrated, and makes ``health()`` not ok for a moment.

    ``send`` while not ``ok`` sends nothing but zero set-points.

    **Time stamps.** A pose carries the time its encoder frames were received on the bus (``msg.timestamp``, which
    python-can fills on receive with the wall clock: ``time.time()`` for ``virtual`` and ``udp_multicast``, the
    kernel's receive time for ``socketcan``), mapped by each ``poll`` onto the driver host's ``time.monotonic()``. A
    stamp that is missing, in the future of its receipt (beyond :data:`STAMP_SLACK`) or older than
    :data:`STAMP_MAX_AGE` (a wall-clock step, NTP) is replaced by the receive time and counted (``stamp_fallbacks``).
    """

    name = "can"

    def __init__(self, config: CanLinkConfig) -> None:
        self.config = config
        self.interface, self.channel, self.bitrate = config.interface, config.channel, config.bitrate
        self.radius, self.track = config.wheel_radius, config.track_width
        self.left = _Axis("left", config.left_node, Wheel(config.left_sign))
        self.right = _Axis("right", config.right_node, Wheel(config.right_sign))
        self.axes = (self.left, self.right)
        self.odometry = Odometry(config.wheel_radius, config.track_width, config.max_wheel_speed, self.left.wheel,
                                 self.right.wheel, config.initial_pose)
        self.open_timeout = config.open_timeout
        self.heartbeat_timeout = config.heartbeat_timeout
        self.bus: can.BusABC | None = None
        self._health = LinkHealth()
        self._phase = "closed"  # closed -> arming -> running (-> arming again on clear_faults)
        self._arm_deadline = 0.0
        self._down_reason: str | None = None
        self._reopen_at = 0.0
        self._backoff = Backoff(config.reopen_backoff, config.reopen_backoff_max)
        self._send_failures = 0
        self.counters: dict[str, int] = {
            "error_frames": 0, "bus_failures": 0, "reopens": 0, "send_failures": 0, "faults": 0,
            "heartbeat_losses": 0, "rejected_estimates": 0, "resyncs": 0, "stamp_fallbacks": 0,
        }
        self._hb_lost = {ax.side: False for ax in self.axes}
        self.rejected_at = -math.inf  # when the last implausible estimate was rejected
        self.overrun_at = -math.inf  # when estimates last claimed more travel than the wheel can do

    # ----------------------------------------------------------------------------------------------- link
    def _open_bus(self) -> can.BusABC:
        import can

        kwargs: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.interface == "socketcan":
            pass  # the bitrate of a SocketCAN device is set with `ip link`, not here
        elif self.interface == "udp_multicast":
            kwargs["fd"] = self.config.fd
        else:
            kwargs["bitrate"] = self.bitrate
        return can.Bus(**kwargs)

    def open(self, now: float) -> None:
        import can

        try:
            self.bus = self._open_bus()
        except (can.CanError, OSError, ValueError) as exc:
            raise DriverError(f"cannot open CAN bus {self.interface}:{self.channel}: {exc}") from exc
        self._health.connected = True
        self._phase = "idle"
        t_end = time.monotonic() + min(self.open_timeout, 1.0)
        while time.monotonic() < t_end and any(ax.heartbeat_at is None for ax in self.axes):
            self.poll(time.monotonic(), block=0.02)  # the controllers' Heartbeats say how they are

    def engage(self, now: float, clear_faults: bool = False) -> None:
        """A person's act: both axes into velocity control and closed loop (see the class docstring)."""
        if self.bus is None or self._phase == "closed":
            raise DriverError(f"CAN bus {self.interface}:{self.channel} not open")
        t_hb = time.monotonic() + self.open_timeout
        while time.monotonic() < t_hb and any(not ax.heartbeat_at for ax in self.axes):
            self.poll(time.monotonic(), block=0.02)
        silent = [f"{ax.side} controller (node {ax.node})" for ax in self.axes if ax.heartbeat_at is None]
        if silent:
            raise DriverError(f"no heartbeat from the {' and the '.join(silent)}")
        faulted = [ax for ax in self.axes if ax.error or ax.fault]
        if faulted and not clear_faults:
            what = "; ".join(f"{ax.side} axis error: {', '.join(error_names(ax.error or ax.fault_error))}"
                             for ax in faulted)
            raise DriverError(f"{what}: check the robot, then engage with --clear-faults")
        self._arm(time.monotonic(), every_axis=True)
        t_feed = 0.0
        while True:
            t = time.monotonic()
            if t >= t_feed:  # the watchdogs count from arming: feed them while the axes come up
                self._zero(t)
                t_feed = t + 0.05
            self.poll(t, block=0.02)
            if self._phase == "running":
                if self._health.ok:
                    return
                raise DriverError(f"motor controllers not ready after {self.open_timeout} s: {self._health.text}")

    def failsafe(self) -> FailsafeReport:
        return FailsafeReport(drive_on_s=None, text=(
            "if the host dies each ODrive drives on until its own watchdog trips (axis.config.enable_watchdog, "
            "watchdog_timeout: off by default; CANSimple 0.6 cannot read it: check it with odrivetool)"))

    def _arm(self, now: float, every_axis: bool) -> None:
        """Clear errors, velocity control + passthrough, zero set-point, closed loop; then wait (phase arming) until
        both Heartbeats confirm or ``open_timeout`` passes. Only ``open`` and ``clear_faults`` call this."""
        for ax in self.axes:
            self._send(encode(ax.node, "Clear_Errors", {"Identify": 0}))
            self._send(encode(ax.node, "Set_Controller_Mode", {"Control_Mode": ControlMode.VELOCITY_CONTROL,
                                                               "Input_Mode": InputMode.PASSTHROUGH}))
            self._send(encode(ax.node, "Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}))
            if every_axis or ax.state != AxisState.CLOSED_LOOP_CONTROL or ax.error:
                self._send(encode(ax.node, "Set_Axis_State",
                                  {"Axis_Requested_State": AxisState.CLOSED_LOOP_CONTROL}))
            ax.fault, ax.fault_error = False, 0
        self._phase = "arming"
        self._arm_deadline = now + self.open_timeout

    @property
    def pose(self) -> list[float]:
        """The odometry's pose [x, y, theta] (from ``initial_pose``)."""
        return self.odometry.pose

    def wheel_turn_rates(self, v: float, omega: float) -> tuple[float, float]:
        """(left, right) Input_Vel in rev/s for body speed v (m/s) and yaw rate omega (rad/s), signs applied."""
        return self.odometry.wheel_turn_rates(v, omega)

    def send(self, v: float, omega: float, now: float) -> None:
        self._evaluate(now)
        if not self._health.ok:
            self._zero(now)  # a fault, a lost controller, arming: nothing but zero set-points
            return
        ql, qr = self.wheel_turn_rates(v, omega)
        self._send(encode(self.left.node, "Set_Input_Vel", {"Input_Vel": ql, "Input_Torque_FF": 0.0}))
        self._send(encode(self.right.node, "Set_Input_Vel", {"Input_Vel": qr, "Input_Torque_FF": 0.0}))
        sent = time.monotonic()  # a host preempted since ``now`` wrote the frames only now
        self.odometry.command(self.left.wheel, ql, now, sent)
        self.odometry.command(self.right.wheel, qr, now, sent)

    def stop(self, now: float) -> None:
        self._zero(now)

    def _zero(self, now: float) -> None:
        """Zero set-points to both axes at ``now`` (holds a healthy wheel in closed loop; harmless to an idle one)."""
        for ax in self.axes:
            self._send(encode(ax.node, "Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}))
            self.odometry.command(ax.wheel, 0.0, now, time.monotonic())

    # ----------------------------------------------------------------------------------------------- receive
    def poll(self, now: float, block: float = 0.0) -> list[Pose]:
        import can

        out: list[Pose] = []
        if self.bus is None and self._phase != "closed" and now >= self._reopen_at:
            self._reopen(now)
        if self.bus is not None:
            offset = time.monotonic() - time.time()  # wall clock (python-can stamps) -> driver-host monotonic
            timeout = block
            for _ in range(MAX_FRAMES_PER_POLL):
                try:
                    frame = self.bus.recv(timeout=timeout)
                except (can.CanError, OSError) as exc:
                    self._bus_failed(f"receive failed: {exc}", now)
                    break
                timeout = 0.0
                if frame is None:
                    break
                pose = self._frame(frame, time.monotonic(), offset, now)
                if pose is not None:
                    out.append(pose)
                if self.bus is None:  # a bus-off error frame
                    break
        self._evaluate(now)
        return out

    def _frame(self, frame: can.Message, received: float, offset: float, now: float) -> Pose | None:
        self._health.frames_received += 1
        if frame.is_error_frame:
            self._health.errors += 1
            self.counters["error_frames"] += 1
            if frame.arbitration_id & CAN_ERR_BUSOFF:
                self._bus_failed("bus-off (error frame)", now)
            return None
        try:
            node, name, sig = decode(frame)
        except ValueError:
            self._health.malformed += 1
            return None
        ax = self.left if node == self.left.node else self.right if node == self.right.node else None
        if ax is None or sig.get("_rtr"):
            return None  # another device on the bus, or a request
        stamp = self._stamp(frame, received, offset)
        if name == "Heartbeat":
            self._heartbeat(ax, sig, stamp)
        elif name == "Get_Encoder_Estimates":
            return self._encoder(ax, float(sig["Pos_Estimate"]), float(sig["Vel_Estimate"]), stamp)
        return None

    def _stamp(self, frame: can.Message, received: float, offset: float) -> float:
        """The frame's own receive stamp on the driver host's monotonic base (see the class docstring)."""
        ts = frame.timestamp
        if ts and math.isfinite(ts):
            mono = ts + offset
            if received - STAMP_MAX_AGE <= mono <= received + STAMP_SLACK:
                return min(mono, received)
        self.counters["stamp_fallbacks"] += 1
        return received

    def _heartbeat(self, ax: _Axis, sig: dict[str, Any], stamp: float) -> None:
        ax.state, ax.error = int(sig["Axis_State"]), int(sig["Axis_Error"])
        ax.procedure_result = int(sig["Procedure_Result"])
        ax.heartbeat_at = stamp if ax.heartbeat_at is None else max(ax.heartbeat_at, stamp)
        self._backoff.reset()  # the bus carries the controllers' frames again
        if self._phase != "running":
            return  # arming: old Heartbeats (from before the request) still report the fault being cleared
        if ax.error or ax.state != AxisState.CLOSED_LOOP_CONTROL:
            if not ax.fault:
                ax.fault, ax.fault_state = True, ax.state
                self.counters["faults"] += 1
                self._zero(stamp)  # both wheels, now: not at the driver host's next tick
            ax.fault_error |= ax.error

    def _encoder(self, ax: _Axis, pos: float, vel: float, stamp: float) -> Pose | None:
        """One encoder estimate into the odometry (:class:`drivers.can.odometry.Odometry`); a rejected one is counted
        and keeps ``health()`` not ok for :data:`ODOMETRY_ALARM_S` with the reason."""
        step = self.odometry.estimate(ax.wheel, pos, vel, stamp)
        if step.overrun:
            self.overrun_at = time.monotonic()  # more travel than the wheel can do: not cleared by a resync
        if step.rejected:
            self._reject()
        if step.resynced:
            self.counters["resyncs"] += 1
            self.rejected_at = -math.inf  # a real move of the encoder, not an implausible one
        return step.pose

    def _reject(self) -> None:
        self._health.malformed += 1
        self.counters["rejected_estimates"] += 1
        self.rejected_at = time.monotonic()

    # ----------------------------------------------------------------------------------------------- bus
    def _send(self, frame: can.Message) -> bool:
        import can

        if self.bus is None:
            return False
        try:
            self.bus.send(frame, timeout=0.05)
        except (can.CanError, OSError) as exc:
            self._health.errors += 1
            self.counters["send_failures"] += 1
            self._send_failures += 1
            if self._send_failures >= SEND_FAILURES_DOWN:
                self._bus_failed(f"send failed: {exc}", time.monotonic())
            return False
        self._health.frames_sent += 1
        self._send_failures = 0
        return True

    def _bus_failed(self, reason: str, now: float) -> None:
        """Release the bus and schedule a reopen (backoff doubles per failed attempt, up to its bound)."""
        self.counters["bus_failures"] += 1
        self._health.errors += 1
        bus, self.bus = self.bus, None
        if bus is not None:
            with contextlib.suppress(Exception):
                bus.shutdown()
        self._health.connected = False
        self._down_reason = reason
        self._send_failures = 0
        self._reopen_at = now + self._backoff.delay

    def _reopen(self, now: float) -> None:
        import can

        try:
            self.bus = self._open_bus()
        except (can.CanError, OSError, ValueError) as exc:
            self._down_reason = f"reopen failed: {exc}"
            self._backoff.grow()
            self._reopen_at = now + self._backoff.delay
            return
        self.counters["reopens"] += 1
        self._health.connected = True
        self._down_reason = None
        # until a controller's frame arrives on the new bus, the next failure waits longer
        self._backoff.grow()

    # ----------------------------------------------------------------------------------------------- state
    def _advance(self, now: float) -> None:
        """What time changes (``poll`` and ``send`` call it): arming ends once both axes confirm closed loop, or when
        ``open_timeout`` has passed (an axis that did not come up is then a latched fault); a controller whose
        Heartbeats stop while running is counted once per loss."""
        if self._phase == "arming":
            if all(ax.ready(now, self.heartbeat_timeout) for ax in self.axes):
                self._phase = "running"
            elif now > self._arm_deadline:
                self._phase = "running"
                for ax in self.axes:  # (an axis that is silent is reported as a lost heartbeat)
                    if ax.heartbeat_at is not None and (ax.error or ax.state != AxisState.CLOSED_LOOP_CONTROL):
                        ax.fault, ax.fault_error, ax.fault_state = True, ax.error, ax.state
                        self.counters["faults"] += 1
        for ax in self.axes:
            lost = self._phase == "running" and self._heartbeat_lost(ax, now)
            if lost and not self._hb_lost[ax.side]:
                self.counters["heartbeat_losses"] += 1
            self._hb_lost[ax.side] = lost

    def _heartbeat_lost(self, ax: _Axis, now: float) -> bool:
        return ax.heartbeat_at is None or now - ax.heartbeat_at > self.heartbeat_timeout

    def _reasons(self, now: float) -> list[tuple[LinkReason, str]]:
        """Why the link is not fit to drive at ``now`` (none: it is), from the bus, the latched faults, the
        Heartbeats' age and the arming phase, each typed and in words. Pure."""
        reasons: list[tuple[LinkReason, str]] = []
        if self._phase == "idle":
            # a silent controller first: not engaged is what a person does next, a controller that does not answer
            # is what is wrong (doctor fails on it; before, only engage said "no heartbeat")
            reasons += self._silent(now)
            reasons.append(("not_engaged", "axes idle: not engaged"))
        if self.bus is None:
            reasons.append(("link_down", f"CAN bus down ({self._down_reason}); reopening in "
                                         f"{max(0.0, self._reopen_at - now):.2f} s"))
        if self._phase == "arming":
            reasons.append(("arming", "arming: waiting for both axes in closed loop"))
        reasons += [("fault", ax.describe()) for ax in self.axes if ax.fault]
        if now - max(self.rejected_at, self.overrun_at) < ODOMETRY_ALARM_S:
            reasons.append(("odometry", f"odometry: implausible encoder estimates rejected "
                                        f"({self.counters['rejected_estimates']} so far): a faulty encoder or forged "
                                        "frames"))
        if self._phase == "running":
            reasons += self._silent(now)
        return reasons

    def _silent(self, now: float) -> list[tuple[LinkReason, str]]:
        """The controllers whose Heartbeat is older than ``heartbeat_timeout`` (or never came)."""
        out: list[tuple[LinkReason, str]] = []
        for ax in self.axes:
            if self._heartbeat_lost(ax, now):
                age = "" if ax.heartbeat_at is None else f" for {now - ax.heartbeat_at:.2f} s"
                out.append(("no_heartbeat", f"{ax.side} controller (node {ax.node}): no heartbeat{age}"))
        return out

    @staticmethod
    def _verdict(reasons: list[tuple[LinkReason, str]]) -> tuple[bool, LinkReason, str]:
        """``ok``, the first reason typed, and every reason in words (``"ready"`` when there is none)."""
        if not reasons:
            return True, "ok", "ready"
        return False, reasons[0][0], "; ".join(text for _, text in reasons)

    def _evaluate(self, now: float) -> None:
        """Advance the state to ``now`` and set ``ok``, ``reason`` and ``text`` from it."""
        h = self._health
        if self._phase == "closed":
            h.ok = False
            return
        self._advance(now)
        h.ok, h.reason, h.text = self._verdict(self._reasons(now))

    def health(self, now: float) -> LinkHealth:
        h = self._health
        if self._phase == "closed":
            ok, reason, text = False, h.reason, h.text
        else:
            ok, reason, text = self._verdict(self._reasons(now))
        left, right = (AxisHealth(node=ax.node, state=state_name(ax.state), error=ax.error,
                                  errors=tuple(error_names(ax.error)), procedure_result=ax.procedure_result,
                                  heartbeat_age=None if ax.heartbeat_at is None else now - ax.heartbeat_at,
                                  fault=ax.fault) for ax in self.axes)
        return replace(h, ok=ok, reason=reason, text=text,
                       detail=CanHealthDetail(CanCounters(**self.counters), left, right))

    def clear_faults(self, now: float) -> None:
        """The operator's act: Clear_Errors to both controllers, velocity control again, zero set-point, closed loop
        for an axis that is not in it. Returns at once; ``ok`` comes back when both Heartbeats confirm (at most
        ``open_timeout``), else the axis that did not re-arm is a latched fault again."""
        if self._phase == "closed" or self.bus is None:
            return  # nothing reachable: the text still says why
        if self._phase == "idle":  # not engaged: clear the errors, never arm (engage does that)
            for ax in self.axes:
                self._send(encode(ax.node, "Clear_Errors", {"Identify": 0}))
                ax.fault, ax.fault_error = False, 0
            return
        self._arm(now, every_axis=False)
        self._evaluate(now)

    def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0) -> None:
        if self.bus is None:
            self._phase = "closed"
            self._health.connected = self._health.ok = False
            self._health.text, self._health.reason = "closed", "closed"
            return
        try:
            # a link that never armed the axes (not engaged, a dry run, a half-open link let go) sends nothing: the
            # controllers are someone else's to command; one that did stops them, waits until the wheels have
            # stopped, and only with ``disarm`` puts them in IDLE
            if self._phase == "running":
                t_end = time.monotonic() + stop_timeout
                turns = stop_speed / (2.0 * math.pi * self.radius)  # rev/s of a wheel at stop_speed
                while time.monotonic() < t_end:  # zero until both wheels have stopped
                    self.stop(0.0)
                    self.poll(time.monotonic(), block=0.02)
                    if all(abs(ax.wheel.vel) < turns for ax in self.axes):
                        break
                self.stop(0.0)
                if disarm:
                    for ax in self.axes:
                        self._send(encode(ax.node, "Set_Axis_State", {"Axis_Requested_State": AxisState.IDLE}))
        finally:
            if self.bus is not None:
                with contextlib.suppress(Exception):
                    self.bus.shutdown()
            self.bus = None
            self._phase = "closed"
            self._health.connected = self._health.ok = False
            self._health.text, self._health.reason = "closed", "closed"

