"""The MAVLink driver: an ArduPilot Rover in GUIDED mode behind the :class:`drivers.base.Driver` protocol, wiring
the connection and its command protocol (:mod:`.client`), the vehicle's state and the pure decisions on it
(:mod:`.state`: the judgement, its changes, set-point pacing, the failsafe report) and the pose builder (:mod:`.pose`).
The operator always wins: only :meth:`MavlinkDriver.engage`, a person's act, selects GUIDED and arms. It works at the
``now`` it is given and its waits' clock (:class:`drivers.base.LinkBase`), so its tests run on a fake clock."""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

from bridge.core.auth import load_key
from bridge.core.clock import ClockOffset
from drivers.base import SYSTEM, Clock, DriverError, FailsafeReport, LinkBase, LinkHealth, Pose, whole_numbers
from drivers.mavlink.client import NO_ACK, Command, MavlinkClient, result_name
from drivers.mavlink.config import MavlinkLinkConfig
from drivers.mavlink.dialect import load_pymavlink
from drivers.mavlink.fence import FENCE_MESSAGES
from drivers.mavlink.fence import upload as upload_fence
from drivers.mavlink.pose import Attitude, PoseBuilder, Position, ground_speed, telemetry_valid
from drivers.mavlink.state import (
    FAILSAFE_PARAMS,
    NOT_OPENED,
    LinkView,
    SetpointPacer,
    Vehicle,
    Verdict,
    change,
    failsafe_report,
    judge,
    position_fresh,
)

log = logging.getLogger("scmbridge.driver.mavlink")

#: s a refusal waits, at most, for the STATUSTEXT that explains it (ArduPilot sends it after the COMMAND_ACK)
REFUSAL_TEXT_WAIT_S = 0.5
#: s between two tries of a mode change or an arming the vehicle refused (pre-arm checks can clear)
RETRY_AFTER_S = 1.0
#: s a GUIDED the vehicle accepted has to show in its HEARTBEAT
MODE_CONFIRM_S = 2.5
#: s the failsafe parameters have, at most, to answer at open
PARAMS_WAIT_S = 2.0
#: s between two zero set-points while ``close`` waits for the vehicle to stop
CLOSE_PERIOD_S = 0.05
#: SET_POSITION_TARGET_LOCAL_NED's type_mask for "Use Vel+Yaw Rate" (ArduPilot's "Rover Commands in Guided Mode")
TYPE_MASK_VEL_YAWRATE = 0x05E7


@dataclass(frozen=True, slots=True)
class MavlinkHealthDetail:
    """The MAVLink link's detail in :class:`drivers.base.LinkHealth`: the vehicle as it last reported itself, and the
    link's counts."""

    mode: str  # the Rover mode's name ("GUIDED", "HOLD"; "unknown" before the first HEARTBEAT)
    custom_mode: int | None
    armed: bool
    heartbeat_age: float | None  # s since the last HEARTBEAT
    position_age: float | None  # s since the last LOCAL_POSITION_NED
    statustexts: tuple[str, ...]  # the last STATUSTEXTs, oldest first
    last_refusal: str  # the last command the vehicle refused, in words
    bad_signatures: int  # messages refused by MAVLink 2 signing
    foreign_ids: tuple[tuple[int, int], ...]  # (system, component) of the last foreign senders
    foreign: int = 0  # messages from another system or component, dropped
    setpoints_sent: int = 0
    setpoints_withheld: int = 0  # send() while the vehicle does not accept set-points
    setpoints_deferred: int = 0  # a changed command held back by max_setpoint_hz
    stray_acks: int = 0  # COMMAND_ACKs for no command in flight
    reconnects: int = 0
    link_losses: int = 0
    invalid_values: int = 0  # telemetry outside what a vehicle can send, dropped
    clock_restarts: int = 0  # the vehicle-clock offset estimate restarted

    def status_counters(self) -> dict[str, int]:
        return whole_numbers(self)


