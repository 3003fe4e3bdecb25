"""CAN link: a differential-drive base with one ODrive motor controller (firmware 0.6, CANSimple) per wheel.

Frames as ODrive firmware 0.6 defines them, from ``odrive_cansimple.dbc`` (node 0 layout; the node offset is added
at run time: arbitration id = node_id << 5 | cmd_id, 11-bit, little endian, IEEE float32); enumerations and error
names in :mod:`drivers.odrive`, with the ODrive sources they were checked against. The driver turns (v, omega) into
wheel turn rates with the wheel radius and track width, and integrates odometry from the controllers' encoder
estimates. Configuration: :class:`CanLinkConfig` (``[link.can]`` in the driver host's file). python-can and
cantools are imported when a driver is built or a frame coded, not with the module (the configuration needs neither).

**Start-up** (``open``) only opens the bus and listens: no axis enters closed loop until a person engages
(``scmbridge engage``, or ``engage_on_start``), since a restarted driver host must not take the robot back.
**Engage** (:meth:`CanDriver.engage`) refuses, naming the axis and its errors, while an axis reports an error (the
watchdog error a killed session left, an ODrive's own estop) unless the person also asks to clear it (``--clear-
faults``); then per axis Clear_Errors, Set_Controller_Mode(VELOCITY_CONTROL, PASSTHROUGH), Set_Input_Vel(0),
Set_Axis_State(CLOSED_LOOP_CONTROL), and it waits, at most ``open_timeout``, feeding the watchdogs with zero set-
points, until both Heartbeats report closed loop without error. **Close**: zero set-points until both axes report
less than ``stop_speed`` (at most ``stop_timeout``), then IDLE. Velocity control must be set explicitly: an ODrive's
factory control mode is POSITION_CONTROL, in which Set_Input_Vel is only a feed-forward and the wheel holds its
position. The input mode is PASSTHROUGH, not VEL_RAMP: the set-point the driver host applies is the one it echoes on
``applied`` and the one the station's learner model is identified on; a ramp inside the controller would add a lag
nothing upstream models (acceleration is bounded by the driver host's hard limits and the transfer's bounds instead).

**Supervision** (in ``poll`` and ``send``; ``health`` reports it and changes nothing):

- *controller fault*, latched: a Heartbeat with a non-zero ``Axis_Error``, or an axis that left closed loop (its
  watchdog, an Estop frame from another bus node, an operator's tool). Both axes get zero set-points at once (the
  healthy wheel must not keep driving: the robot would pivot), ``ok`` is False and ``text`` names the axis and the
  errors (``"left axis error: WATCHDOG_TIMER_EXPIRED"``). Only :meth:`CanDriver.clear_faults` (the operator) clears
  and re-arms; the driver never does it by itself.
- *heartbeat lost*: no Heartbeat from a controller for ``heartbeat_timeout`` -> ``ok`` False, ``text`` names the
  node. Not latched: when Heartbeats return, what they report decides (a controller whose own watchdog tripped
  meanwhile reports WATCHDOG_TIMER_EXPIRED, which is a latched fault).
- *bus failure*: a python-can error on receive (``can.CanOperationError`` and the other ``can.CanError``), three
  send failures in a row, or a bus-off error frame -> the bus is shut down and reopened with a backoff that doubles
  from ``reopen_backoff`` up to ``reopen_backoff_max`` (retried for as long as the link runs); ``ok`` is False while
  it is down. Error frames are counted apart from malformed frames. On SocketCAN the controller itself leaves bus-off
  only if the interface restarts it: ``ip link set can0 type can bitrate 500000 restart-ms 100``.

``send`` while not ``ok`` sends nothing but zero set-points.

**Odometry.** Every decoded estimate is validated before it touches the pose: finite (``decode``), ``|Vel_Estimate|``
at most ``max_wheel_speed``, ``|Pos_Estimate|`` at most :data:`MAX_ABS_POSITION`, and a position step no larger than
``max_wheel_speed`` times the time between the two frames (plus :data:`JUMP_SLACK`). A rejected estimate is counted
(``malformed``, and ``rejected_estimates``) and never integrated. Each wheel's travel also has a budget that refills
at the fastest the wheel can turn given what it was told (twice the commanded rate plus a slack, at most
``max_wheel_speed``): many small steps, each plausible alone, cannot add up to more (crafted frames at 2 kHz once
gave 101 m of odometry in 2 s). An implausible estimate makes ``health()`` not ok for a moment, with the reason. When
:data:`RESYNC_AFTER` rejected steps in a row agree with each other, the encoder really moved (a controller reboot, a
Set_Absolute_Position): the reference is re-anchored there without integrating the step (``resyncs``).

**Time stamps.** A pose carries the time its encoder frames were received on the bus (``msg.timestamp``, which
python-can fills on receive), not the time ``poll`` ran. python-can stamps with the wall clock: ``time.time()`` for
the ``virtual`` and ``udp_multicast`` interfaces, the kernel's receive time (CLOCK_REALTIME) for ``socketcan``. The
driver host's clock is ``time.monotonic()``; each ``poll`` measures the offset between the two and maps every frame
onto the monotonic base. A stamp that is missing, in the future of its receipt (beyond :data:`STAMP_SLACK`) or older
than :data:`STAMP_MAX_AGE` (a wall-clock step, NTP) is replaced by the receive time and counted
(``stamp_fallbacks``).
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field, replace
from importlib import resources
from typing import TYPE_CHECKING, Annotated, Any

from bridge.core.backoff import Backoff
from bridge.core.config import Cfg, Finite, Rule, meta
from drivers.base import DriverError, FailsafeReport, LinkHealth, Pose, whole_numbers
from drivers.odrive import AxisState, ControlMode, InputMode, error_names, state_name

if TYPE_CHECKING:
    import can
    import cantools

#: error class bit of a bus-off error frame (Linux ``include/uapi/linux/can/error.h``: ``CAN_ERR_BUSOFF``); python-can's
#: socketcan interface puts the error class into the error frame's ``arbitration_id``.
CAN_ERR_BUSOFF = 0x40
#: rev: a position estimate beyond this is garbage (float32 resolution there is ~1 rev; 1e7 rev of a 0.1 m wheel is
#: 6000 km).
MAX_ABS_POSITION = 1e7
#: s of motion at ``max_wheel_speed`` tolerated on top of the interval between two encoder frames (stamp jitter).
JUMP_SLACK = 0.02
#: rev/s a wheel may turn beyond twice its commanded rate (pushed, rolling on after a stop)
COMMAND_SLACK_REV_S = 0.5
#: s of motion the odometry's travel budget holds at most (frame jitter, a burst of frames read at once)
BURST_S = 0.1
#: implausible encoder estimates keep the link's health not ok this long, s
ODOMETRY_ALARM_S = 2.0
#: consecutive rejected position steps that agree with each other before the encoder reference is re-anchored.
RESYNC_AFTER = 3
#: s a frame's stamp may lie after its receipt (clock granularity) and still be believed.
STAMP_SLACK = 0.05
#: s a frame's stamp may lie before its receipt (it waited in the socket buffer) and still be believed.
STAMP_MAX_AGE = 1.0
#: consecutive send failures that mean the bus is down (one can be a full transmit queue).
SEND_FAILURES_DOWN = 3
#: frames read in one ``poll`` at most, so a flooded bus cannot hold the driver host's loop.
MAX_FRAMES_PER_POLL = 2000


class CanLinkConfig(Cfg):
    """``[link.can]``: a differential-drive base with one ODrive 0.6 (CANSimple) controller per wheel."""

    interface: Annotated[str, meta("python-can interface: socketcan, virtual, udp_multicast, pcan, ...")] = "socketcan"
    channel: Annotated[str, meta("bus channel: can0, a virtual channel name, a multicast group", min_length=1)] = "can0"
    bitrate: Annotated[int, meta("bit/s (ignored by socketcan: set it with `ip link`)", ge=10_000, le=8_000_000)] = (
        500_000)
    fd: Annotated[bool, meta("CAN FD (udp_multicast needs an explicit false)")] = False
    left_node: Annotated[int, meta("left wheel's CANSimple node id", ge=0, le=63)] = 0
    right_node: Annotated[int, meta("right wheel's CANSimple node id", ge=0, le=63)] = 1
    left_sign: Annotated[float, meta("+1 or -1: -1 for a mirrored motor")] = 1.0
    right_sign: Annotated[float, meta("+1 or -1: -1 for a mirrored motor")] = -1.0
    wheel_radius: Annotated[float, meta("m", gt=0.0, le=10.0)] = 0.1
    track_width: Annotated[float, meta("distance between the wheels, m", gt=0.0, le=100.0)] = 0.4
    initial_pose: Annotated[tuple[Finite, Finite, Finite], meta("odometry origin [x, y, theta]")] = (0.0, 0.0, 0.0)
    open_timeout: Annotated[float, meta("s to wait for both axes in closed loop (at open and after clear_faults)",
                                        gt=0.0, le=120.0)] = 2.0
    heartbeat_timeout: Annotated[float, meta(
        "s without a controller's Heartbeat before the link is reported lost and the other wheel stopped (ODrive sends "
        "one every 0.1 s by default; keep it at or below the controllers' watchdog_timeout)", ge=0.05, le=10.0)] = 0.5
    max_wheel_speed: Annotated[float, meta("rev/s: an encoder estimate faster than this, or a position step it cannot "
                                           "explain, is rejected as implausible", gt=0.0, le=1000.0)] = 5.0
    reopen_backoff: Annotated[float, meta("s before the first attempt to reopen a failed bus; doubles per failed "
                                          "attempt", gt=0.0, le=10.0)] = 0.1
    reopen_backoff_max: Annotated[float, meta("s: the longest wait between two attempts to reopen a failed bus",
                                              gt=0.0, le=60.0)] = 2.0

    def __post_init__(self) -> None:
        if self.reopen_backoff_max < self.reopen_backoff:
            raise Rule(f"reopen_backoff_max = {self.reopen_backoff_max} < reopen_backoff = "
                             f"{self.reopen_backoff}: the longest wait cannot be shorter than the first")
        if self.left_node == self.right_node:
            raise Rule(f"left_node and right_node are both {self.left_node}; each wheel needs its own node")
        for name in ("left_sign", "right_sign"):
            if getattr(self, name) not in (1.0, -1.0):
                raise Rule(f"{name} = {getattr(self, name)}: must be 1 or -1")


_DB: cantools.database.can.Database | None = None


def database() -> cantools.database.can.Database:
    """The shipped CANSimple DBC (loaded once)."""
    global _DB
    if _DB is None:
        import cantools

        text = resources.files("drivers").joinpath("odrive_cansimple.dbc").read_text()
        _DB = cantools.database.load_string(text, database_format="dbc")
    return _DB


def encode(node: int, name: str, signals: dict[str, float] | None = None) -> can.Message:
    """A CANSimple frame for ``node`` (0..63)."""
    import can

    if not 0 <= node < 64:
        raise ValueError(f"CANSimple node id must be 0..63, got {node}")
    msg = database().get_message_by_name(name)
    data = msg.encode(signals or {}) if msg.signals else b""
    return can.Message(arbitration_id=(node << 5) | msg.frame_id, data=data, is_extended_id=False)


def decode(frame: can.Message) -> tuple[int, str, dict[str, Any]]:
    """(node, message name, signals) of a CANSimple frame; ValueError for anything that is not one (wrong length,
    non-finite float, unknown command, extended id, error frame)."""
    if frame.is_extended_id or frame.is_error_frame:
        raise ValueError("not a CANSimple frame (extended id or error frame)")
    node, cmd = frame.arbitration_id >> 5, frame.arbitration_id & 0x1F
    try:
        msg = database().get_message_by_frame_id(cmd)
    except KeyError:
        raise ValueError(f"unknown CANSimple command 0x{cmd:02x}") from None
    if frame.is_remote_frame:
        return node, msg.name, {"_rtr": True}
    if len(frame.data) != msg.length:
        raise ValueError(f"{msg.name}: {len(frame.data)} data bytes, expected {msg.length}")
    sig = msg.decode(bytes(frame.data), decode_choices=False) if msg.signals else {}
    for k, v in sig.items():
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{msg.name}.{k} is not finite")
    return node, msg.name, dict(sig)


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
    sign: float
    state: int = AxisState.UNDEFINED  # from the last Heartbeat
    error: int = 0  # ODriveError word of the last Heartbeat
    procedure_result: int = 0
    heartbeat_at: float | None = None
    fault: bool = False  # latched controller fault (cleared only by clear_faults)
    fault_error: int = 0  # union of the error bits seen since the fault latched
    fault_state: int = AxisState.UNDEFINED  # the state the axis was in when it latched
    commanded: float = 0.0  # rev/s: the last Input_Vel sent to it
    budget: float = 0.0  # rev the encoder may still move (refilled at the plausible wheel speed)
    budget_at: float | None = None  # the stamp the budget was last refilled at
    pos: float | None = None  # rev: the odometry reference (last estimate integrated, or the anchor)
    vel: float = 0.0  # rev/s
    stamp: float | None = None  # of ``pos``
    new: tuple[float, float, float] | None = None  # (pos, vel, stamp) accepted, waiting for the other wheel
    jumps: list[tuple[float, float]] = field(default_factory=list)  # rejected steps in a row: (pos, stamp)

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
    """The CAN link behind the :class:`drivers.base.Driver` protocol (see the module docstring)."""

    name = "can"

    def __init__(self, config: CanLinkConfig) -> None:
        self.config = config
        self.interface, self.channel, self.bitrate = config.interface, config.channel, config.bitrate
        self.radius, self.track = config.wheel_radius, config.track_width
        self.left = _Axis("left", config.left_node, config.left_sign)
        self.right = _Axis("right", config.right_node, config.right_sign)
        self.axes = (self.left, self.right)
        self.open_timeout = config.open_timeout
        self.heartbeat_timeout = config.heartbeat_timeout
        self.max_wheel_speed = config.max_wheel_speed
        self.pose = [float(a) for a in config.initial_pose]
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
        """A person's act: both axes into velocity control and closed loop (see the module docstring)."""
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
                self._zero()
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

    def wheel_turn_rates(self, v: float, omega: float) -> tuple[float, float]:
        """(left, right) Input_Vel in rev/s for body speed v (m/s) and yaw rate omega (rad/s), signs applied."""
        vl = v - omega * self.track / 2.0
        vr = v + omega * self.track / 2.0
        k = 1.0 / (2.0 * math.pi * self.radius)
        return self.left.sign * vl * k, self.right.sign * vr * k

    def send(self, v: float, omega: float, now: float) -> None:
        self._evaluate(now)
        if not self._health.ok:
            self._zero()  # a fault, a lost controller, arming: nothing but zero set-points
            return
        ql, qr = self.wheel_turn_rates(v, omega)
        self.left.commanded, self.right.commanded = ql, qr
        self._send(encode(self.left.node, "Set_Input_Vel", {"Input_Vel": ql, "Input_Torque_FF": 0.0}))
        self._send(encode(self.right.node, "Set_Input_Vel", {"Input_Vel": qr, "Input_Torque_FF": 0.0}))

    def stop(self, now: float) -> None:
        self._zero()

    def _zero(self) -> None:
        """Zero set-points to both axes (holds a healthy wheel in closed loop; harmless to an idle one)."""
        for ax in self.axes:
            ax.commanded = 0.0
            self._send(encode(ax.node, "Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}))

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
        """The frame's own receive stamp on the driver host's monotonic base (see the module docstring)."""
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
                self._zero()  # both wheels, now: not at the driver host's next tick
            ax.fault_error |= ax.error

    def _encoder(self, ax: _Axis, pos: float, vel: float, stamp: float) -> Pose | None:
        """Validate one estimate; integrate one odometry step once both wheels have a new accepted one."""
        if abs(vel) > self.max_wheel_speed or abs(pos) > MAX_ABS_POSITION:
            self._reject()
            return None
        if ax.pos is None or ax.stamp is None:
            ax.pos, ax.vel, ax.stamp = pos, vel, stamp  # the anchor: nothing to integrate yet
            return None
        ref_pos, _, ref_stamp = ax.new if ax.new is not None else (ax.pos, ax.vel, ax.stamp)
        plausible = self._plausible_step(ref_pos, ref_stamp, pos, stamp)
        if not (plausible and self._spend(ax, abs(pos - ref_pos), stamp)):
            self._reject()
            ax.jumps.append((pos, stamp))
            del ax.jumps[:-RESYNC_AFTER]
            if len(ax.jumps) == RESYNC_AFTER and all(
                    self._plausible_step(p0, t0, p1, t1) for (p0, t0), (p1, t1) in zip(ax.jumps, ax.jumps[1:])):
                # the encoder really moved: re-anchor both wheels there, without integrating the step
                self.counters["resyncs"] += 1
                self.rejected_at = -math.inf  # a real move of the encoder, not an implausible one
                ax.pos, ax.vel, ax.stamp, ax.new = pos, vel, stamp, None
                ax.jumps.clear()
                other = self.right if ax is self.left else self.left
                if other.new is not None:
                    other.pos, other.vel, other.stamp = other.new
                    other.new = None
            return None
        ax.jumps.clear()
        ax.new = (pos, vel, stamp)
        if self.left.new is None or self.right.new is None:
            return None
        # both wheels have a new estimate: one odometry step (midpoint heading)
        assert self.left.pos is not None and self.right.pos is not None
        circ = 2.0 * math.pi * self.radius
        (pl, vl_, tl), (pr, vr_, tr) = self.left.new, self.right.new
        dl = (pl - self.left.pos) * circ * self.left.sign
        dr = (pr - self.right.pos) * circ * self.right.sign
        self.left.pos, self.left.vel, self.left.stamp = pl, vl_, tl
        self.right.pos, self.right.vel, self.right.stamp = pr, vr_, tr
        self.left.new = self.right.new = None
        ds = 0.5 * (dl + dr)
        dth = (dr - dl) / self.track
        x, y, th = self.pose
        x += ds * math.cos(th + 0.5 * dth)
        y += ds * math.sin(th + 0.5 * dth)
        th += dth
        self.pose = [x, y, th]
        v = 0.5 * circ * (vl_ * self.left.sign + vr_ * self.right.sign)
        w = circ * (vr_ * self.right.sign - vl_ * self.left.sign) / self.track
        return Pose(max(tl, tr), x, y, th, v, w)

    def _plausible_step(self, p0: float, t0: float, p1: float, t1: float) -> bool:
        return abs(p1 - p0) <= self.max_wheel_speed * (max(t1 - t0, 0.0) + JUMP_SLACK)

    def _spend(self, ax: _Axis, dp: float, stamp: float) -> bool:
        """Whether the wheel may have moved ``dp`` rev by ``stamp``: its travel budget refills at the fastest it can
        turn (twice the commanded rate plus :data:`COMMAND_SLACK_REV_S`, at most ``max_wheel_speed``) and holds at
        most :data:`BURST_S` of it. Many small steps in quick succession (each plausible alone) cannot add up to
        more than the wheel can do, nor can a wheel told to stand still run away."""
        rate = min(self.max_wheel_speed, 2.0 * abs(ax.commanded) + COMMAND_SLACK_REV_S)
        if ax.budget_at is not None:  # a gap between frames allows the gap's worth; a steady stream, BURST_S's
            gap = max(0.0, stamp - ax.budget_at)
            ax.budget = min(rate * max(BURST_S, gap), ax.budget + rate * gap)
        else:
            ax.budget = rate * BURST_S
        ax.budget_at = max(stamp, ax.budget_at or stamp)
        if dp > ax.budget + 1e-9:
            self.overrun_at = time.monotonic()  # more travel than the wheel can do: not cleared by a resync
            return False
        ax.budget -= dp
        return True

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

    def _reasons(self, now: float) -> list[str]:
        """Why the link is not fit to drive at ``now`` (none: it is), from the bus, the latched faults, the
        Heartbeats' age and the arming phase. Pure."""
        reasons: list[str] = []
        if self._phase == "idle":
            reasons.append("axes idle: not engaged")
        if self.bus is None:
            reasons.append(f"CAN bus down ({self._down_reason}); reopening in {max(0.0, self._reopen_at - now):.2f} s")
        if self._phase == "arming":
            reasons.append("arming: waiting for both axes in closed loop")
        reasons += [ax.describe() for ax in self.axes if ax.fault]
        if now - max(self.rejected_at, self.overrun_at) < ODOMETRY_ALARM_S:
            reasons.append(f"odometry: implausible encoder estimates rejected ({self.counters['rejected_estimates']} "
                           "so far): a faulty encoder or forged frames")
        if self._phase == "running":
            for ax in self.axes:
                if self._heartbeat_lost(ax, now):
                    age = "" if ax.heartbeat_at is None else f" for {now - ax.heartbeat_at:.2f} s"
                    reasons.append(f"{ax.side} controller (node {ax.node}): no heartbeat{age}")
        return reasons

    def _evaluate(self, now: float) -> None:
        """Advance the state to ``now`` and set ``ok`` and ``text`` from it."""
        h = self._health
        if self._phase == "closed":
            h.ok = False
            return
        self._advance(now)
        reasons = self._reasons(now)
        h.ok = not reasons
        h.text = "; ".join(reasons) if reasons else "ready"

    def health(self, now: float) -> LinkHealth:
        h = self._health
        if self._phase == "closed":
            ok, text = False, h.text
        else:
            reasons = self._reasons(now)
            ok, text = not reasons, "; ".join(reasons) if reasons else "ready"
        left, right = (AxisHealth(node=ax.node, state=state_name(ax.state), error=ax.error,
                                  errors=tuple(error_names(ax.error)), procedure_result=ax.procedure_result,
                                  heartbeat_age=None if ax.heartbeat_at is None else now - ax.heartbeat_at,
                                  fault=ax.fault) for ax in self.axes)
        return replace(h, ok=ok, text=text, detail=CanHealthDetail(CanCounters(**self.counters), left, right))

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
            self._health.text = "closed"
            return
        try:
            t_end = time.monotonic() + stop_timeout
            turns = stop_speed / (2.0 * math.pi * self.radius)  # rev/s of a wheel at stop_speed
            while self._phase == "running" and time.monotonic() < t_end:  # zero until both wheels have stopped
                self.stop(0.0)
                self.poll(time.monotonic(), block=0.02)
                if all(abs(ax.vel) < turns for ax in self.axes):
                    break
            self.stop(0.0)
            for ax in self.axes:
                self._send(encode(ax.node, "Set_Axis_State", {"Axis_Requested_State": AxisState.IDLE}))
        finally:
            if self.bus is not None:
                with contextlib.suppress(Exception):
                    self.bus.shutdown()
            self.bus = None
            self._phase = "closed"
            self._health.connected = self._health.ok = False
            self._health.text = "closed"


#: the link's plugin entry (``drivers.LINKS``): its ``[link.can]`` section, its driver, and whether ``scmbridge
#: learner`` emulates it (the two ODrive controllers, :mod:`sim_learner.can_ecu`)
CONFIG = CanLinkConfig
DRIVER = CanDriver
EMULATED = True
