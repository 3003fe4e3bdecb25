"""The wire contract: Zenoh keys and one msgspec Struct per key, MessagePack on the wire (docs/ARCHITECTURE.md).

This module is a leaf: it imports nothing of the project, so drivers, emulators, the station and a lab's own tools
(an external teacher, a motion-capture bridge, a recorder) can all depend on it while it depends on nothing.

Constructing or encoding a Struct does not validate; *decoding* does (types, ``Meta`` ranges, NaN/inf against
the bounds, unknown fields). So every trust boundary decodes with :func:`decode`, which raises
:class:`MessageError` with the reason; callers count and drop. The bounds below are sanity bounds of the wire
format (a command of 1000 m/s is not a command), not the vehicle's hard limits, which the driver host applies.

Stamps are ``time.monotonic()`` seconds of the *sender's* clock. Pairing in the station only compares stamps that
come from one clock (the driver host's ``state`` and ``applied``), so base station and robot need no clock sync.

Senders of sequenced streams (``cmd``, ``state``) carry an ``epoch``: a number the sender picks once per start
(:func:`new_epoch`). A receiver follows one ``(epoch, seq)`` stream; a new epoch is recognised at once when the
stream it follows has gone silent (a restarted station or robot), so an old, replayed or forged sequence number
cannot lock anyone out for longer than a silence timeout (see ``bridge.core.gate.SeqGate``).
"""

from __future__ import annotations

import re
import secrets
from typing import Annotated, Literal, TypeVar

import msgspec
from msgspec import Meta, Struct

# ------------------------------------------------------------------------------------------------------- keys
PREFIX = "scm"
#: every topic of one robot's namespace ``scm/<robot>/<topic>``; who publishes each is in docs/ARCHITECTURE.md
TOPICS = ("state", "cmd", "teacher", "applied", "pairs", "limits", "mission", "mocap", "status", "estop", "control",
          "engage", "journal")
_ROBOT = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def check_robot(robot: str) -> str:
    """A robot name is one key chunk: letters, digits, ``_`` and ``-`` (no ``/``, ``*``, ``$``, ``?``, ``#``)."""
    if not isinstance(robot, str) or not _ROBOT.match(robot):
        raise ValueError(f"robot name {robot!r} must be 1-64 characters of [A-Za-z0-9_-]")
    return robot


def key(robot: str, topic: str) -> str:
    """The key of ``topic`` for ``robot``, e.g. ``key("rover1", "cmd") == "scm/rover1/cmd"``."""
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r}; topics: {', '.join(TOPICS)}")
    return f"{PREFIX}/{check_robot(robot)}/{topic}"


def status_key(robot: str, node: str) -> str:
    """Each node publishes its health under its own sub-key so several nodes' status do not overwrite."""
    return f"{key(robot, 'status')}/{check_robot(node)}"


def alive_key(robot: str, node: str) -> str:
    """A node's Zenoh liveliness token (``scm/<robot>/alive/<node>``): it stays while the node's session lives,
    also while the process is stalled, so operator tools can find every robot, not only those that answer now."""
    return f"{PREFIX}/{check_robot(robot)}/alive/{check_robot(node)}"


class Keys:
    """All keys of one robot, as attributes: ``Keys("rover1").cmd == "scm/rover1/cmd"``."""

    state: str
    cmd: str
    teacher: str
    applied: str
    pairs: str
    limits: str
    mission: str
    mocap: str
    status: str
    estop: str
    control: str
    engage: str

    def __init__(self, robot: str) -> None:
        self.robot = check_robot(robot)
        for topic in TOPICS:
            setattr(self, topic, key(robot, topic))


def new_epoch() -> int:
    """A sender's epoch for this start: random, positive, 62 bits (collisions between two starts are negligible)."""
    return secrets.randbits(62) + 1


def new_nonce() -> str:
    """A person's request's nonce (:class:`EngageRequest`, :class:`MissionRequest`, an estop release): 128 random
    bits in hex; the receiver refuses a nonce it has seen within the validity window (``bridge.core.acts``)."""
    return secrets.token_hex(16)


# --------------------------------------------------------------------------------------------------- messages

