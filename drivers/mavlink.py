"""MAVLink link: an ArduPilot Rover in GUIDED mode (pymavlink, MAVLink 2, ardupilotmega).

The operator always wins. ``open()`` never changes the vehicle's mode nor arms it (a restarted driver host must not
take a vehicle back from the operator): :meth:`MavlinkDriver.engage`, a person's explicit act (``scmbridge engage``,
or ``engage_on_start`` in the driver host's configuration), is the only place this driver selects GUIDED and arms,
reading every COMMAND_ACK. When the vehicle leaves GUIDED (an RC mode switch, a failsafe) the driver stops sending
set-points and says so in :meth:`MavlinkDriver.health` (``ok`` False, ``"operator took control: mode HOLD"``); it
drives again only when the operator has put the vehicle back in GUIDED (and armed), with no action on our side.

open(), bounded by ``open_timeout``, steps 1-3 and the failsafe parameters (``FS_GCS_ENABLE``, ``FS_GCS_TIMEOUT``,
``FS_ACTION``, ``FS_TIMEOUT``: PARAM_REQUEST_READ / PARAM_VALUE), reported by :meth:`MavlinkDriver.failsafe`;
engage(), bounded by ``open_timeout``, steps 4-5:

1. connect (a TCP or serial connection that fails is tried again with backoff) and wait for a HEARTBEAT from
   ``target_system``/``target_component`` whose mode is not INITIALISING;
2. ask for LOCAL_POSITION_NED and ATTITUDE at ``rate_hz`` (MAV_CMD_SET_MESSAGE_INTERVAL);
3. wait until LOCAL_POSITION_NED streams. This is the readiness test: ArduPilot sends LOCAL_POSITION_NED only once
   its EKF has an origin (GCS_Common.cpp ``send_local_position``), and it silently ignores every set-point until then
   (Rover/GCS_Mavlink.cpp ``handle_set_position_target_local_ned``: "need ekf origin"). A rover without GPS can have a
   position estimate, pass its arming checks and accept GUIDED, and still ignore us: commands would be "applied"
   while it does not move;
4. MAV_CMD_DO_SET_MODE GUIDED (custom mode from pymavlink's Rover table), confirmed by a HEARTBEAT (a mode set while
   the vehicle boots is acknowledged and then lost);
5. MAV_CMD_COMPONENT_ARM_DISARM (ArduPilot acks it only once armed); a refusal is retried until the timeout
   (pre-arm checks can clear), and reported with the vehicle's own explanation: ``"arming refused:
   MAV_RESULT_FAILED (PreArm: Hardware safety switch)"``.

Every command waits for its COMMAND_ACK (``ack_timeout``, ``command_retries``): the ACK must name the command and,
when MAVLink 2 carries them, address our system and component. ArduPilot sends the STATUSTEXT that explains a
refusal after the ACK (its text queue), so a refusal waits briefly for it.

send(v, omega): SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_NED, type_mask 0x05E7 ("Use Vel+Yaw Rate" in
ArduPilot's "Rover Commands in Guided Mode"), vx = v (negative: backwards), yaw_rate = -omega (NED is clockwise).
Only while the vehicle is GUIDED, armed, heard from and streaming its position; a changed command (a stop always)
goes at once (at most ``max_setpoint_hz`` set-points a second in all: changing commands once took 97 % of a
57600-baud radio; a stop after motion always at once), an unchanged one is repeated at ``setpoint_rate_hz``
(ArduPilot stops after GUID_TIMEOUT, 3 s, without one). poll(): LOCAL_POSITION_NED + ATTITUDE -> ENU poses (x_enu =
y_ned, y_enu = x_ned, theta = pi/2 - yaw, v = the NED velocity projected on the heading, so reversing is negative).
Every message is filtered by the vehicle's system and component ids; the others are counted (``detail.foreign``).

Poses: each is stamped at its LOCAL_POSITION_NED's ``time_boot_ms``, put on the driver host's monotonic clock with
the sliding-window minimum of ``receipt - time_boot_ms`` (:class:`bridge.core.clock.ClockOffset`, ``clock_window_s``; a
reboot, or a confirmed step of its clock (``bridge.core.clock``), starts it again), not at its receipt: the
host polls at its tick, so receipt stamps fall on a 20 ms grid and a 0.05 s interval between two poses read as 0.04
or 0.06 s. Its heading is the ATTITUDE's at the same vehicle time, interpolated between the two ATTITUDEs around it
(a position waits, usually within the same burst, for the ATTITUDE at or after it). ``scmbridge bench pairing``
measures what this buys (README.md, "Reliability").

Signing (``signing_key_file``, made by ``scmbridge keys mavlink``; the autopilot gets the same key through
SETUP_SIGNING, e.g. from a ground station): MAVLink 2 message signing as ArduPilot implements it
(libraries/GCS_MAVLink/GCS_Signing.cpp): every message this driver sends is signed, and an unsigned or badly signed
message, or one whose signature timestamp goes back, is refused (``health(now).detail.bad_signatures``).

Supervision: no HEARTBEAT for ``heartbeat_timeout`` -> ``connected`` and ``ok`` False, ``"no heartbeat for 3.2 s"``;
a connection that failed (TCP EOF, a serial error) is re-opened with backoff, UDP just keeps listening. When
heartbeats return the message intervals are asked again (a rebooted autopilot forgot them) and ``ok`` comes back
only if the vehicle is GUIDED and armed. STATUSTEXTs are logged and the last ``statustext_keep`` are in
``health(now).detail.statustexts``.

close(): if the vehicle is still ours (GUIDED), zero set-points until it reports (LOCAL_POSITION_NED) a speed below
``stop_speed`` (at most ``stop_timeout``: a rover disarmed while moving coasts), then disarm and wait
(``close_timeout``) for the ACK or the HEARTBEAT's armed flag, then close: ArduPilot's TCP port drops a command that
arrives just before its peer closes (libraries/AP_HAL_SITL/UARTDriver.cpp), so closing at once would leave the
vehicle armed. A vehicle the operator has taken over is left alone.

Configuration: :class:`MavlinkLinkConfig` (``[link.mavlink]`` in the driver host's file). pymavlink is imported
when the first driver is built (:func:`load_pymavlink`), not with the module: the configuration does not need it.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Annotated, Any

from bridge.core.auth import load_key
from bridge.core.backoff import Backoff
from bridge.core.clock import ClockOffset
from bridge.core.config import Cfg, Rule, meta
from drivers.base import DriverError, FailsafeReport, LinkHealth, Pose, whole_numbers

log = logging.getLogger("scmbridge.driver.mavlink")

#: pymavlink (ardupilotmega dialect, MAVLink 2) and the Rover's mode numbers, set by :func:`load_pymavlink`
mavutil: Any = None
MAV: Any = None
ROVER_MODES: dict[int, str] = {}
GUIDED: int
INITIALISING: int
SOURCE_COMPONENT: int
#: the vehicle's own failsafe settings read at open (Rover/Parameters.cpp, GCS failsafe in Rover/failsafe.cpp)
FAILSAFE_PARAMS = ("FS_GCS_ENABLE", "FS_GCS_TIMEOUT", "FS_ACTION", "FS_TIMEOUT")
#: Rover stops a GUIDED velocity target not renewed for this long (Rover/mode_guided.cpp), s
GUIDED_TIMEOUT_S = 3.0
TYPE_MASK_VEL_YAWRATE = 0x05E7
NO_ACK = -1  # a command that got no COMMAND_ACK after all its tries
_BACKOFF0 = 0.25
#: the most the ATTITUDE and LOCAL_POSITION_NED samples may be apart for the heading to be carried to the position's
#: time with the reported yaw rate (two 20 Hz periods); further apart, the last heading is used as it is
ATTITUDE_MAX_LAG = 0.1
#: Telemetry a vehicle can really send (the wire's own ranges are wider still): |x|, |y| in m, speeds in m/s, yaw in
#: rad (ArduPilot sends [-pi, pi]; a full turn either way is tolerated), yaw rate in rad/s. A message outside them,
#: NaN/inf included, is counted malformed (``detail.invalid_values``) and dropped before it can reach a pose.
POSITION_MAX, SPEED_MAX, YAW_MAX, YAW_RATE_MAX = 1e6, 100.0, 2 * math.pi, 100.0


def load_pymavlink() -> None:
    """Import pymavlink and set the names above (once): reading a driver host's configuration, which holds every
    link's section, must not load it."""
    global mavutil, MAV, ROVER_MODES, GUIDED, INITIALISING, SOURCE_COMPONENT
    if mavutil is not None:
        return
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil as loaded

    loaded.set_dialect("ardupilotmega")
    mav = loaded.mavlink
    ROVER_MODES = loaded.mode_mapping_bynumber(mav.MAV_TYPE_GROUND_ROVER)
    GUIDED = loaded.mode_mapping_byname(mav.MAV_TYPE_GROUND_ROVER)["GUIDED"]
    INITIALISING = loaded.mode_mapping_byname(mav.MAV_TYPE_GROUND_ROVER)["INITIALISING"]
    SOURCE_COMPONENT = mav.MAV_COMP_ID_MISSIONPLANNER
    MAV, mavutil = mav, loaded


