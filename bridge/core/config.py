"""Typed configuration: the station's settings as msgspec Structs, from TOML, and what every configuration is made of.

The driver host's configuration (:mod:`bridge.nodes.driver_config`) and each link's (``CONFIG`` in its module under
``drivers/``) are built from the same pieces: :class:`Cfg` (unknown keys are errors), :func:`meta` (a key's meaning
and range), :class:`Rule` (a cross-field rule) and the decoder here (``msgspec.convert``, its errors put in the
project's words). Every command that takes a configuration decodes it here before it opens any link or session. A
mistake is refused with :class:`ConfigError`, whose text is one line naming the file, the key path and the problem
(for an unknown key, the nearest valid name): ``driver.toml: driver.cmd_timout: unknown key (did you mean
'cmd_timeout'?)``. Numbers are finite and within the ranges written in
their types; cross-field rules (``min < max``, distinct CAN nodes) are checked in ``__post_init__``. ``scmbridge
config check FILE`` validates a file and ``scmbridge config show --kind station|driver|mission`` prints a commented
default made from these types (docs/ARCHITECTURE.md, "Configuration").
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
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

import msgspec
from msgspec import Meta, Struct, field

from bridge.core.errors import UsageError
from bridge.core.paths import TEXT_FILE, NotAFile, read_bounded, state_dir
from bridge.core.wire import MissionSpec
from transfer import paper

if TYPE_CHECKING:  # imported where first used: a tool that only reads a file never loads the numerical stack
    from transfer.domain import Bounds
    from transfer.mission import Mission


class ConfigError(UsageError, ValueError):
    """A configuration the user has to fix; ``str()`` is the one line to print."""

    def __init__(self, source: str, where: str, problem: str) -> None:
        self.source, self.where, self.problem = source, where, problem
        super().__init__(f"{source}: {where}: {problem}" if where else f"{source}: {problem}")


class Rule(ValueError):
    """A cross-field rule a configuration breaks (raised by ``__post_init__``; a ValueError, so ``msgspec.convert``
    reports it with the path of the table it belongs to)."""


def meta(description: str, **bounds: float) -> Meta:
    """A key's meaning and range, as ``config show`` prints them and the validator checks them."""
    return Meta(description=description, **bounds)


Finite = Annotated[float, Meta(ge=-1e9, le=1e9)]  # a NaN or inf fails the comparison and is refused
Range = tuple[Finite, Finite]
RobotName = Annotated[str, Meta(pattern=r"^[A-Za-z0-9_\-]{1,64}$", description="one Zenoh key chunk")]
Port = Annotated[int, Meta(ge=0, le=65535)]
#: a station's tick rate, Hz: below, a command's validity (three periods) would exceed the wire's 10 s
RATE_HZ_RANGE = (0.5, 200.0)


class Cfg(Struct, forbid_unknown_fields=True, kw_only=True, frozen=True):
    """Base: unknown keys are errors."""


class BoundsConfig(Cfg):
    """A (v, omega) command box."""

    v: Annotated[Range, meta("linear speed [min, max], m/s")]
    w: Annotated[Range, meta("yaw rate [min, max], rad/s (counter-clockwise positive)")]

    def __post_init__(self) -> None:
        for name, (lo, hi) in (("v", self.v), ("w", self.w)):
            if not lo < hi:
                raise Rule(f"{name} = [{lo}, {hi}]: min must be < max")

    def bounds(self) -> Bounds:
        from transfer.domain import Bounds

        return Bounds(tuple(self.v), tuple(self.w))


