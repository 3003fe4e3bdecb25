"""The station's guards on where its robot goes (pure: poses, times and distances are arguments; docs/ARCHITECTURE.md
section 6, "The corridor, the fence and the pose jump").

The transfer method drives a robot along a mission's path; nothing in it bounds where the robot is when the mapping is
wrong (an unseen vehicle that runs away) or the pose is (an EKF reset, a motion-capture glitch, a driver host restart
whose emulated pose starts again at the origin). These guards do, each pausing a running mission with its own typed
reason so that only a person drives on (``scmbridge mission resume``):

- **the corridor** (``left_corridor``): a pose farther than ``corridor_m`` from the path (the mission file's, else the
  station's ``[station] corridor_m``), or one that will be within :data:`STOP_LOOKAHEAD_S` at the speed it moves away
  from the path (measured over the last :data:`OUTWARD_WINDOW_S`): a vehicle running away fast needs its stop
  before the line to stop near it. The station publishes stops at once and its status says the distance
  (``off_path_m``) and where the robot left;
- **the fence** (``fence``): a pose outside a polygon in the lab's frame (the mission's ``fence``, else the station's);
- **the pose jump** (``pose_jump``): a pose farther from the last one than the robot could have moved in the interval
  between them: its learned top speed (the configured one before anything is learned) times :data:`JUMP_MARGIN`,
  plus :data:`JUMP_SLACK_M` of pose noise. A jump is never progress: the mission's progress may grow only by what
  the robot's continuous track covered since the mission was started, from where the robot was then
  (:meth:`Guards.progress_cap`; a jump is not track, a pause does not end it), so a pose that lands on the goal does
  not finish the mission.

A resume (or a start) with the robot outside the corridor or the fence is refused, saying how far it is; a person
drives it back first, or resumes with ``--override`` (:attr:`bridge.core.wire.MissionRequest.override`): the guard
then lets the station drive it back, and re-arms once the robot is inside again; moving farther away than it was when
overridden (by more than the corridor) trips it again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bridge.core import wire as M

#: a pose may move this many times the robot's top speed between two poses before it is a jump
JUMP_MARGIN = 1.5
#: m of pose noise (motion capture, an EKF's corrections) a pose may move on top of that
JUMP_SLACK_M = 0.3
#: the progress along the path may grow by this many times the track's length since the last start or resume ...
PROGRESS_MARGIN = 1.5
#: ... plus this, once (a path's corner, where the closest point moves faster than the robot), m
PROGRESS_SLACK_M = 0.5
#: s ahead the corridor looks at the speed the robot moves away from the path: a stop given that early leaves a
#: vehicle the station's tick, the link and its braking (up to about 1.5 m/s at 1 m/s^2) to stop near the line
STOP_LOOKAHEAD_S = 1.0
#: s over which that outward speed is measured (the station's ticks' distances from the path)
OUTWARD_WINDOW_S = 0.3
#: the trips kept for the summary and the report
TRIPS_KEPT = 64


def inside(x: float, y: float, polygon: list[tuple[float, float]] | np.ndarray) -> bool:
    """Whether ``(x, y)`` is inside ``polygon`` (its vertices in order; even-odd rule; a point on an edge is in)."""
    pts = np.asarray(polygon, dtype=float)
    n, hit = len(pts), False
    for i in range(n):
        (ax, ay), (bx, by) = pts[i], pts[(i + 1) % n]
        if _segment_distance(x, y, ax, ay, bx, by) == 0.0:
            return True
        if (ay > y) != (by > y) and x < ax + (y - ay) * (bx - ax) / (by - ay):
            hit = not hit
    return hit


def _segment_distance(x: float, y: float, ax: float, ay: float, bx: float, by: float) -> float:
    dx, dy = bx - ax, by - ay
    t = 0.0 if dx == dy == 0.0 else min(1.0, max(0.0, ((x - ax) * dx + (y - ay) * dy) / (dx * dx + dy * dy)))
    return math.hypot(x - ax - t * dx, y - ay - t * dy)


def outside_by(x: float, y: float, polygon: list[tuple[float, float]] | np.ndarray) -> float:
    """How far ``(x, y)`` is outside ``polygon``, m (0 inside or on it)."""
    if inside(x, y, polygon):
        return 0.0
    pts = np.asarray(polygon, dtype=float)
    return min(_segment_distance(x, y, *pts[i], *pts[(i + 1) % len(pts)]) for i in range(len(pts)))


@dataclass(frozen=True)
class Trip:
    """A guard that paused the mission: its reason, where and when (wall clock) and how far out."""

    reason: M.Reason
    x: float
    y: float
    distance: float  # left_corridor: from the path; fence: outside it; pose_jump: the jump
    progress: float  # the mission's progress then (0..1)
    wall_time: float
    text: str


@dataclass
class Guards:
    """The corridor, the fence and the pose-jump guard of one station (see the module docstring)."""

    corridor_m: float = 1.0  # the station's (a mission's own wins: configure)
    fence: list[tuple[float, float]] = field(default_factory=list)
    station_corridor_m: float = 1.0
    station_fence: list[tuple[float, float]] = field(default_factory=list)
    # the track: the last pose (x, y, stamp, epoch, receipt), and its length since this station started
    last: tuple[float, float, float, int, float] | None = None
    odometer: float = 0.0
    anchor: tuple[float, float] = (0.0, 0.0)  # (arc length, odometer) where the mission's track began
    anchor_pending: bool = False  # the track begins at the next pose seen while running (started without a pose)
    # overridden by a person: the distance out it was then (None: armed)
    corridor_override: float | None = None
    fence_override: float | None = None
    trips: list[Trip] = field(default_factory=list)
    jumps: int = 0  # pose jumps seen (running or not)
    recent: list[tuple[float, float]] = field(default_factory=list)  # (time, distance from the path) while checked

    def __post_init__(self) -> None:
        self.station_corridor_m, self.station_fence = self.corridor_m, list(self.fence)

    def configure(self, spec: M.MissionSpec) -> None:
        """A mission's corridor and fence (its own, else the station's); any override ends with the mission."""
        self.corridor_m = spec.corridor_m if spec.corridor_m is not None else self.station_corridor_m
        self.fence = [(float(a), float(b)) for a, b in spec.fence] if spec.fence else list(self.station_fence)
        self.corridor_override = self.fence_override = None

    # ----------------------------------------------------------------------------------------- pose jump
    def pose(self, st: M.LearnerState, at: float, top_speed: float) -> float | None:
        """A new pose (``at``: its receipt on the station's clock; ``top_speed``: the most the robot can move, m/s):
        None when it continues the track, else how far it jumped (it then starts the track again)."""
        last = self.last
        self.last = (st.x, st.y, st.stamp, st.epoch, at)
        if last is None:
            return None
        step = math.hypot(st.x - last[0], st.y - last[1])
        dt = at - last[4]
        if st.epoch == last[3]:  # the same pose stream: its own stamps say the interval (a batch arrives at once)
            dt = max(dt, st.stamp - last[2])
        if step > JUMP_MARGIN * top_speed * max(dt, 0.0) + JUMP_SLACK_M:
            self.jumps += 1
            return step
        self.odometer += step
        return None

    def pause(self) -> None:
        """Not checked for a while (the mission is not running): the outward speed is measured afresh."""
        self.recent.clear()

    def begin(self, s: float | None) -> None:
        """The mission's track begins here: at arc length ``s`` (a start: the pose's closest point; a restored
        mission: its saved progress), or at the next pose seen while running (None: no pose yet, or a new path)."""
        self.anchor_pending = s is None
        if s is not None:
            self.anchor = (s, self.odometer)

    def progress_cap(self) -> float:
        """The farthest arc length the mission's progress may have reached: where its track began plus what the
        continuous track covered since, with a margin (:data:`PROGRESS_MARGIN`, :data:`PROGRESS_SLACK_M`)."""
        s0, odo0 = self.anchor
        return s0 + PROGRESS_MARGIN * (self.odometer - odo0) + PROGRESS_SLACK_M

    # ------------------------------------------------------------------------------------ corridor, fence
    def outward(self, now: float, off_path: float) -> float:
        """The speed the robot moves away from the path, m/s (0 when it does not), over the last
        :data:`OUTWARD_WINDOW_S` of checks (``now``: the station's clock)."""
        self.recent.append((now, off_path))
        while len(self.recent) > 2 and now - self.recent[1][0] >= OUTWARD_WINDOW_S:
            del self.recent[0]
        t0, d0 = self.recent[0]
        return max(0.0, (off_path - d0) / (now - t0)) if now - t0 > 0.05 else 0.0

    def check(self, x: float, y: float, off_path: float, progress: float, wall: float,
              now: float | None = None) -> Trip | None:
        """While running: the trip if the pose at ``(x, y)``, ``off_path`` m from the path, leaves the corridor (or
        will within :data:`STOP_LOOKAHEAD_S`, at ``now`` on the station's clock) or the fence (an override re-arms
        once the robot is back inside); ``wall``: the wall clock now."""
        ahead = off_path + (STOP_LOOKAHEAD_S * self.outward(now, off_path) if now is not None else 0.0)
        if self.corridor_override is not None:
            if off_path <= self.corridor_m:
                self.corridor_override = None
            elif off_path > self.corridor_override + self.corridor_m:
                return self._trip(wall, "left_corridor", x, y, off_path, progress,
                                  f"left the corridor again: {off_path:.2f} m from the path (overridden at "
                                  f"{self.corridor_override:.2f} m)")
        elif off_path > self.corridor_m:
            return self._trip(wall, "left_corridor", x, y, off_path, progress,
                              f"left the corridor: {off_path:.2f} m from the path (corridor_m = {self.corridor_m:g}) "
                              f"at ({x:.2f}, {y:.2f})")
        elif ahead > self.corridor_m:
            return self._trip(wall, "left_corridor", x, y, off_path, progress,
                              f"leaving the corridor: {off_path:.2f} m from the path and moving away at "
                              f"{(ahead - off_path) / STOP_LOOKAHEAD_S:.2f} m/s (corridor_m = {self.corridor_m:g}) at "
                              f"({x:.2f}, {y:.2f})")
        if self.fence:
            out = outside_by(x, y, self.fence)
            if self.fence_override is not None:
                if out == 0.0:
                    self.fence_override = None
                elif out > self.fence_override + self.corridor_m:
                    return self._trip(wall, "fence", x, y, out, progress, f"outside the fence again: {out:.2f} m out")
            elif out > 0.0:
                return self._trip(wall, "fence", x, y, out, progress,
                                  f"outside the fence: {out:.2f} m out at ({x:.2f}, {y:.2f})")
        return None

    def refusal(self, x: float, y: float, off_path: float, override: bool, robot: str) -> str:
        """Why a start or resume with the robot at ``(x, y)`` is refused ("" when it is not); with ``override`` it
        is not, and the guards the robot is out of let it be driven back."""
        out = outside_by(x, y, self.fence) if self.fence else 0.0
        why = []
        if off_path > self.corridor_m:
            why.append(f"the robot is {off_path:.2f} m from the path (corridor_m = {self.corridor_m:g})")
        if out > 0.0:
            why.append(f"the robot is {out:.2f} m outside the fence")
        if not why:
            return ""
        if override:
            self.corridor_override = off_path if off_path > self.corridor_m else None
            self.fence_override = out if out > 0.0 else None
            return ""
        return (f"refused: {' and '.join(why)}: drive it back, or scmbridge mission resume --override --robot "
                f"{robot} to have the station drive it back")

    def jump_trip(self, x: float, y: float, jump: float, progress: float, wall: float) -> Trip:
        """The trip of a pose jump of ``jump`` m to ``(x, y)`` while running (``wall``: the wall clock now)."""
        return self._trip(wall, "pose_jump", x, y, jump, progress,
                          f"the pose jumped {jump:.2f} m to ({x:.2f}, {y:.2f}), farther than the robot could move")

    def _trip(self, wall: float, reason: M.Reason, x: float, y: float, distance: float, progress: float,
              text: str) -> Trip:
        trip = Trip(reason, float(x), float(y), float(distance), float(progress), wall, text)
        self.trips.append(trip)
        del self.trips[:-TRIPS_KEPT]
        return trip


__all__ = ["JUMP_MARGIN", "JUMP_SLACK_M", "PROGRESS_MARGIN", "PROGRESS_SLACK_M", "Guards", "Trip", "inside",
           "outside_by"]
