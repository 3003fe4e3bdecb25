"""The worlds of the paper's experiments: an S-shaped path through obstacles, a misaligned start, a goal.

Two sizes: the MPC case (teacher v <= 0.6 m/s, learner v <= 0.3 m/s) and the motion-primitive case (teacher
v <= 3 m/s, learner v <= 1 m/s, primitives 1 s long), the second a scaled copy of the first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from transfer.teacher.path import Path


@dataclass(frozen=True)
class World:
    """A path to follow, circular obstacles (x, y, r), the start pose and the goal radius."""

    name: str
    path: Path
    obstacles: NDArray[np.float64]
    start: NDArray[np.float64]
    goal_radius: float

    @property
    def goal(self) -> NDArray[np.float64]:
        return self.path.points[-1]

    def collides(self, xy: NDArray[np.float64], radius: float = 0.0) -> bool:
        """Does a disc of ``radius`` at xy touch an obstacle?"""
        if self.obstacles.size == 0:
            return False
        d = np.hypot(self.obstacles[:, 0] - xy[0], self.obstacles[:, 1] - xy[1])
        return bool(np.any(d < self.obstacles[:, 2] + radius))

    def clearance(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance from xy to each obstacle's edge."""
        return np.hypot(self.obstacles[:, 0] - xy[0], self.obstacles[:, 1] - xy[1]) - self.obstacles[:, 2]


def s_path(length: float = 8.0, amplitude: float = 1.2, n: int = 400) -> NDArray[np.float64]:
    """An S: y = A sin(2 pi x / length) for x in [0, length] (up through one bend, down through the other)."""
    x = np.linspace(0.0, length, n)
    return np.stack([x, amplitude * np.sin(2 * math.pi * x / length)], axis=-1)


def mpc_world(scale: float = 1.0) -> World:
    """The MPC case: an 8 m S-path (about 10 m of arc), obstacles on the outside of both bends and beside the
    middle, a start 0.3 m beside the path facing 45 degrees away from it. ``scale`` < 1 shortens it (tests)."""
    pts = s_path(8.0 * scale, 1.2 * scale)
    obstacles = np.array([[2.0, 1.9, 0.35], [6.0, -1.9, 0.35], [4.0, 0.75, 0.25], [3.1, -0.4, 0.2]])
    obstacles *= scale  # positions and radii: the same geometry, smaller
    return World("mpc-s-path", Path(pts), obstacles, np.array([0.0, -0.3, -math.pi / 4 + 0.0]), 0.25)


def primitives_world() -> World:
    """The motion-primitive case: the same S scaled by 4 (32 m), for 1 s primitives at up to ~1.2 m/s; the start
    is on the path, heading 45 degrees off it."""
    pts = s_path(32.0, 4.8)
    obstacles = np.array([[8.0, 7.4, 1.2], [24.0, -7.4, 1.2], [16.0, 2.9, 0.9], [12.4, -1.6, 0.7]])
    path = Path(pts)
    # like the paper's Jackal run: on the path's start, heading pi/4 off the desired orientation
    start = np.array([0.0, 0.0, path.heading[0] - math.pi / 4])
    return World("primitives-s-path", path, obstacles, start, 1.0)