class MavlinkLinkConfig(Cfg):
    """``[link.mavlink]``: an ArduPilot Rover in GUIDED mode."""

    url: Annotated[str, meta("pymavlink connection: tcp:HOST:5760 (SITL), udpout:HOST:PORT, /dev/ttyUSB0",
                             min_length=1)] = (
        "udpout:127.0.0.1:14550")
    baud: Annotated[int, meta("serial baud rate", ge=1200, le=4_000_000)] = 57600
    target_system: Annotated[int, meta("the vehicle's MAVLink system id", ge=1, le=255)] = 1
    target_component: Annotated[int, meta("the autopilot's component id", ge=0, le=255)] = 1
    source_system: Annotated[int, meta("our system id (a ground control station)", ge=1, le=255)] = 255
    rate_hz: Annotated[float, meta("LOCAL_POSITION_NED and ATTITUDE rate requested, Hz", gt=0.0, le=100.0)] = 20.0
    clock_window_s: Annotated[float, meta("window of the vehicle-clock offset estimate that stamps poses at their "
                                          "time_boot_ms, s", gt=0.0, le=600.0)] = 5.0
    setpoint_rate_hz: Annotated[float, meta(
        "set-points repeating an unchanged command, Hz (a changed command and a stop go at once; 50 Hz set-points fill "
        "56 % of a 57600-baud radio)", gt=0.0, le=50.0)] = 10.0
    max_setpoint_hz: Annotated[float, meta(
        "the most set-points per second, changed commands included (a 57600-baud radio carries ~90 a second and "
        "nothing else then); a stop after motion always goes at once", gt=0.0, le=200.0)] = 25.0
    open_timeout: Annotated[float, meta("s for heartbeat, EKF position, GUIDED and arming", gt=0.0, le=300.0)] = 30.0
    heartbeat_timeout: Annotated[float, meta("s without the vehicle's 1 Hz HEARTBEAT before the link counts as down",
                                             ge=1.5, le=60.0)] = 3.0
    position_timeout: Annotated[float, meta("s without LOCAL_POSITION_NED before the vehicle counts as not ready "
                                            "(ArduPilot sends none without an EKF origin)", gt=0.0, le=60.0)] = 1.0
    ack_timeout: Annotated[float, meta("s to wait for each COMMAND_ACK before sending the command again", gt=0.0,
                                       le=30.0)] = 1.0
    command_retries: Annotated[int, meta("times a command without COMMAND_ACK is sent again", ge=0, le=10)] = 3
    close_timeout: Annotated[float, meta("s close() waits for the disarm to be acknowledged", gt=0.0, le=60.0)] = 3.0
    reconnect_max_s: Annotated[float, meta("longest wait between attempts to re-open a failed connection, s (the "
                                           "wait doubles from 0.25 s)", ge=0.25, le=300.0)] = 5.0
    statustext_keep: Annotated[int, meta("the vehicle's last STATUSTEXTs kept for health() and error texts", ge=1,
                                         le=100)] = 8
    disarm_on_close: Annotated[bool, meta("disarm when the driver host stops (only a vehicle still in GUIDED)")] = True
    signing_key_file: Annotated[str, meta(
        "MAVLink 2 signing key (scmbridge keys mavlink; the autopilot gets the same key with SETUP_SIGNING): every "
        "message we send is signed and unsigned or badly signed ones are refused; empty: no signing")] = ""

    def __post_init__(self) -> None:
        if self.position_timeout < 2.0 / self.rate_hz:
            raise Rule(f"position_timeout = {self.position_timeout} s is shorter than two LOCAL_POSITION_NED "
                             f"periods at rate_hz = {self.rate_hz}")


