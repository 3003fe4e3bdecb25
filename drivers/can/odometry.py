"""Differential-drive odometry from the two controllers' encoder estimates, and the checks that keep an implausible
estimate (a faulty encoder, a forged frame) out of the pose. Pure: stamps come in with the estimates, nothing here
reads a clock or touches the bus."""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

from drivers.base import Pose

#: rev: a position estimate beyond this is garbage (float32 resolution there is ~1 rev; 1e7 rev of a 0.1 m wheel is
#: 6000 km).
MAX_ABS_POSITION = 1e7
#: s of motion at ``max_wheel_speed`` tolerated on top of the interval between two encoder frames (stamp jitter).
JUMP_SLACK = 0.02
#: rev/s a wheel may turn beyond twice its commanded rate (pushed, rolling on after a stop)
COMMAND_SLACK_REV_S = 0.5
#: s of motion the odometry's travel budget holds at most (frame jitter, a burst of frames read at once)
BURST_S = 0.1
#: consecutive rejected position steps that agree with each other before the encoder reference is re-anchored.
RESYNC_AFTER = 3
#: s of commands a wheel remembers: an estimate is judged by the commands in force when it was measured, not when it
#: is read (a loaded host reads frames late, after it has already told the wheel something else)
COMMAND_MEMORY_S = 2.0


@dataclass
class Wheel:
    """One wheel's odometry: its reference, the estimate waiting for the other wheel's, its travel budget."""

    sign: float  # +1 or -1: -1 for a mirrored motor
    commanded: float = 0.0  # rev/s: the last Input_Vel sent to it
    history: list[tuple[float, float]] = field(default_factory=list)  # (when, |Input_Vel|) sent, oldest first
    budget: float = 0.0  # rev the encoder may still move (refilled at the plausible wheel speed)
    budget_at: float | None = None  # the stamp the budget was last refilled at
    pos: float | None = None  # rev: the odometry reference (last estimate integrated, or the anchor)
    vel: float = 0.0  # rev/s
    stamp: float | None = None  # of ``pos``
    new: tuple[float, float, float] | None = None  # (pos, vel, stamp) accepted, waiting for the other wheel
    jumps: list[tuple[float, float]] = field(default_factory=list)  # rejected steps in a row: (pos, stamp)


@dataclass(frozen=True, slots=True)
class Step:
    """What one encoder estimate did: the pose it completed, or why it was not integrated."""

    pose: Pose | None = None  # both wheels had a new accepted estimate: one odometry step
    rejected: bool = False  # implausible: never integrated
    overrun: bool = False  # more travel than the wheel can do since the last estimates (a reason to reject)
    resynced: bool = False  # agreeing rejected steps: the encoder really moved, the reference re-anchored there


