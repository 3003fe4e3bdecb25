"""A mission as the method sees it: a path to follow to its goal, circular obstacles, an optional start pose.

Pure data and geometry (no I/O): the station and the simulations both decide "goal reached" and "collision" here,
with one rule each. Mission files are read by ``bridge.core.config.load_mission`` (docs/ARCHITECTURE.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.teacher.path import Polyline

#: the fraction of the path a vehicle must have covered before it can be at the goal (a path may loop back)
GOAL_MIN_PROGRESS = 0.9
#: m: exploration (perturbing a command to learn a missing pair) happens only this far from every obstacle's edge
EXPLORE_CLEARANCE = 0.3


@dataclass(frozen=True)
class Mission:
    """A polyline path, obstacles ``(K, 3)`` as rows ``(x, y, r)``, the goal tolerance and an optional start."""

    name: str
    path: Polyline
    obstacles: NDArray[np.float64]
    goal_tolerance: float
    start: NDArray[np.float64] | None = None
    frame: str = "world"

    def __post_init__(self) -> None:
        obs = np.asarray(self.obstacles, dtype=float).reshape(-1, 3)
        if not np.all(np.isfinite(obs)) or np.any(obs[:, 2] <= 0):
            raise ValueError("obstacles must be finite rows (x, y, r) with r > 0")
        if not (np.isfinite(self.goal_tolerance) and self.goal_tolerance > 0):
            raise ValueError(f"goal tolerance must be a positive number, got {self.goal_tolerance}")
        object.__setattr__(self, "obstacles", obs)
        if self.start is not None:
            start = np.asarray(self.start, dtype=float).reshape(3)
            if not np.all(np.isfinite(start)):
                raise ValueError("the start pose must be finite")
            object.__setattr__(self, "start", start)

    @property
    def goal(self) -> NDArray[np.float64]:
        """The last waypoint."""
        return self.path.points[-1]

    def progress(self, xy: ArrayLike) -> float:
        """Covered fraction of the path, in [0, 1], at the point of the path closest to ``xy``."""
        s, _ = self.path.project(np.asarray(xy, dtype=float))
        return s / self.path.length

    def reached(self, x: ArrayLike) -> bool:
        """The one goal rule: at least ``GOAL_MIN_PROGRESS`` of the path covered and within the goal tolerance of
        the goal. (Passing the path's end is not enough: a vehicle 3 m beside the last waypoint is not there.)"""
        xy = np.asarray(x, dtype=float)[:2]
        return self.reached_at(self.path.project(xy)[0], xy)

    def reached_at(self, s: float, xy: ArrayLike) -> bool:
        """:meth:`reached` for a point ``xy`` whose closest point on the path is at arc length ``s``."""
        p = np.asarray(xy, dtype=float)[:2]
        return s >= GOAL_MIN_PROGRESS * self.path.length and float(np.hypot(*(p - self.goal))) < self.goal_tolerance

    def collides(self, xy: ArrayLike, radius: float = 0.0) -> bool:
        """Does a disc of ``radius`` at ``xy`` touch an obstacle?"""
        if self.obstacles.size == 0:
            return False
        p = np.asarray(xy, dtype=float)
        d = np.hypot(self.obstacles[:, 0] - p[0], self.obstacles[:, 1] - p[1])
        return bool(np.any(d < self.obstacles[:, 2] + radius))

    def clearance(self, xy: ArrayLike) -> NDArray[np.float64]:
        """Distance from ``xy`` to each obstacle's edge (negative inside)."""
        p = np.asarray(xy, dtype=float)
        return np.hypot(self.obstacles[:, 0] - p[0], self.obstacles[:, 1] - p[1]) - self.obstacles[:, 2]

    def min_clearance(self, xy: ArrayLike) -> float:
        """Distance to the nearest obstacle's edge (inf without obstacles)."""
        return float(self.clearance(xy).min()) if self.obstacles.size else float("inf")

    def may_explore(self, xy: ArrayLike, clearance: float = EXPLORE_CLEARANCE) -> bool:
        """May a transfer policy explore (perturb) here? Only at least ``clearance`` from every obstacle's edge."""
        return self.min_clearance(xy) >= clearance

    def scaled(self, k: float, name: str | None = None) -> Mission:
        """The same mission ``k`` times smaller or larger (positions and radii; the goal tolerance and the start's
        heading kept)."""
        start = None
        if self.start is not None:
            start = np.array([self.start[0] * k, self.start[1] * k, self.start[2]])
        return Mission(name or self.name, Polyline(self.path.points * k), self.obstacles * k, self.goal_tolerance,
                       start, self.frame)


__all__ = ["EXPLORE_CLEARANCE", "GOAL_MIN_PROGRESS", "Mission"]
