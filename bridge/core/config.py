"""Typed configuration: the station's, the driver host's and each link's settings as msgspec Structs, from TOML.

Every command that takes a configuration decodes it here before it opens any link or session. A mistake is refused
with :class:`ConfigError`, whose text is one line naming the file, the key path and the problem (for an unknown
key, the nearest valid name): ``driver.toml: driver.cmd_timout: unknown key (did you mean 'cmd_timeout'?)``.
Numbers are finite and within the ranges written in their types; cross-field rules (``min < max``, distinct CAN
nodes) are checked in ``__post_init__``. ``scmbridge config check FILE`` validates a file and ``scmbridge config
show --kind station|driver|mission`` prints a commented default made from these types (docs/ARCHITECTURE.md,
"Configuration").
"""

from __future__ import annotations

import difflib
import math
import re
import sys
import types

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

import msgspec
from msgspec import Meta, Struct, field

from bridge.core.errors import UsageError
from bridge.core.paths import state_dir
from bridge.core.wire import MissionSpec
from transfer import paper
from transfer.domain import Bounds
from transfer.mission import Mission
from transfer.teacher.path import Polyline


class ConfigError(UsageError, ValueError):
    """A configuration the user has to fix; ``str()`` is the one line to print."""

    def __init__(self, source: str, where: str, problem: str) -> None:
        self.source, self.where, self.problem = source, where, problem
        super().__init__(f"{source}: {where}: {problem}" if where else f"{source}: {problem}")


class Rule(Exception):
    """A cross-field rule a configuration breaks (raised by ``__post_init__``; not a ValueError, so msgspec passes it
    through untouched and the validator reports it at the table it belongs to)."""


def _m(description: str, **bounds: float) -> Meta:
    return Meta(description=description, **bounds)