# -------------------------------------------------------------------------------------------------- station
class StationSection(Cfg):
    """``[station]``: the loop, persistence and the mission."""

    rate_hz: Annotated[float, meta("control tick rate, Hz (the paper's 10 Hz)", ge=RATE_HZ_RANGE[0],
                                   le=RATE_HZ_RANGE[1])] = 10.0
    pair_dt: Annotated[float, meta("pairing interval, s", ge=0.01, le=10.0)] = 0.1
    pair_settle_s: Annotated[float, meta(
        "keep only pairs whose learner command had been steady (within pair_settle_tol) this long before the pair's "
        "interval, s; for a vehicle whose body lags its command (ArduPilot Rover: ~0.3 s), so that the probe of a "
        "learned limit is held until the speed settles; 0: every pair, as the paper's learners", ge=0.0, le=5.0)] = 0.0
    pair_settle_edge_s: Annotated[float, meta(
        "pair_settle_s for a command on an edge of the learner's range (the probe of a limit, a step from rest to "
        "the top), if longer: for a body slower to reach its top than to follow a mission's small steps (ArduPilot's "
        "Ackermann rover: ~2 s); 0: pair_settle_s for every command", ge=0.0, le=10.0)] = 0.0
    pair_settle_tol: Annotated[float, meta(
        "pair_settle_s: how far the commands of that time may differ from the pair's, share of the learner's range "
        "on each axis", gt=0.0, le=1.0)] = 0.05
    horizon: Annotated[int, meta("MPC horizon N, steps", ge=2, le=200)] = 20
    persist_every_s: Annotated[float, meta("save the pair store this often, s", ge=0.1, le=86400.0)] = 5.0
    store_path: Annotated[str, meta("pair store file; empty: pairs-<robot>.bin in the state directory")] = ""
    mission: Annotated[str, meta("mission file (TOML); empty: the paper's S-path shipped with scmbridge")] = ""
    max_pose_age_s: Annotated[float, meta("a pose older than this stops planning (the station publishes stops), s",
                                          gt=0.0, le=60.0)] = 0.5
    corridor_m: Annotated[float, meta(
        "the corridor: a pose farther than this from the mission's path stops the robot and pauses the mission "
        "(reason left_corridor; only a person resumes); a mission file's corridor_m wins, m", gt=0.0, le=1e3)] = 1.0
    fence: Annotated[list[tuple[Finite, Finite]], meta(
        "the lab's fence: a polygon [[x, y], ...] in the missions' frame (>= 3 vertices); a pose outside it stops "
        "the robot and pauses the mission (reason fence); a mission file's fence wins; empty: none",
        max_length=1000)] = []

    def __post_init__(self) -> None:
        if self.fence and len(self.fence) < 3:
            raise Rule(f"fence has {len(self.fence)} vertices: a polygon needs at least 3")