# Finite floats: a NaN or inf fails the ge/le comparison at decode time and is rejected.
Stamp = Annotated[float, Meta(ge=0.0, le=1e12)]
Seq = Annotated[int, Meta(ge=0, le=2**63 - 1)]
Coord = Annotated[float, Meta(ge=-1e6, le=1e6)]  # metres
Angle = Annotated[float, Meta(ge=-1e3, le=1e3)]  # radians (not necessarily wrapped)
Speed = Annotated[float, Meta(ge=-100.0, le=100.0)]  # m/s
Rate = Annotated[float, Meta(ge=-100.0, le=100.0)]  # rad/s
Name = Annotated[str, Meta(max_length=64)]
Epoch = Annotated[int, Meta(ge=0, le=2**63 - 1)]  # 0: a sender that does not say (tests, old tools)
Text = Annotated[str, Meta(max_length=1024)]
#: a wall-clock time (``time.time()``, s since 1970): what a person's request is stamped with, since the tool and the
#: node that acts on it may be different machines; 0: not stamped (an old tool: refused where it matters)
WallTime = Annotated[float, Meta(ge=0.0, le=1e11)]
Nonce = Annotated[str, Meta(max_length=64)]

Method = Literal["scm", "affine", "barycentric", "direct", "perturb", "stop", "calibrate"]


class _Msg(Struct, forbid_unknown_fields=True, omit_defaults=True):
    """Base: unknown fields are an error, defaults are not sent."""


class LearnerState(_Msg, kw_only=True):
    """``scm/<robot>/state``: the learner's pose in ENU (x east, y north, theta CCW from x), from its telemetry."""

    stamp: Stamp
    seq: Seq
    x: Coord
    y: Coord
    theta: Angle
    v: Speed | None = None
    omega: Rate | None = None
    source: Name = ""
    epoch: Epoch = 0


class Command(_Msg, kw_only=True):
    """``scm/<robot>/cmd``: the learner command to apply, how it was obtained and for how long it is valid.

    ``valid_ms`` counts from the moment the driver host receives the message (clocks need not agree). ``sender``
    and ``epoch`` identify the station run that sent it (see the module docstring). A ``stop`` is a stop: the
    driver host applies exactly zero for it, whatever ``v`` and ``omega`` say.
    """

    stamp: Stamp
    seq: Seq
    v: Speed
    omega: Rate
    method: Method
    valid_ms: Annotated[int, Meta(ge=1, le=10_000)] = 300
    region: Annotated[list[Annotated[int, Meta(ge=0)]], Meta(max_length=8)] = []
    sender: Name = ""
    epoch: Epoch = 0


class TeacherCommand(_Msg, kw_only=True):
    """``scm/<robot>/teacher``: the teacher's own command and the prediction behind it (logging and plots)."""

    stamp: Stamp
    seq: Seq
    v: Speed
    omega: Rate
    solver: Name = ""
    ok: bool = True
    predicted_x: Annotated[list[Coord], Meta(max_length=512)] = []
    predicted_y: Annotated[list[Coord], Meta(max_length=512)] = []
    sender: Name = ""
    epoch: Epoch = 0


class Applied(_Msg, kw_only=True):
    """``scm/<robot>/applied``: what the vehicle really got and when (driver-host clock).

    ``cmd_seq`` is the ``Command.seq`` it came from, or absent for a stop the driver host decided itself
    (``reason`` says why: stop (a stop command), refused (outside what the vehicle can do in that direction: never
    mirrored into motion the other way), deadman, estop, stale, start (no command yet), fault (a controller error),
    operator (the vehicle's operator took control), link_down, no_telemetry (no pose from the vehicle lately),
    disengaged (no person has engaged the vehicle since the host started), conflict (two senders on one command
    epoch: stopped until one of them has been silent for the silence timeout)).
    """

    stamp: Stamp
    seq: Seq
    v: Speed
    omega: Rate
    reason: Literal["cmd", "clamped", "refused", "stop", "deadman", "estop", "stale", "start", "fault",
                    "operator", "link_down", "no_telemetry", "disengaged", "conflict"]
    cmd_seq: Seq | None = None


