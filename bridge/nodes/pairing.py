"""Command pairs from live telemetry: which learner command really moved the vehicle between two poses.

The driver host echoes every command the vehicle got (``applied``) and publishes poses (``state``), both stamped
with its own monotonic clock. Events are fed in time order. A *segment* is a run of echoes carrying the same
driving command (reason ``cmd`` or ``clamped``); the first and the latest pose inside a segment bracket an interval
over which that one command was in force. A pair ``<f_T^-1(x(t1), x(t2)), u_L>`` is formed when the segment ends
(the command changes, or the vehicle is stopped) or when its bracketed span reaches ``dt`` (long segments give one
pair per ``dt``), and only if the span is at least ``min_span`` (0.4 ``dt`` by default). Deadman stops, estops
and telemetry gaps longer than ``max_gap`` never produce a pair. Pure: times are arguments.

Why 0.4 ``dt``: telemetry at twice the command rate puts two poses about ``dt / 2`` apart inside each command, and
the vehicle's scheduling jitter must not reject them (docs/ARCHITECTURE.md section 4; the measurement is in
docs/RELIABILITY.md).

What it learns from is checked first (forged or garbled telemetry must not be learned, nor stop learning): with
the receipt time given, an event stamped further ahead of the last one than the time that passed between their
receipts is dropped (``implausible_stamp``), and a run of events behind a stamp that was accepted by mistake
(the first event ever was forged) is followed again after ``RESYNC_AFTER`` (``resyncs``); a pose that moves
faster than ``max_speed`` or turns faster than ``max_turn`` from the last accepted pose is dropped
(``implausible_pose``) unless ``RESYNC_AFTER`` poses in a row agree with each other (the robot was relocated: the
interval restarts, no pair spans the jump); a pair whose learner command lies outside ``command_bounds`` or whose
teacher part lies outside ``teacher_bounds`` (symmetric, times ``margin``) is never formed (``implausible_pair``).

*Settled pairs only* (``settle_s`` > 0; off by default, as the paper's learners answer within one tick). A vehicle
whose body lags its command (ArduPilot Rover SITL's skid body: about 0.3 s to its speed) moves, over the 0.1 s
after a command changes, partly as the *earlier* commands asked: the pair then says the learner reaches less than it
does, most of all for a step to the learner's top command, the probe that fixes a learned limit (paper §4.2, Eq.
learn_capability: its boundary pair *is* the limit). With ``settle_s``, a pair is kept only if every command in
force during the ``settle_s`` before its interval began was within ``settle_tol`` of its own (each axis, as a share
of ``command_bounds``' span; in command units without bounds) and the vehicle was driving throughout; others are
counted (``unsettled``) and dropped. The transfer's probe of a never-driven limit is sent again at each tick until a
boundary pair is learned (:meth:`transfer.policy._PolicyBase._probe_limits`), so dropping its first pairs holds the
probe until the speed has settled, and only the settled pair fixes the limit. A body that takes longer to reach its
top from rest than to follow the small steps of a mission's commands (SITL's Ackermann body: about 2 s) gets a
longer hold for the commands on an edge of the learner's range (``settle_edge_s``), so its probes are read settled
without thinning every other pair as much. docs/BENCHMARKS.md, "The transfer on SITL", has the figures.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections import deque
from typing import Any

import numpy as np
from numpy.typing import NDArray

from transfer.domain import Bounds
from transfer.pairs import teacher_equivalent

DRIVING = ("cmd", "clamped")
Pair = tuple[NDArray[np.float64], NDArray[np.float64]]
#: a pose (x, y, theta) as the pairer keeps it: three floats (scalar maths on each pose, arrays only for a pair)
Pose = tuple[float, float, float]
#: events in a row that agree with each other and not with what was accepted before: follow them
RESYNC_AFTER = 3
#: how far an event's stamp may run ahead of its receipt, relative to the last accepted event, s
STAMP_TOLERANCE = 0.25
#: how long an event waits for earlier-stamped ones still on their way before it is fed to the pairer, s
REORDER_WINDOW = 0.2
#: a span this much short of ``min_span`` is still at least it, s: stamps put onto this host's clock carry float
#: rounding, and poses are often exactly ``min_span`` apart (ArduPilot sends its 20 Hz positions from a 50 Hz loop:
#: 40 and 60 ms apart), which the last digit must not reject
SPAN_ROUNDING = 1e-6


class Reorder:
    """Puts telemetry back in stamp order before the pairer sees it.

    A pose is stamped when the vehicle measured it, an echo when the command was sent; over a real link (or a
    loaded host) a pose measured just before a command can arrive after that command's echo. Fed as it comes, the
    pose would be older than an event already used and the pairer would drop it (``out_of_order``). Each event is
    held for ``window`` after its receipt; events leave in stamp order, and one never leaves while an earlier-stamped
    event is still held, so anything that arrives less than ``window`` late takes its place. A forged stamp delays
    the stream by at most ``window`` (it leaves when its own wait is over; the pairer judges it then). Events with
    a non-finite stamp leave at once (the pairer counts them). Pure: times are arguments."""

    def __init__(self, window: float = REORDER_WINDOW) -> None:
        self.window = float(window)
        self._heap: list[tuple[float, int, int, float, Any]] = []
        self._seq = itertools.count()
        self._now: list[Any] = []

    def push(self, stamp: float, kind: int, received: float, item: Any) -> None:
        """Hold ``item`` (stamped ``stamp``, received at ``received``); ``kind`` orders events of one stamp (echoes
        before poses: the command is in force from its own instant)."""
        if not math.isfinite(stamp):
            self._now.append(item)
        else:
            heapq.heappush(self._heap, (stamp, kind, next(self._seq), received, item))

    def ready(self, now: float) -> list[Any]:
        """The held events that may go to the pairer at ``now``, oldest stamp first."""
        out, self._now = self._now, []
        heap = self._heap
        while heap and now - heap[0][3] >= self.window:
            out.append(heapq.heappop(heap)[4])
        return out

    def __len__(self) -> int:
        return len(self._heap) + len(self._now)


def _grown(b: Bounds, margin: float) -> Bounds:
    """The plausible box around ``b``: symmetric about zero (a vehicle may reverse or stand still whatever its
    box), ``margin`` times its largest magnitude on each axis."""
    v, w = margin * float(np.max(np.abs(b.v))), margin * float(np.max(np.abs(b.w)))
    return Bounds((-v, v), (-w, w))


def _box(b: Bounds | None) -> tuple[float, float, float, float] | None:
    """``b``'s limits as :meth:`Bounds.contains` (default tolerance) compares against, as floats: (v_lo, v_hi,
    omega_lo, omega_hi); None for no bounds."""
    if b is None:
        return None
    tol = 1e-12  # Bounds.contains's default
    lo, hi = (b.lo - tol * b.span).tolist(), (b.hi + tol * b.span).tolist()
    return lo[0], hi[0], lo[1], hi[1]


def _inside(box: tuple[float, float, float, float] | None, u) -> bool:
    """:meth:`Bounds.contains` of one command (v, omega) in scalar maths (once per pair); always with no box."""
    return box is None or (box[0] <= u[0] <= box[1] and box[2] <= u[1] <= box[3])


class Settling:
    """Whether a pair's command had been steady long enough before its interval (module docstring, "Settled pairs
    only"): the changes of the command kept as far back as a pair's settling window reaches, and the pairs dropped
    for it (``unsettled``). Pure: times are arguments."""

    def __init__(self, settle_s: float, settle_tol: float, settle_edge_s: float, command_bounds: Bounds | None) -> None:
        self.settle_s = float(settle_s)
        self.settle_edge_s = max(float(settle_edge_s), self.settle_s)
        #: the command bounds' edges (v_lo, v_hi, w_lo, w_hi), within a millionth of their span
        self.edges = None if command_bounds is None else (
            *(float(x) for x in command_bounds.v), *(float(x) for x in command_bounds.w))
        self.edge_eps = (1.0, 1.0) if command_bounds is None else tuple(1e-6 * float(x) for x in command_bounds.span)
        span = (1.0, 1.0) if command_bounds is None else tuple(float(x) for x in command_bounds.span)
        self.tol = (float(settle_tol) * span[0], float(settle_tol) * span[1])  # command units, per axis
        #: (stamp, command or None for a stop) of each change of the command, the last one in force now
        self.changes: deque[tuple[float, tuple[float, float] | None]] = deque()
        self.unsettled = 0  # pairs dropped because their command had not been steady for settle_s

    def note(self, stamp: float, key: tuple[float, float] | None) -> None:
        """The command in force changed to ``key`` (None: stopped) at ``stamp``."""
        if self.settle_s <= 0:
            return
        changes = self.changes
        changes.append((stamp, key))
        while len(changes) >= 2 and changes[1][0] < stamp - self.settle_edge_s:
            changes.popleft()  # no longer in force within any later pair's window (each starts after `stamp`)

    def keeps(self, segment: tuple[float, float], t1: float) -> bool:
        """Whether a pair of command ``segment`` whose interval begins at ``t1`` is settled (else counted)."""
        if self.settle_s > 0 and t1 - self._steady_since() < self._settle_for(segment):
            self.unsettled += 1
            return False
        return True

    def _steady_since(self) -> float:
        """Since when the commands in force have been within the settling tolerance of the current segment's
        (the stamp of the earliest change in that run; +inf when not driving)."""
        changes = self.changes
        if not changes or changes[-1][1] is None:
            return math.inf
        ref = changes[-1][1]
        tv, tw = self.tol
        since = changes[-1][0]
        for t, u in reversed(changes):
            if u is None or abs(u[0] - ref[0]) > tv or abs(u[1] - ref[1]) > tw:
                break
            since = t
        return since

    def _settle_for(self, u: tuple[float, float]) -> float:
        """How long command ``u`` must have been steady: ``settle_edge_s`` on an edge of the command bounds (the
        largest step a body answers, from rest to its top: the probe that fixes a limit), else ``settle_s``."""
        e = self.edges
        if e is None or self.settle_edge_s == self.settle_s:
            return self.settle_s
        ev, ew = self.edge_eps
        v, w = u
        if v <= e[0] + ev or v >= e[1] - ev or w <= e[2] + ew or w >= e[3] - ew:
            return self.settle_edge_s
        return self.settle_s


class Motion:
    """Whether a pose is one the vehicle could have reached from the last accepted one, no faster than
    ``max_speed`` and turning no faster than ``max_turn`` (module docstring); after ``RESYNC_AFTER`` poses in a row
    that agree with each other, the vehicle's new place. Counts the poses it drops (``implausible_pose``). Pure."""

    def __init__(self, dt: float, max_speed: float, max_turn: float) -> None:
        self.dt = dt
        self.max_speed, self.max_turn = float(max_speed), float(max_turn)
        self.pose: tuple[float, Pose] | None = None  # the last accepted pose
        self.odd_poses: list[tuple[float, Pose]] = []  # implausible poses in a row
        self.implausible_pose = 0
        #: the last pose dropped as out of reach, in words (what it moved and turned in how long): a person
        #: reading "implausible poses" on the status needs to know whether it was a jump or a stamp
        self.last_dropped = ""

    def judge(self, stamp: float, p: Pose) -> str:
        """``ok`` (accepted), ``dropped``, or ``moved`` (dropped, but the run of poses that agree says the vehicle
        was relocated: it is its new place, no pair may span the jump)."""
        if not (math.isfinite(p[0]) and math.isfinite(p[1]) and math.isfinite(p[2])):
            self.implausible_pose += 1
            self.last_dropped = "not finite"
            return "dropped"
        if self.pose is None or self._reachable(self.pose, (stamp, p)):
            self.pose, self.odd_poses = (stamp, p), []
            return "ok"
        self.implausible_pose += 1
        self.last_dropped = self._describe(self.pose, (stamp, p))
        run = self.odd_poses
        if run and not self._reachable(run[-1], (stamp, p)):
            run.clear()
        run.append((stamp, p))
        if len(run) >= RESYNC_AFTER:
            self.pose, self.odd_poses = (stamp, p), []
            return "moved"
        return "dropped"

    def _describe(self, a: tuple[float, Pose], b: tuple[float, Pose]) -> str:
        """What pose ``b`` did after the accepted ``a``, against the bounds (for :attr:`last_dropped`)."""
        (xa, ya, tha), (xb, yb, thb) = a[1], b[1]
        return (f"{math.hypot(xb - xa, yb - ya):.3f} m and {abs(math.remainder(thb - tha, math.tau)):.3f} rad in "
                f"{b[0] - a[0]:.3f} s (at most {self.max_speed:.2f} m/s, {self.max_turn:.2f} rad/s)")

    def _reachable(self, a: tuple[float, Pose], b: tuple[float, Pose]) -> bool:
        dt = max(b[0] - a[0], self.dt / 10)  # two poses in one instant: judge them over a tenth of a pair
        (xa, ya, tha), (xb, yb, thb) = a[1], b[1]  # scalar maths: once per pose, a hot path
        step = math.hypot(xb - xa, yb - ya)
        turn = abs(math.remainder(thb - tha, math.tau))
        return step <= self.max_speed * dt and turn <= self.max_turn * dt