class TransferSection(Cfg):
    """``[transfer]``: refinement grid, the mapper, the exploration and what bounds the teacher (``limits``)."""

    grid: Annotated[tuple[Annotated[int, Meta(ge=2, le=100)], Annotated[int, Meta(ge=2, le=100)]],
                    meta("cells of the normalised learner domain [n_v, n_omega]")] = (11, 11)
    k_min: Annotated[int, meta("pairs a cell needs before it holds a refined pair", ge=1, le=1000)] = 5
    mapper: Annotated[Literal["scm", "affine", "barycentric", "identity"], meta("how a region maps commands")] = "scm"
    seed: Annotated[int, meta("random generator seed of the exploration", ge=0, le=2**32 - 1)] = 0
    exploration: Annotated[Literal["guided", "paper", "off"], meta(
        "guided: explore (perturb) where the command needs a missing pair, at the least detour, steered by the "
        "teacher's plan, and fill the map's holes on the teacher's curve, slower, within fill_budget; paper: the "
        "paper's algorithm as published; off: never perturb (map, or extrapolate "
        "from the learned region)")] = "guided"
    limits: Annotated[Literal["learned", "teacher"], meta(
        "what bounds the station's own teacher (the MPC's inputs, the primitives it plans with): learned, the "
        "learner's limits learned from the pairs (the paper's method, Section 4.2; with mapper = \"identity\" no wider "
        "than the learner's own range, which the commands are clipped to); teacher, the teacher's own range "
        "(teacher_bounds), as if nothing were known of the learner: with mapper = \"identity\" and exploration = "
        "\"off\" the paper's baseline learner, which applies the teacher's commands directly (Section 5.2; "
        "scmbridge sim mpc's teacher_range baseline). Pairs are still formed and stored, and the limits message "
        "still says what was learned; an external teacher bounds itself")] = "learned"
    explore_clearance_m: Annotated[float, meta("no exploration closer than this to an obstacle's edge, whatever the "
                                               "exploration setting, m", ge=0.0, le=100.0)] = 0.3
    # = transfer.policy.FILL_BUDGET, repeated: this module stays free of the numerical stack
    # (tests/unit/bridge/core/test_config.py)
    fill_budget: Annotated[float, meta(
        "guided: the share of the commands served from the learned region that may fill a hole of the map, driving "
        "the teacher's curve slower (0: never)", ge=0.0, lt=1.0)] = 0.08
    # = transfer.policy.TURN_PROBES, repeated for the same reason as fill_budget
    turn_probe: Annotated[Literal["at-command", "at-top-speed"], meta(
        "at which learner speed the probe of a never-driven yaw-rate limit is sent: at-command (the paper's: the "
        "speed the command maps to, the slowest while nothing is learned); at-top-speed (for a learner that cannot "
        "turn in place, e.g. an Ackermann rover: probed at its slowest speed it barely turns, and the learned limits "
        "then allow almost no turn at any speed)")] = "at-command"
    turn: Annotated[Literal["in-place", "needs-speed"], meta(
        "in-place: the learner can turn at any speed (a skid-steer or differential drive; the paper's); "
        "needs-speed: it cannot turn in place (an Ackermann rover): its yaw-rate limit on each side is learned as a "
        "curvature (omega <= kappa v, shown in the limits and pairs show), the MPC plans within it, and the yaw-rate "
        "limits are probed at the learner's top speed (whatever turn_probe says); the teacher's speed must then be "
        "forward only (teacher_bounds v >= 0)")] = "in-place"
    map_choice: Annotated[bool, meta(
        "with mapper = \"scm\": choose per command between the SC map and the triangle's linear interpolation: "
        "the SC map in a triangle that spans a hole of the pairs where the response is flat and the triangle's line "
        "misses its neighbours' pairs, the line elsewhere (docs/PAPER.md, 'The transfer's choice of map'); false, "
        "the paper's SC map wherever it has a region. Off by default: it does not beat interpolation's median on "
        "every store, changes little in the closed loop, and on a calibrated store takes the line everywhere")] = False
    at_limit: Annotated[Literal["row", "region"], meta(
        "how a command at a driven learned limit is mapped: row, interpolated along the limit's row of pairs (a "
        "mission's own pairs there are nearly collinear, so its mapping regions are slivers); region, by the mapping "
        "region just inside the limit, at the learner's extreme on that axis: for a store calibrated at the "
        "learner's extremes (scmbridge calibrate; the paper's calibrated start), whose quadrilaterals there are "
        "well shaped; the row where it has none (docs/PAPER.md, 'The calibrated start')")] = "row"
    adapt: Annotated[bool | Literal["reloaded"], meta(
        "re-learn a cell whose learner changed (a sagging battery, a dragging wheel, a new floor; docs/PAPER.md, "
        "'a learner that changes'): true, always; \"reloaded\", when the station starts on a saved store that "
        "holds refined pairs (a store learned on another day, or before a restart, is checked cell by cell against "
        "today's pairs); false, never (the paper's store). On by default from the first run: where nothing changes "
        "it costs the paper's case nothing measurable (docs/PAPER.md)")] = True
    # = transfer.store.CHANGE_TOL, repeated for the same reason as fill_budget
    change_tol: Annotated[float, meta(
        "adapt: a cell's recent pairs this far from its refined pair (share of the teacher's range) mean its learner "
        "changed (or five standard deviations of their noise, if more)", ge=0.001, le=0.5)] = 0.02
    turn_reach: Annotated[list[Annotated[float, Meta(ge=0.0, le=1e3)]], meta(
        "what was measured of a learner that cannot turn in place: [right, left, speed], its tightest curvature each "
        "way (rad/m) and the speed it was measured at (m/s), as scmbridge demo --sitl's identification writes it; a "
        "mission whose path bends more than it can follow within the corridor is paused before it leaves it (reason "
        "outside_assumption, docs/ARCHITECTURE.md section 6). Empty: not measured, not checked")] = []

    def __post_init__(self) -> None:
        if len(self.turn_reach) not in (0, 3):
            raise Rule(f"turn_reach = {self.turn_reach}: [right, left, speed] or empty")

    def adapts(self, reloaded: bool) -> bool:
        """Whether the store re-learns changed cells (``adapt``'s values): ``reloaded`` says the station started on a
        saved store that holds refined pairs (the one place this rule lives)."""
        return reloaded if self.adapt == "reloaded" else bool(self.adapt)

    def probe_turns(self) -> str:
        """Where the station probes the yaw-rate limits (``turn_probe``'s values): at the top speed for a learner that
        cannot turn in place, whatever ``turn_probe`` says (the one place this rule lives)."""
        return "at-top-speed" if self.turn == "needs-speed" else self.turn_probe


