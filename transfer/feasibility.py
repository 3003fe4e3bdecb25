"""Whether a mission's path is inside the method's assumption for the vehicle that was measured.

The transfer maps the teacher's commands into what the learner can do (paper §3): it assumes the learner's command
set covers what the task needs of the teacher, i.e. that the teacher's path is feasible for the learner. A car
(a learner that cannot turn in place) turns no tighter than its steering lets it: a curvature ``kappa_v`` (rad/m,
its turn rate over its speed) at its top turn command, on each side. A path that bends more than that cannot be
followed whatever the mapping does: the vehicle drives a wider arc, outside the path's bend, and leaves the corridor.

The measure: the path's curvature, averaged over :data:`WINDOW_M` of arc (a polyline's corners are turns spread over
its segments), is the bend it must turn, ``kappa_p`` on each side, of radius ``1 / kappa_p``. A vehicle that turns no
tighter than ``1 / kappa_v`` and follows the bend at its tightest drives ``1 / kappa_v - 1 / kappa_p`` outside the
bend's arc once the bend has turned it round; the check allows :data:`CORRIDOR_SHARE` of the corridor for that and
keeps the rest for the vehicle's own tracking error and its stop. More than that: the path is outside the method's
assumption for this vehicle, and the station pauses the mission before it leaves the corridor
(:mod:`bridge.nodes.station_assumption`, reason ``outside_assumption``; docs/ARCHITECTURE.md section 6).

A vehicle that turns in place (a skid-steer, a differential drive) turns any curvature: never outside by this
measure. What is measured comes from the supervised identification (:mod:`transfer.identify`); nothing measured,
nothing checked.

Pure: the path's points, the corridor and what was measured are arguments.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

#: m of arc the path's curvature is averaged over (a bend the vehicle must turn, not one polyline corner)
WINDOW_M = 0.3
#: the share of the corridor a vehicle that turns wider than the path's bend may drive outside the bend's arc
CORRIDOR_SHARE = 0.25


@dataclass(frozen=True)
class Reach:
    """What was measured of a vehicle's turn: its tightest curvature on each side (rad/m, both >= 0; None: not
    measured that side) and the speed it was measured at (m/s)."""

    right: float | None
    left: float | None
    speed: float


@dataclass(frozen=True)
class Outside:
    """A path outside the assumption: on which side, how much it bends and where, how much the vehicle turns."""

    side: str  # "left" or "right"
    path_kappa: float  # rad/m
    at_s: float  # arc length of the tightest bend, m
    vehicle_kappa: float  # rad/m
    speed: float  # m/s, what the vehicle's figure was measured at
    need_kappa: float  # the least the vehicle should turn for this bend and corridor, rad/m

    def text(self) -> str:
        """The reason in words, for a person (the station's status text)."""
        return (f"outside the method's assumption: the path bends {self.side} at {self.path_kappa:.2f} rad/m "
                f"({self.at_s:.1f} m along it); this vehicle turns at most {self.vehicle_kappa:.2f} rad/m at "
                f"{self.speed:.2f} m/s (it needs {self.need_kappa:.2f} rad/m to stay in the corridor)")


def path_bends(points: ArrayLike, window_m: float = WINDOW_M) -> tuple[np.ndarray, np.ndarray]:
    """The arc length of each vertex and the path's signed curvature there (left positive, rad/m), averaged over
    ``window_m`` of arc around it."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    seg = np.diff(p, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    keep = np.concatenate([[True], seg_len > 1e-9])  # repeated points turn nothing
    p = p[keep]
    if len(p) < 3:
        return np.zeros(len(p)), np.zeros(len(p))
    seg = np.diff(p, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    s = np.concatenate([[0.0], np.cumsum(seg_len)])
    turn = np.diff(np.arctan2(seg[:, 1], seg[:, 0]))
    turn = (turn + np.pi) % (2.0 * np.pi) - np.pi
    # the heading turned from the start to each vertex (a corner's turn at its vertex); the heading turned between
    # s - w/2 and s + w/2, over the arc between them, is the mean curvature there
    at_vertex = np.concatenate([[0.0], np.cumsum(turn), [float(np.sum(turn))]])
    half = 0.5 * window_m
    lo = np.interp(np.clip(s - half, 0.0, s[-1]), s, at_vertex)
    hi = np.interp(np.clip(s + half, 0.0, s[-1]), s, at_vertex)
    span = np.clip(s + half, 0.0, s[-1]) - np.clip(s - half, 0.0, s[-1])
    return s, (hi - lo) / np.maximum(span, 1e-9)


def outside_assumption(points: ArrayLike, reach: Reach, corridor_m: float, from_s: float = 0.0,
                       window_m: float = WINDOW_M) -> Outside | None:
    """Whether the path (from arc length ``from_s`` on) bends more, on either side, than a vehicle of ``reach`` can
    follow within ``corridor_m`` (module docstring); None when it can (or nothing was measured)."""
    s, kappa = path_bends(points, window_m)
    ahead = s >= from_s - 1e-9
    if not ahead.any():
        return None
    worst: Outside | None = None
    for side, sign, vk in (("left", 1.0, reach.left), ("right", -1.0, reach.right)):
        if vk is None or not math.isfinite(vk):
            continue
        k = sign * kappa[ahead]
        i = int(np.argmax(k))
        kp = float(k[i])
        if kp <= 1e-6:
            continue
        # the least curvature whose arc stays within CORRIDOR_SHARE of the corridor outside the bend's
        need = 1.0 / (1.0 / kp + CORRIDOR_SHARE * corridor_m)
        if vk < need and (worst is None or need - vk > worst.need_kappa - worst.vehicle_kappa):
            worst = Outside(side, kp, float(s[ahead][i]), float(max(vk, 0.0)), float(reach.speed), need)
    return worst


__all__ = ["CORRIDOR_SHARE", "WINDOW_M", "Outside", "Reach", "outside_assumption", "path_bends"]
