"""The CAN bus supervisor: a differential-drive base with one ODrive 0.6 controller per wheel behind the
:class:`drivers.base.Driver` protocol. It owns the python-can bus (opened, failed, reopened with a backoff), turns
frames into the axis state machine's inputs (:mod:`.axis`, pure) and the odometry's (:mod:`.odometry`, pure), and puts
on the bus the frames they ask for, encoded by :mod:`.codec`. Its frame is :class:`drivers.base.LinkBase`: the tick's
methods work at the ``now`` they are given, its bounded waits move the time by its clock's ``wait``, and two
measurements read that clock (see :class:`CanDriver`), so its tests run on a fake clock."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from bridge.core.backoff import Backoff
from bridge.core.clock import HeldOffset
from drivers.base import SYSTEM, Clock, DriverError, FailsafeReport, LinkBase, LinkHealth, Pose, Verdict, whole_numbers
from drivers.can.axis import Axes, Axis, AxisHealth, Frame, Reason, verdict
from drivers.can.codec import decode, encode
from drivers.can.config import CanLinkConfig
from drivers.can.odometry import Odometry, Wheel

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
#: s between zero set-points fed to the controllers' watchdogs while the axes come up (engage)
ARM_FEED_S = 0.05
#: s a bounded wait (open, engage, close) lets pass between two reads of the bus
WAIT_READ_S = 0.02


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
class CanHealthDetail:
    """The CAN link's detail in :class:`drivers.base.LinkHealth`."""

    counters: CanCounters
    left: AxisHealth
    right: AxisHealth

    def status_counters(self) -> dict[str, int]:
        return whole_numbers(self.counters)