class PairRecord(_Msg, kw_only=True, array_like=True):
    """One refined command pair ``<u_T, u_L>`` with its stable id, version and cluster size."""

    id: Annotated[int, Meta(ge=0)]
    version: Annotated[int, Meta(ge=0)]
    count: Annotated[int, Meta(ge=0)]
    teacher_v: Speed
    teacher_omega: Rate
    learner_v: Speed
    learner_omega: Rate


class CellChange(_Msg, kw_only=True, array_like=True):
    """A refinement cell whose learner changed and was re-learned (``[transfer] adapt``): its id (the refined pair's),
    how often, and the station's wall-clock time of the last change (``time.time()``; None: not known)."""

    id: Annotated[int, Meta(ge=0)]
    count: Annotated[int, Meta(ge=1)]
    at: WallTime | None = None


class Pairs(_Msg, kw_only=True):
    """``scm/<robot>/pairs``: the refined pairs and the learned limits on the teacher domain (query reply)."""

    stamp: Stamp
    robot: Name
    pairs: Annotated[list[PairRecord], Meta(max_length=100_000)] = []
    limits_box: Annotated[list[Annotated[float, Meta(ge=-100, le=100)]], Meta(min_length=4, max_length=4)] | None = (
        None  # [v_min, v_max, omega_min, omega_max] on the teacher domain
    )
    limits_hull: Annotated[list[Annotated[list[Annotated[float, Meta(ge=-100, le=100)]], Meta(min_length=2, max_length=2)]], Meta(max_length=10_000)] = []  # noqa: E501
    # the station's command bounds [v_min, v_max, omega_min, omega_max] and refinement grid [n_v, n_omega], so a
    # reader can draw and index the pairs without the station's configuration (absent from older stations)
    teacher_bounds: Annotated[list[Annotated[float, Meta(ge=-100, le=100)]], Meta(min_length=4, max_length=4)] | None = None  # noqa: E501
    learner_bounds: Annotated[list[Annotated[float, Meta(ge=-100, le=100)]], Meta(min_length=4, max_length=4)] | None = None  # noqa: E501
    grid: Annotated[list[Annotated[int, Meta(ge=1, le=1000)]], Meta(min_length=2, max_length=2)] | None = None
    # the cells re-learned because their learner changed, the most recent last (empty, so not sent, when none was or
    # from a station older than the field)
    changed: Annotated[list[CellChange], Meta(max_length=100_000)] = []


Bound = Annotated[float, Meta(ge=-100, le=100)]


class Limits(_Msg, kw_only=True):
    """``scm/<robot>/limits``: the learned learner limits on the teacher domain, for a teacher that bounds itself.

    ``box`` is [v_min, v_max, omega_min, omega_max]; ``hull`` the convex hull's vertices (counter-clockwise, teacher
    units); ``curvature`` the yaw-rate bound per unit of speed of a learner that cannot turn in place. ``version``
    grows whenever the limits change. Published by the station when they change and each second.
    """

    stamp: Stamp
    robot: Name
    version: Annotated[int, Meta(ge=0)]
    box: Annotated[list[Bound], Meta(min_length=4, max_length=4)]
    hull: Annotated[list[Annotated[list[Bound], Meta(min_length=2, max_length=2)]], Meta(max_length=10_000)] = []
    #: a learner that cannot turn in place (``[transfer] turn = "needs-speed"``): the learned curvatures [k_lo, k_hi]
    #: (rad/m), k_lo v <= omega <= k_hi v; a side not learned yet is null; absent for a learner that turns in place
    curvature: Annotated[list[Annotated[float, Meta(ge=-1e6, le=1e6)] | None], Meta(min_length=2, max_length=2)] \
        | None = None


XY = Annotated[list[Coord], Meta(min_length=2, max_length=2)]