class TeacherSection(Cfg):
    """``[teacher]``: who computes the teacher commands the station maps."""

    kind: Annotated[Literal["mpc", "primitives", "external"], meta(
        "mpc: the built-in MPC follows the mission; primitives: the paper's motion-primitive planner (Section 5.1) "
        "over the primitives the learned limits allow (calibrate first); external: a lab's own teacher publishes "
        "scm/<robot>/teacher and the station only maps (transfer-only service)")] = "mpc"
    primitives_grid: Annotated[int, meta("primitives: an n x n library over the teacher's range", ge=2, le=31)] = 11
    primitive_s: Annotated[float, meta("primitives: each primitive's duration, s", gt=0.0, le=60.0)] = 1.0
    timeout_s: Annotated[float, meta("external: no teacher command for this long makes the station publish stops, s",
                                     gt=0.0, le=10.0)] = 0.3
    mpc_solver: Annotated[Literal["rti-qpoases", "rti-daqp", "ipopt"], meta(
        "mpc: how the MPC is solved: rti-qpoases / rti-daqp, one QP per tick from compiled code (real-time "
        "iteration; built once per machine, in the background, into the cache directory); ipopt, the full "
        "nonlinear program each tick (the reference, about ten times slower)")] = "rti-qpoases"
    obstacle_slots: Annotated[int, meta("mpc: obstacles the MPC considers at once, the nearest within its reach",
                                        ge=1, le=64)] = 12
    curve_margin: Annotated[float, meta(
        "mpc: once the learned limits lost yaw-rate reach (a side's edge came inside the widest it held: a learner "
        "that turns less than it did, e.g. a dragging wheel or a sagging battery), slow down for a bend the learned "
        "yaw-rate limit cannot turn at the top speed, using this share of the limit (0.9 leaves a tenth for the "
        "correction); until then, and with 0 always, the paper's MPC at its top speed everywhere (docs/PAPER.md, "
        "'a learner that changes')", ge=0.0, le=1.0)] = 0.9
    slow_for_bends: Annotated[Literal["changed", "always"], meta(
        "mpc: when curve_margin slows for bends: changed, once the learner changed or lost yaw-rate reach (the "
        "paper's MPC until then); always, from the first tick wherever the learned yaw-rate limit cannot turn a bend "
        "at the top speed (a learner that turns too little from the start, e.g. a weak steering loop)")] = "changed"


class CalibrationSection(Cfg):
    """``[calibration]``: the calibration stage (``scmbridge calibrate``), bounded in time and distance."""

    grid: Annotated[tuple[Annotated[int, Meta(ge=2, le=21)], Annotated[int, Meta(ge=2, le=21)]],
                    meta("learner commands [n_v, n_omega] spanning the learner's box, extremes included")] = (5, 5)
    hold_s: Annotated[float, meta("each command is held this long, s", gt=0.0, le=60.0)] = 1.0
    max_distance_m: Annotated[float, meta("stop calibrating when the robot is this far from where it started, m",
                                          gt=0.0, le=1000.0)] = 2.0
    return_radius_m: Annotated[float, meta("beyond this distance the robot drives back toward the start between "
                                           "commands, m", gt=0.0, le=1000.0)] = 0.8
    max_time_s: Annotated[float, meta("stop calibrating after this long, s", gt=0.0, le=36000.0)] = 300.0

    def __post_init__(self) -> None:
        if self.return_radius_m >= self.max_distance_m:
            raise Rule(f"return_radius_m = {self.return_radius_m} must be below max_distance_m = "
                             f"{self.max_distance_m}")