class CanDriver(LinkBase):
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

    **Supervision** (in ``poll`` and ``send``; ``health`` reports it and changes nothing). The controllers' part is
    the pure :class:`drivers.can.axis.Axes`; this class adds the bus and the odometry:

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
    python-can fills on receive with the wall clock (Python's ``time`` function) for ``virtual`` and
    ``udp_multicast``, the kernel's receive time for ``socketcan``), mapped by each ``poll`` onto the driver host's
    clock (``clock``) with the offset ``clock() - clock.wall()``, read in a bracket (:meth:`_offset`). A stamp that
    is missing, in the future of its receipt (beyond :data:`STAMP_SLACK`) or older than :data:`STAMP_MAX_AGE` (a
    wall-clock step, NTP) is replaced by the receive time and counted (``stamp_fallbacks``). Frames read by a
    ``poll`` were received by its ``now``.

    **Time.** ``poll``, ``send``, ``stop``, ``health``, ``open`` and ``engage`` work at the ``now`` they are given;
    ``open``, ``engage`` and ``close`` wait between two reads of the bus with the clock's ``wait``
    (:meth:`LinkBase._pause`); ``close`` starts at the host's ``now`` where it is given one. The
    clock is read for two measurements a tick's ``now`` cannot give: the moment frames left (a host preempted after
    ``now`` wrote them later: the odometry counts the old command in force until then) and, with ``clock.wall`` at
    once, the offset that maps python-can's wall-clock stamps onto it.

    ``open_bus`` (default: ``can.Bus`` from the configuration) builds the bus at open and at each reopen: a test hands
    in its own python-can bus, as python-can's ``BusABC`` lets any interface stand in.
    """

    name = "can"
    COUNTERS = CanCounters
    COUNTED_ELSEWHERE = ("faults", "heartbeat_losses")  # the axes' (drivers.can.axis.Axes)

    def __init__(self, config: CanLinkConfig, *, clock: Clock = SYSTEM,
                 open_bus: Callable[[], can.BusABC] | None = None) -> None:
        super().__init__(clock)
        self.config = config
        self.interface, self.channel = config.interface, config.channel  # the bus it opens, for people to read
        self.left = Axis("left", config.left_node, Wheel(config.left_sign))
        self.right = Axis("right", config.right_node, Wheel(config.right_sign))
        self.axes = Axes(self.left, self.right, config.open_timeout, config.heartbeat_timeout)
        self.odometry = Odometry(config.wheel_radius, config.track_width, config.max_wheel_speed, self.left.wheel,
                                 self.right.wheel, config.initial_pose)
        self.open_timeout = config.open_timeout
        self.bus: can.BusABC | None = None
        self._bus_factory = open_bus
        self._down_reason: str | None = None
        self._reopen_at = 0.0
        self._backoff = Backoff(config.reopen_backoff, config.reopen_backoff_max)
        self._send_failures = 0
        self.rejected_at = -math.inf  # when the last implausible estimate was rejected
        self.overrun_at = -math.inf  # when estimates last claimed more travel than the wheel can do
        self._wall_offset = HeldOffset()  # wall clock minus host clock (:meth:`_offset`)

    @property
    def counters(self) -> dict[str, int]:
        """Every count of :class:`CanCounters` by name (a copy): the bus's and odometry's, and the axes'."""
        return {**self.counts, "faults": self.axes.faults, "heartbeat_losses": self.axes.heartbeat_losses}

    # ----------------------------------------------------------------------------------------------- link
    def _open_bus(self) -> can.BusABC:
        if self._bus_factory is not None:
            return self._bus_factory()
        import can

        c = self.config
        kwargs: dict[str, Any] = {"interface": c.interface, "channel": c.channel}
        if c.interface == "socketcan":
            pass  # the bitrate of a SocketCAN device is set with `ip link`, not here
        elif c.interface == "udp_multicast":
            kwargs["fd"] = self.config.fd
        else:
            kwargs["bitrate"] = c.bitrate
        return can.Bus(**kwargs)

    def open(self, now: float) -> None:
        import can

        try:
            self.bus = self._open_bus()
        except (can.CanError, OSError, ValueError) as exc:
            raise DriverError(f"cannot open CAN bus {self.config.interface}:{self.config.channel}: {exc}") from exc
        self._health.connected = True
        self.axes.phase = "idle"
        self._changed()
        self._listen(now, now + min(self.open_timeout, 1.0))  # the controllers' Heartbeats say how they are

    def _listen(self, now: float, t_end: float) -> float:
        """Read the bus until both controllers were heard or ``t_end``; the time then."""
        self.poll(now)
        while now < t_end and not self.axes.heard():
            now = self._pause(WAIT_READ_S)
            self.poll(now)
        return now

    def engage(self, now: float, clear_faults: bool = False) -> None:
        """A person's act: both axes into velocity control and closed loop (see the class docstring)."""
        if self.bus is None or self.axes.phase == "closed":
            raise DriverError(f"CAN bus {self.config.interface}:{self.config.channel} not open")
        t = self._listen(now, now + self.open_timeout)
        refusal = self.axes.engage_refusal(clear_faults)
        if refusal is not None:
            raise DriverError(refusal)
        self._put(self.axes.arm(t, every_axis=True), t)
        t_feed = -math.inf
        while True:
            if t >= t_feed:  # the watchdogs count from arming: feed them while the axes come up
                self._zero(t)
                t_feed = t + ARM_FEED_S
            self.poll(t)
            if self.axes.phase == "running":
                if self._health.ok:
                    return
                raise DriverError(f"motor controllers not ready after {self.open_timeout} s: {self._health.text}")
            t = self._pause(WAIT_READ_S)

    def failsafe(self) -> FailsafeReport:
        return FailsafeReport(drive_on_s=None, text=(
            "if the host dies each ODrive drives on until its own watchdog trips (axis.config.enable_watchdog, "
            "watchdog_timeout: off by default; CANSimple 0.6 cannot read it: check it with odrivetool)"))

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
        self._send(encode(self.left.node, "Set_Input_Vel", {"Input_Vel": ql, "Input_Torque_FF": 0.0}), now)
        self._send(encode(self.right.node, "Set_Input_Vel", {"Input_Vel": qr, "Input_Torque_FF": 0.0}), now)
        sent = self.clock()  # a measurement: a host preempted since ``now`` wrote the frames only now
        self.odometry.command(self.left.wheel, ql, now, sent)
        self.odometry.command(self.right.wheel, qr, now, sent)

    def stop(self, now: float) -> None:
        self._zero(now)

    def _zero(self, now: float) -> None:
        """Zero set-points to both axes at ``now`` (holds a healthy wheel in closed loop; harmless to an idle one)."""
        self._put(self.axes.zero(), now)
        sent = self.clock()  # a measurement, as in send
        for ax in self.axes:
            self.odometry.command(ax.wheel, 0.0, now, sent)

    # ----------------------------------------------------------------------------------------------- receive
    def poll(self, now: float) -> list[Pose]:
        import can

        out: list[Pose] = []
        if self.bus is None and self.axes.phase != "closed" and now >= self._reopen_at:
            self._reopen(now)
        if self.bus is not None:
            offset = self._offset()
            read = False
            for _ in range(MAX_FRAMES_PER_POLL):
                try:
                    frame = self.bus.recv(timeout=0.0)
                except (can.CanError, OSError) as exc:
                    self._bus_failed(f"receive failed: {exc}", now)
                    break
                if frame is None:
                    break
                read = True
                pose = self._frame(frame, now, offset, now)
                if pose is not None:
                    out.append(pose)
                if self.bus is None:  # a bus-off error frame
                    break
            if read:  # what the frames said is judged afresh
                self._changed()
        self._evaluate(now)
        return out

    def _offset(self) -> float:
        """A measurement: what maps python-can's wall-clock stamps onto the host's clock (host minus wall). Two
        reads one after the other are off by however long the thread waited between them: a poll's poses are then
        all stamped that much early, and one the vehicle seems to reach too fast for its stamp is dropped by the
        station as implausible. So the reads are bracketed, and a poll whose bracket stayed wide keeps the last tight
        one (:class:`bridge.core.clock.HeldOffset`; a step of the wall clock makes stamps implausible, which fall back
        to the receipt time, until the next tight read)."""
        return -self._wall_offset.read(self.clock, self.clock.wall)

    def _frame(self, frame: can.Message, received: float, offset: float, now: float) -> Pose | None:
        self._health.frames_received += 1
        if frame.is_error_frame:
            self._health.errors += 1
            self.counts["error_frames"] += 1
            if frame.arbitration_id & CAN_ERR_BUSOFF:
                self._bus_failed("bus-off (error frame)", now)
            return None
        try:
            node, name, sig = decode(frame)
        except ValueError:
            self._health.malformed += 1
            return None
        ax = self.axes.by_node(node)
        if ax is None or sig.get("_rtr"):
            return None  # another device on the bus, or a request
        stamp = self._stamp(frame, received, offset)
        if name == "Heartbeat":
            self._backoff.reset()  # the bus carries the controllers' frames again
            if self.axes.heartbeat(ax, sig["Axis_State"], sig["Axis_Error"], sig["Procedure_Result"], stamp):
                self._zero(stamp)  # both wheels, now: not at the driver host's next tick
        elif name == "Get_Encoder_Estimates":
            return self._encoder(ax, float(sig["Pos_Estimate"]), float(sig["Vel_Estimate"]), stamp, now)
        return None

    def _stamp(self, frame: can.Message, received: float, offset: float) -> float:
        """The frame's own receive stamp on the driver host's clock (see the class docstring)."""
        ts = frame.timestamp
        if ts and math.isfinite(ts):
            mono = ts + offset
            if received - STAMP_MAX_AGE <= mono <= received + STAMP_SLACK:
                return min(mono, received)
        self.counts["stamp_fallbacks"] += 1
        return received

    def _encoder(self, ax: Axis, pos: float, vel: float, stamp: float, now: float) -> Pose | None:
        """One encoder estimate into the odometry (:class:`drivers.can.odometry.Odometry`); a rejected one is counted
        and keeps ``health()`` not ok for :data:`ODOMETRY_ALARM_S` (from the ``poll`` that read it) with the reason."""
        step = self.odometry.estimate(ax.wheel, pos, vel, stamp)
        if step.overrun:
            self.overrun_at = now  # more travel than the wheel can do: not cleared by a resync
        if step.rejected:
            self._health.malformed += 1
            self.counts["rejected_estimates"] += 1
            self.rejected_at = now
        if step.resynced:
            self.counts["resyncs"] += 1
            self.rejected_at = -math.inf  # a real move of the encoder, not an implausible one
        return step.pose

    # ----------------------------------------------------------------------------------------------- bus
    def _put(self, frames: list[Frame], now: float) -> None:
        """Encode and send what the axis state machine asks for."""
        for node, name, signals in frames:
            self._send(encode(node, name, signals), now)

    def _send(self, frame: can.Message, now: float) -> bool:
        import can

        if self.bus is None:
            return False
        try:
            self.bus.send(frame, timeout=0.05)
        except (can.CanError, OSError) as exc:
            self._health.errors += 1
            self.counts["send_failures"] += 1
            self._send_failures += 1
            if self._send_failures >= SEND_FAILURES_DOWN:
                self._bus_failed(f"send failed: {exc}", now)
            return False
        self._health.frames_sent += 1
        self._send_failures = 0
        return True

    def _bus_failed(self, reason: str, now: float) -> None:
        """Release the bus and schedule a reopen (backoff doubles per failed attempt, up to its bound)."""
        self.counts["bus_failures"] += 1
        self._health.errors += 1
        bus, self.bus = self.bus, None
        if bus is not None:
            with contextlib.suppress(Exception):
                bus.shutdown()
        self._health.connected = False
        self._down_reason = reason
        self._send_failures = 0
        self._reopen_at = now + self._backoff.delay
        self._changed()

    def _reopen(self, now: float) -> None:
        import can

        try:
            self.bus = self._open_bus()
        except (can.CanError, OSError, ValueError) as exc:
            self._down_reason = f"reopen failed: {exc}"
            self._backoff.grow()
            self._reopen_at = now + self._backoff.delay
            return
        self.counts["reopens"] += 1
        self._health.connected = True
        self._down_reason = None
        self._changed()
        # until a controller's frame arrives on the new bus, the next failure waits longer
        self._backoff.grow()

    # ----------------------------------------------------------------------------------------------- state
    def _reasons(self, now: float) -> list[Reason]:
        """Why the link is not fit to drive at ``now``: the axes' reasons with the bus's and the odometry's. Pure."""
        down = None
        if self.bus is None:
            down = f"CAN bus down ({self._down_reason}); reopening in {max(0.0, self._reopen_at - now):.2f} s"
        odometry = None
        if now - max(self.rejected_at, self.overrun_at) < ODOMETRY_ALARM_S:
            odometry = (f"odometry: implausible encoder estimates rejected ({self.counts['rejected_estimates']} so "
                        "far): a faulty encoder or forged frames")
        return self.axes.reasons(now, down, odometry)

    def _judge_link(self, now: float) -> Verdict:
        return verdict(self._reasons(now))

    def _evaluate(self, now: float) -> None:
        """Advance the state to ``now`` and set ``ok``, ``reason`` and ``text`` from it (judged once per moment and
        change: :meth:`LinkBase._verdict`)."""
        h = self._health
        if self.axes.phase == "closed":
            h.ok = False
            return
        if self.axes.advance(now):
            self._changed()
        h.ok, h.reason, h.text = self._verdict(now)

    def health(self, now: float) -> LinkHealth:
        h = self._health
        if self.axes.phase == "closed":
            ok, reason, text = False, h.reason, h.text
        else:
            ok, reason, text = self._verdict(now)
        return replace(h, ok=ok, reason=reason, text=text, detail=CanHealthDetail(
            CanCounters(**self.counters), self.left.health(now), self.right.health(now)))

    def clear_faults(self, now: float) -> None:
        """The operator's act: Clear_Errors to both controllers, velocity control again, zero set-point, closed loop
        for an axis that is not in it. Returns at once; ``ok`` comes back when both Heartbeats confirm (at most
        ``open_timeout``), else the axis that did not re-arm is a latched fault again."""
        if self.axes.phase == "closed" or self.bus is None:
            return  # nothing reachable: the text still says why
        if self.axes.phase == "idle":  # not engaged: clear the errors, never arm (engage does that)
            self._put(self.axes.clear(), now)
            return
        self._put(self.axes.arm(now, every_axis=False), now)
        self._changed()
        self._evaluate(now)

    def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0,
              now: float | None = None) -> None:
        try:
            # a link that never armed the axes (not engaged, a dry run, a half-open link let go) sends nothing: the
            # controllers are someone else's to command; one that did stops them, waits until the wheels have
            # stopped, and only with ``disarm`` puts them in IDLE
            if self.bus is not None and self.axes.phase == "running":
                now = self.clock() if now is None else now  # (a caller without a tick: read once), then the waits
                self._stop_until_still(now, stop_speed, stop_timeout, WAIT_READ_S, self._wheel_speed)
                if disarm:
                    self._put(self.axes.idle(), now)
        finally:
            if self.bus is not None:
                with contextlib.suppress(Exception):
                    self.bus.shutdown()
            self.bus = None
            self.axes.phase = "closed"
            self._closed_health()

    def _wheel_speed(self, now: float) -> float:
        """Read the bus at ``now``; the faster wheel's rim speed it reports, m/s (closing waits for it)."""
        self.poll(now)
        return max(abs(ax.wheel.vel) for ax in self.axes) * 2.0 * math.pi * self.config.wheel_radius