class MissionSpec(_Msg, kw_only=True):
    """A mission: a path to follow to its goal, the obstacles, the frame the poses are in.

    The same Struct is a mission file (TOML, ``scmbridge station --mission FILE``) and the ``scm/<robot>/mission``
    message that gives a running station a new mission. ``path`` is a polyline of waypoints (>= 2, metres, in
    ``frame``); the goal is its last point, reached within ``goal_tolerance``; ``obstacles`` are discs
    ``[x, y, r]``; ``start`` is the pose a simulation starts from (a real robot starts where it is).
    """

    name: Name = "mission"
    frame: Name = "world"
    path: Annotated[list[XY], Meta(min_length=2, max_length=100_000)]
    goal_tolerance: Annotated[float, Meta(gt=0.0, le=1e3)] = 0.25
    obstacles: Annotated[list[Annotated[list[Coord], Meta(min_length=3, max_length=3)]], Meta(max_length=10_000)] = []
    start: Annotated[list[Coord], Meta(min_length=3, max_length=3)] | None = None
    stamp: Stamp = 0.0
    #: the mission's corridor: the station stops the robot and pauses the mission when its pose is farther than this
    #: from the path (None: the station's ``[station] corridor_m``)
    corridor_m: Annotated[float, Meta(gt=0.0, le=1e3)] | None = None
    #: a polygon (>= 3 vertices, in ``frame``) the robot must stay inside (empty: the station's ``[station] fence``)
    fence: Annotated[list[XY], Meta(max_length=1000)] = []

    def __post_init__(self) -> None:
        if self.fence and len(self.fence) < 3:
            raise ValueError(f"the fence has {len(self.fence)} vertices; a polygon needs at least 3")
        for i, (_, _, r) in enumerate(self.obstacles):
            if not r > 0.0:
                raise ValueError(f"obstacle {i} has radius {r}; a radius must be > 0")
        pts = self.path
        if all(pts[i] == pts[i + 1] for i in range(len(pts) - 1)):
            raise ValueError("the path has no length (all waypoints are the same point)")


#: what a node is doing, for ``scmbridge status`` and the log; ``text`` gives the one reason in words
NodeState = Literal["", "driving", "idle", "running", "paused", "finished", "aborted", "waiting", "estop", "operator",
                    "link_down", "fault", "no_pose", "starting", "dry_run", "parked"]


#: why a node is in its state, typed: what programs decide on (the station's fitness, ``scmbridge status``), while
#: ``text`` says it in words for people and may be reworded freely. Both nodes: ``ok`` (nothing stands in the way:
#: driving), ``no_telemetry`` (no fresh pose). The driver host (in this order): ``estop`` (latched; also in a dry
#: run), ``latch_unsaved`` (latched, and the latch or its release could not be saved: the host refuses to engage
#: until a release is saved; a station takes it as ``estop``), ``dry_run``, ``starting`` (opening the link),
#: ``link_down``, ``not_engaged`` (no person engaged the vehicle yet, or the operator has yet to hand it over),
#: ``operator`` (a person took the vehicle), ``fault`` (the link says the vehicle cannot drive: a controller fault, a
#: lost controller heartbeat, ...), ``conflict`` (two command senders).
#: The station: ``idle``, ``paused``, ``aborted`` (the mission's phase), ``goal_reached``, ``calibration_done``,
#: ``robot_not_ready`` (the driver host's status is missing, late or not ok), ``teacher`` (the command source gives
#: nothing to drive: an external teacher silent or saying stop, no primitive within the learned limits),
#: ``persist_failed`` (the pair store or the mission state not saved), ``integrity`` (another command sender, or
#: implausible telemetry), and its guards (a paused mission, only a person resumes): ``left_corridor`` (the pose
#: farther than the corridor from the path), ``pose_jump`` (the pose moved farther than the robot could in one
#: interval), ``fence`` (the pose outside the lab's fence), ``outside_assumption`` (the mission's path bends more
#: than the measured vehicle can follow within the corridor: outside the method's assumption)
Reason = Literal["ok", "no_telemetry", "estop", "dry_run", "starting", "link_down", "not_engaged", "operator", "fault",
                 "conflict", "idle", "paused", "aborted", "goal_reached", "calibration_done", "robot_not_ready",
                 "teacher", "persist_failed", "integrity", "latch_unsaved", "left_corridor", "pose_jump", "fence",
                 "outside_assumption"]


#: how many changed cells a station's status names (the most recent; ``scmbridge pairs show`` names them all)
STATUS_CHANGED_CELLS = 16


#: measured body speeds ``[v, omega]`` (m/s, rad/s), finite and bounded
BodySpeeds = Annotated[list[Annotated[float, Meta(ge=-100.0, le=100.0)]], Meta(min_length=2, max_length=2)]


