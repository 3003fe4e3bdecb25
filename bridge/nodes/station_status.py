"""What the station says about itself: its status (``scm/<robot>/status/station``), the learned limits it publishes
(``scm/<robot>/limits``), and the one reason it does not drive, in words (pure: times are arguments; no Zenoh;
docs/ARCHITECTURE.md, "Reasons are typed, words are for people").

The station's core (:mod:`bridge.nodes.station_core`) decides each tick whether it drives and keeps its typed
reason; this module turns that into what people and programs read:

- :func:`not_driving` and :func:`paused_text`: the one reason the robot is not driven, typed from the mission's
  phase and in words for the status line and the log (``idle: ...``, ``paused: estop latched by operator``,
  ``waiting for the robot: ...``, ``goal reached``);
- :class:`Integrity`: what makes the station's work untrustworthy right now (another sender's commands on this
  robot's key, telemetry dropped as implausible): its status is then not ok for :data:`INTEGRITY_WINDOW_S`;
- :class:`StatusReport`: the status message (ok, state, reason, text, latencies, :class:`StationCounters`), sent
  each second and at once when what a person reads it for changes (:func:`status_key`), at most
  :data:`STATUS_MAX_HZ` a second;
- :class:`LimitsReport`: the learned limits, when their box moved or each second, versioned.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from bridge.core import wire as M
from bridge.core.clock import machine
from bridge.nodes.mission_control import MissionControl
from bridge.nodes.pairing import IntervalPairer
from bridge.nodes.sources import Why
from transfer.store import PairStore

#: an integrity problem (another sender, implausible telemetry) keeps the status not ok this long, s
INTEGRITY_WINDOW_S = 5.0
#: the station's reasons under which it does what it should (its status is then ok, unless its work is untrustworthy)
GOOD_REASONS: tuple[M.Reason, ...] = ("ok", "goal_reached", "calibration_done")
#: the status (and the forced limits) go out this often, s; and at once when what it says changes, but at most
#: STATUS_MAX_HZ a second
STATUS_EVERY_S = 1.0
STATUS_MAX_HZ = 20.0
#: between two forced ones, the limits go out when an edge of their box moved more than this fraction of the
#: teacher's range (half a percent: the store's own tolerance for moving a refined pair)
LIMITS_MOVE_TOL = 0.005


# ------------------------------------------------------------------------------------------ why not driving
def not_driving(control: MissionControl, robot: str, unfit: Why | None) -> Why:
    """The one reason the robot is not driven this tick (typed from the mission's phase, in words for the status
    line and the log), whatever the words: a paused mission whose reason is empty still stops. ``unfit``: why the
    robot is not fit to drive now (None: it is)."""
    c = control
    if c.phase == "idle":
        if c.replaced_by:  # a program's mission, loaded idle: say where it came from before anyone starts it
            return Why(f"idle: {c.reason}", "idle")
        return Why(f"idle: waiting for a person (scmbridge mission start --robot {robot})", "idle")
    if c.phase == "finished":
        return Why("goal reached", "goal_reached")
    if c.phase == "running":
        if unfit is None:  # (may_drive refuses a running mission only for an unfit robot)
            unfit = Why("not fit", "robot_not_ready")
        return Why(f"waiting for the robot: {unfit.text}", unfit.reason)
    if c.phase == "paused":  # a guard's pause says which guard (left_corridor, fence, pose_jump)
        return Why(paused_text(control, robot, unfit), c.guard or "paused")
    return Why(c.reason or c.phase, "aborted")  # by whom


def paused_text(control: MissionControl, robot: str, unfit: Why | None) -> str:
    """Why a paused mission is paused, as it is now, and the next step: a pause the robot caused (an estop, a lost
    pose, ...) says the robot's reason now, or that it is fit again, and a person's (or a restart's) stays, and
    either way says how to drive on once the robot is fit (not a stale reason: "estop latched" after the release,
    or "no pose" after a driver host's crash with the poses back)."""
    c = control
    cause = "paused" if c.paused_by_robot else (c.reason or "paused")
    if unfit is not None:
        return f"{cause}: {unfit.text}" if c.paused_by_robot else f"{cause}; waiting for the robot: {unfit.text}"
    return f"{cause}; the robot is ready: scmbridge mission resume --robot {robot} to drive on"


# ---------------------------------------------------------------------------------------------- integrity
class Integrity:
    """What makes a station's work untrustworthy right now: another sender's commands on its robot's key, and
    telemetry the pairer dropped as implausible, each for :data:`INTEGRITY_WINDOW_S` after it was last seen."""

    def __init__(self) -> None:
        self.foreign_at, self.foreign_epoch = -np.inf, 0  # the last command of another sender on our key
        self.implausible_seen: tuple[int, float] = (0, -np.inf)  # (the pairer's count, when it last grew)

    def foreign_command(self, epoch: int, now: float) -> None:
        """A command of another sender (``epoch``: its epoch, not ours) heard at ``now``."""
        self.foreign_at, self.foreign_epoch = now, epoch

    def problems(self, now: float, pairer: IntervalPairer) -> list[str]:
        """The problems of the last :data:`INTEGRITY_WINDOW_S`, in words (empty: none)."""
        out = []
        if now - self.foreign_at < INTEGRITY_WINDOW_S:
            out.append(f"another sender publishes commands for this robot (epoch {self.foreign_epoch:x}): a second "
                       "station or a forger")
        p = pairer
        bad = p.implausible_stamp + p.implausible_pose + p.implausible_pair
        if bad > self.implausible_seen[0]:
            self.implausible_seen = (bad, now)
        if now - self.implausible_seen[1] < INTEGRITY_WINDOW_S:
            last = f"; the last pose dropped: {p.motion.last_dropped}" if p.motion.last_dropped else ""
            out.append(f"implausible telemetry dropped before pairing ({p.implausible_stamp} stamps, "
                       f"{p.implausible_pose} poses, {p.implausible_pair} pairs so far{last})")
        return out


# ------------------------------------------------------------------------------------------------- status
@dataclass
class StationCounters:
    """Every counter on the station's status. :meth:`as_dict` gives the status's ``counters``, derived from the
    fields (a new counter is one field): the optional ones (None, or a zero ``method_calibrate`` / ``method_affine`` /
    ``foreign_commands`` / ``pairs_unsettled``) only once they mean something; ``inputs`` are the transport's own counts
    (``malformed_<input>``), merged as they are."""

    method_scm: int = 0
    method_direct: int = 0
    method_perturb: int = 0
    method_affine: int = 0
    method_barycentric: int = 0
    method_stop: int = 0
    method_calibrate: int = 0
    obstacles_dropped: int = 0
    persist_failures: int = 0
    missions: int = 0
    explore_vetoed: int = 0
    primitive_replans: int | None = None
    primitives_allowed: int | None = None
    foreign_commands: int = 0
    inputs: dict[str, int] = field(default_factory=dict)
    missed_deadlines: int = 0
    refined_pairs: int = 0
    raw_pairs: int = 0
    # the pairer's own counts under their status names (the pairer's name in each field's metadata: observe)
    pairs_rejected: int = field(default=0, metadata={"pairer": "rejected"})
    pairs_formed: int = field(default=0, metadata={"pairer": "formed"})
    pairs_out_of_order: int = field(default=0, metadata={"pairer": "out_of_order"})
    implausible_stamps: int = field(default=0, metadata={"pairer": "implausible_stamp"})
    implausible_poses: int = field(default=0, metadata={"pairer": "implausible_pose"})
    implausible_pairs: int = field(default=0, metadata={"pairer": "implausible_pair"})
    pairer_resyncs: int = field(default=0, metadata={"pairer": "resyncs"})
    # pairs dropped because their command had not settled ([station] pair_settle_s)
    pairs_unsettled: int = field(default=0, metadata={"pairer": "unsettled"})
    goal_reached: int = 0
    cells_relearned: int = 0  # cells whose learner changed, re-learned (transfer.store, ``adapt``)
    # shared changes applied: cells the robot had not driven since, moved provisionally by the change two cells
    # re-learned together (transfer.store, ``adapt``); shown once there is one
    shared_changes: int = 0
    # learned limits' edges whose boundary pairs showed a change, learned again from the recent ones (transfer.limits,
    # ``adapt``); shown once there is one
    limits_relearned: int = 0
    calibration_index: int | None = None
    calibration_total: int | None = None
    ticks: int = 0
    # the station's guards (bridge.nodes.station_guards): pauses for leaving the corridor or the fence, pose jumps
    corridor_trips: int = 0
    fence_trips: int = 0
    pose_jumps: int = 0

    # method_affine: only a station configured with the comparison mapper ``affine`` sends such commands
    _SHOWN_IF_NONZERO = ("method_calibrate", "method_affine", "foreign_commands", "pairs_unsettled", "shared_changes",
                         "limits_relearned", "corridor_trips", "fence_trips", "pose_jumps")

    def count_method(self, method: str) -> None:
        """One more command sent by ``method`` (a wire ``Command`` method)."""
        name = f"method_{method}"
        setattr(self, name, getattr(self, name) + 1)

    def observe(self, pairer: IntervalPairer, store: PairStore, control: MissionControl) -> None:
        """Take the counts the pairer, the store and the mission keep themselves (before a status)."""
        # the refined pairs counted, not made (the store's cached ids: one per configured cell)
        self.refined_pairs, self.raw_pairs, self.cells_relearned = (store.n_configured(), store.raw_count,
                                                                    store.relearned)
        self.shared_changes, self.limits_relearned = store.shifts.shared, store.limits.relearned
        for name, attr in _PAIRER_COUNTS:
            setattr(self, name, getattr(pairer, attr))
        self.goal_reached = int(control.phase == "finished")

    def as_dict(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "inputs":
                out.update(v)
            elif v is None or (f.name in self._SHOWN_IF_NONZERO and v == 0):
                continue
            else:
                out[f.name] = int(v)
        return out


#: (status counter, pairer attribute), derived once from :class:`StationCounters`'s fields
_PAIRER_COUNTS = tuple((f.name, f.metadata["pairer"]) for f in dataclasses.fields(StationCounters)
                       if "pairer" in f.metadata)


def pairing_figures(counters: dict[str, int]) -> dict[str, object]:
    """A run's pairs from its station's last status ``counters``: the refined and raw pairs, and under ``pairing``
    the pairer's own counts, which say why intervals made no pair (unsettled commands, telemetry gaps, order)."""
    return {"refined_pairs": counters.get("refined_pairs"), "raw_pairs": counters.get("raw_pairs"),
            "pairing": {name: counters[name] for name, _ in _PAIRER_COUNTS if name in counters}}


def status_key(reason: M.Reason, phase: M.MissionPhase, unfit_reason: M.Reason | None,
               driver_reason: M.Reason | None, persist_failing: bool) -> tuple:
    """What a person reads the status for, typed: the station's reason and phase, why the robot is (not) fit and the
    driver host's reason, whether saves fail (not the words: "no pose for 2.3 s" changes every tick)."""
    return reason, phase, unfit_reason, driver_reason, persist_failing


def verdict(reason: M.Reason, phase: M.MissionPhase, persist_error: str,
            problems: list[str]) -> tuple[bool, M.Reason, M.NodeState]:
    """The status's ``ok``, ``reason`` and ``state`` from the station's typed reason and the mission's phase: ok
    while it does what it should (:data:`GOOD_REASONS`) unless its work is untrustworthy (a save that fails, an
    integrity problem: the reason then says which)."""
    shown = reason
    if reason in GOOD_REASONS and (persist_error or problems):  # doing what it should, but untrustworthy
        shown = "persist_failed" if persist_error else "integrity"
    state: M.NodeState = "driving" if reason == "ok" else ("waiting" if phase == "running" else
                                                          "parked" if phase == "finished" else phase)
    return shown in GOOD_REASONS, shown, state


@dataclass(frozen=True)
class StatusFacts:
    """What one status message says, gathered by the core: its typed ``reason`` and words ``why`` (the one reason
    it does or does not drive), the mission's ``phase`` and ``progress``, a failing save's ``persist_error`` (empty:
    none), the integrity ``problems``, the ``counters``, the recent ``tick_ms`` and ``solve_ms``, the loop's
    ``rate_hz``, its :func:`status_key` and the ids of the cells re-learned last (``changed_cells``)."""

    reason: M.Reason
    why: str
    phase: M.MissionPhase
    progress: float
    persist_error: str
    problems: list[str]
    counters: dict[str, int]
    tick_ms: Iterable[float]
    solve_ms: Iterable[float]
    rate_hz: float
    key: tuple
    changed_cells: list[str] = field(default_factory=list)
    off_path_m: float | None = None


class StatusReport:
    """The station's status messages: their sequence, and whether what a person reads one for changed since the
    last one sent (:meth:`changed`: it then goes out at this tick, not up to a second later)."""

    def __init__(self) -> None:
        self.seq = 0
        self.sent_key: tuple | None = None  # the status_key of the last status sent, and when
        self.sent_at = -np.inf

    def changed(self, now: float, key: tuple) -> bool:
        """Whether ``key`` (:func:`status_key`) differs from the last status sent, which left at least
        ``1 / STATUS_MAX_HZ`` ago."""
        return self.sent_key is not None and now - self.sent_at >= 1.0 / STATUS_MAX_HZ and key != self.sent_key

    def message(self, now: float, facts: StatusFacts) -> M.Status:
        """The status at ``now``: ok, state, the one reason, progress, latencies and every counter; counted as
        sent."""
        ok, reason, state = verdict(facts.reason, facts.phase, facts.persist_error, facts.problems)
        text = "; ".join([facts.why, *([facts.persist_error] if facts.persist_error else []), *facts.problems])
        sm, tk = sorted(facts.solve_ms) or [0.0], sorted(facts.tick_ms) or [0.0]
        (solve_median,), (p50, p99) = quantiles(sm, (0.5,)), quantiles(tk, (0.5, 0.99))
        msg = M.Status(stamp=now, seq=self.seq, node="station", ok=ok, state=state, reason=reason,
                       progress=min(1.0, max(0.0, facts.progress)), rates_hz={"loop": facts.rate_hz},
                       latencies_ms={"solve_median": solve_median, "solve_max": float(sm[-1]),
                                     "tick_p50": p50, "tick_p99": p99, "tick_max": float(tk[-1])},
                       counters=facts.counters, text=text[:1024], host=machine(), changed_cells=facts.changed_cells,
                       off_path_m=None if facts.off_path_m is None else min(1e7, facts.off_path_m))
        self.seq += 1
        self.sent_key, self.sent_at = facts.key, now
        return msg


def quantiles(ordered: list[float], qs: tuple[float, ...]) -> list[float]:
    """The quantiles ``qs`` (0 to 1) of ``ordered`` (sorted, not empty), interpolated linearly as
    ``numpy.percentile`` does by default: a status each second reads them from a few hundred figures, where numpy's
    call costs more than the sort."""
    n, out = len(ordered), []
    for q in qs:
        h = (n - 1) * q
        i = int(h)
        j = min(i + 1, n - 1)
        out.append(float(ordered[i] + (h - i) * (ordered[j] - ordered[i])))
    return out


# ------------------------------------------------------------------------------------------------- limits
class LimitsReport:
    """The ``limits`` messages of one store: sent when an edge of the learned box moved by more than
    :data:`LIMITS_MOVE_TOL` of the teacher's range since the last one, or forced (each second) as they are; a new
    version whenever what is sent changed."""

    def __init__(self, store: PairStore, robot: str) -> None:
        self.store, self.robot = store, robot
        self.sent: tuple[list[float], int, list | None] | None = None  # the box, the hull's size, the curvatures
        self.version = 0

    def message(self, now: float, force: bool) -> M.Limits | None:
        """The limits to send at ``now`` (None: nothing moved enough). (Every pair on a boundary nudges the box's
        mean a little: the hull is built for a message, not each tick.) A learner that cannot turn in place sends
        them when a learned curvature moved too (its box's yaw-rate edge may sit at the teacher's range)."""
        limits = self.store.limits
        box = limits.box.as_list()
        curvature = None
        if limits.needs_speed:
            curvature = [None if x is None else round(x, 6) for x in limits.known_curvature()]
        sent = self.sent
        if sent is not None and not force:
            sv, sw = self.store.teacher_bounds.span.tolist()
            tol = (sv, sv, sw, sw)
            if (all(abs(a - b) <= LIMITS_MOVE_TOL * t for a, b, t in zip(box, sent[0], tol))
                    and (curvature is None or not _curvature_moved(curvature, sent[2]))):
                return None
        hull = self.store.limits.hull.tolist()  # (K, 2) floats: the rows as lists of two Python floats
        key = (box, len(hull), curvature)
        if sent != key:
            self.version += 1
        self.sent = key
        return M.Limits(stamp=now, robot=self.robot, version=self.version, box=box, hull=hull, curvature=curvature)


def _curvature_moved(now: list, before: list | None) -> bool:
    """A learned curvature appeared, or moved by more than :data:`LIMITS_MOVE_TOL` of itself (rad/m)."""
    if before is None:
        return True
    return any((a is None) != (b is None) or (a is not None and abs(a - b) > LIMITS_MOVE_TOL * max(abs(b), 1e-3))
               for a, b in zip(now, before))


__all__ = ["GOOD_REASONS", "INTEGRITY_WINDOW_S", "LIMITS_MOVE_TOL", "STATUS_EVERY_S", "STATUS_MAX_HZ", "Integrity",
           "LimitsReport", "StationCounters", "StatusFacts", "StatusReport", "not_driving", "paused_text",
           "status_key", "verdict"]
