"""The robot-side speed limiter, pure (times are arguments): how fast each command may change before a vehicle sees it.

The driver host's gate (:mod:`bridge.core.gate`) clamps each command into the hard limits' box; it does not bound how
hard the vehicle is driven from one command to the next. A station's own MPC bounds its steps (``du_max``), but an
external teacher's step, a perturbation or a stop-to-full command would reach the wheels as a step. This limiter
bounds, per axis (``v`` and ``omega``), the acceleration and the jerk of what the vehicle gets, on the robot, whatever
sent the command, as ros2_control's diff_drive_controller does with its ``SpeedLimiter`` (velocity, acceleration and
jerk limits per axis; the velocity box is the gate's here). Its differences, each for the vehicle's sake:

- **a stop is immediate and exactly zero.** :meth:`SpeedLimiter.stop` (a stop command, the deadman, an estop, any
  reason the gate or the host stops) gives zero at once and forgets the motion: the next command ramps up from rest.
  Only commands that keep the vehicle driving are ramped, down as well as up;
- **never past the command.** A jerk-limited ramp carries its acceleration: run as it is it overshoots the
  target (the vehicle would get more than it was asked for). Here an axis that would pass its target takes the
  target: the limiter only ever holds the vehicle back;
- **the interval is measured, and bounded.** The host ticks at its rate and also at once for each command, so the
  interval between two limited commands varies; it is measured (the acceleration is carried explicitly, not
  derived from two equal intervals), and bounded by ``max_dt`` so that a stalled loop does not allow one large step.

An axis without a limit (``None``, the configuration's default) passes its command as it is: a host without these
keys behaves as before. The limited command is what the host sends and echoes on ``applied`` (docs/ARCHITECTURE.md,
section 6), so pairs learn what the vehicle really got.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass
class AxisLimiter:
    """One axis: ``accel`` (units/s², absolute, both directions) and ``jerk`` (units/s³); None: no limit."""

    accel: float | None = None
    jerk: float | None = None
    value: float = 0.0  # the last output
    rate: float = 0.0  # its rate of change at the last output (the acceleration carried for the jerk limit)

    def __post_init__(self) -> None:
        for name, x in (("accel", self.accel), ("jerk", self.jerk)):
            if x is not None and not (math.isfinite(x) and x > 0.0):
                raise ValueError(f"{name} limit must be a positive number or None, got {x}")

    @property
    def unlimited(self) -> bool:
        return self.accel is None and self.jerk is None

    def limit(self, target: float, dt: float) -> float:
        """The output toward ``target`` after ``dt`` s (> 0), within the acceleration and jerk limits, never past
        ``target``."""
        if self.unlimited:
            self.rate = 0.0
            self.value = target
            return target
        rate = (target - self.value) / dt
        if self.jerk is not None:
            step = self.jerk * dt
            rate = min(max(rate, self.rate - step), self.rate + step)
        if self.accel is not None:
            rate = min(max(rate, -self.accel), self.accel)
        out = self.value + rate * dt
        if (target - self.value) * (target - out) <= 0.0:  # at or past the target: take it, never more
            out = target
        self.rate = (out - self.value) / dt
        self.value = out
        return out

    def rest(self) -> None:
        """The vehicle was stopped: the next ramp starts from rest."""
        self.value, self.rate = 0.0, 0.0


@dataclass
class SpeedLimiter:
    """Acceleration and jerk limits on ``v`` and ``omega`` (see the module docstring). ``period``: the host's tick
    period, s (the interval of the first step after the host starts); ``max_dt``: the longest interval one step may
    use, s (two periods when not given)."""

    v: AxisLimiter = field(default_factory=AxisLimiter)
    omega: AxisLimiter = field(default_factory=AxisLimiter)
    period: float = 0.02
    max_dt: float | None = None
    last: float | None = None  # when the last output was given (None: never, or since a stop)
    limited: int = 0  # commands the vehicle got changed by the limiter (a count for the host's status)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period) and self.period > 0.0):
            raise ValueError(f"period must be a positive number, got {self.period}")
        if self.max_dt is None:
            self.max_dt = 2.0 * self.period

    @property
    def unlimited(self) -> bool:
        return self.v.unlimited and self.omega.unlimited

    def limit(self, v: float, omega: float, now: float) -> tuple[float, float]:
        """The command the vehicle gets at ``now`` for a driving command ``(v, omega)``."""
        if self.unlimited:
            self.last = now
            return v, omega
        last = self.last
        # the first command since the host started: one period from rest (the vehicle stood still)
        dt = self.period if last is None else min(self.max_dt, now - last)  # type: ignore[type-var]
        self.last = now
        if dt <= 0.0:  # the same instant again (a woken tick right after a periodic one): nothing may change yet
            out_v, out_w = self.v.value, self.omega.value
        else:
            out_v, out_w = self.v.limit(v, dt), self.omega.limit(omega, dt)
        if (out_v, out_w) != (v, omega):
            self.limited += 1
        return out_v, out_w

    def stop(self, now: float) -> tuple[float, float]:
        """A stop: exactly zero, at once; the next command ramps from rest."""
        self.v.rest()
        self.omega.rest()
        self.last = now
        return 0.0, 0.0


__all__ = ["AxisLimiter", "SpeedLimiter"]