class Status(_Msg, kw_only=True):
    """``scm/<robot>/status/<node>``: health of one node; counters only grow. ``state`` says in one word what the
    node is doing (``driving``, ``paused``, ``estop``, ...), ``reason`` why (typed: :data:`Reason`; None from a node
    older than the field) and ``text`` why in words, for people only; ``progress`` is the station's share of its
    mission done (0..1); ``host`` the node's machine and boot (``lab-pc/3f2a9c1e``: equal for two nodes that share a
    monotonic clock; None from a node older than the field)."""

    stamp: Stamp
    seq: Seq
    node: Name
    ok: bool = True
    state: NodeState = ""
    progress: Annotated[float, Meta(ge=0.0, le=1.0)] | None = None
    rates_hz: dict[Name, Annotated[float, Meta(ge=0, le=1e6)]] = {}
    latencies_ms: dict[Name, Annotated[float, Meta(ge=0, le=1e9)]] = {}
    counters: dict[Name, Annotated[int, Meta(ge=0)]] = {}
    text: Text = ""
    reason: Reason | None = None
    host: Name | None = None
    #: the station's: the ids of the cells it re-learned because their learner changed (``[transfer] adapt``), the
    #: most recent last, at most :data:`STATUS_CHANGED_CELLS` of them (empty, so not sent, when none was)
    changed_cells: Annotated[list[Annotated[int, Meta(ge=0, le=1_000_000)]], Meta(max_length=64)] = []
    #: the driver host's: the vehicle's measured body speeds ``[v, omega]`` (m/s, rad/s) from its link's poses or
    #: speeds while they are fresh (None: not measured now, or a node older than the field): ``scmbridge status``
    #: says *moving* or *stopped* from it, never from what was commanded
    measured: BodySpeeds | None = None
    #: the driver host's: a person engaged the vehicle (None: a node older than the field, or not a driver host)
    engaged: bool | None = None
    #: the station's: the latest pose's distance from its mission's path, m (None: no pose or no mission)
    off_path_m: Annotated[float, Meta(ge=0.0, le=1e7)] | None = None


class Estop(_Msg, kw_only=True):
    """``scm/<robot>/estop``: stop now. ``engaged=False`` releases a latched estop, but only from a ``source`` the
    driver host's configuration names (releasing is as deliberate as engaging), stamped with a fresh wall-clock
    ``wall_time`` and a ``nonce`` not seen before (a release without them, recorded and replayed, or from an old
    tool, is refused). A stop (``engaged=True``) is always honoured, stamped or not. The key is also a queryable: a
    ``get`` on it returns each driver host's :class:`EstopState`."""

    stamp: Stamp
    seq: Seq = 0
    engaged: bool = True
    source: Name = ""
    reason: Text = ""
    wall_time: WallTime = 0.0
    nonce: Nonce = ""
    #: the process the act is for: its ``epoch`` and an ``echo`` of its monotonic clock, read off one of its answers
    #: (``bridge.core.acts``); 0: names none (an older tool: refused where it matters)
    target: Epoch = 0
    echo: Stamp = 0.0


class EstopState(_Msg, kw_only=True):
    """A driver host's answer to a query on ``scm/<robot>/estop``: is the estop latched there, and by whom."""

    stamp: Stamp
    node: Name
    latched: bool
    source: Name = ""
    reason: Text = ""
    #: why the last release was refused (a source not configured, a stale or replayed request), for a few seconds
    release_refused: Text = ""
    #: this process's epoch (a new one at each start): a person's act names it (``bridge.core.acts``; 0: older node)
    epoch: Epoch = 0


MissionAction = Literal["start", "pause", "resume", "abort", "send", "status"]
MissionPhase = Literal["idle", "running", "paused", "finished", "aborted"]


class MissionRequest(_Msg, kw_only=True):
    """A query on ``scm/<robot>/control``: a person's request to the station (``send`` carries the new mission).

    Every action but ``status`` must carry a fresh wall-clock ``wall_time`` (within 10 s of the station's clock) and
    a ``nonce`` the station has not seen: a request recorded and replayed, or one from an old tool without them, is
    refused (``bridge.core.acts``)."""

    stamp: Stamp
    action: MissionAction
    spec: MissionSpec | None = None
    source: Name = ""
    wall_time: WallTime = 0.0
    nonce: Nonce = ""
    #: a person's explicit override of a guard's pause (``mission resume --override``): resume with the robot still
    #: outside the corridor or the fence, to drive it back (the guard re-arms once it is back inside)
    override: bool = False
    #: the process the act is for: its ``epoch`` and an ``echo`` of its monotonic clock, read off one of its answers
    #: (``bridge.core.acts``); 0: names none (an older tool: refused where it matters)
    target: Epoch = 0
    echo: Stamp = 0.0