def telemetry_valid(msg: Any) -> bool:
    """A LOCAL_POSITION_NED or ATTITUDE whose values are finite and within the bounds above (other types: True)."""
    t = msg.get_type()
    if t == "LOCAL_POSITION_NED":
        bounded = ((msg.x, POSITION_MAX), (msg.y, POSITION_MAX), (msg.vx, SPEED_MAX), (msg.vy, SPEED_MAX))
    elif t == "ATTITUDE":
        bounded = ((msg.yaw, YAW_MAX), (msg.yawspeed, YAW_RATE_MAX))
    else:
        return True
    return all(math.isfinite(val) and abs(val) <= lim for val, lim in bounded)


def mode_name(custom_mode: int | None) -> str:
    """Rover's name for a custom mode number (``"HOLD"``), ``"unknown"`` before the first HEARTBEAT."""
    if custom_mode is None:
        return "unknown"
    load_pymavlink()
    return ROVER_MODES.get(custom_mode, f"mode {custom_mode}")


def result_name(result: int) -> str:
    """``"MAV_RESULT_FAILED"`` for 4; ``"no COMMAND_ACK"`` for :data:`NO_ACK`."""
    if result == NO_ACK:
        return "no COMMAND_ACK"
    load_pymavlink()
    entry = MAV.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT {result}"


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


@dataclass
class _Command:
    """One COMMAND_LONG in flight: sent, re-sent without an ACK, then done with a result."""

    command: int
    params: tuple[float, ...]
    what: str  # "arming", "mode change to GUIDED", "LOCAL_POSITION_NED interval"
    tries: int = 0
    next_try: float = 0.0
    first_sent: float = math.inf
    result: int | None = None
    on_done: Callable[[_Command], None] | None = None


@dataclass(slots=True)
class _Position:
    """One LOCAL_POSITION_NED: the vehicle's time of it, its stamp on our clock, NED position and velocity."""

    ms: int
    stamp: float
    x: float
    y: float
    vx: float
    vy: float


@dataclass
class _Vehicle:
    """What the vehicle last told us."""

    custom_mode: int | None = None
    armed: bool = False
    hb_time: float | None = None
    pos_time: float | None = None
    att: tuple[float, float] | None = None  # yaw (NED, rad), yaw rate (clockwise, rad/s)
    att_ms: int = 0  # the last ATTITUDE's time_boot_ms
    att_prev: tuple[int, float] | None = None  # the ATTITUDE before it: (time_boot_ms, yaw)
    pending: _Position | None = None  # a position waiting for the ATTITUDE at or after its time
    boot_ms: int = 0
    rebooted: bool = False
    texts: deque[tuple[float, str]] = field(default_factory=deque)  # (receive time, text), bounded
    text_count: int = 0


