"""The learner's command range measured, not read: a short supervised identification before the transfer.

The paper takes the learner's range as known (its Table 2); a lab's vehicle says only what it *accepts* (a rover's
``WP_SPEED`` and ``ATC_STR_RAT_MAX``, a CAN robot's configured bounds), which can be many times what the teacher
ever needs: a store spread over 0.05-5 m/s has an 11 x 11 grid of 0.45 m/s cells, and the transfer of a teacher that
drives at most 0.6 m/s then has one or two cells to map into. So before the mission the vehicle is driven through a
few bounded probes, each held ``hold_s`` (the vehicle stopped between them), and the range the transfer works in is
what they measured; the accepted range only bounds it:

1. ``straight``: the teacher's top speed (never more than the vehicle accepts) from rest: the speed reached and
   how long it took to settle (what the station's pairing waits for, ``pair_settle_s``);
2. ``creep+`` / ``creep-``: the lowest forward speed with the top turn command each way: a vehicle that turns as
   much at a crawl as at ``v_low``, and so more sharply (its turn rate over its speed), turns in place; one whose
   turn falls with its speed needs speed (``turn``): a car's tightest curvature is the same at every speed, so its
   creep probes turn as sharply as its turn probes whatever speed each probe happened to reach (one slowed by a
   stall, a throttle that creeps as fast as ``v_low``), where the turn rates alone would read it as turning in place
   (a vehicle that turns in place but cannot creep slower than ``v_low`` reads as needing speed: the safer mistake,
   its turns bounded by a curvature it can exceed, where a car read as turning in place is asked to turn on the spot);
3. ``turn+`` / ``turn-``: ``v_low`` with the top turn command each way from rest: the turn rate reached on each
   side, and how long it took to settle (a car's turn waits for its speed and its steering).

The range: the command that reaches the teacher's top (the probe's command scaled by what it reached, assuming a
response proportional near there): more than the probe's command for a vehicle weaker than the teacher, less for
one that overshoots it (a learner beyond the teacher's range is outside the method's assumption, paper §3), never
more than the vehicle accepts; the same for the turn rate on each side of a vehicle that turns in place (one that
needs speed keeps its accepted turn command: the station learns its curvature). Each probe stays within
``max_distance`` of where it started (it ends early at the bound and is measured over what it drove), and the
whole plan within twice that of where it started (it stops there).

Pure: time and pose are arguments (the station's tick gives them, :class:`bridge.nodes.sources.CalibrationSource`
runs this plan as it runs the calibration plan); :meth:`IdentifyPlan.result` is the measurement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.calibration import CalibrationStep
from transfer.domain import Bounds
from transfer.feasibility import Reach

#: the measured range never ends below these (m/s, rad/s): a vehicle that overshoots its commands many times over
#: keeps a range the station can still probe
V_FLOOR, W_FLOOR = 0.1, 0.1
#: a vehicle turns in place when its creep probes turn at least this share of its turn probes' rate ...
CREEP_RATE = 0.6
#: ... and at least this many times as sharply (turn rate over speed): a car's ratio is about 1 at any speed
CREEP_CURVATURE = 1.5


@dataclass(frozen=True)
class Identified:
    """What the probes measured (speeds m/s, turn rates rad/s, times s) and the range that follows."""

    v_max: float  # the learner's top forward command the transfer works with
    w_range: tuple[float, float]  # its turn command's range
    turns_in_place: bool
    settle_s: float  # time for the speed or the turn rate to settle after a step (63 % of the way: the lag)
    settle_top_s: float  # ... and to 90 % of the way from rest to the top (a step to an edge of the range)
    reached: dict[str, tuple[float, float]] = field(default_factory=dict)  # probe -> (speed, turn rate) measured
    why: str = ""

    def reach(self) -> Reach | None:
        """A car's tightest turn measured (:class:`transfer.feasibility.Reach`: the turn probes' turn rate over their
        speed, each side), None for a vehicle that turns in place (it turns any curvature) or when the turn probes
        did not move it."""
        if self.turns_in_place:
            return None
        got = {k: self.reached[k] for k in ("turn+", "turn-") if k in self.reached and self.reached[k][0] > 0.02}
        if not got:
            return None
        left = abs(got["turn+"][1]) / got["turn+"][0] if "turn+" in got else None
        right = abs(got["turn-"][1]) / got["turn-"][0] if "turn-" in got else None
        return Reach(right=right, left=left, speed=max(v for v, _ in got.values()))

    def as_dict(self) -> dict:
        return {"v_max": round(self.v_max, 4), "w_range": [round(x, 4) for x in self.w_range],
                "turns_in_place": self.turns_in_place, "settle_s": round(self.settle_s, 2),
                "settle_top_s": round(self.settle_top_s, 2),
                "reached": {k: [round(a, 4), round(b, 4)] for k, (a, b) in self.reached.items()}, "why": self.why}


def _turns_in_place(creep: list[tuple[float, float]], turn: list[tuple[float, float]]) -> bool:
    """Whether the creep probes' (speed, turn rate) pairs show a vehicle that turns in place, against the turn
    probes' (module docstring, ``creep+`` / ``creep-``): as fast a turn at a crawl (:data:`CREEP_RATE`), and so a
    sharper one (:data:`CREEP_CURVATURE`; a creep that did not move forward turns infinitely sharply)."""
    w_creep, w_turn = (sum(abs(w) for _, w in probes) for probes in (creep, turn))
    if w_turn <= 0.02 or w_creep < CREEP_RATE * w_turn:
        return False
    v_creep, v_turn = (sum(abs(v) for v, _ in probes) for probes in (creep, turn))
    return w_creep * v_turn >= CREEP_CURVATURE * w_turn * max(v_creep, 1e-6)


class IdentifyPlan:
    """See the module docstring. ``step(now, pose)`` each control tick, as :class:`transfer.calibration.
    CalibrationPlan`; ``result()`` once :attr:`finished`."""

    def __init__(self, accepted: Bounds, teacher_top: tuple[float, float], *, v_low: float = 0.15,
                 hold_s: float = 3.0, straight_s: float = 4.5, pause_s: float = 1.0, max_distance: float = 2.5,
                 window_s: float = 1.0) -> None:
        if hold_s <= window_s or max_distance <= 0 or pause_s < 0:
            raise ValueError("hold_s must exceed window_s; max_distance must be positive")
        self.lb = accepted
        (v0, v1), (w0, w1) = accepted.v, accepted.w
        vt, wt = teacher_top
        self.v_top_teacher, self.w_top_teacher = float(vt), float(wt)
        self.v_probe = float(min(v1, vt))
        self.v_low = float(min(max(v_low, v0), self.v_probe))
        wl, wr = float(min(w1, wt)), float(max(w0, -wt))
        self.probes: list[tuple[str, NDArray[np.float64], float]] = [
            ("straight", np.array([self.v_probe, 0.0]), straight_s),
            ("creep+", np.array([v0, wl]), hold_s), ("creep-", np.array([v0, wr]), hold_s),
            ("turn+", np.array([self.v_low, wl]), hold_s), ("turn-", np.array([self.v_low, wr]), hold_s)]
        self.w_probe = (wr, wl)
        self.pause_s, self.max_distance, self.window_s = float(pause_s), float(max_distance), float(window_s)
        self.start: NDArray[np.float64] | None = None
        self.probe_start = np.zeros(3)
        self.index = 0
        self.phase = "pause"
        self.t_phase = 0.0
        self.samples: dict[str, list[tuple[float, float, float, float]]] = {}  # probe -> (t, x, y, theta)
        self.finished: CalibrationStep | None = None

    @property
    def total(self) -> int:
        return len(self.probes)

    def _finish(self, reason: str) -> CalibrationStep:
        self.finished = CalibrationStep(np.zeros(2), "done", min(self.index, self.total - 1), self.total, True, reason)
        return self.finished

    def step(self, now: float, pose: ArrayLike) -> CalibrationStep:
        """The command to send now (a probe's, a stop between probes, or done)."""
        x = np.asarray(pose, dtype=float).reshape(3)
        if self.finished is not None:
            return self.finished
        if self.start is None:
            self.start, self.t_phase = x.copy(), now
        name, u, hold = self.probes[self.index]
        if self.phase == "pause":
            if now - self.t_phase < self.pause_s:
                return CalibrationStep(np.array([0.0, 0.0]), "pause", self.index, self.total)
            self.phase, self.t_phase, self.probe_start = "probe", now, x.copy()
        if float(np.hypot(*(x[:2] - self.start[:2]))) > 2 * self.max_distance:
            return self._finish(f"stopped at the distance bound ({2 * self.max_distance:g} m from the start)")
        self.samples.setdefault(name, []).append((now, float(x[0]), float(x[1]), float(x[2])))
        out = float(np.hypot(*(x[:2] - self.probe_start[:2]))) > self.max_distance
        if now - self.t_phase >= hold or out:
            self.index += 1
            self.phase, self.t_phase = "pause", now
            if self.index >= self.total:
                return self._finish(f"all {self.total} probes driven" + (" (the last ended at the distance bound)"
                                                                         if out else ""))
            return self.step(now, x)
        return CalibrationStep(u.copy(), name, self.index, self.total)

    # ------------------------------------------------------------------------------------------- the measurement
    def _rates(self, name: str) -> tuple[float, float]:
        """The forward speed and turn rate over the probe's last ``window_s`` (0, 0 without samples)."""
        s = self.samples.get(name, [])
        if len(s) < 2:
            return 0.0, 0.0
        t_end = s[-1][0]
        w = [p for p in s if p[0] >= t_end - self.window_s] or s[-2:]
        if len(w) < 2:
            w = s[-2:]
        (t0, x0, y0, _), (t1, x1, y1, _) = w[0], w[-1]
        dt = t1 - t0
        if dt <= 0:
            return 0.0, 0.0
        heading = np.unwrap([p[3] for p in w])
        mid = float(np.mean(heading))
        v = ((x1 - x0) * math.cos(mid) + (y1 - y0) * math.sin(mid)) / dt
        return float(v), float((heading[-1] - heading[0]) / dt)

    def _settling(self, name: str = "straight") -> tuple[float, float]:
        """From a probe's poses (from rest): seconds to 63 % and to 90 % of what it settled at, its forward speed
        (``straight``) or its turn rate (a turn probe)."""
        s = self.samples.get(name, [])
        if len(s) < 4:
            return 0.5, 0.5
        t = np.array([p[0] for p in s])
        if name == "straight":
            xy = np.array([[p[1], p[2]] for p in s])
            rate = np.hypot(*np.diff(xy, axis=0).T) / np.maximum(np.diff(t), 1e-6)
        else:
            rate = np.abs(np.diff(np.unwrap([p[3] for p in s]))) / np.maximum(np.diff(t), 1e-6)
        ts = 0.5 * (t[1:] + t[:-1]) - t[0]
        top = float(np.median(rate[ts >= ts[-1] - self.window_s])) if len(rate) else 0.0
        if top <= 0:
            return 0.5, 0.5

        def first(share: float) -> float:
            above = np.nonzero(rate >= share * top)[0]
            return float(ts[above[0]]) if above.size else float(ts[-1])

        return first(0.63), first(0.9)

    def result(self) -> Identified:
        """The measured range (see the module docstring); the accepted range where a probe measured nothing."""
        reached = {name: self._rates(name) for name, _, _ in self.probes if name in self.samples}
        v1, (w0, w1) = self.lb.v[1], self.lb.w
        v_st = reached.get("straight", (0.0, 0.0))[0]
        why = []
        if v_st > 0.02:
            v_max = float(np.clip(self.v_probe * self.v_top_teacher / v_st, min(self.v_probe, V_FLOOR), v1))
        else:
            v_max, _ = float(v1), why.append("the straight probe did not move: the accepted top speed kept")
        turns_in_place = _turns_in_place([reached.get(k, (0.0, 0.0)) for k in ("creep+", "creep-")],
                                         [reached.get(k, (0.0, 0.0)) for k in ("turn+", "turn-")])
        w_lo, w_hi = float(w0), float(w1)
        if turns_in_place:  # the command that reaches the teacher's top rate on each side, within what is accepted
            up, down = reached.get("turn+", (0.0, 0.0))[1], reached.get("turn-", (0.0, 0.0))[1]
            cmd_down, cmd_up = self.w_probe
            if up > 0.02:
                w_hi = float(np.clip(cmd_up * self.w_top_teacher / up, min(cmd_up, W_FLOOR), w1))
            if down < -0.02:
                w_lo = float(np.clip(cmd_down * self.w_top_teacher / -down, w0, max(cmd_down, -W_FLOOR)))
        # the slower of the speed and the turn rate: a car's turn follows its speed and its steering both
        t63, t90 = (max(x) for x in zip(*(self._settling(n) for n in ("straight", "turn+", "turn-"))))
        return Identified(v_max=v_max, w_range=(w_lo, w_hi), turns_in_place=turns_in_place, settle_s=t63,
                          settle_top_s=t90, reached=reached, why="; ".join(why))


__all__ = ["IdentifyPlan", "Identified"]