class FleetSection(Cfg):
    """``[fleet]``: which station host serves which robots when a lab shards its robots over several base-station
    machines behind its Zenoh routers (``scmbridge station --shard HOST``; deploy/README.md, "Several base
    stations"). Every host reads the same file; a robot is served by exactly one host."""

    shards: Annotated[dict[RobotName, list[RobotName]], meta(
        "station host name -> the robots it serves, e.g. base1 = [\"r1\", \"r2\"]")] = field(default_factory=dict)
    robots: Annotated[list[RobotName], meta(
        "the lab's robots besides the shards' (scmbridge estop --all --fleet names each that does not confirm)")] = \
        field(default_factory=list)

    def __post_init__(self) -> None:
        seen: dict[str, str] = {}
        for host, robots in self.shards.items():
            if not robots:
                raise Rule(f"shard {host!r} serves no robot")
            for r in robots:
                if r in seen:
                    raise Rule(f"robot {r!r} is in shards {seen[r]!r} and {host!r}: each robot has one station")
                seen[r] = host


DEFAULT_TEACHER_BOUNDS = BoundsConfig(v=paper.MPC_TEACHER_V, w=paper.MPC_TEACHER_W)
DEFAULT_LEARNER_BOUNDS = BoundsConfig(v=paper.MPC_LEARNER_V, w=paper.MPC_LEARNER_W)


class StationConfig(Cfg):
    """A station's configuration file."""

    robot: RobotName = "learner"
    station: StationSection = field(default_factory=StationSection)
    teacher_bounds: Annotated[BoundsConfig, meta(
        "the teacher's command range (the paper's MPC teacher by default)")] = DEFAULT_TEACHER_BOUNDS
    learner_bounds: Annotated[BoundsConfig, meta("the learner's own command range")] = DEFAULT_LEARNER_BOUNDS
    transfer: TransferSection = field(default_factory=TransferSection)
    teacher: TeacherSection = field(default_factory=TeacherSection)
    calibration: CalibrationSection = field(default_factory=CalibrationSection)
    fleet: FleetSection = field(default_factory=FleetSection)

    def __post_init__(self) -> None:
        if self.transfer.turn == "needs-speed" and self.teacher_bounds.v[0] < 0.0:
            raise Rule(f'transfer.turn = "needs-speed" takes a forward-only teacher (teacher_bounds v >= 0), got v = '
                       f"{list(self.teacher_bounds.v)}: a curvature bound omega <= kappa v does not hold backwards")

    def store_file(self, robot: str | None = None) -> Path:
        """The pair store: ``store_path``, else ``pairs-<robot>.bin`` in the state directory (never the working
        directory: two stations started in one directory must not share a file)."""
        return Path(self.station.store_path or state_dir() / f"pairs-{robot or self.robot}.bin")


C = TypeVar("C", bound=Struct)


# ------------------------------------------------------------------------------------------------- decoding
Path_ = tuple[str | int, ...]
#: msgspec's type names in its messages, as a person reads them
_WORDS = {"int": "a whole number", "float": "a number", "str": "text", "bool": "true or false", "array": "a list",
          "object": "a table", "null": "nothing"}
_GOT = {**_WORDS, "bool": "true/false"}
#: a msgspec ValidationError's text: the problem, then where (a dict key's own problem says ``key`` in the dict)
_AT = re.compile(r"(?s)(.*?)(?: - at `(key)` in `(\$[^`]*)`| - at `(\$[^`]*)`)?")
#: one step of msgspec's path: ``.field``, ``[index]``, or ``[...]`` (a dict's value, its key unnamed)
_STEP = re.compile(r"\.(\w+)|\[(\d+)\]|(\[\.\.\.\])")