class MavlinkDriver:
    """The MAVLink link behind the :class:`drivers.base.Driver` protocol (see the module docstring)."""

    name = "mavlink"
    #: the operator putting the vehicle in GUIDED and arming it, seen while the host runs, is a person's engage
    operator_engages = True

    def __init__(self, config: MavlinkLinkConfig) -> None:
        load_pymavlink()
        self.config = config
        self.url, self.baud = config.url, config.baud
        self.target = (config.target_system, config.target_component)
        self.source_system = config.source_system
        self.rate_hz = config.rate_hz
        self.open_timeout = config.open_timeout
        self.disarm_on_close = config.disarm_on_close
        self.signing_key: bytes | None = None  # read at open (the driver host checks the file at start)
        self._bad_sig_before = 0  # refused signatures on connections closed since
        self.conn: Any = None
        self.v = _Vehicle(texts=deque(maxlen=config.statustext_keep))
        self._health = LinkHealth()
        self._t0 = time.monotonic()
        self._opened = False  # open() succeeded: from now on the mode and arming are the operator's
        self._closed = False
        self._hb_due = 0.0
        self._queue: deque[_Command] = deque()  # commands, one at a time (an ACK names only the command)
        self._sp_last: tuple[float, float] | None = None
        self._sp_time = -math.inf
        self._sp_period = 1.0 / config.setpoint_rate_hz
        self._sp_min_gap = 1.0 / config.max_setpoint_hz
        self._link_up = False
        self._conn_failed: str | None = None
        self._lost_reason = ""
        self._conn_time = math.inf
        self._reconnect_due = 0.0
        self._backoff = Backoff(_BACKOFF0, config.reconnect_max_s)
        self._state: tuple[bool, bool, str, str] = (False, False, "not opened", "closed")
        self._counts = {"foreign": 0, "setpoints_sent": 0, "setpoints_withheld": 0, "setpoints_deferred": 0,
                        "stray_acks": 0,
                        "reconnects": 0, "link_losses": 0, "invalid_values": 0, "clock_restarts": 0}
        self._foreign_ids: deque[tuple[int, int]] = deque(maxlen=8)
        self._clock = ClockOffset(config.clock_window_s)  # the vehicle's time_boot_ms -> our monotonic clock
        self._last_refusal = ""
        self.params: dict[str, float] = {}  # the failsafe parameters the vehicle reported at open
        self._last_position: _Position | None = None
        self._last_position_time = -math.inf

    # ------------------------------------------------------------------------------------------ properties
    @property
    def custom_mode(self) -> int | None:
        return self.v.custom_mode

    @property
    def armed(self) -> bool:
        return self.v.armed

    @property
    def statustexts(self) -> list[str]:
        """The vehicle's last STATUSTEXTs (at most ``statustext_keep``), oldest first."""
        return [t for _, t in self.v.texts]

    # ---------------------------------------------------------------------------------------- connection
    def _connect(self) -> None:
        """Open the pymavlink connection once (no retries inside pymavlink: the caller backs off)."""
        conn = mavutil.mavlink_connection(self.url, baud=self.baud, source_system=self.source_system,
                                          source_component=SOURCE_COMPONENT, dialect="ardupilotmega",
                                          autoreconnect=False, retries=0)
        if self.signing_key is not None:  # MAVLink 2 signing: ours signed, unsigned or forged ones refused
            conn.setup_signing(self.signing_key, sign_outgoing=True, allow_unsigned_callback=None)
        if hasattr(conn, "handle_eof"):  # TCP: pymavlink prints and would reconnect itself on EOF; we do it
            def failed() -> None:
                self._conn_failed = "connection closed by the vehicle"
            conn.handle_eof = failed
            conn.handle_disconnect = failed
        self.conn = conn
        self._conn_failed = None
        self._conn_time = time.monotonic()  # the vehicle counts as heard only once it speaks on this connection

    def _close_conn(self) -> None:
        """Close the pymavlink connection if there is one (a failing close is not an error worth more)."""
        self._bad_sig_before = self._bad_signatures()
        try:
            if self.conn is not None:
                self.conn.close()
        except OSError:
            pass
        self.conn = None

    def _drop_connection(self, reason: str, now: float) -> None:
        log.warning("MAVLink connection %s lost: %s; re-opening in %.2f s", self.url, reason, self._backoff.delay)
        self._health.errors += 1
        self._lost_reason = reason
        self._close_conn()
        self._conn_failed = None
        self._reconnect_due = now + self._backoff.delay
        self._backoff.grow()

    def _try_reconnect(self, now: float) -> None:
        if self.conn is not None or now < self._reconnect_due:
            return
        try:
            self._connect()
        except Exception as exc:  # pymavlink raises OSError, SerialException, ConnectionRefusedError...
            log.debug("re-opening %s failed: %s", self.url, exc)
            self._reconnect_due = now + self._backoff.delay
            self._backoff.grow()
            return
        self._counts["reconnects"] += 1
        log.info("MAVLink connection %s re-opened", self.url)
        self._heartbeat(now, force=True)

    def _heartbeat(self, now: float, force: bool = False) -> None:
        """Our GCS HEARTBEAT, 1 Hz (ArduPilot's GCS failsafe and a udp peer's address depend on it)."""
        if self.conn is None or not (force or now >= self._hb_due):
            return
        try:
            self.conn.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, MAV.MAV_STATE_ACTIVE)
            self._health.frames_sent += 1
        except OSError as exc:
            self._conn_failed = str(exc)
        self._hb_due = now + 1.0

    def _service(self, now: float) -> None:
        """Housekeeping every call does: reconnect, our heartbeat, commands in flight, link supervision."""
        if self._conn_failed is not None and self.conn is not None:
            self._drop_connection(self._conn_failed, now)
        self._try_reconnect(now)
        self._heartbeat(now)
        self._service_commands(now)

    # -------------------------------------------------------------------------------------------- receive
    def _pump(self, block: float) -> list[Pose]:
        """Read what arrived (waiting up to ``block`` s for the first message); update the vehicle's state."""
        out: list[Pose] = []
        if self.conn is None:
            if block > 0:
                time.sleep(block)
            return out
        t_end = time.monotonic() + block
        while self.conn is not None and self._conn_failed is None:
            remaining = t_end - time.monotonic()
            try:
                msg = self.conn.recv_match(blocking=remaining > 0, timeout=max(remaining, 0.0) or None)
            except Exception as exc:  # a serial port unplugged, a socket reset
                self._conn_failed = f"{type(exc).__name__}: {exc}"
                break
            if msg is None:
                break
            self._handle(msg, out)
        return out

    def _handle(self, msg: Any, out: list[Pose]) -> None:
        t = msg.get_type()
        if t == "BAD_DATA":
            self._health.malformed += 1
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src != self.target:  # another vehicle, another ground station, a camera: not ours
            self._health.frames_received += 1
            self._counts["foreign"] += 1
            if src not in self._foreign_ids:
                self._foreign_ids.append(src)
            return
        if not telemetry_valid(msg):  # a NaN yaw would end in math.cos(): the receive loop, and the link, would die
            self._health.malformed += 1
            self._counts["invalid_values"] += 1
            return
        self._health.frames_received += 1
        now = time.monotonic()
        v = self.v
        if t == "HEARTBEAT":
            v.custom_mode = int(msg.custom_mode)
            v.armed = bool(msg.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED)
            v.hb_time = now
        elif t == "LOCAL_POSITION_NED":
            self._boot_ms(msg.time_boot_ms)
            v.pos_time = now
            # stamped at the vehicle's own time of the sample, on our clock (module docstring, "Poses")
            stamp, steady = self._clock.restamp_checked(msg.time_boot_ms / 1000.0, now)
            self._counts["clock_restarts"] += not steady
            p = _Position(int(msg.time_boot_ms), stamp, float(msg.x), float(msg.y), float(msg.vx), float(msg.vy))
            self._last_position, self._last_position_time = p, now
            if v.pending is not None and v.att is not None:
                out.append(self._pose(v.pending))  # no ATTITUDE came after it: the last one, carried forward
            v.pending = None
            if v.att is not None and v.att_ms >= p.ms:
                out.append(self._pose(p))
            else:
                v.pending = p  # its heading comes with the next ATTITUDE (usually in the same burst)
        elif t == "ATTITUDE":
            self._boot_ms(msg.time_boot_ms)
            v.att_prev = (v.att_ms, v.att[0]) if v.att is not None else None
            v.att = (float(msg.yaw), float(msg.yawspeed))
            v.att_ms = int(msg.time_boot_ms)
            if v.pending is not None and v.att_ms >= v.pending.ms:
                out.append(self._pose(v.pending))
                v.pending = None
        elif t == "COMMAND_ACK":
            self._ack(msg)
        elif t == "PARAM_VALUE":
            name = str(msg.param_id).rstrip("\x00")
            if name in FAILSAFE_PARAMS and math.isfinite(msg.param_value):
                self.params[name] = float(msg.param_value)
        elif t == "STATUSTEXT":
            text = "".join(c if c.isprintable() else "\ufffd" for c in str(msg.text).rstrip("\x00"))  # for logs
            v.texts.append((now, text))
            v.text_count += 1
            sev = int(msg.severity)
            level = (logging.ERROR if sev <= MAV.MAV_SEVERITY_ERROR else logging.WARNING
                     if sev == MAV.MAV_SEVERITY_WARNING else logging.INFO if sev < MAV.MAV_SEVERITY_DEBUG
                     else logging.DEBUG)
            log.log(level, "vehicle: %s", text)

    def _pose(self, p: _Position) -> Pose:
        """An ENU pose from a position and the heading at its time: interpolated between the ATTITUDEs around it,
        else carried from the nearest one with its yaw rate (at most ``ATTITUDE_MAX_LAG`` away). The two streams
        are sent apart (ArduPilot schedules each message on its own interval): a heading from up to one period earlier
        mixed the previous command's turn into the pairs."""
        v = self.v
        assert v.att is not None
        yaw, yawspeed = v.att
        if v.att_prev is not None and v.att_prev[0] <= p.ms < v.att_ms:
            t0, yaw0 = v.att_prev
            yaw = yaw0 + math.remainder(yaw - yaw0, 2.0 * math.pi) * (p.ms - t0) / (v.att_ms - t0)
        elif abs(p.ms - v.att_ms) <= 1000.0 * ATTITUDE_MAX_LAG:
            yaw += yawspeed * (p.ms - v.att_ms) / 1000.0
        yaw = math.remainder(yaw, 2.0 * math.pi)
        speed = p.vx * math.cos(yaw) + p.vy * math.sin(yaw)  # signed: on the heading
        # theta = pi/2 - yaw, in [-pi/2, 3pi/2] as before: the station's MPC is not robust to the jump a wrap to
        # [-pi, pi] puts at a westward heading (the mavlink demo drifts off its S-path with it)
        return Pose(p.stamp, p.y, p.x, math.pi / 2 - yaw, speed, -yawspeed)

    def _boot_ms(self, boot_ms: int) -> None:
        """A vehicle clock that jumps back by more than a second rebooted: it forgot our message intervals."""
        if boot_ms + 1000 < self.v.boot_ms:
            self.v.rebooted = True
            log.warning("the vehicle rebooted (time since boot %d ms, was %d ms)", boot_ms, self.v.boot_ms)
            self._clock.reset()  # a new vehicle clock: forget the old offset
            self.v.att, self.v.att_prev, self.v.pending = None, None, None  # times of the old clock
            self._request_streams()
        self.v.boot_ms = int(boot_ms)

    def _ack(self, msg: Any) -> None:
        ours = (getattr(msg, "target_system", 0) in (0, self.source_system)
                and getattr(msg, "target_component", 0) in (0, SOURCE_COMPONENT))
        head = self._queue[0] if self._queue else None
        if ours and head is not None and head.tries > 0 and head.result is None and msg.command == head.command:
            head.result = int(msg.result)
        else:
            self._counts["stray_acks"] += 1

    # -------------------------------------------------------------------------------------------- commands
    def _submit(self, command: int, params: tuple[float, ...], what: str,
                on_done: Callable[[_Command], None] | None = None) -> _Command:
        c = _Command(command, tuple(float(p) for p in params) + (0.0,) * (7 - len(params)), what, on_done=on_done)
        self._queue.append(c)
        self._service_commands(time.monotonic())
        return c

    def _service_commands(self, now: float) -> None:
        while self._queue:
            c = self._queue[0]
            if c.result is not None:
                self._queue.popleft()
                if c.on_done is not None:
                    c.on_done(c)
                continue
            if now < c.next_try or self.conn is None:
                return
            if c.tries > self.config.command_retries:
                c.result = NO_ACK
                continue
            try:  # confirmation counts the re-sends, as the MAVLink command protocol asks
                self.conn.mav.command_long_send(self.target[0], self.target[1], c.command, c.tries, *c.params)
                self._health.frames_sent += 1
            except OSError as exc:
                self._conn_failed = str(exc)
                return
            c.first_sent = min(c.first_sent, now)
            c.tries += 1
            c.next_try = now + self.config.ack_timeout
            return

    def _wait(self, done: Callable[[], bool], t_end: float) -> bool:
        """Pump and service until ``done()`` or ``t_end``."""
        while True:
            now = time.monotonic()
            self._service(now)
            if done():
                return True
            if now >= t_end:
                return False
            self._pump(min(0.05, max(0.0, t_end - now)))

    def _run(self, command: int, params: tuple[float, ...], what: str, t_end: float,
             done: Callable[[], bool] | None = None) -> int:
        """Send a command and wait for its ACK (or ``done()``, or ``t_end``); the MAV_RESULT, or NO_ACK."""
        c = self._submit(command, params, what)
        self._wait(lambda: c.result is not None or (done is not None and done()), t_end)
        by_state = c.result is None and done is not None and done()
        if c.result is None:  # out of time (or confirmed by the vehicle's state) before an ACK
            c.result = NO_ACK
            self._service_commands(time.monotonic())
        return MAV.MAV_RESULT_ACCEPTED if by_state else c.result

    def _refusal(self, what: str, result: int, since: float, wait_text: bool = True) -> str:
        """``"arming refused: MAV_RESULT_FAILED (PreArm: ...)"``, waiting briefly (``wait_text``, in blocking
        calls only) for the STATUSTEXT that explains it."""
        texts = [t for ts, t in self.v.texts if ts >= since]
        if wait_text and not texts and result != NO_ACK:  # ArduPilot queues the text: it follows the ACK
            n = self.v.text_count
            self._wait(lambda: self.v.text_count != n, time.monotonic() + min(0.5, self.config.ack_timeout))
            texts = [t for ts, t in self.v.texts if ts >= since]
        text = f"{what} refused: {result_name(result)}" + (f" ({'; '.join(texts)})" if texts else "")
        self._last_refusal = text
        log.warning("%s", text)
        return text

    def _request_streams(self) -> None:
        """Ask for LOCAL_POSITION_NED and ATTITUDE at ``rate_hz`` (non-blocking; refusals are logged)."""
        period_us = 1e6 / self.rate_hz
        for mid, name in ((MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, "LOCAL_POSITION_NED"),
                          (MAV.MAVLINK_MSG_ID_ATTITUDE, "ATTITUDE")):
            if any(c.command == MAV.MAV_CMD_SET_MESSAGE_INTERVAL and c.params[0] == mid for c in self._queue):
                continue

            def done(c: _Command) -> None:
                if c.result != MAV.MAV_RESULT_ACCEPTED:
                    self._refusal(c.what, c.result if c.result is not None else NO_ACK, c.first_sent, False)

            self._submit(MAV.MAV_CMD_SET_MESSAGE_INTERVAL, (mid, period_us), f"{name} interval", done)

    # ------------------------------------------------------------------------------------------------ open
    def open(self, now: float) -> None:
        """Connect, wait for the vehicle to be ready and read its failsafe settings; never its mode nor arming."""
        t_end = time.monotonic() + self.open_timeout
        self._closed = False
        if self.config.signing_key_file:
            self.signing_key = load_key(self.config.signing_key_file, "mavlink")
        while self.conn is None:
            try:
                self._connect()
            except Exception as exc:  # pymavlink raises plain OSError/SerialException/...
                if time.monotonic() + self._backoff.delay > t_end:
                    raise DriverError(f"cannot open MAVLink connection {self.url}: {exc}") from exc
                time.sleep(self._backoff.delay)
                self._backoff.grow()
        self._heartbeat(time.monotonic(), force=True)
        v = self.v
        if not self._wait(lambda: v.hb_time is not None and v.custom_mode != INITIALISING, t_end):
            if v.hb_time is None:
                others = f" (heard other systems: {sorted(set(self._foreign_ids))})" if self._foreign_ids else ""
                raise DriverError(f"no HEARTBEAT from system {self.target[0]} component {self.target[1]} on "
                                  f"{self.url} within {self.open_timeout} s{others}")
            raise DriverError(f"the vehicle is still initialising after {self.open_timeout} s")
        self._backoff.reset()
        self._request_streams()
        if not self._wait(lambda: self._position_fresh(time.monotonic()) and v.att is not None, t_end):
            raise DriverError(f"vehicle position not ready within {self.open_timeout} s: no LOCAL_POSITION_NED "
                              f"(ArduPilot sends it only once its EKF has an origin){self._texts_note()}")
        self._read_params(FAILSAFE_PARAMS, min(t_end, time.monotonic() + 2.0))
        self._opened = True
        self._link_up = True
        self._update_state(time.monotonic())
        log.info("vehicle on %s: mode %s, %s, position streaming; %s", self.url, mode_name(v.custom_mode),
                 "armed" if v.armed else "disarmed", self.failsafe().text)

    def engage(self, now: float, clear_faults: bool = False) -> None:
        """A person's act: select GUIDED and arm, each confirmed by its COMMAND_ACK and the HEARTBEAT (see the
        module docstring); raises :class:`DriverError` with the vehicle's own reason when it refuses."""
        if self._closed or not self._opened:
            raise DriverError("MAVLink link not open")
        t_end = time.monotonic() + self.open_timeout
        self._enter_guided(t_end)
        self._arm(t_end)
        if self.v.custom_mode != GUIDED:
            raise DriverError(f"operator took control while engaging: mode {mode_name(self.v.custom_mode)}")
        self._update_state(time.monotonic())
        log.info("vehicle engaged: GUIDED, armed")

    def _read_params(self, names: tuple[str, ...], t_end: float) -> None:
        """Ask for each parameter (PARAM_REQUEST_READ) and wait for the PARAM_VALUEs; a missing one stays unknown."""
        for name in names:
            try:
                self.conn.mav.param_request_read_send(self.target[0], self.target[1], name.encode(), -1)
                self._health.frames_sent += 1
            except OSError as exc:
                self._conn_failed = str(exc)
                return
        self._wait(lambda: all(n in self.params for n in names), t_end)

    def failsafe(self) -> FailsafeReport:
        """What the vehicle does on its own when this host dies (stops sending set-points and heartbeats)."""
        p = self.params
        gcs = p.get("FS_GCS_ENABLE")
        known = ", ".join(f"{k}={p[k]:g}" for k in FAILSAFE_PARAMS if k in p) or "no failsafe parameter answered"
        drive_on = GUIDED_TIMEOUT_S  # Rover/mode_guided.cpp: no new target for 3 s -> stop (not a parameter)
        if gcs and p.get("FS_ACTION", 0) and "FS_GCS_TIMEOUT" in p:
            drive_on = min(drive_on, p["FS_GCS_TIMEOUT"] + p.get("FS_TIMEOUT", 0.0))
        text = (f"if the host dies the vehicle drives on for up to {drive_on:g} s (GUIDED stops after "
                f"{GUIDED_TIMEOUT_S:g} s without a target; {known})")
        return FailsafeReport(drive_on_s=drive_on, text=text, params=dict(p))

    def _texts_note(self) -> str:
        return f"; vehicle said: {'; '.join(self.statustexts)}" if self.v.texts else ""

    def _enter_guided(self, t_end: float) -> None:
        v = self.v
        while v.custom_mode != GUIDED:
            sent = time.monotonic()
            r = self._run(MAV.MAV_CMD_DO_SET_MODE, (MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED),
                          "mode change to GUIDED", t_end)
            if r == MAV.MAV_RESULT_ACCEPTED:  # the HEARTBEAT says whether it held
                self._wait(lambda: v.custom_mode == GUIDED, min(t_end, time.monotonic() + 2.5))
                if v.custom_mode != GUIDED:
                    log.warning("GUIDED accepted but the vehicle reports mode %s; asking again",
                                mode_name(v.custom_mode))
            else:
                text = self._refusal("mode change to GUIDED", r, sent)
                if time.monotonic() + 1.0 >= t_end:
                    raise DriverError(text + self._texts_note())
                self._wait(lambda: False, time.monotonic() + 1.0)
            if time.monotonic() >= t_end and v.custom_mode != GUIDED:
                raise DriverError(f"vehicle not in GUIDED within {self.open_timeout} s (mode "
                                  f"{mode_name(v.custom_mode)}){self._texts_note()}")

    def _arm(self, t_end: float) -> None:
        v = self.v
        while not v.armed:
            if v.custom_mode != GUIDED:
                raise DriverError(f"operator took control while opening: mode {mode_name(v.custom_mode)}")
            sent = time.monotonic()
            r = self._run(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (1, 0), "arming", t_end)
            if r == MAV.MAV_RESULT_ACCEPTED:  # ArduPilot acks arming only once armed; HEARTBEATs say so from now on
                v.armed = True
                return
            text = self._refusal("arming", r, sent)
            if time.monotonic() + 1.0 >= t_end:
                raise DriverError(text)
            self._wait(lambda: False, time.monotonic() + 1.0)  # pre-arm checks can clear (the EKF settling)

    # --------------------------------------------------------------------------------------------- state
    def _position_fresh(self, now: float) -> bool:
        return self.v.pos_time is not None and now - self.v.pos_time <= self.config.position_timeout

    def _judge(self, now: float) -> tuple[bool, bool, str, str]:
        """(connected, ok, text, reason) at ``now`` from what the vehicle last said. Pure."""
        v = self.v
        hb_age = math.inf if v.hb_time is None else now - v.hb_time
        connected = (self.conn is not None and hb_age <= self.config.heartbeat_timeout
                     and v.hb_time is not None and v.hb_time >= self._conn_time)
        if self._closed:
            state = (False, False, "closed", "closed")
        elif not self._opened:
            state = (connected, False, "not opened", "closed")
        elif not connected:
            if self.conn is None:
                text = f"connection lost ({self._lost_reason}), re-opening {self.url}; no heartbeat for {hb_age:.1f} s"
            else:
                text = f"no heartbeat for {hb_age:.1f} s"
            state = (False, False, text, "link")
        elif v.custom_mode != GUIDED:
            who = "vehicle rebooted" if v.rebooted else "operator took control"
            state = (True, False, f"{who}: mode {mode_name(v.custom_mode)}{'' if v.armed else ', disarmed'}", "mode")
        elif not v.armed:
            state = (True, False, "vehicle disarmed in GUIDED: waiting for the operator to arm it", "disarmed")
        elif not self._position_fresh(now):
            age = math.inf if v.pos_time is None else now - v.pos_time
            state = (True, False, f"no LOCAL_POSITION_NED for {age:.1f} s (EKF origin lost?)", "position")
        else:
            state = (True, True, "driving: GUIDED, armed", "ok")
        return state

    def _update_state(self, now: float) -> None:
        """Judge the vehicle at ``now`` (:meth:`_judge`) and act on a change: log it, count a lost link, ask a
        vehicle whose heartbeat came back for its streams again (never its mode or arming)."""
        state = self._judge(now)
        v = self.v
        if state[3] == "ok":
            v.rebooted = False
        connected = state[0]
        if self._opened and not self._closed:
            if state[3] != self._state[3]:
                if state[1]:
                    log.info("vehicle accepts commands: %s", state[2])
                else:
                    log.warning("vehicle does not accept commands: %s", state[2])
            if state[3] == "link" and self._link_up:
                self._link_up = False
                self._counts["link_losses"] += 1
            elif connected and not self._link_up:
                self._link_up = True
                self._backoff.reset()
                log.info("heartbeat back from the vehicle (mode %s, %s)", mode_name(v.custom_mode),
                         "armed" if v.armed else "disarmed")
                self._request_streams()  # a rebooted autopilot forgot them; never the mode or arming
        self._state = state
        self._health.connected, self._health.ok, self._health.text = state[0], state[1], state[2]

    # ----------------------------------------------------------------------------------------- the protocol
    def _setpoint(self, v: float, omega: float, now: float) -> None:
        boot_ms = int((now - self._t0) * 1000) & 0xFFFFFFFF
        try:
            self.conn.mav.set_position_target_local_ned_send(
                boot_ms, self.target[0], self.target[1], MAV.MAV_FRAME_BODY_NED, TYPE_MASK_VEL_YAWRATE,
                0, 0, 0, float(v), 0, 0, 0, 0, 0, 0, float(-omega))
        except OSError as exc:
            self._conn_failed = str(exc)
            return
        self._health.frames_sent += 1
        self._counts["setpoints_sent"] += 1
        self._sp_last, self._sp_time = (float(v), float(omega)), now

    def _setpoint_due(self, cmd: tuple[float, float], now: float) -> bool:
        """An unchanged command every ``setpoint_rate_hz``; a changed one at once, but never more than
        ``max_setpoint_hz`` set-points a second (the radio's budget); a stop after motion always at once."""
        if cmd == (0.0, 0.0) and self._sp_last not in (None, (0.0, 0.0)):
            return True
        gap = now - self._sp_time
        if cmd != self._sp_last:
            if gap >= self._sp_min_gap:
                return True
            self._counts["setpoints_deferred"] += 1
            return False
        return gap >= self._sp_period

    def send(self, v: float, omega: float, now: float) -> None:
        """A set-point, only while :meth:`health` is ok (never a mode change or an arming: the operator's)."""
        if self._closed or not self._opened:
            raise DriverError("MAVLink link not open")
        self._service(now)
        self._update_state(now)
        if not self._state[1]:
            self._counts["setpoints_withheld"] += 1
            return
        cmd = (float(v), float(omega))
        if self._setpoint_due(cmd, now):
            self._setpoint(*cmd, now)

    def stop(self, now: float) -> None:
        """A zero set-point at once (then repeated at ``setpoint_rate_hz``) while the vehicle is GUIDED; nothing
        when the operator has it."""
        if self._closed or self.conn is None:
            return
        self._service(now)
        if self.conn is None or self.v.custom_mode != GUIDED:
            return
        if self._setpoint_due((0.0, 0.0), now):
            self._setpoint(0.0, 0.0, now)

    def poll(self, now: float) -> list[Pose]:
        if self._closed or not self._opened:
            return []
        self._service(now)
        poses = self._pump(0.0)
        self._update_state(now)
        return poses

    def health(self, now: float) -> LinkHealth:
        connected, ok, text, _ = self._judge(now)
        v = self.v
        detail = MavlinkHealthDetail(
            mode=mode_name(v.custom_mode), custom_mode=v.custom_mode, armed=v.armed,
            heartbeat_age=None if v.hb_time is None else round(now - v.hb_time, 3),
            position_age=None if v.pos_time is None else round(now - v.pos_time, 3),
            statustexts=tuple(self.statustexts), last_refusal=self._last_refusal,
            bad_signatures=self._bad_signatures(), foreign_ids=tuple(self._foreign_ids), **self._counts)
        return replace(self._health, connected=connected, ok=ok, text=text, detail=detail)

    def _bad_signatures(self) -> int:
        """Messages refused by MAVLink 2 signing (unsigned, forged or replayed), over every connection so far."""
        sig = getattr(getattr(self.conn, "mav", None), "signing", None)
        now = (sig.badsig_count + sig.reject_count) if sig is not None and self.signing_key is not None else 0
        return self._bad_sig_before + now

    def clear_faults(self, now: float) -> None:
        """Nothing to clear on this link: the operator puts the vehicle back in GUIDED and arms it himself."""

    def _speed(self) -> float | None:
        """The vehicle's own speed over ground from its last LOCAL_POSITION_NED, m/s (None before one)."""
        p = self.v.pending
        last = self._last_position
        pos = p if p is not None else last
        return None if pos is None else math.hypot(pos.vx, pos.vy)

    def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0) -> None:
        """Stop a vehicle that is still ours, wait until it reports it has stopped (``stop_speed``, at most
        ``stop_timeout``), disarm it (``disarm``: it was engaged by us) and wait for the acknowledgement, close."""
        if self._closed:
            return
        if self.conn is None:
            self._closed = True
            self._update_state(time.monotonic())
            return
        try:
            now = time.monotonic()
            self._pump(0.0)
            v = self.v
            if v.custom_mode == GUIDED:
                self._setpoint(0.0, 0.0, now)
                t_stop = now + stop_timeout
                while v.armed and v.custom_mode == GUIDED and time.monotonic() < t_stop:
                    speed = self._speed()
                    if speed is not None and speed < stop_speed and self._last_position_time > now:
                        break
                    self._setpoint(0.0, 0.0, time.monotonic())
                    self._wait(lambda: False, time.monotonic() + 0.05)
                else:
                    if v.armed and v.custom_mode == GUIDED:
                        log.warning("the vehicle still reports %.2f m/s after %.1f s of zero set-points",
                                    self._speed() or math.nan, stop_timeout)
                now = time.monotonic()
                if disarm and self.disarm_on_close and v.armed and v.custom_mode == GUIDED:
                    t_end = now + self.config.close_timeout
                    r = self._run(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (0, 0), "disarm", t_end,
                                  done=lambda: v.hb_time is not None and v.hb_time >= now and not v.armed)
                    if r == MAV.MAV_RESULT_ACCEPTED:
                        log.info("vehicle disarmed")
                    else:
                        self._health.errors += 1
                        log.error("%s; the vehicle may still be armed", self._refusal("disarm", r, now))
            elif v.custom_mode is not None and self._opened:
                log.warning("vehicle in mode %s (the operator's): left as it is", mode_name(v.custom_mode))
        finally:
            self._close_conn()
            self._closed = True
            self._update_state(time.monotonic())


#: the link's plugin entry (``drivers.LINKS``): its ``[link.mavlink]`` section, its driver, and whether ``scmbridge
#: learner`` emulates it (an ArduPilot-Rover-like vehicle, :mod:`sim_learner.mavlink_rover`)
CONFIG = MavlinkLinkConfig
DRIVER = MavlinkDriver
EMULATED = True
