"""The closest point of a polyline and the MPC's references along it, in compiled loops (numba, cached on disk):
the same closest point as :meth:`transfer.teacher.path.Polyline.project`, the same samples as
:meth:`~transfer.teacher.path.Polyline.at`, headings unwrapped next to the vehicle's. A few microseconds, where the
numpy calls took tens per tick."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def closest(points: np.ndarray, s_cum: np.ndarray, seg_len: np.ndarray, x: float, y: float) -> tuple[float, float]:
    """(arc length, distance) of the point of the polyline closest to (x, y); the first segment wins a tie."""
    s0, best, _ = _scan(points, s_cum, seg_len, x, y, np.inf)
    return s0, best


@njit(cache=True, error_model="numpy")
def closest_near(points: np.ndarray, s_cum: np.ndarray, seg_len: np.ndarray, x: float, y: float,
                 hint: int) -> tuple[float, float, int]:
    """:func:`closest`, bit for bit, and its segment's index, found faster near segment ``hint`` (the last answer
    for a vehicle that moved a little since): that segment's distance, a hair above, bounds the scan from its
    start, so nearly every other segment is passed over by the cheap test. A bound above the least distance
    changes nothing the scan finds (the first segment of the least distance still wins); only its cost."""
    m = points.shape[0] - 1
    i = min(max(hint, 0), m - 1)
    _, d = _segment(points, seg_len, i, x, y)
    return _scan(points, s_cum, seg_len, x, y, d + d * 1e-9 + 1e-12)


@njit(cache=True, error_model="numpy", inline="always")
def _segment(points: np.ndarray, seg_len: np.ndarray, i: int, x: float, y: float) -> tuple[float, float]:
    """(t along segment ``i``, distance) of the point of segment ``i`` closest to (x, y)."""
    ax, ay = points[i, 0], points[i, 1]
    dx, dy = points[i + 1, 0] - ax, points[i + 1, 1] - ay
    t = ((x - ax) * dx + (y - ay) * dy) / max(seg_len[i] ** 2, 1e-18)
    t = min(max(t, 0.0), 1.0)
    return t, math.hypot(ax + t * dx - x, ay + t * dy - y)


@njit(cache=True, error_model="numpy", inline="always")
def _scan(points: np.ndarray, s_cum: np.ndarray, seg_len: np.ndarray, x: float, y: float,
          bound: float) -> tuple[float, float, int]:
    """The closest point's (arc length, distance, segment) among the segments closer than ``bound`` (inf: all)."""
    best, s0, at = bound, 0.0, 0
    for i in range(points.shape[0] - 1):
        ax, ay = points[i, 0], points[i, 1]
        # a segment starting further than (best + its length) away holds no closer point: skipped without the
        # division and the hypot (1e-9 of slack over the rounding: the same segments win as without the test)
        ex, ey, reach = ax - x, ay - y, best + seg_len[i]
        if ex * ex + ey * ey > reach * reach * (1.0 + 1e-9) + 1e-12:
            continue
        t, d = _segment(points, seg_len, i, x, y)
        if d < best:
            best, s0, at = d, s_cum[i] + t * seg_len[i], i
    return s0, best, at


def references(points: np.ndarray, s_cum: np.ndarray, seg_len: np.ndarray, heading: np.ndarray, x: float,
               y: float, theta: float, spacing: float, n: int) -> np.ndarray:
    """``n`` poses (x, y, heading) from the point of the path closest to (x, y), ``spacing`` metres apart (clipped
    to the path); the first heading within pi of ``theta``, each next within pi of the one before. The two compiled
    loops composed in Python (the MPC's solve finds the closest point once and calls :func:`references_from`)."""
    s0, _ = closest(points, s_cum, seg_len, x, y)
    return references_from(points, s_cum, seg_len, heading, s0, theta, spacing, n)


@njit(cache=True, error_model="numpy")
def references_from(points: np.ndarray, s_cum: np.ndarray, seg_len: np.ndarray, heading: np.ndarray, s0: float,
                    theta: float, spacing: float, n: int) -> np.ndarray:
    """:func:`references` from the path's point at arc length ``s0`` (the closest point, found by the caller)."""
    m = points.shape[0] - 1
    two_pi = 2.0 * math.pi
    out = np.empty((n, 3))
    length = s_cum[-1]
    prev_raw, prev = 0.0, 0.0
    for k in range(n):
        s = min(max(s0 + spacing * k, 0.0), length)
        i = min(max(np.searchsorted(s_cum, s, side="right") - 1, 0), m - 1)
        t = (s - s_cum[i]) / max(seg_len[i], 1e-18)
        out[k, 0] = points[i, 0] + t * (points[i + 1, 0] - points[i, 0])
        out[k, 1] = points[i, 1] + t * (points[i + 1, 1] - points[i, 1])
        h = heading[i]
        if k == 0:
            rel = h - theta
            prev = theta + rel - two_pi * np.round(rel / two_pi)
        else:
            d = h - prev_raw
            prev = prev + d - two_pi * np.round(d / two_pi)
        prev_raw = h
        out[k, 2] = prev
    return out