def _where(path: Path_) -> str:
    """``driver.hard_limits.v[0]`` for ``("driver", "hard_limits", "v", 0)``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out


def _constraints(tp: Any) -> tuple[Any, list[Meta]]:
    """The type under ``Annotated[...]`` layers and ``... | None``, and every ``Meta`` on the way."""
    metas: list[Meta] = []
    while True:
        if get_origin(tp) is Annotated:
            metas += [m for m in get_args(tp)[1:] if isinstance(m, Meta)]
            tp = get_args(tp)[0]
        elif get_origin(tp) in (Union, types.UnionType) and len(options := [
                a for a in get_args(tp) if a is not type(None)]) == 1:
            tp = options[0]
        else:
            return tp, metas


def _fmt(x: float) -> str:
    return repr(float(x)) if isinstance(x, float) else str(x)


def _converts(value: Any, tp: Any) -> bool:
    try:
        msgspec.convert(value, tp)
    except msgspec.ValidationError:
        return False
    return True


def _child(tp: Any, value: Any, step: str | int | None) -> tuple[Any, Any, str | int]:
    """The type and the TOML value one step down msgspec's path (``step`` None: a dict's value, found again as the
    first entry that does not convert)."""
    base, _ = _constraints(tp)
    args = get_args(base)
    if isinstance(base, type) and issubclass(base, Struct):
        return get_type_hints(base, include_extras=True)[step], value[step], step
    if get_origin(base) is dict:
        key = next(k for k, v in value.items() if not _converts(v, args[1])) if step is None else step
        return args[1], value[key], key
    if get_origin(base) is tuple and not (len(args) == 2 and args[1] is Ellipsis):
        return args[step], value[step], step
    return args[0], value[step], step


def _non_finite(value: Any, path: Path_) -> tuple[Path_, float] | None:
    """The first NaN or infinity in a TOML value, with its path (a float without a range accepts them)."""
    if isinstance(value, float) and not math.isfinite(value):
        return path, value
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for k, v in items:
        if bad := _non_finite(v, (*path, k)):
            return bad
    return None


def _problem(text: str, tp: Any, value: Any) -> str:
    """msgspec's complaint ``text`` about ``value`` (of type ``tp``) in the words of docs/ARCHITECTURE.md §5."""
    base, metas = _constraints(tp)
    if get_origin(base) is Literal:
        return f"must be one of {', '.join(repr(a) for a in get_args(base))}, got {value!r}"
    if isinstance(value, float) and not math.isfinite(value) and text.startswith("Expected `float`"):
        return f"expected a finite number, got {value}"
    if m := re.fullmatch(r"Expected `\w+` (>=|>|<=|<) (\S+)", text):
        if m[2].lstrip("-") == "1000000000.0":  # Finite
            return f"expected a number between -1e9 and 1e9, got {_fmt(value)}"
        return f"must be {m[1]} {m[2]}, got {_fmt(value)}"
    if m := re.fullmatch(r"Expected `\w+` of length (>=|<=) (\d+)", text):
        return ("needs at least {}" if m[1] == ">=" else "at most {} allowed").format(m[2]) + f" (length {len(value)})"
    if m := re.fullmatch(r"Expected `array` of length (\d+), got (\d+)", text):
        return f"expected a list of length {m[1]}, got length {m[2]}"
    if text.startswith("Expected `str` matching regex"):
        pattern = next(m for m in metas if m.pattern is not None)
        desc = next((f" ({m.description})" for m in metas if m.description), "")
        return f"{value!r} does not match {pattern.pattern}{desc}"
    if m := re.fullmatch(r"Expected `([^`]+)`, got `(\w+)`", text):
        want = " or ".join(_WORDS.get(w, w) for w in m[1].split(" | ") if w != "null")
        return f"expected {want}, got {_GOT.get(m[2], m[2])}"
    return text.replace("`", "'")  # pragma: no cover - a message msgspec did not write when this was