class MissionState(_Msg, kw_only=True):
    """The station's answer on ``scm/<robot>/control``: the mission's phase after the request, whether the request
    was done (``accepted``) and, in words, what was done or why it was refused (``text``) and why the mission is
    where it is (``reason``: ``paused: estop latched by operator``)."""

    stamp: Stamp
    robot: Name
    phase: MissionPhase
    mission: Name = ""
    accepted: bool = True
    text: Text = ""
    reason: Text = ""
    progress: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.0
    #: the mission came from a publisher on ``scm/<robot>/mission``, not from a person's ``send``: where from and
    #: when (wall clock), so the operator looks at it before ``start`` (empty once a person started or sent one)
    replaced_by: Text = ""
    replaced_at: WallTime = 0.0
    #: this process's epoch (a new one at each start): a person's act names it (``bridge.core.acts``; 0: older node)
    epoch: Epoch = 0


class EngageRequest(_Msg, kw_only=True):
    """A query on ``scm/<robot>/engage``: a person asks the driver host to take the vehicle into its control
    (``engaged=False``: hand it back, stopped; ``clear_faults``: also clear what the controllers latched).

    Engaging needs a fresh wall-clock ``wall_time`` and a ``nonce`` the host has not seen (a recorded request
    replayed, or one from an old tool, is refused); handing the vehicle back (a stop) is always honoured."""

    stamp: Stamp
    engaged: bool = True
    source: Name = ""
    clear_faults: bool = False
    wall_time: WallTime = 0.0
    nonce: Nonce = ""
    #: the process the act is for: its ``epoch`` and an ``echo`` of its monotonic clock, read off one of its answers
    #: (``bridge.core.acts``); 0: names none (an older tool: refused where it matters)
    target: Epoch = 0
    echo: Stamp = 0.0


class EngageState(_Msg, kw_only=True):
    """The driver host's answer on ``scm/<robot>/engage``: engaged or not after the request, and in words what was
    done or why not (``waiting for the operator: mode HOLD, disarmed``)."""

    stamp: Stamp
    node: Name
    engaged: bool
    accepted: bool = True
    text: Text = ""
    #: this process's epoch (a new one at each start): a person's act names it (``bridge.core.acts``; 0: older node)
    epoch: Epoch = 0


class MessageError(ValueError):
    """A payload that failed to decode or validate; the receiver counts it and drops it."""


MsgT = TypeVar("MsgT", bound=Struct)

_encoder = msgspec.msgpack.Encoder()
_decoders: dict[type, msgspec.msgpack.Decoder] = {}


def encode(msg: Struct) -> bytes:
    """MessagePack bytes of ``msg`` (no validation: senders build messages from checked values)."""
    return _encoder.encode(msg)


#: what a decoder raises for a payload that is not a valid message (msgspec lets invalid UTF-8 in a str field escape
#: as UnicodeDecodeError: found by hypothesis)
DECODE_ERRORS = (msgspec.ValidationError, msgspec.DecodeError, UnicodeDecodeError)


def decoder(kind: type[MsgT]) -> msgspec.msgpack.Decoder:
    """The one decoder of ``kind`` (it validates as it decodes): ``decoder(kind).decode(data)`` is :func:`decode`
    without the wrapping, for a loop that decodes many samples and handles :data:`DECODE_ERRORS` itself."""
    dec = _decoders.get(kind)
    if dec is None:
        dec = _decoders[kind] = msgspec.msgpack.Decoder(kind)
    return dec


def decode(data: bytes | bytearray | memoryview, kind: type[MsgT]) -> MsgT:
    """Decode *and validate* ``data`` as ``kind``; raise :class:`MessageError` naming the problem."""
    try:
        return decoder(kind).decode(data)
    except DECODE_ERRORS as exc:
        raise MessageError(f"bad {kind.__name__}: {exc}") from exc