class MavlinkDriver(LinkBase):
    """The MAVLink link (pymavlink, MAVLink 2, ardupilotmega).

    ``open()`` never changes the vehicle's mode nor arms it (a restarted driver host must not take a vehicle back
    from the operator); :meth:`engage` is the only place this driver selects GUIDED and arms, reading every
    COMMAND_ACK. When the vehicle leaves GUIDED (an RC mode switch, a failsafe) the driver stops sending set-points
    and says so in :meth:`health` (``ok`` False, ``"operator took control: mode HOLD"``); it drives again only when
    the operator has put the vehicle back in GUIDED (and armed), with no action on our side.

    Every message is filtered by the vehicle's system and component ids; the others are counted (``detail.foreign``).
    Signing (``signing_key_file``, made by ``scmbridge keys mavlink``; the autopilot gets the same key through
    SETUP_SIGNING): MAVLink 2 message signing as ArduPilot implements it (libraries/GCS_MAVLink/GCS_Signing.cpp):
    every message this driver sends is signed, and an unsigned or badly signed message, or one whose signature
    timestamp goes back, is refused (``health(now).detail.bad_signatures``).

    Time (:class:`drivers.base.LinkBase`): ``poll``, ``send``, ``stop``, ``health``, ``open`` and ``engage`` work at
    the ``now`` they are given; the bounded waits of ``open``, ``engage`` and ``close`` go through the client
    (:meth:`drivers.mavlink.client.MavlinkClient.wait`: reads block on the connection in real time, its ``clock``
    says when they returned) and, without a connection, the clock's ``wait``. The vehicle is judged once per moment
    and change (:meth:`LinkBase._verdict`).

    Supervision: no HEARTBEAT for ``heartbeat_timeout`` -> ``connected`` and ``ok`` False, ``"no heartbeat for 3.2
    s"``; a connection that failed (TCP EOF, a serial error) is re-opened with backoff, UDP just keeps listening.
    When heartbeats return the message intervals are asked again (a rebooted autopilot forgot them) and ``ok`` comes
    back only if the vehicle is GUIDED and armed. STATUSTEXTs are logged and the last ``statustext_keep`` are in
    ``health(now).detail.statustexts``.
    """

    name = "mavlink"
    COUNTERS = MavlinkHealthDetail
    COUNTED_ELSEWHERE = ("setpoints_deferred",)  # the pacer's
    #: the operator putting the vehicle in GUIDED and arming it, seen while the host runs, is a person's engage
    operator_engages = True

    def __init__(self, config: MavlinkLinkConfig, *, clock: Clock = SYSTEM) -> None:
        super().__init__(clock)
        self.dialect = load_pymavlink()
        self.config = config
        self.target = (config.target_system, config.target_component)
        self.vehicle = Vehicle(texts=deque(maxlen=config.statustext_keep))
        self.poses = PoseBuilder()
        self.fence_sink: Any = None  # while a fence is uploaded: where its messages go (drivers.mavlink.fence)
        self.client = MavlinkClient(config, self.dialect, self._health, self.counts,
                                    on_message=lambda msg: self._handle(msg, [], self.client.now),
                                    clock=clock)
        self._t0 = clock()
        self._opened = False  # open() succeeded: from now on the mode and arming are the operator's
        self._closed = False
        self._changed()
        self._pacer = SetpointPacer(1.0 / config.setpoint_rate_hz, 1.0 / config.max_setpoint_hz)
        self._link_up = False
        self._state: Verdict = NOT_OPENED
        self._foreign_ids: deque[tuple[int, int]] = deque(maxlen=8)
        self._clock = ClockOffset(config.clock_window_s)  # the vehicle's time_boot_ms -> our monotonic clock
        self._last_refusal = ""
        self.params: dict[str, float] = {}  # the failsafe parameters the vehicle reported at open
        self._last_position: Position | None = None
        self._last_position_time = -math.inf

    # ------------------------------------------------------------------------------------------ properties
    @property
    def _modes(self) -> Any:
        """pymavlink's Rover mode table (the dialect's)."""
        return self.dialect.modes

    @property
    def custom_mode(self) -> int | None:
        return self.vehicle.custom_mode

    @property
    def armed(self) -> bool:
        return self.vehicle.armed

    @property
    def statustexts(self) -> list[str]:
        """The vehicle's last STATUSTEXTs (at most ``statustext_keep``), oldest first."""
        return [t for _, t in self.vehicle.texts]

    # -------------------------------------------------------------------------------------------- receive
    def _pump(self, now: float) -> list[Pose]:
        """Read what arrived by ``now`` (without waiting); update the vehicle's state."""
        out: list[Pose] = []
        self.client.receive(0.0, lambda msg: self._handle(msg, out, now))
        return out

    def _handle(self, msg: Any, out: list[Pose], now: float) -> None:
        """One message, received by ``now`` (a tick's, or the time a wait read it at)."""
        self._changed()
        t = msg.get_type()
        if t == "BAD_DATA":
            self._health.malformed += 1
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src != self.target:  # another vehicle, another ground station, a camera: not ours
            self._health.frames_received += 1
            self.counts["foreign"] += 1
            if src not in self._foreign_ids:
                self._foreign_ids.append(src)
            return
        if not telemetry_valid(msg):  # a NaN yaw would end in math.cos(): the receive loop, and the link, would die
            self._health.malformed += 1
            self.counts["invalid_values"] += 1
            return
        self._health.frames_received += 1
        v = self.vehicle
        mav = self.dialect.mav
        if self.fence_sink is not None and t in FENCE_MESSAGES:
            self.fence_sink(msg)
        if t == "HEARTBEAT":
            v.heard(msg.custom_mode, bool(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED), now, self._modes.guided)
        elif t == "LOCAL_POSITION_NED":
            self._boot_ms(msg.time_boot_ms)
            v.pos_time = now
            # stamped at the vehicle's own time of the sample, on our clock (docs/ARCHITECTURE.md, section 4)
            stamp, steady = self._clock.restamp_checked(msg.time_boot_ms / 1000.0, now)
            self.counts["clock_restarts"] += not steady
            p = Position(int(msg.time_boot_ms), stamp, float(msg.x), float(msg.y), float(msg.vx), float(msg.vy))
            self._last_position, self._last_position_time = p, now
            out += self.poses.position(p)
        elif t == "ATTITUDE":
            self._boot_ms(msg.time_boot_ms)
            out += self.poses.attitude(Attitude(int(msg.time_boot_ms), float(msg.yaw), float(msg.yawspeed)))
        elif t == "COMMAND_ACK":
            self.client.ack(msg)
        elif t == "PARAM_VALUE":
            name = str(msg.param_id).rstrip("\x00")
            if name in FAILSAFE_PARAMS and math.isfinite(msg.param_value):
                self.params[name] = float(msg.param_value)
        elif t == "STATUSTEXT":
            text = "".join(c if c.isprintable() else "\ufffd" for c in str(msg.text).rstrip("\x00"))  # for logs
            v.texts.append((now, text))
            v.text_count += 1
            sev = int(msg.severity)
            level = (logging.ERROR if sev <= mav.MAV_SEVERITY_ERROR else logging.WARNING
                     if sev == mav.MAV_SEVERITY_WARNING else logging.INFO if sev < mav.MAV_SEVERITY_DEBUG
                     else logging.DEBUG)
            log.log(level, "vehicle: %s", text)

    def _boot_ms(self, boot_ms: int) -> None:
        """A vehicle clock that went back (:meth:`Vehicle.boot`): it rebooted and forgot our message intervals."""
        was = self.vehicle.boot_ms
        if self.vehicle.boot(boot_ms):
            log.warning("the vehicle rebooted (time since boot %d ms, was %d ms)", boot_ms, was)
            self._clock.reset()  # a new vehicle clock: forget the old offset
            self.poses.reset()  # times of the old clock
            self._request_streams()

    # -------------------------------------------------------------------------------------------- commands
    def _refusal(self, what: str, result: int, since: float, wait_text: bool = True) -> str:
        """``"arming refused: MAV_RESULT_FAILED (PreArm: ...)"``, waiting briefly (``wait_text``, in blocking
        calls only) for the STATUSTEXT that explains it: ArduPilot sends it after the ACK (its text queue)."""
        texts = self.vehicle.said_since(since)
        if wait_text and not texts and result != NO_ACK:
            n = self.vehicle.text_count
            self.client.wait(lambda: self.vehicle.text_count != n,
                             self.client.now + min(REFUSAL_TEXT_WAIT_S, self.config.ack_timeout))
            texts = self.vehicle.said_since(since)
        text = f"{what} refused: {result_name(result)}" + (f" ({'; '.join(texts)})" if texts else "")
        self._last_refusal = text
        log.warning("%s", text)
        return text

    def _request_streams(self) -> None:
        """Ask for LOCAL_POSITION_NED and ATTITUDE at ``rate_hz`` (MAV_CMD_SET_MESSAGE_INTERVAL; non-blocking,
        refusals are logged)."""
        mav = self.dialect.mav
        period_us = 1e6 / self.config.rate_hz
        for mid, name in ((mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, "LOCAL_POSITION_NED"),
                          (mav.MAVLINK_MSG_ID_ATTITUDE, "ATTITUDE")):
            if self.client.in_flight(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mid):
                continue

            def done(c: Command) -> None:
                if c.result != mav.MAV_RESULT_ACCEPTED:
                    self._refusal(c.what, c.result if c.result is not None else NO_ACK, c.first_sent, False)

            self.client.submit(mav.MAV_CMD_SET_MESSAGE_INTERVAL, (mid, period_us), f"{name} interval", done)

    # ------------------------------------------------------------------------------------------------ open
    def open(self, now: float) -> None:
        """Connect, wait for the vehicle to be ready and read its failsafe settings; never its mode nor arming.
        Bounded by ``open_timeout``:

        1. connect (a TCP or serial connection that fails is tried again with backoff) and wait for a HEARTBEAT from
           ``target_system``/``target_component`` whose mode is not INITIALISING;
        2. ask for LOCAL_POSITION_NED and ATTITUDE at ``rate_hz`` (MAV_CMD_SET_MESSAGE_INTERVAL);
        3. wait until LOCAL_POSITION_NED streams. This is the readiness test: ArduPilot sends LOCAL_POSITION_NED only
           once its EKF has an origin (GCS_Common.cpp ``send_local_position``), and it silently ignores every
           set-point until then (Rover/GCS_Mavlink.cpp ``handle_set_position_target_local_ned``: "need ekf origin").
           A rover without GPS can have a position estimate, pass its arming checks and accept GUIDED, and still
           ignore us: commands would be "applied" while it does not move;

        then the failsafe parameters (PARAM_REQUEST_READ / PARAM_VALUE), reported by :meth:`failsafe`."""
        client = self.client
        client.now = now
        t_end = now + self.config.open_timeout
        self._closed = False
        self._changed()
        if self.config.signing_key_file:
            client.signing_key = load_key(self.config.signing_key_file, "mavlink")
        while client.conn is None:
            try:
                client.connect(now)
            except Exception as exc:  # pymavlink raises plain OSError/SerialException/...
                if now + client.backoff.delay > t_end:
                    raise DriverError(f"cannot open MAVLink connection {self.config.url}: {exc}") from exc
                now = client.now = self._pause(client.backoff.delay)
                client.backoff.grow()
        client.heartbeat(now, force=True)
        v = self.vehicle
        if not client.wait(lambda: v.hb_time is not None and v.custom_mode != self._modes.initialising, t_end):
            if v.hb_time is None:
                others = f" (heard other systems: {sorted(set(self._foreign_ids))})" if self._foreign_ids else ""
                raise DriverError(f"no HEARTBEAT from system {self.target[0]} component {self.target[1]} on "
                                  f"{self.config.url} within {self.config.open_timeout} s{others}")
            raise DriverError(f"the vehicle is still initialising after {self.config.open_timeout} s")
        client.backoff.reset()
        self._request_streams()
        fresh = self.config.position_timeout
        if not client.wait(lambda: position_fresh(v, client.now, fresh) and self.poses.att is not None, t_end):
            raise DriverError(f"vehicle position not ready within {self.config.open_timeout} s: no LOCAL_POSITION_NED "
                              f"(ArduPilot sends it only once its EKF has an origin){self.vehicle.note()}")
        self._read_params(FAILSAFE_PARAMS, min(t_end, client.now + PARAMS_WAIT_S))
        self._opened = True
        self._changed()
        self._link_up = True
        self._update_state(client.now)
        log.info("vehicle on %s: mode %s, %s, position streaming; %s", self.config.url, self._modes.name(v.custom_mode),
                 "armed" if v.armed else "disarmed", self.failsafe().text)

    def engage(self, now: float, clear_faults: bool = False) -> None:
        """A person's act, bounded by ``open_timeout``: raises :class:`DriverError` with the vehicle's own reason
        when it refuses.

        4. MAV_CMD_DO_SET_MODE GUIDED (custom mode from pymavlink's Rover table), confirmed by a HEARTBEAT (a mode set
           while the vehicle boots is acknowledged and then lost);
        5. MAV_CMD_COMPONENT_ARM_DISARM (ArduPilot acks it only once armed); a refusal is retried until the timeout
           (pre-arm checks can clear), and reported with the vehicle's own explanation: ``"arming refused:
           MAV_RESULT_FAILED (PreArm: Hardware safety switch)"``."""
        if self._closed or not self._opened:
            raise DriverError("MAVLink link not open")
        self.client.now = max(self.client.now, now)
        t_end = now + self.config.open_timeout
        self._enter_guided(t_end)
        self._arm(t_end)
        mode = self.vehicle.custom_mode
        if mode != self._modes.guided:
            raise DriverError(f"operator took control while engaging: mode {self._modes.name(mode)}")
        self._update_state(self.client.now)
        log.info("vehicle engaged: GUIDED, armed")

    def upload_fence(self, polygon: list[tuple[float, float]]) -> str:
        """A person's request: ``polygon`` (ENU metres, the frame of this driver's poses) as the vehicle's own fence,
        enabled, with Hold at a breach (:func:`drivers.mavlink.fence.upload`: every step confirmed by the vehicle);
        bounded by ``open_timeout``; what was done, or :class:`DriverError`."""
        if self._closed or not self._opened:
            raise DriverError("MAVLink link not open")
        return upload_fence(self, polygon, self.client.now + self.config.open_timeout)

    def _read_params(self, names: tuple[str, ...], t_end: float) -> None:
        """Ask for each parameter (PARAM_REQUEST_READ) and wait for the PARAM_VALUEs; a missing one stays unknown."""
        for name in names:
            if not self.client.send(lambda m, n=name: m.param_request_read_send(self.target[0], self.target[1],
                                                                             n.encode(), -1)):
                return
        self.client.wait(lambda: all(n in self.params for n in names), t_end)

    def failsafe(self) -> FailsafeReport:
        """What the vehicle does on its own when this host dies (:func:`drivers.mavlink.state.failsafe_report`)."""
        return failsafe_report(self.params)

    def _enter_guided(self, t_end: float) -> None:
        v, mav, guided = self.vehicle, self.dialect.mav, self._modes.guided
        while v.custom_mode != guided:
            sent = self.client.now
            r = self.client.run(mav.MAV_CMD_DO_SET_MODE, (mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, guided),
                                "mode change to GUIDED", t_end)
            if r == mav.MAV_RESULT_ACCEPTED:  # the HEARTBEAT says whether it held
                self.client.wait(lambda: v.custom_mode == guided, min(t_end, self.client.now + MODE_CONFIRM_S))
                if v.custom_mode != guided:
                    log.warning("GUIDED accepted but the vehicle reports mode %s; asking again",
                                self._modes.name(v.custom_mode))
            else:
                text = self._refusal("mode change to GUIDED", r, sent)
                if self.client.now + RETRY_AFTER_S >= t_end:
                    raise DriverError(text + self.vehicle.note())
                self.client.wait(lambda: False, self.client.now + RETRY_AFTER_S)
            if self.client.now >= t_end and v.custom_mode != guided:
                raise DriverError(f"vehicle not in GUIDED within {self.config.open_timeout} s (mode "
                                  f"{self._modes.name(v.custom_mode)}){self.vehicle.note()}")

    def _arm(self, t_end: float) -> None:
        v, mav = self.vehicle, self.dialect.mav
        while not v.armed:
            if v.custom_mode != self._modes.guided:
                raise DriverError(f"operator took control while engaging: mode {self._modes.name(v.custom_mode)}")
            sent = self.client.now
            r = self.client.run(mav.MAV_CMD_COMPONENT_ARM_DISARM, (1, 0), "arming", t_end)
            if r == mav.MAV_RESULT_ACCEPTED:  # ArduPilot acks arming only once armed; HEARTBEATs say so from now on
                v.armed = True
                return
            text = self._refusal("arming", r, sent)
            if self.client.now + RETRY_AFTER_S >= t_end:
                raise DriverError(text)
            self.client.wait(lambda: False, self.client.now + RETRY_AFTER_S)  # pre-arm checks can clear (EKF settling)

    # --------------------------------------------------------------------------------------------- state
    def _judge(self, now: float) -> Verdict:
        """The vehicle at ``now`` (:meth:`_judge_link`), judged once per moment and change
        (:meth:`LinkBase._verdict`)."""
        return self._verdict(now)  # type: ignore[return-value]

    def _judge_link(self, now: float) -> Verdict:  # type: ignore[override]
        """The vehicle at ``now`` from what it last said (:func:`drivers.mavlink.state.judge`). Pure."""
        c = self.client
        link = LinkView(opened=self._opened, closed=self._closed, connection=c.conn is not None,
                        connected_at=c.conn_time, lost_reason=c.lost_reason, url=self.config.url)
        return judge(self.vehicle, link, now, self._modes, self.config.heartbeat_timeout, self.config.position_timeout)

    def _update_state(self, now: float) -> None:
        """Judge the vehicle at ``now`` and act on a change: log it, count a lost link, ask a vehicle whose heartbeat
        came back for its streams again (never its mode or arming)."""
        state = self._judge(now)
        v = self.vehicle
        if state.reason == "ok":
            v.rebooted = False
        if self._opened and not self._closed:
            what = change(self._state, state, self._link_up)
            if what.said:
                if state.ok:
                    log.info("vehicle accepts commands: %s", state.text)
                else:
                    log.warning("vehicle does not accept commands: %s", state.text)
            if what.lost:
                self._link_up = False
                self.counts["link_losses"] += 1
            elif what.back:
                self._link_up = True
                self.client.backoff.reset()
                log.info("heartbeat back from the vehicle (mode %s, %s)", self._modes.name(v.custom_mode),
                         "armed" if v.armed else "disarmed")
                self._request_streams()  # a rebooted autopilot forgot them; never the mode or arming
        self._state = state
        h = self._health
        h.connected, h.ok, h.text, h.reason = state.connected, state.ok, state.text, state.reason

    # ----------------------------------------------------------------------------------------- set-points
    def _setpoint(self, v: float, omega: float, now: float) -> None:
        """SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_NED, velocity and yaw rate only: vx = v (negative:
        backwards), yaw_rate = -omega (NED is clockwise)."""
        boot_ms = int((now - self._t0) * 1000) & 0xFFFFFFFF
        mav = self.dialect.mav
        if not self.client.send(lambda m: m.set_position_target_local_ned_send(
                boot_ms, self.target[0], self.target[1], mav.MAV_FRAME_BODY_NED, TYPE_MASK_VEL_YAWRATE,
                0, 0, 0, float(v), 0, 0, 0, 0, 0, 0, float(-omega))):
            return
        self.counts["setpoints_sent"] += 1
        self._pacer.sent((float(v), float(omega)), now)

    def _service(self, now: float) -> None:
        """The client's housekeeping at ``now``; a connection it dropped or opened is a change to judge again."""
        c = self.client
        before = (c.conn is None, c.conn_time, c.lost_reason)
        c.service(now)
        if (c.conn is None, c.conn_time, c.lost_reason) != before:
            self._changed()

    def send(self, v: float, omega: float, now: float) -> None:
        """A set-point, only while :meth:`health` is ok (never a mode change or an arming: the operator's)."""
        if self._closed or not self._opened:
            raise DriverError("MAVLink link not open")
        self._service(now)
        self._update_state(now)
        if not self._state.ok:
            self.counts["setpoints_withheld"] += 1
            return
        cmd = (float(v), float(omega))
        if self._pacer.due(cmd, now):
            self._setpoint(*cmd, now)

    def stop(self, now: float) -> None:
        """A zero set-point at once (then repeated at ``setpoint_rate_hz``) while the vehicle is GUIDED; nothing
        when the operator has it."""
        if self._closed or self.client.conn is None:
            return
        self._service(now)
        if self.client.conn is None or self.vehicle.custom_mode != self._modes.guided:
            return
        if self._pacer.due((0.0, 0.0), now):
            self._setpoint(0.0, 0.0, now)

    def poll(self, now: float) -> list[Pose]:
        """The poses that arrived: each stamped at its LOCAL_POSITION_NED's ``time_boot_ms`` on this host's clock
        (:class:`bridge.core.clock.ClockOffset`, ``clock_window_s``; restarted by a reboot or a step of the vehicle's
        clock), with the heading the ATTITUDEs give at that time (:mod:`drivers.mavlink.pose`)."""
        if self._closed or not self._opened:
            return []
        self._service(now)
        poses = self._pump(now)
        self._update_state(now)
        return poses

    def health(self, now: float) -> LinkHealth:
        state = self._judge(now)
        v = self.vehicle
        detail = MavlinkHealthDetail(
            mode=self._modes.name(v.custom_mode), custom_mode=v.custom_mode, armed=v.armed,
            heartbeat_age=None if v.hb_time is None else round(now - v.hb_time, 3),
            position_age=None if v.pos_time is None else round(now - v.pos_time, 3),
            statustexts=tuple(self.statustexts), last_refusal=self._last_refusal,
            bad_signatures=self.client.bad_signatures(), foreign_ids=tuple(self._foreign_ids),
            setpoints_deferred=self._pacer.deferred, **self.counts)
        return replace(self._health, connected=state.connected, ok=state.ok, text=state.text, reason=state.reason,
                       detail=detail)

    def clear_faults(self, now: float) -> None:
        """Nothing to clear on this link: the operator puts the vehicle back in GUIDED and arms it himself."""

    def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0,
              now: float | None = None) -> None:
        """Stop a vehicle that is still ours (GUIDED): zero set-points until it reports (LOCAL_POSITION_NED) a speed
        below ``stop_speed`` (at most ``stop_timeout``: a rover disarmed while moving coasts), then disarm it
        (``disarm``: it was engaged by us) and wait (``close_timeout``) for the ACK or the HEARTBEAT's armed flag,
        then close: ArduPilot's TCP port drops a command that arrives just before its peer closes
        (libraries/AP_HAL_SITL/UARTDriver.cpp), so closing at once would leave the vehicle armed. A vehicle the
        operator has taken over is left alone. ``now``: the host's time (None: read once)."""
        if self._closed:
            return
        if self.client.conn is None:
            self._closed = True
            self._changed()
            self._update_state(self.clock() if now is None else now)
            return
        mav, guided = self.dialect.mav, self._modes.guided
        try:
            now = self.client.now = max(self.client.now, self.clock() if now is None else now)
            self._pump(now)
            v = self.vehicle
            if v.custom_mode == guided:
                self._setpoint(0.0, 0.0, now)
                t_stop = now + stop_timeout
                while v.armed and v.custom_mode == guided and self.client.now < t_stop:
                    speed = ground_speed(self.poses.pending or self._last_position)
                    if speed is not None and speed < stop_speed and self._last_position_time > now:
                        break
                    self._setpoint(0.0, 0.0, self.client.now)
                    self.client.wait(lambda: False, self.client.now + CLOSE_PERIOD_S)
                else:
                    if v.armed and v.custom_mode == guided:
                        log.warning("the vehicle still reports %.2f m/s after %.1f s of zero set-points",
                                    ground_speed(self.poses.pending or self._last_position) or math.nan, stop_timeout)
                now = self.client.now
                if disarm and self.config.disarm_on_close and v.armed and v.custom_mode == guided:
                    t_end = now + self.config.close_timeout
                    r = self.client.run(mav.MAV_CMD_COMPONENT_ARM_DISARM, (0, 0), "disarm", t_end,
                                        done=lambda: v.hb_time is not None and v.hb_time >= now and not v.armed)
                    if r == mav.MAV_RESULT_ACCEPTED:
                        log.info("vehicle disarmed")
                    else:
                        self._health.errors += 1
                        log.error("%s; the vehicle may still be armed", self._refusal("disarm", r, now))
            elif v.custom_mode is not None and self._opened:
                log.warning("vehicle in mode %s (the operator's): left as it is", self._modes.name(v.custom_mode))
        finally:
            self.client.close()
            self._closed = True
            self._changed()
            self._update_state(self.client.now)