Finite = Annotated[float, Meta(ge=-1e9, le=1e9)]  # a NaN or inf fails the comparison and is refused
Range = tuple[Finite, Finite]
RobotName = Annotated[str, Meta(pattern=r"^[A-Za-z0-9_\-]{1,64}$", description="one Zenoh key chunk")]
Port = Annotated[int, Meta(ge=0, le=65535)]
SourceName = Annotated[str, Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$", description="a non-blank source name")]
#: a station's tick rate, Hz: below, a command's validity (three periods) would exceed the wire's 10 s
RATE_HZ_RANGE = (0.5, 200.0)
#: hard limits beyond these are a mistake, not a vehicle (m/s, rad/s)
HARD_V_MAX, HARD_W_MAX = 20.0, 20.0


class _Cfg(Struct, forbid_unknown_fields=True, kw_only=True, frozen=True):
    """Base: unknown keys are errors."""


class BoundsConfig(_Cfg):
    """A (v, omega) command box."""

    v: Annotated[Range, _m("linear speed [min, max], m/s")]
    w: Annotated[Range, _m("yaw rate [min, max], rad/s (counter-clockwise positive)")]

    def __post_init__(self) -> None:
        for name, (lo, hi) in (("v", self.v), ("w", self.w)):
            if not lo < hi:
                raise Rule(f"{name} = [{lo}, {hi}]: min must be < max")

    def bounds(self) -> Bounds:
        return Bounds(tuple(self.v), tuple(self.w))


# ------------------------------------------------------------------------------------------------------ links
class CanLinkConfig(_Cfg):
    """``[link.can]``: a differential-drive base with one ODrive 0.6 (CANSimple) controller per wheel."""

    interface: Annotated[str, _m("python-can interface: socketcan, virtual, udp_multicast, pcan, ...")] = "socketcan"
    channel: Annotated[str, _m("bus channel: can0, a virtual channel name, a multicast group", min_length=1)] = "can0"
    bitrate: Annotated[int, _m("bit/s (ignored by socketcan: set it with `ip link`)", ge=10_000, le=8_000_000)] = (
        500_000)
    fd: Annotated[bool, _m("CAN FD (udp_multicast needs an explicit false)")] = False
    left_node: Annotated[int, _m("left wheel's CANSimple node id", ge=0, le=63)] = 0
    right_node: Annotated[int, _m("right wheel's CANSimple node id", ge=0, le=63)] = 1
    left_sign: Annotated[float, _m("+1 or -1: -1 for a mirrored motor")] = 1.0
    right_sign: Annotated[float, _m("+1 or -1: -1 for a mirrored motor")] = -1.0
    wheel_radius: Annotated[float, _m("m", gt=0.0, le=10.0)] = 0.1
    track_width: Annotated[float, _m("distance between the wheels, m", gt=0.0, le=100.0)] = 0.4
    initial_pose: Annotated[tuple[Finite, Finite, Finite], _m("odometry origin [x, y, theta]")] = (0.0, 0.0, 0.0)
    open_timeout: Annotated[float, _m("s to wait for both axes in closed loop (at open and after clear_faults)",
                                      gt=0.0, le=120.0)] = 2.0
    heartbeat_timeout: Annotated[float, _m("s without a controller's Heartbeat before the link is reported lost and "
                                           "the other wheel stopped (ODrive sends one every 0.1 s by default; keep it "
                                           "at or below the controllers' watchdog_timeout)", ge=0.05, le=10.0)] = 0.5
    max_wheel_speed: Annotated[float, _m("rev/s: an encoder estimate faster than this, or a position step it cannot "
                                         "explain, is rejected as implausible", gt=0.0, le=1000.0)] = 5.0
    reopen_backoff: Annotated[float, _m("s before the first attempt to reopen a failed bus; doubles per failed "
                                        "attempt", gt=0.0, le=10.0)] = 0.1
    reopen_backoff_max: Annotated[float, _m("s: the longest wait between two attempts to reopen a failed bus",
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


class MavlinkLinkConfig(_Cfg):
    """``[link.mavlink]``: an ArduPilot Rover in GUIDED mode."""

    url: Annotated[str, _m("pymavlink connection: tcp:HOST:5760 (SITL), udpout:HOST:PORT, /dev/ttyUSB0",
                           min_length=1)] = (
        "udpout:127.0.0.1:14550")
    baud: Annotated[int, _m("serial baud rate", ge=1200, le=4_000_000)] = 57600
    target_system: Annotated[int, _m("the vehicle's MAVLink system id", ge=1, le=255)] = 1
    target_component: Annotated[int, _m("the autopilot's component id", ge=0, le=255)] = 1
    source_system: Annotated[int, _m("our system id (a ground control station)", ge=1, le=255)] = 255
    rate_hz: Annotated[float, _m("LOCAL_POSITION_NED and ATTITUDE rate requested, Hz", gt=0.0, le=100.0)] = 20.0
    clock_window_s: Annotated[float, _m("window of the vehicle-clock offset estimate that stamps poses at their "
                                        "time_boot_ms, s", gt=0.0, le=600.0)] = 5.0
    setpoint_rate_hz: Annotated[float, _m("set-points repeating an unchanged command, Hz (a changed command and a stop "
                                          "go at once; 50 Hz set-points fill 56 % of a 57600-baud radio)",
                                          gt=0.0, le=50.0)] = 10.0
    max_setpoint_hz: Annotated[float, _m(
        "the most set-points per second, changed commands included (a 57600-baud radio carries ~90 a second and "
        "nothing else then); a stop after motion always goes at once", gt=0.0, le=200.0)] = 25.0
    open_timeout: Annotated[float, _m("s for heartbeat, EKF position, GUIDED and arming", gt=0.0, le=300.0)] = 30.0
    heartbeat_timeout: Annotated[float, _m("s without the vehicle's 1 Hz HEARTBEAT before the link counts as down",
                                           ge=1.5, le=60.0)] = 3.0
    position_timeout: Annotated[float, _m("s without LOCAL_POSITION_NED before the vehicle counts as not ready "
                                          "(ArduPilot sends none without an EKF origin)", gt=0.0, le=60.0)] = 1.0
    ack_timeout: Annotated[float, _m("s to wait for each COMMAND_ACK before sending the command again", gt=0.0,
                                     le=30.0)] = 1.0
    command_retries: Annotated[int, _m("times a command without COMMAND_ACK is sent again", ge=0, le=10)] = 3
    close_timeout: Annotated[float, _m("s close() waits for the disarm to be acknowledged", gt=0.0, le=60.0)] = 3.0
    reconnect_max_s: Annotated[float, _m("longest wait between attempts to re-open a failed connection, s (the "
                                         "wait doubles from 0.25 s)", ge=0.25, le=300.0)] = 5.0
    statustext_keep: Annotated[int, _m("the vehicle's last STATUSTEXTs kept for health() and error texts", ge=1,
                                       le=100)] = 8
    disarm_on_close: Annotated[bool, _m("disarm when the driver host stops (only a vehicle still in GUIDED)")] = True
    signing_key_file: Annotated[str, _m(
        "MAVLink 2 signing key (scmbridge keys mavlink; the autopilot gets the same key with SETUP_SIGNING): every "
        "message we send is signed and unsigned or badly signed ones are refused; empty: no signing")] = ""

    def __post_init__(self) -> None:
        if self.position_timeout < 2.0 / self.rate_hz:
            raise Rule(f"position_timeout = {self.position_timeout} s is shorter than two LOCAL_POSITION_NED "
                             f"periods at rate_hz = {self.rate_hz}")


class UdpLinkConfig(_Cfg):
    """``[link.udp]``: MessagePack datagrams to a small robot (the UDP shim).

    Both ends pin each other: the driver takes datagrams only from ``robot_host:robot_port`` and the robot obeys
    (and streams its state to) only its configured peer, which is this driver's ``bind_host:bind_port``. So the
    driver's port is fixed (``bind_port``), and the robot's firmware is configured with it.
    """

    robot_host: Annotated[str, _m("the robot's address (resolved once, when the link opens)", min_length=1)] = (
        "127.0.0.1")
    robot_port: Annotated[Port, _m("the robot's UDP port")] = 47800
    bind_host: Annotated[str, _m("our address (127.0.0.1 for loopback tests)")] = "127.0.0.1"
    bind_port: Annotated[Port, _m("our UDP port: the robot's configured peer, so fixed; 0: any free (only for a "
                                  "robot that pins its first sender)")] = 47801
    open_timeout: Annotated[float, _m("s to wait for the robot's first state", gt=0.0, le=120.0)] = 2.0
    state_timeout_s: Annotated[float, _m("the robot's state older than this: the link is not ok (the host stops); "
                                         "also the silence after which a new robot epoch (a reboot) is taken, s",
                                         gt=0.0, le=60.0)] = 0.5
    max_state_rate_hz: Annotated[float, _m("the fastest the robot may count its state seq (it streams at ~50 Hz): "
                                           "a state whose seq jumps further ahead than this allows is refused, Hz",
                                           gt=0.0, le=100_000.0)] = 200.0
    clock_window_s: Annotated[float, _m("window of the robot-clock offset estimate that stamps poses at the robot's "
                                        "own stamps, s", gt=0.0, le=600.0)] = 5.0
    key_file: Annotated[str, _m("the datagram key both ends use (scmbridge keys udp): every datagram carries a keyed "
                                "tag and unauthenticated ones are dropped; empty: none (loopback tests only)")] = ""

    def __post_init__(self) -> None:
        if self.robot_port == 0:
            raise Rule("robot_port must be the robot's port (1-65535)")


class LinkSection(_Cfg):
    """``[link.<name>]``: the settings of each link this driver host may use (``--link`` picks one)."""

    can: CanLinkConfig = field(default_factory=CanLinkConfig)
    mavlink: MavlinkLinkConfig = field(default_factory=MavlinkLinkConfig)
    udp: UdpLinkConfig = field(default_factory=UdpLinkConfig)


LINK_CONFIGS: dict[str, type[_Cfg]] = {"can": CanLinkConfig, "mavlink": MavlinkLinkConfig, "udp": UdpLinkConfig}

# ---------------------------------------------------------------------------------------------- driver host
DEFAULT_HARD_LIMITS = BoundsConfig(v=(-0.5, 0.5), w=(-1.0, 1.0))


class DriverSection(_Cfg):
    """``[driver]``: the driver host's loop and safety settings."""

    rate_hz: Annotated[float, _m("control loop rate, Hz", ge=1.0, le=1000.0)] = 50.0
    cmd_timeout: Annotated[float, _m("deadman: no valid command for this long stops the vehicle, s", ge=0.02,
                                     le=10.0)] = 0.3
    hard_limits: Annotated[BoundsConfig, _m("every command is clamped into this box before a vehicle sees it")] = (
        DEFAULT_HARD_LIMITS)
    max_send_hz: Annotated[float, _m("the most commands per second handed to the link (a command is sent as it "
                                     "arrives, but never sooner than 1/max_send_hz after the last)", ge=1.0,
                                     le=1000.0)] = 100.0
    max_telemetry_age_s: Annotated[float, _m("no pose from the link for this long stops the vehicle (it would drive "
                                             "blind), s", gt=0.0, le=60.0)] = 0.5
    estop_release_sources: Annotated[tuple[SourceName, ...],
                                     _m("Estop sources allowed to release a latched estop (scmbridge estop "
                                        "--release --source NAME); at least one", min_length=1)] = ("operator",)

    pose_source: Annotated[Literal["link", "mocap"], _m(
        "where the published state comes from: the link's own telemetry, or a motion-capture bridge publishing "
        "scm/<robot>/mocap (restamped onto this host's clock)")] = "link"
    mocap_window_s: Annotated[float, _m("mocap: the clock-offset estimate is the least (receipt - stamp) over this "
                                        "window, s", gt=0.1, le=600.0)] = 5.0
    engage_on_start: Annotated[bool, _m(
        "engage the vehicle when the host starts (MAVLink: select GUIDED and arm; CAN: closed loop). Off: the host "
        "waits for a person (scmbridge engage, or the operator selecting GUIDED and arming), also after a restart")] = (
        False)
    stop_speed: Annotated[float, _m("closing: zero commands until the vehicle reports less than this, then disarm, "
                                    "m/s", gt=0.0, le=5.0)] = 0.05
    stop_timeout: Annotated[float, _m("closing: the longest wait for the vehicle to stop before disarming, s", gt=0.0,
                                      le=60.0)] = 3.0
    max_drive_on_s: Annotated[float, _m("warn when the vehicle's own failsafe lets it drive on longer than this after "
                                        "the host dies, s", gt=0.0, le=600.0)] = 1.0

    def __post_init__(self) -> None:
        if self.max_send_hz < self.rate_hz:
            raise Rule(f"max_send_hz = {self.max_send_hz} is below rate_hz = {self.rate_hz}: every tick sends")
        (v_lo, v_hi), (w_lo, w_hi) = self.hard_limits.v, self.hard_limits.w
        if max(abs(v_lo), abs(v_hi)) > HARD_V_MAX or max(abs(w_lo), abs(w_hi)) > HARD_W_MAX:
            raise Rule(f"hard_limits v = [{v_lo}, {v_hi}], w = [{w_lo}, {w_hi}] are beyond any rover this drives "
                       f"(|v| <= {HARD_V_MAX} m/s, |w| <= {HARD_W_MAX} rad/s): a typo would let anything through")


class DriverConfig(_Cfg):
    """A driver host's configuration file."""

    robot: RobotName = "learner"
    driver: DriverSection = field(default_factory=DriverSection)
    link: LinkSection = field(default_factory=LinkSection)


# -------------------------------------------------------------------------------------------------- station
class StationSection(_Cfg):
    """``[station]``: the loop, persistence and the mission."""

    rate_hz: Annotated[float, _m("control tick rate, Hz (the paper's 10 Hz)", ge=RATE_HZ_RANGE[0],
                                 le=RATE_HZ_RANGE[1])] = 10.0
    pair_dt: Annotated[float, _m("pairing interval, s", ge=0.01, le=10.0)] = 0.1
    horizon: Annotated[int, _m("MPC horizon N, steps", ge=2, le=200)] = 20
    persist_every_s: Annotated[float, _m("save the pair store this often, s", ge=0.1, le=86400.0)] = 5.0
    store_path: Annotated[str, _m("pair store file; empty: pairs-<robot>.bin in the state directory")] = ""
    mission: Annotated[str, _m("mission file (TOML); empty: the paper's S-path shipped with scmbridge")] = ""
    max_pose_age_s: Annotated[float, _m("a pose older than this stops planning (the station publishes stops), s",
                                        gt=0.0, le=60.0)] = 0.5


class TransferSection(_Cfg):
    """``[transfer]``: refinement grid and the mapper."""

    grid: Annotated[tuple[Annotated[int, Meta(ge=2, le=100)], Annotated[int, Meta(ge=2, le=100)]],
                    _m("cells of the normalised learner domain [n_v, n_omega]")] = (11, 11)
    k_min: Annotated[int, _m("pairs a cell needs before it holds a refined pair", ge=1, le=1000)] = 5
    mapper: Annotated[Literal["scm", "affine", "barycentric", "identity"], _m("how a region maps commands")] = "scm"
    seed: Annotated[int, _m("random generator seed of the exploration", ge=0, le=2**32 - 1)] = 0
    exploration: Annotated[Literal["guided", "paper", "off"], _m(
        "guided: explore (perturb) only where the command needs a missing pair, at the least detour, steered by "
        "the teacher's plan; paper: the paper's algorithm as published; off: never perturb (map, or extrapolate "
        "from the learned region)")] = "guided"
    explore_clearance_m: Annotated[float, _m("no exploration closer than this to an obstacle's edge, whatever the "
                                             "exploration setting, m", ge=0.0, le=100.0)] = 0.3


class TeacherSection(_Cfg):
    """``[teacher]``: who computes the teacher commands the station maps."""

    kind: Annotated[Literal["mpc", "primitives", "external"], _m(
        "mpc: the built-in MPC follows the mission; primitives: the paper's motion-primitive planner (Section 5.1) "
        "over the primitives the learned limits allow (calibrate first); external: a lab's own teacher publishes "
        "scm/<robot>/teacher and the station only maps (transfer-only service)")] = "mpc"
    primitives_grid: Annotated[int, _m("primitives: an n x n library over the teacher's range", ge=2, le=31)] = 11
    primitive_s: Annotated[float, _m("primitives: each primitive's duration, s", gt=0.0, le=60.0)] = 1.0
    timeout_s: Annotated[float, _m("external: no teacher command for this long makes the station publish stops, s",
                                   gt=0.0, le=10.0)] = 0.3


class CalibrationSection(_Cfg):
    """``[calibration]``: the calibration stage (``scmbridge calibrate``), bounded in time and distance."""

    grid: Annotated[tuple[Annotated[int, Meta(ge=2, le=21)], Annotated[int, Meta(ge=2, le=21)]],
                    _m("learner commands [n_v, n_omega] spanning the learner's box, extremes included")] = (5, 5)
    hold_s: Annotated[float, _m("each command is held this long, s", gt=0.0, le=60.0)] = 1.0
    max_distance_m: Annotated[float, _m("stop calibrating when the robot is this far from where it started, m",
                                        gt=0.0, le=1000.0)] = 2.0
    return_radius_m: Annotated[float, _m("beyond this distance the robot drives back toward the start between "
                                         "commands, m", gt=0.0, le=1000.0)] = 0.8
    max_time_s: Annotated[float, _m("stop calibrating after this long, s", gt=0.0, le=36000.0)] = 300.0

    def __post_init__(self) -> None:
        if self.return_radius_m >= self.max_distance_m:
            raise Rule(f"return_radius_m = {self.return_radius_m} must be below max_distance_m = "
                             f"{self.max_distance_m}")


DEFAULT_TEACHER_BOUNDS = BoundsConfig(v=paper.MPC_TEACHER_V, w=paper.MPC_TEACHER_W)
DEFAULT_LEARNER_BOUNDS = BoundsConfig(v=paper.MPC_LEARNER_V, w=paper.MPC_LEARNER_W)


class StationConfig(_Cfg):
    """A station's configuration file."""

    robot: RobotName = "learner"
    station: StationSection = field(default_factory=StationSection)
    teacher_bounds: Annotated[BoundsConfig, _m("the teacher's command range (the paper's MPC teacher by default)")] = (
        DEFAULT_TEACHER_BOUNDS)
    learner_bounds: Annotated[BoundsConfig, _m("the learner's own command range")] = DEFAULT_LEARNER_BOUNDS
    transfer: TransferSection = field(default_factory=TransferSection)
    teacher: TeacherSection = field(default_factory=TeacherSection)
    calibration: CalibrationSection = field(default_factory=CalibrationSection)

    def store_file(self, robot: str | None = None) -> Path:
        """The pair store: ``store_path``, else ``pairs-<robot>.bin`` in the state directory (never the working
        directory: two stations started in one directory must not share a file)."""
        return Path(self.station.store_path or state_dir() / f"pairs-{robot or self.robot}.bin")


KINDS: dict[str, type[Struct]] = {"station": StationConfig, "driver": DriverConfig, "mission": MissionSpec}
C = TypeVar("C", bound=Struct)


# ------------------------------------------------------------------------------------------------- decoding
Path_ = tuple[str | int, ...]


def _where(path: Path_) -> str:
    """``driver.hard_limits.v[0]`` for ``("driver", "hard_limits", "v", 0)``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out


def _constraints(tp: Any) -> tuple[Any, list[Meta]]:
    """The type under ``Annotated[...]`` layers and every ``Meta`` on the way."""
    metas: list[Meta] = []
    while get_origin(tp) is Annotated:
        args = get_args(tp)
        metas += [m for m in args[1:] if isinstance(m, Meta)]
        tp = args[0]
    return tp, metas


def _fmt(x: float) -> str:
    return repr(float(x)) if isinstance(x, float) else str(x)


def _check_meta(value: Any, metas: list[Meta], path: Path_) -> None:
    """The ranges, lengths and patterns written in the type."""
    for m in metas:
        for attr, ok, text in (("gt", lambda v, b: v > b, "must be > {}"), ("ge", lambda v, b: v >= b, "must be >= {}"),
                               ("lt", lambda v, b: v < b, "must be < {}"), ("le", lambda v, b: v <= b,
                                                                             "must be <= {}")):
            bound = getattr(m, attr)
            if bound is not None and isinstance(value, (int, float)) and not ok(value, bound):
                if abs(bound) == 1e9:
                    raise _Problem(path, "a finite number" if not math.isfinite(value) else "out of range",
                                   f"expected a number between -1e9 and 1e9, got {_fmt(value)}")
                raise _Problem(path, "out of range", text.format(_fmt(bound)) + f", got {_fmt(value)}")
        if m.min_length is not None and len(value) < m.min_length:
            raise _Problem(path, "too short", f"needs at least {m.min_length} (length {len(value)})")
        if m.max_length is not None and len(value) > m.max_length:
            raise _Problem(path, "too long", f"at most {m.max_length} allowed (length {len(value)})")
        if m.pattern is not None and isinstance(value, str) and not re.search(m.pattern, value):
            desc = f" ({m.description})" if m.description else ""
            raise _Problem(path, "bad text", f"{value!r} does not match {m.pattern}{desc}")


class _Problem(Exception):
    """One problem found by :func:`validate`: where, what kind, and the words for a person."""

    def __init__(self, path: Path_, kind: str, detail: str) -> None:
        super().__init__(detail)
        self.path, self.kind, self.detail = path, kind, detail


_NAMES = {bool: "true or false", int: "a whole number", float: "a number", str: "text"}


def _kind_name(tp: Any) -> str:
    tp, _ = _constraints(tp)
    if isinstance(tp, type) and issubclass(tp, Struct):
        return "a table"
    if get_origin(tp) in (list, tuple):
        return "a list"
    if get_origin(tp) is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    return _NAMES.get(tp, getattr(tp, "__name__", str(tp)))


def _got(value: Any) -> str:
    return {bool: "true/false", int: "a whole number", float: "a number", str: "text", list: "a list",
            dict: "a table"}.get(type(value), type(value).__name__)


def validate(value: Any, tp: Any, path: Path_ = ()) -> None:
    """Check ``value`` (as decoded from TOML) against the type ``tp`` and raise :class:`_Problem` at the first
    mistake, with its path and kind. Walks the type itself, so every message is ours, not msgspec's."""
    base, metas = _constraints(tp)
    origin = get_origin(base)
    if origin in (Union, types.UnionType):
        options = [a for a in get_args(base)]
        if value is None and type(None) in options:
            return
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                validate(value, option, path)
                return
            except _Problem as exc:
                errors.append(exc)
        raise errors[0]
    if isinstance(base, type) and issubclass(base, Struct):
        _validate_struct(value, base, path)
    elif origin is Literal:
        if value not in get_args(base) or type(value) is bool and True in get_args(base):
            raise _Problem(path, "not one of", f"must be {_kind_name(base)}, got {value!r}")
    elif origin in (list, tuple):
        if not isinstance(value, list):
            raise _Problem(path, "wrong type", f"expected a list, got {_got(value)}")
        args = get_args(base)
        if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
            if len(value) != len(args):
                raise _Problem(path, "wrong length", f"expected a list of length {len(args)}, got length {len(value)}")
            for k, (item, item_tp) in enumerate(zip(value, args)):
                validate(item, item_tp, (*path, k))
        else:
            for k, item in enumerate(value):
                validate(item, args[0], (*path, k))
    elif base is bool:
        if not isinstance(value, bool):
            raise _Problem(path, "wrong type", f"expected true or false, got {_got(value)}")
    elif base is int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise _Problem(path, "wrong type", f"expected a whole number, got {_got(value)}")
    elif base is float:
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise _Problem(path, "wrong type", f"expected a number, got {_got(value)}")
        if not math.isfinite(value):
            raise _Problem(path, "not finite", f"expected a finite number, got {value}")
    elif base is str and not isinstance(value, str):
        raise _Problem(path, "wrong type", f"expected text, got {_got(value)}")
    _check_meta(value, metas, path)


def _validate_struct(value: Any, kind: type[Struct], path: Path_) -> None:
    if not isinstance(value, dict):
        raise _Problem(path, "wrong type", f"expected a table, got {_got(value)}")
    hints = get_type_hints(kind, include_extras=True)
    fields = list(kind.__struct_fields__)
    for key in value:
        if key not in hints:
            close = difflib.get_close_matches(str(key), fields, n=1, cutoff=0.5)
            hint = f" (did you mean '{close[0]}'?)" if close else f" (valid: {', '.join(fields)})"
            raise _Problem((*path, key), "unknown key", f"unknown key{hint}")
    required = set(fields) - set(kind.__struct_defaults__ and fields[len(fields) - len(kind.__struct_defaults__):])
    for name in fields:
        if name in value:
            validate(value[name], hints[name], (*path, name))
        elif name in required:
            raise _Problem((*path, name), "missing key", "required key is missing")
    try:
        msgspec.convert(value, kind)
    except Rule as exc:
        raise _Problem(path, "rule", str(exc)) from None
    except msgspec.ValidationError as exc:  # a wire Struct's own rule (a mission file): its ValueError is the cause
        if not isinstance(exc.__cause__, ValueError):
            raise
        raise _Problem(path, "rule", str(exc.__cause__)) from None


def parse_toml(data: bytes, source: str) -> dict[str, Any]:
    """The TOML table in ``data``; :class:`ConfigError` (one line) for text that is not UTF-8 or not TOML."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(source, "", f"not UTF-8 text (byte {exc.start}): a TOML file is UTF-8") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(source, "", f"not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(source, "", "not valid TOML: nested too deeply") from None


def read_table(path: str | Path) -> dict[str, Any]:
    """The TOML table of the file at ``path``; :class:`ConfigError` (one line) for every way reading can fail."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise ConfigError(str(p), "", "no such file") from None
    except IsADirectoryError:
        raise ConfigError(str(p), "", "is a directory, not a configuration file") from None
    except OSError as exc:
        raise ConfigError(str(p), "", f"cannot read: {exc.strerror or exc}") from None
    return parse_toml(data, str(p))


def from_table(table: dict[str, Any], kind: type[C], source: str) -> C:
    """``table`` validated (:func:`validate`) and converted into ``kind``; :class:`ConfigError` naming the key."""
    try:
        validate(table, kind)
    except _Problem as exc:
        raise ConfigError(source, _where(exc.path), exc.detail) from None
    return msgspec.convert(table, kind)


def decode_toml(data: bytes | str, kind: type[C], source: str = "<config>") -> C:
    """Decode TOML text into ``kind``; raise :class:`ConfigError` (one line) on any problem."""
    raw = data.encode() if isinstance(data, str) else data
    return from_table(parse_toml(raw, source), kind, source)


def load(path: str | Path | None, kind: type[C]) -> C:
    """The configuration in ``path`` (the defaults when ``path`` is None), or :class:`ConfigError`."""
    if path is None:
        return msgspec.convert({}, kind)
    return from_table(read_table(path), kind, str(path))


def load_station(path: str | Path | None) -> StationConfig:
    return load(path, StationConfig)


def load_driver(path: str | Path | None) -> DriverConfig:
    return load(path, DriverConfig)


def guess_kind(data: dict[str, Any]) -> str:
    """Which kind of file a decoded TOML table is, from its top-level keys."""
    if "path" in data:
        return "mission"
    if "driver" in data or "link" in data:
        return "driver"
    return "station"


# ---------------------------------------------------------------------------------------------------- missions
SHIPPED_MISSIONS = {"paper-s-path": "paper_s_path.toml", "paper-primitives-s-path": "paper_primitives_s_path.toml"}


def mission_from_spec(spec: MissionSpec) -> Mission:
    """The method's :class:`transfer.mission.Mission` for a validated spec (file or message)."""
    return Mission(spec.name, Polyline(spec.path), spec.obstacles or [], spec.goal_tolerance, spec.start, spec.frame)


def load_mission_spec(path: str | Path | None = None) -> MissionSpec:
    """A mission file (TOML), or a shipped mission by name (``paper-s-path``, the default)."""
    name = str(path) if path else "paper-s-path"
    if name in SHIPPED_MISSIONS:
        text = resources.files("bridge").joinpath("missions", SHIPPED_MISSIONS[name]).read_bytes()
        return decode_toml(text, MissionSpec, f"<shipped mission {name}>")
    return load(name, MissionSpec)


def load_mission(path: str | Path | None = None) -> Mission:
    """See :func:`load_mission_spec`; geometry problems (a degenerate path) are ConfigErrors too."""
    spec = load_mission_spec(path)
    try:
        return mission_from_spec(spec)
    except ValueError as exc:
        raise ConfigError(str(path or "paper-s-path"), "", str(exc)) from None


__all__ = [
    "KINDS",
    "LINK_CONFIGS",
    "BoundsConfig",
    "CalibrationSection",
    "CanLinkConfig",
    "ConfigError",
    "DriverConfig",
    "DriverSection",
    "MavlinkLinkConfig",
    "StationConfig",
    "StationSection",
    "TeacherSection",
    "TransferSection",
    "UdpLinkConfig",
    "decode_toml",
    "load",
    "load_driver",
    "load_mission",
    "load_mission_spec",
    "load_station",
    "mission_from_spec",
]