class IntervalPairer:
    """Turns time-ordered applied echoes and poses into command pairs (see the module docstring). Its pieces: the
    settling rule (:class:`Settling`) and the motion check (:class:`Motion`); their counts read as its own."""

    def __init__(self, dt: float, min_span: float | None = None, max_gap: float | None = None, *,
                 max_speed: float = math.inf, max_turn: float = math.inf, command_bounds: Bounds | None = None,
                 teacher_bounds: Bounds | None = None, margin: float = 1.5, settle_s: float = 0.0,
                 settle_tol: float = 0.05, settle_edge_s: float = 0.0) -> None:
        """``settle_s``, ``settle_tol``: keep only pairs whose command had been steady that long, within that share
        of the command range (module docstring, "Settled pairs only"); ``settle_s`` 0: every pair, as the paper.
        ``settle_edge_s``: as long for a command on an edge of ``command_bounds`` (the probe of a limit), if longer
        than ``settle_s``."""
        if dt <= 0:
            raise ValueError("dt must be positive")
        if settle_s < 0 or settle_tol <= 0 or settle_edge_s < 0:
            raise ValueError("settle_s and settle_edge_s must be >= 0 and settle_tol > 0")
        if settle_edge_s > settle_s and (settle_s == 0 or command_bounds is None):
            raise ValueError("settle_edge_s needs settle_s > 0 and the command bounds whose edges it applies to")
        self.dt = float(dt)
        self.min_span = 0.4 * self.dt if min_span is None else float(min_span)
        self.max_gap = 2.0 * self.dt if max_gap is None else float(max_gap)
        self.motion = Motion(self.dt, max_speed, max_turn)
        self.command_bounds = None if command_bounds is None else _grown(command_bounds, margin)
        self.teacher_bounds = None if teacher_bounds is None else _grown(teacher_bounds, margin)
        self._command_box = _box(self.command_bounds)
        self._teacher_box = _box(self.teacher_bounds)
        self.settling = Settling(settle_s, settle_tol, settle_edge_s, command_bounds)
        self.anchor: tuple[float, float] | None = None  # (stamp, receipt) of the last accepted event
        self.behind: list[tuple[float, float]] = []  # (stamp, receipt) of events in a row behind the anchor
        self.implausible_stamp = 0
        self.implausible_pair = 0
        self.resyncs = 0
        self.segment: tuple[float, float] | None = None  # the command in force, None when not driving
        self.first: tuple[float, Pose] | None = None
        self.last: tuple[float, Pose] | None = None
        self.last_event = -np.inf
        self.rejected = 0
        self.formed = 0
        self.out_of_order = 0  # events older than one already fed: ignored

    # the pieces' counts and settings, read as the pairer's (the station's status observes them by name)
    @property
    def implausible_pose(self) -> int:
        return self.motion.implausible_pose

    @property
    def unsettled(self) -> int:
        return self.settling.unsettled

    @property
    def settle_s(self) -> float:
        return self.settling.settle_s

    @property
    def settle_edge_s(self) -> float:
        return self.settling.settle_edge_s

    @property
    def _settle_tol(self) -> tuple[float, float]:
        return self.settling.tol

    def _admit(self, stamp: float, received: float | None) -> bool:
        """Whether an event stamped ``stamp`` (received at ``received``, when known) may be used (see the module
        docstring); updates the order and the anchor."""
        if not math.isfinite(stamp):
            self.implausible_stamp += 1
            return False
        if received is not None and self.anchor is not None:
            s0, r0 = self.anchor
            if stamp - s0 > (received - r0) + STAMP_TOLERANCE:
                self.implausible_stamp += 1  # ahead of what the time between receipts allows: not the sender's
                return False
        if stamp < self.last_event:
            self.out_of_order += 1
            if received is None:
                return False
            run = self.behind
            if run and not (stamp > run[-1][0] and abs((stamp - run[-1][0]) - (received - run[-1][1]))
                            <= STAMP_TOLERANCE):
                run.clear()
            run.append((stamp, received))
            if len(run) < RESYNC_AFTER:
                return False
            self.resyncs += 1  # the stamp followed so far was forged: follow the sender's stream again
            self.segment, self.first, self.last, self.motion.pose = None, None, None, None
        self.behind.clear()
        self.last_event = stamp
        if received is not None:
            self.anchor = (stamp, received)
        return True

    def applied(self, stamp: float, v: float, omega: float, reason: str, received: float | None = None,
                ) -> Pair | None:
        if not self._admit(stamp, received):
            return None
        key = (float(v), float(omega)) if reason in DRIVING else None
        if key == self.segment:
            return None
        out = self._close()
        self.segment, self.first, self.last = key, None, None
        self.settling.note(stamp, key)
        return out

    def _plausible_pose(self, stamp: float, p: Pose) -> bool:
        """A pose the vehicle could have reached (:class:`Motion`); a relocation restarts the interval there."""
        verdict = self.motion.judge(stamp, p)
        if verdict == "moved":
            self.resyncs += 1
            self.first, self.last = None, None  # no pair spans the jump
        return verdict == "ok"

    def state(self, stamp: float, pose: Pose | NDArray[np.float64], received: float | None = None) -> Pair | None:
        """A pose (x, y, theta; three floats, or an array of them) stamped ``stamp``; the pair it closes, if any."""
        p: Pose = pose if type(pose) is tuple else tuple(np.asarray(pose, dtype=float).tolist())
        if not self._admit(stamp, received) or not self._plausible_pose(stamp, p):
            return None
        if self.segment is None:
            return None
        prev = self.last if self.last is not None else self.first
        if prev is not None and stamp - prev[0] > self.max_gap:
            self.rejected += 1  # a telemetry gap: restart the interval here
            self.first, self.last = (stamp, p), None
            return None
        if self.first is None:
            self.first = (stamp, p)
            return None
        self.last = (stamp, p)
        if stamp - self.first[0] >= self.dt:
            out = self._close()
            self.first, self.last = (stamp, p), None
            return out
        return None

    def _close(self) -> Pair | None:
        if self.segment is None or self.first is None or self.last is None:
            return None
        (t1, x1), (t2, x2) = self.first, self.last
        if t2 - t1 < self.min_span - SPAN_ROUNDING:
            self.rejected += 1
            return None
        if not self.settling.keeps(self.segment, t1):
            return None
        teacher, learner = teacher_equivalent(np.array(x1), np.array(x2), t2 - t1), np.array(self.segment)
        if not (_inside(self._command_box, self.segment) and _inside(self._teacher_box, teacher.tolist())):
            self.implausible_pair += 1
            return None
        self.formed += 1
        return teacher, learner
