"""The simulated learner body that every link emulator drives: pose integration in (emulated) real time.

A link emulator turns its wire protocol into ``command(v, omega)`` calls and reads ``pose``; this class owns the
physics (the degraded learner response of :mod:`sim_learner.dynamics`), so all links emulate the same vehicle. Time
is passed in (``now`` seconds, any monotonic clock) so tests can drive it deterministically.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from sim_learner.dynamics import LearnerModel
from transfer.teacher.unicycle import euler


@dataclass(slots=True)
class BodyState:
    """Pose (ENU, theta CCW from x) and the body velocities the vehicle really moves with."""

    x: float
    y: float
    theta: float
    v: float = 0.0
    omega: float = 0.0


class SimVehicle:
    """A learner vehicle: holds the last command, integrates the learner dynamics with sub-steps of ``max_dt``.

    ``command`` is what the vehicle's low-level controller was told (already in the learner's command units);
    the motion follows ``model.response(command)``. ``stop()`` zeroes the command (a controller watchdog or a
    disarm). Gaussian position noise, if any, is added to the *reported* pose only (a measurement error, as in the
    paper), never to the integrated state.
    """

    def __init__(
        self,
        model: LearnerModel,
        x0: tuple[float, float, float] = (0.0, 0.0, 0.0),
        *,
        now: float = 0.0,
        max_dt: float = 0.01,
        pos_noise: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> None:
        if pos_noise > 0.0 and rng is None:
            raise ValueError("position noise needs an explicit random generator")
        self.model = model
        self.state = BodyState(*map(float, x0))
        self.cmd = (0.0, 0.0)
        self.moving = False  # False: the wheels are held (zero velocity), whatever the last command was
        self.t = float(now)
        self.distance = 0.0  # signed path length travelled (what wheel encoders integrate)
        self.theta0 = self.state.theta
        self.max_dt = float(max_dt)
        self.pos_noise = float(pos_noise)
        self.rng = rng
        self.rolling = False  # moving by itself (roll), not by a command
        self._lock = threading.RLock()  # a link emulator's thread commands it while a test or mocap thread reads it

    def command(self, v: float, omega: float, now: float) -> None:
        """Integrate up to ``now`` under the old command, then take the new one."""
        with self._lock:
            self._command(v, omega, now)

    def _command(self, v: float, omega: float, now: float) -> None:
        self.advance(now)
        if not (np.isfinite(v) and np.isfinite(omega)):
            raise ValueError(f"non-finite command ({v}, {omega}) reached the vehicle")
        self.cmd, self.rolling = (float(v), float(omega)), False
        # an exact zero is a stop (wheels held), not a command in the learner's range: the paper's learner maps
        # every command through d(h(n(.))) and would creep at v_min
        self.moving = not (v == 0.0 and omega == 0.0)

    def roll(self, v: float, omega: float, now: float) -> None:
        """The body moves at ``(v, omega)`` from ``now`` by itself, not by a command through the learner's response
        (a vehicle braking to a stop, or coasting with its motors off)."""
        with self._lock:
            self.advance(now)
            self.cmd, self.moving, self.rolling = (float(v), float(omega)), True, True

    def stop(self, now: float) -> None:
        """Hold the wheels from ``now`` on."""
        with self._lock:
            self._stop(now)

    def _stop(self, now: float) -> None:
        self.advance(now)
        self.moving = False
        self.state.v = 0.0
        self.state.omega = 0.0

    def advance(self, now: float) -> BodyState:
        """Integrate the dynamics from the last update to ``now`` (no-op if ``now`` is not later)."""
        with self._lock:
            return self._advance(now)

    def _advance(self, now: float) -> BodyState:
        dt_total = float(now) - self.t
        if dt_total <= 0.0:
            return self.state
        if self.moving and self.rolling:
            v, w = self.cmd
        elif self.moving:
            v, w = (float(a) for a in self.model.response(np.asarray(self.cmd)))
        else:
            v, w = 0.0, 0.0
        s = self.state
        n = max(1, int(np.ceil(dt_total / self.max_dt)))
        h = dt_total / n
        x, y, th = s.x, s.y, s.theta
        for _ in range(n):
            x, y, th = euler(x, y, th, v, w, h, math.cos, math.sin)
        s.x, s.y, s.theta, s.v, s.omega = float(x), float(y), float(th), v, w
        self.distance += v * dt_total
        self.t = float(now)
        return s

    def measured_pose(self, now: float) -> tuple[float, float, float]:
        """The pose a sensor would report at ``now`` (with the configured position noise)."""
        with self._lock:
            return self._measured_pose(now)

    def _measured_pose(self, now: float) -> tuple[float, float, float]:
        s = self.advance(now)
        x, y = s.x, s.y
        if self.pos_noise > 0.0 and self.rng is not None:
            dx, dy = self.rng.normal(0.0, self.pos_noise, size=2)
            x, y = x + float(dx), y + float(dy)
        return x, y, s.theta
