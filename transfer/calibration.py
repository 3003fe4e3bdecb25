"""The paper's calibration stage as a bounded plan: drive a grid of learner commands, come back, stop at the bound.

Paper §4 (learner limits): "a series of extreme learner commands are imparted to the learner to assess its motion
limits" before the transfer. On a real robot that has to stay inside a lab, so the plan

- drives each command of an ``n_v x n_omega`` grid spanning the learner's box (extremes included, so the learned
  limits are measured, not extrapolated) for ``hold_s``;
- between commands, when the robot is farther than ``return_radius`` from where it started, steers back toward
  the start with a proportional heading controller on the learner's own commands (slow, turning in place as far
  as the learner can) until it is within half the radius, or back inside the radius but no longer getting closer
  for ``stall_s`` (a learner that cannot turn in place circles the start), or for at most ``return_timeout_s``;
- ends, stopping the robot, when the grid is done, when the robot is farther than ``max_distance`` from the start
  (it says so: the bound was reached), or after ``max_time_s``.

Pure: time and pose are arguments; the caller sends the commands and records the pairs they make.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.domain import Bounds
from transfer.limits import calibration_commands
from transfer.teacher.unicycle import wrap_angle


@dataclass(frozen=True)
class CalibrationStep:
    """What to send now: a learner command, or ``done`` (then a stop) with the reason."""

    u_L: NDArray[np.float64]
    phase: str  # drive | return | done
    index: int  # the grid command being driven (or last driven)
    total: int
    done: bool = False
    reason: str = ""


class CalibrationPlan:
    """See the module docstring. ``step(now, pose)`` each control tick."""

    def __init__(self, learner_bounds: Bounds, grid: tuple[int, int] = (5, 5), *, hold_s: float = 1.0,
                 max_distance: float = 2.0, return_radius: float | None = None, max_time_s: float = 300.0,
                 return_timeout_s: float = 20.0, heading_gain: float = 1.5, stall_s: float = 2.0) -> None:
        if hold_s <= 0 or max_distance <= 0 or max_time_s <= 0:
            raise ValueError("hold_s, max_distance and max_time_s must be positive")
        self.lb = learner_bounds
        self.commands = calibration_commands(learner_bounds, grid)
        self.hold_s, self.max_distance, self.max_time_s = float(hold_s), float(max_distance), float(max_time_s)
        self.return_radius = 0.4 * self.max_distance if return_radius is None else float(return_radius)
        self.return_timeout_s, self.k, self.stall_s = float(return_timeout_s), float(heading_gain), float(stall_s)
        self.phase_best: tuple[float, float] | None = None  # (closest distance so far, when) in a return
        self.start: NDArray[np.float64] | None = None
        self.t0 = self.t_phase = 0.0
        self.index = 0
        self.phase = "drive"
        self.finished: CalibrationStep | None = None

    @property
    def total(self) -> int:
        return int(self.commands.shape[0])

    def _finish(self, reason: str) -> CalibrationStep:
        self.finished = CalibrationStep(np.zeros(2), "done", min(self.index, self.total - 1), self.total, True, reason)
        return self.finished

    def step(self, now: float, pose: ArrayLike) -> CalibrationStep:
        x = np.asarray(pose, dtype=float).reshape(3)
        if self.finished is not None:
            return self.finished
        if self.start is None:
            self.start, self.t0, self.t_phase = x.copy(), now, now
        dist = float(np.hypot(*(x[:2] - self.start[:2])))
        if dist > self.max_distance:
            return self._finish(f"stopped at the distance bound ({dist:.2f} m > {self.max_distance} m)")
        if now - self.t0 > self.max_time_s:
            return self._finish(f"stopped at the time bound ({self.max_time_s:.0f} s)")
        if self.phase == "drive":
            if now - self.t_phase < self.hold_s:
                return CalibrationStep(self.commands[self.index].copy(), "drive", self.index, self.total)
            self.index += 1
            if self.index >= self.total:
                return self._finish(f"all {self.total} commands driven")
            self.phase, self.t_phase = ("return" if dist > self.return_radius else "drive"), now
            return self.step(now, x)
        # return toward the start, until close enough, or no longer getting closer (a learner that cannot turn in
        # place circles round the start point), or the return's timeout
        if self.phase_best is None or dist < self.phase_best[0] - 0.01:
            self.phase_best = (dist, now)
        stalled = dist <= self.return_radius and now - self.phase_best[1] > self.stall_s  # back inside, circling
        if dist <= 0.5 * self.return_radius or stalled or now - self.t_phase > self.return_timeout_s:
            self.phase, self.t_phase, self.phase_best = "drive", now, None
            return self.step(now, x)
        return CalibrationStep(self._toward_start(x), "return", self.index, self.total)

    def _toward_start(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Learner command steering back to the start: turn toward it, move slowly until facing it."""
        assert self.start is not None
        err = float(wrap_angle(math.atan2(self.start[1] - x[1], self.start[0] - x[0]) - x[2]))
        (v0, v1), (w0, w1) = self.lb.v, self.lb.w
        w = float(np.clip(self.k * err, w0, w1))
        slow = v0 if v0 > 0 else min(v1, 0.25 * (v1 - max(v0, 0.0)))
        v = slow if abs(err) > 0.6 else slow + 0.5 * (v1 - slow)
        return np.array([v, w])


__all__ = ["CalibrationPlan", "CalibrationStep"]
