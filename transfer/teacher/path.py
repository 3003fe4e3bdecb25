"""Desired paths as polylines with arc length: closest point, progress, deviation and reference sampling.

The class is ``Polyline``, not ``Path``, so it never shadows :class:`pathlib.Path` where both are used.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class Polyline:
    """A polyline path with arc length: closest point, progress and sampling of references."""

    def __init__(self, points: NDArray[np.float64]) -> None:
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 2:
            raise ValueError("a path needs an (M >= 2, 2) array of points")
        self.points = p
        seg = np.diff(p, axis=0)
        self.seg_len = np.hypot(seg[:, 0], seg[:, 1])
        self.s = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        self.length = float(self.s[-1])
        self.heading = np.arctan2(seg[:, 1], seg[:, 0])
        #: signed curvature at each vertex, 1/m (left turns positive): the heading's change there over the mean of
        #: the two segments' lengths; 0 at the ends. A corner of a coarse polyline is a turn over its segments.
        self.curvature = np.zeros(p.shape[0])
        if p.shape[0] > 2:
            turn = np.diff(self.heading)
            turn = (turn + np.pi) % (2.0 * np.pi) - np.pi
            self.curvature[1:-1] = turn / np.maximum(0.5 * (self.seg_len[:-1] + self.seg_len[1:]), 1e-9)
        self._seg = seg
        self._len2 = np.maximum(self.seg_len**2, 1e-18)

    def project(self, xy: NDArray[np.float64]) -> tuple[float, float]:
        """(arc length of the closest point, distance to the path)."""
        a, d = self.points[:-1], self._seg
        t = np.clip(((xy - a) * d).sum(axis=1) / self._len2, 0.0, 1.0)
        e = a + t[:, None] * d - xy
        dist = np.hypot(e[:, 0], e[:, 1])
        i = int(np.argmin(dist))
        return float(self.s[i] + t[i] * self.seg_len[i]), float(dist[i])

    def at(self, s: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Poses (x, y, heading) at arc lengths s (clipped to the path)."""
        s = np.clip(np.asarray(s, dtype=float), 0.0, self.length)
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.seg_len) - 1)
        t = (s - self.s[i]) / np.maximum(self.seg_len[i], 1e-18)
        xy = self.points[i] + t[..., None] * (self.points[i + 1] - self.points[i])
        return np.concatenate([xy, self.heading[i][..., None]], axis=-1)

    def distance(self, xy: NDArray[np.float64]) -> float:
        return self.project(np.asarray(xy, dtype=float))[1]
