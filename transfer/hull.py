"""The convex hull of a few points in the plane: the learned limits' hull (``transfer/limits.py``), which the
``limits`` message carries (docs/ARCHITECTURE.md, section 3).

Andrew's monotone chain on Python floats: the points sorted once, then the lower and the upper chain, each point
kept only where the chain turns left. The learned limits' hull holds a few tens of points (a cell's mean of its
boundary pairs, and the refined pairs) and is built again each time a message reports it: for that many points
this costs less than a general hull library's set-up for each call.

Pure: no clocks, no files.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: a turn whose cross product is at most this (squared units of the points: the limits' are normalised, in [0, 1])
#: is no turn: the middle point lies on the line of the others (to rounding) and is not a vertex
COLLINEAR = 1e-12


def convex_hull(points: ArrayLike) -> NDArray[np.float64] | None:
    """The vertices of the convex hull of ``points`` ((n, 2)), counter-clockwise from the lowest-leftmost one, with
    no point that lies on an edge; None when the points span no area (fewer than three, or all on one line)."""
    pts = sorted(map(tuple, np.asarray(points, dtype=float).reshape(-1, 2).tolist()))
    if len(pts) < 3:
        return None
    lower = _chain(pts)
    upper = _chain(pts[::-1])
    ring = lower[:-1] + upper[:-1]
    if len(ring) < 3:
        return None
    return np.array(ring, dtype=float)


def _chain(pts: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """One half of the hull: walking ``pts`` in order, each point replaces the last ones while they do not turn
    left (:data:`COLLINEAR`)."""
    out: list[tuple[float, float]] = []
    for p in pts:
        px, py = p
        while len(out) >= 2:
            (ax, ay), (bx, by) = out[-2], out[-1]
            if (bx - ax) * (py - ay) - (by - ay) * (px - ax) > COLLINEAR:
                break
            out.pop()
        out.append(p)
    return out


__all__ = ["COLLINEAR", "convex_hull"]