def curve_speed(points: np.ndarray, s_cum: np.ndarray, seg_len: np.ndarray, curvature: np.ndarray, x: float,
                y: float, v_max: float, v_min: float, w_lo: float, w_hi: float, margin: float,
                horizon: float) -> float:
    """The top speed at which every bend of the path within ``horizon`` s (at ``v_max``) of the point closest to
    (x, y) can be turned at ``margin`` of the yaw-rate bound on its side (``w_hi`` for a left bend, ``w_lo`` for a
    right one): ``v = margin * |w| / |curvature|``, never above ``v_max`` nor below ``v_min``. The two compiled
    loops composed in Python, as :func:`references`."""
    s0, _ = closest(points, s_cum, seg_len, x, y)
    return curve_speed_from(s_cum, curvature, s0, v_max, v_min, w_lo, w_hi, margin, horizon)


@njit(cache=True, error_model="numpy")
def curve_speed_from(s_cum: np.ndarray, curvature: np.ndarray, s0: float, v_max: float, v_min: float, w_lo: float,
                     w_hi: float, margin: float, horizon: float) -> float:
    """:func:`curve_speed` from the path's point at arc length ``s0`` (the closest point, found by the caller)."""
    s1 = s0 + v_max * horizon
    v = v_max
    i = np.searchsorted(s_cum, s0, side="left")
    while i < s_cum.shape[0] and s_cum[i] <= s1:
        k = curvature[i]
        if k > 0.0:
            v = min(v, margin * max(w_hi, 0.0) / k)
        elif k < 0.0:
            v = min(v, margin * min(w_lo, 0.0) / k)
        i += 1
    return max(v, v_min)


@njit(cache=True, error_model="numpy")
def nearest_obstacles(obstacles: np.ndarray, x: float, y: float, reach: float, slots: np.ndarray) -> tuple[int, int]:
    """The obstacles (rows x, y, radius) whose clearance from (x, y) (centre distance less radius) is at most
    ``reach``, nearest first (a stable sort: of equal clearances the first listed first), written into the rows of
    ``slots`` (an unused slot: 0, 0, -1); returns (how many were written, how many within reach did not fit)."""
    n = obstacles.shape[0]
    near = np.empty(n, dtype=np.int64)
    clear = np.empty(n)
    m = 0
    for i in range(n):
        c = math.hypot(obstacles[i, 0] - x, obstacles[i, 1] - y) - obstacles[i, 2]
        if c <= reach:
            j = m  # insertion: after every kept one of no larger clearance
            while j > 0 and clear[j - 1] > c:
                clear[j], near[j] = clear[j - 1], near[j - 1]
                j -= 1
            clear[j], near[j] = c, i
            m += 1
    k = min(m, slots.shape[0])
    for j in range(slots.shape[0]):
        if j < k:
            slots[j, 0], slots[j, 1], slots[j, 2] = obstacles[near[j], 0], obstacles[near[j], 1], obstacles[near[j], 2]
        else:
            slots[j, 0], slots[j, 1], slots[j, 2] = 0.0, 0.0, -1.0
    return k, m - k


def warm(curve: bool = True) -> None:
    """The compiled loops a solve calls loaded from numba's on-disk cache (compiled into it once per machine) now, not
    in a solve: the closest point near the last one, the references from it, the obstacles, and, with ``curve``, the
    slowing for bends. The MPC calls it when it is made (the install makes one that slows for bends). Not
    :func:`closest`: only :func:`references` searches the whole path, and no solve calls it."""
    pts, s_cum, seg = np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([0.0, 1.0]), np.array([1.0])
    closest_near(pts, s_cum, seg, 0.0, 0.0, 0)
    references_from(pts, s_cum, seg, np.zeros(1), 0.0, 0.0, 0.1, 2)
    nearest_obstacles(np.zeros((1, 3)), 0.0, 0.0, 1.0, np.empty((1, 3)))
    if curve:
        curve_speed_from(s_cum, np.zeros(2), 0.0, 1.0, 0.1, -1.0, 1.0, 0.9, 1.0)