class Odometry:
    """Validates each estimate and integrates one step (midpoint heading) once both wheels have a new one.

    An estimate is rejected when ``|Vel_Estimate|`` exceeds ``max_wheel_speed``, ``|Pos_Estimate|`` exceeds
    :data:`MAX_ABS_POSITION`, or its step from the reference is more than ``max_wheel_speed`` can do in the time
    between the two frames (plus :data:`JUMP_SLACK`). Each wheel's travel also has a budget that refills at the
    fastest the wheel can turn given what it was told: many small steps, each plausible alone, cannot add up to
    more. When :data:`RESYNC_AFTER` rejected steps in a row agree with each other, the encoder really moved (a
    controller reboot, a Set_Absolute_Position): the reference is re-anchored there without integrating the step."""

    def __init__(self, radius: float, track: float, max_wheel_speed: float, left: Wheel, right: Wheel,
                 pose: tuple[float, float, float]) -> None:
        self.radius, self.track, self.max_wheel_speed = radius, track, max_wheel_speed
        self.left, self.right = left, right
        self.pose = [float(a) for a in pose]

    def wheel_turn_rates(self, v: float, omega: float) -> tuple[float, float]:
        """(left, right) Input_Vel in rev/s for body speed v (m/s) and yaw rate omega (rad/s), signs applied."""
        vl = v - omega * self.track / 2.0
        vr = v + omega * self.track / 2.0
        k = 1.0 / (2.0 * math.pi * self.radius)
        return self.left.sign * vl * k, self.right.sign * vr * k

    def command(self, w: Wheel, rate: float, at: float, sent: float | None = None) -> None:
        """Input_Vel ``rate`` (rev/s) decided for wheel ``w`` at ``at`` and on the bus by ``sent`` (the stamps' time
        base). A host preempted between deciding and writing the frame leaves the old command in force until the
        frame leaves: a slower new command counts from ``sent``, a faster one already from ``at``."""
        old = abs(w.commanded)
        w.commanded = rate
        if sent is not None and sent > at and old > abs(rate):
            bisect.insort(w.history, (at, old))
            bisect.insort(w.history, (sent, abs(rate)))
        else:
            bisect.insort(w.history, (at, abs(rate)))
        latest = w.history[-1][0]
        while len(w.history) > 1 and w.history[1][0] < latest - COMMAND_MEMORY_S:
            del w.history[0]  # keep the one command still in force at the memory's start

    def _rate_in_force(self, w: Wheel, t0: float, t1: float) -> float:
        """The largest |Input_Vel| the wheel was told to turn at between ``t0`` and ``t1`` (the one in force at
        ``t0`` and any sent since, up to ``t1``); the current command where there is no history."""
        top, before = abs(w.commanded) if not w.history else 0.0, None
        for at, rate in w.history:
            if at <= t0:
                before = rate
            elif at <= t1:
                top = max(top, rate)
        return top if before is None else max(top, before)

    def estimate(self, w: Wheel, pos: float, vel: float, stamp: float) -> Step:
        """One wheel's encoder estimate (rev, rev/s) received at ``stamp``."""
        if abs(vel) > self.max_wheel_speed or abs(pos) > MAX_ABS_POSITION:
            return Step(rejected=True)
        if w.pos is None or w.stamp is None:
            w.pos, w.vel, w.stamp = pos, vel, stamp  # the anchor: nothing to integrate yet
            return Step()
        ref_pos, _, ref_stamp = w.new if w.new is not None else (w.pos, w.vel, w.stamp)
        plausible = self.plausible_step(ref_pos, ref_stamp, pos, stamp)
        overrun = plausible and not self._spend(w, abs(pos - ref_pos), stamp)
        if not plausible or overrun:
            w.jumps.append((pos, stamp))
            del w.jumps[:-RESYNC_AFTER]
            resync = len(w.jumps) == RESYNC_AFTER and all(
                self.plausible_step(p0, t0, p1, t1) for (p0, t0), (p1, t1) in zip(w.jumps, w.jumps[1:]))
            if resync:  # the encoder really moved: re-anchor both wheels there, without integrating the step
                w.pos, w.vel, w.stamp, w.new = pos, vel, stamp, None
                w.jumps.clear()
                other = self.right if w is self.left else self.left
                if other.new is not None:
                    other.pos, other.vel, other.stamp = other.new
                    other.new = None
            return Step(rejected=True, overrun=overrun, resynced=resync)
        w.jumps.clear()
        w.new = (pos, vel, stamp)
        if self.left.new is None or self.right.new is None:
            return Step()
        return Step(pose=self._integrate())

    def _integrate(self) -> Pose:
        """Both wheels have a new estimate: one odometry step with the midpoint heading."""
        left, right = self.left, self.right
        assert left.pos is not None and right.pos is not None and left.new is not None and right.new is not None
        circ = 2.0 * math.pi * self.radius
        (pl, vl_, tl), (pr, vr_, tr) = left.new, right.new
        dl = (pl - left.pos) * circ * left.sign
        dr = (pr - right.pos) * circ * right.sign
        left.pos, left.vel, left.stamp = pl, vl_, tl
        right.pos, right.vel, right.stamp = pr, vr_, tr
        left.new = right.new = None
        ds = 0.5 * (dl + dr)
        dth = (dr - dl) / self.track
        x, y, th = self.pose
        x += ds * math.cos(th + 0.5 * dth)
        y += ds * math.sin(th + 0.5 * dth)
        th += dth
        self.pose = [x, y, th]
        v = 0.5 * circ * (vl_ * left.sign + vr_ * right.sign)
        omega = circ * (vr_ * right.sign - vl_ * left.sign) / self.track
        return Pose(max(tl, tr), x, y, th, v, omega)

    def plausible_step(self, p0: float, t0: float, p1: float, t1: float) -> bool:
        """Whether a wheel can turn from ``p0`` at ``t0`` to ``p1`` at ``t1`` (rev, s) at ``max_wheel_speed``."""
        return abs(p1 - p0) <= self.max_wheel_speed * (max(t1 - t0, 0.0) + JUMP_SLACK)

    def _spend(self, w: Wheel, dp: float, stamp: float) -> bool:
        """Whether the wheel may have moved ``dp`` rev by ``stamp``: its travel budget refills at the fastest it can
        turn (twice the rate it was told over the interval, plus :data:`COMMAND_SLACK_REV_S`, at most
        ``max_wheel_speed``; a replaced command still counts for :data:`BURST_S`, the wheel's response) and holds at
        most :data:`BURST_S` of it, so neither a stream of small steps nor a wheel told to stand still runs away."""
        since = stamp - BURST_S if w.budget_at is None else min(w.budget_at, stamp) - BURST_S
        rate = min(self.max_wheel_speed, 2.0 * self._rate_in_force(w, since, stamp) + COMMAND_SLACK_REV_S)
        if w.budget_at is not None:  # a gap between frames allows the gap's worth; a steady stream, BURST_S's
            gap = max(0.0, stamp - w.budget_at)
            w.budget = min(rate * max(BURST_S, gap), w.budget + rate * gap)
        else:
            w.budget = rate * BURST_S
        w.budget_at = max(stamp, w.budget_at or stamp)
        if dp > w.budget + 1e-9:
            return False
        w.budget -= dp
        return True