def validated(msg: MsgT) -> MsgT:
    """Round-trip a locally built message through the decoder: the cheap way to check it before sending."""
    return decode(encode(msg), type(msg))


def validated_bytes(msg: MsgT) -> tuple[MsgT, bytes]:
    """:func:`validated`, and the bytes it checked: the sender puts them on the wire as they are instead of
    encoding the message a second time (the same bytes: encoding is deterministic)."""
    data = encode(msg)
    return decode(data, type(msg)), data


class JournalSample(Struct, kw_only=True, forbid_unknown_fields=True):
    """One input a station tick took (:class:`StationJournal`): ``kind`` ``state`` or ``applied``, its receipt time
    on the station's clock and its wire bytes as decoded (encoded again: the same values)."""

    kind: Literal["state", "applied"]
    at: Stamp
    data: Annotated[bytes, Meta(max_length=4096)]


class StationJournal(_Msg, kw_only=True):
    """``scm/<robot>/journal``: what a station's core was given, one event each, in order, so that ``scmbridge replay
    --through-station`` feeds a fresh core the same and compares its commands with the recorded ones
    (docs/OPERATING.md, "Why did it do that"). ``event``: ``tick`` (``periodic``, the inputs it took: poses and
    echoes with their receipt times, the driver host's status, a new mission, an external teacher's command, the
    transport's counts, the missed deadlines; ``compiled``: the MPC ran its compiled code), ``driver`` (a status
    noted between two ticks, before a request) or ``request`` (a person's mission request acted on). ``stamp``: the
    event's time on the station's clock; ``seq`` counts events from 0 at the station's start; ``config`` and
    ``store``: digests of its configuration and of the pair store it started from; ``control``: the mission state
    it started with (the first event only). Published while someone subscribes (a recorder; the first events are
    kept until one is heard)."""

    stamp: Stamp
    seq: Seq
    robot: Name
    epoch: Epoch
    event: Literal["tick", "driver", "request"]
    periodic: bool = True
    telemetry: Annotated[list[JournalSample], Meta(max_length=100000)] = []
    driver: Annotated[bytes, Meta(max_length=65536)] = b""
    driver_at: Stamp = 0.0
    mission: Annotated[bytes, Meta(max_length=1 << 22)] = b""
    teacher: Annotated[bytes, Meta(max_length=65536)] = b""
    teacher_at: Stamp = 0.0
    input_counts: dict[Name, Annotated[int, Meta(ge=0)]] = {}
    missed: Annotated[int, Meta(ge=0)] = 0
    request: Annotated[bytes, Meta(max_length=1 << 22)] = b""
    compiled: bool = False
    rate_hz: Annotated[float, Meta(gt=0.0, le=1000.0)] = 10.0
    wall_offset: Annotated[float, Meta(ge=-1e12, le=1e12)] = 0.0
    config: Name = ""
    store: Name = ""
    control: Annotated[bytes, Meta(max_length=1 << 22)] = b""


def _every_message_type() -> list[type]:
    found, todo = [], list(_Msg.__subclasses__())
    while todo:
        kind = todo.pop()
        found.append(kind)
        todo += kind.__subclasses__()
    return found


# Every message type's decoder is built here, at import, by one thread: msgspec (0.22) building a Decoder while
# another thread decodes can crash the process (SIGSEGV), so the many robot threads of one station process must
# never build one on first use. A type outside this module still gets its decoder on first use.
for _kind in _every_message_type():
    _decoders[_kind] = msgspec.msgpack.Decoder(_kind)


__all__ = [
    "TOPICS",
    "Applied",
    "Command",
    "CellChange",
    "EngageRequest",
    "EngageState",
    "Estop",
    "EstopState",
    "JournalSample",
    "Keys",
    "LearnerState",
    "Limits",
    "MessageError",
    "Method",
    "MissionRequest",
    "MissionSpec",
    "MissionState",
    "PairRecord",
    "Pairs",
    "Reason",
    "StationJournal",
    "Status",
    "TeacherCommand",
    "check_robot",
    "decode",
    "encode",
    "key",
    "new_epoch",
    "new_nonce",
    "status_key",
    "alive_key",
    "validated",
    "validated_bytes",
]