def _config_error(exc: msgspec.ValidationError, table: dict[str, Any], kind: type[Struct], source: str) -> ConfigError:
    """msgspec's error as the project's one line: the file, the key path in dotted form, the problem."""
    text, key, key_in, at = _AT.fullmatch(str(exc)).groups()  # type: ignore[union-attr]
    tp, value, path = kind, table, ()
    try:
        for m in _STEP.finditer(key_in or at or "$"):
            tp, value, step = _child(tp, value, m[1] or (int(m[2]) if m[2] else None))
            path = (*path, step)
    except (KeyError, IndexError, TypeError, StopIteration):  # pragma: no cover - a path msgspec names is there
        return ConfigError(source, _where(path), text.replace("`", "'"))
    if isinstance(exc.__cause__, ValueError):  # a Rule (or a wire Struct's ValueError) from __post_init__
        bad = _non_finite(value, path)
        return ConfigError(source, _where(bad[0]), f"expected a finite number, got {bad[1]}") if bad else (
            ConfigError(source, _where(path), str(exc.__cause__)))
    if text.startswith("Object contains unknown field"):
        fields = list(_constraints(tp)[0].__struct_fields__)
        unknown = next(k for k in value if k not in fields)
        close = difflib.get_close_matches(str(unknown), fields, n=1, cutoff=0.5)
        hint = f" (did you mean '{close[0]}'?)" if close else f" (valid: {', '.join(fields)})"
        return ConfigError(source, _where((*path, unknown)), f"unknown key{hint}")
    if m := re.fullmatch(r"Object missing required field `(\w+)`", text):
        return ConfigError(source, _where((*path, m[1])), "required key is missing")
    if key:  # a dict's key
        key_tp = get_args(_constraints(tp)[0])[0]
        bad_key = next(k for k in value if not _converts(k, key_tp))
        return ConfigError(source, _where(path), "key " + _problem(text, key_tp, bad_key))
    return ConfigError(source, _where(path), _problem(text, tp, value))


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
    try:  # a regular file of bounded size: a FIFO would hang the command, /dev/zero fill its memory
        data = read_bounded(p, TEXT_FILE)
    except FileNotFoundError:
        raise ConfigError(str(p), "", "no such file") from None
    except (IsADirectoryError, NotAFile) as exc:
        if p.is_dir():
            raise ConfigError(str(p), "", "is a directory, not a configuration file") from None
        raise ConfigError(str(p), "", str(exc)) from None
    except OSError as exc:
        raise ConfigError(str(p), "", f"cannot read: {exc.strerror or exc}") from None
    return parse_toml(data, str(p))


def from_table(table: dict[str, Any], kind: type[C], source: str) -> C:
    """``table`` converted into ``kind`` (``msgspec.convert``: the types' ranges, unknown keys, the ``Rule``s of
    ``__post_init__``); :class:`ConfigError` naming the key, and for an unknown key the nearest valid name. Every
    number is finite, also one whose type has no range."""
    try:
        out = msgspec.convert(table, kind)
    except msgspec.ValidationError as exc:
        raise _config_error(exc, table, kind, source) from None
    if bad := _non_finite(table, ()):
        raise ConfigError(source, _where(bad[0]), f"expected a finite number, got {bad[1]}")
    return out


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
    from transfer.mission import Mission
    from transfer.teacher.path import Polyline

    return Mission(spec.name, Polyline(spec.path), spec.obstacles or [], spec.goal_tolerance, spec.start, spec.frame)


def load_mission_spec(path: str | Path | None = None) -> MissionSpec:
    """A mission file (TOML), or a shipped mission by name (``paper-s-path``, the default)."""
    name = str(path) if path else "paper-s-path"
    if name in SHIPPED_MISSIONS:
        text = resources.files("bridge").joinpath("missions", SHIPPED_MISSIONS[name]).read_bytes()
        return decode_toml(text, MissionSpec, f"<shipped mission {name}>")
    return load(name, MissionSpec)


def load_fence(path: str | Path) -> list[tuple[float, float]]:
    """The fence of a mission file (its ``fence``) or a station configuration (``[station] fence``): a polygon in the
    lab's frame; :class:`ConfigError` when the file has none."""
    kind = guess_kind(read_table(path))
    fence = load_mission_spec(path).fence if kind == "mission" else load_station(path).station.fence
    if not fence:
        where = "fence" if kind == "mission" else "[station] fence"
        raise ConfigError(str(path), where, "no fence in this file (a polygon [[x, y], ...] of >= 3 vertices)")
    return [(float(x), float(y)) for x, y in fence]


def load_mission(path: str | Path | None = None) -> Mission:
    """See :func:`load_mission_spec`; geometry problems (a degenerate path) are ConfigErrors too."""
    spec = load_mission_spec(path)
    try:
        return mission_from_spec(spec)
    except ValueError as exc:
        raise ConfigError(str(path or "paper-s-path"), "", str(exc)) from None


__all__ = [
    "BoundsConfig",
    "CalibrationSection",
    "Cfg",
    "ConfigError",
    "Finite",
    "Port",
    "RobotName",
    "Rule",
    "StationConfig",
    "StationSection",
    "TeacherSection",
    "TransferSection",
    "decode_toml",
    "load",
    "load_fence",
    "load_mission",
    "load_mission_spec",
    "load_station",
    "meta",
    "mission_from_spec",
]
