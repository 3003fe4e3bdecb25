"""Compiled polygon checks of the SC rectangle map (numba, cached on disk): is a polygon simple, counter-clockwise
and without spikes (``transfer.scm.geometry`` words the answer), and which points lie inside one."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from transfer.scm._scalar import PI


@njit(cache=True, error_model="numpy")
def _orient(a: complex, b: complex, c: complex) -> float:
    return (b - a).real * (c - a).imag - (b - a).imag * (c - a).real


@njit(cache=True, error_model="numpy")
def _on_seg(a: complex, b: complex, c: complex, tol: float) -> bool:
    return (min(a.real, b.real) - tol <= c.real <= max(a.real, b.real) + tol
            and min(a.imag, b.imag) - tol <= c.imag <= max(a.imag, b.imag) + tol)


@njit(cache=True, error_model="numpy")
def segments_cross(p1: complex, p2: complex, q1: complex, q2: complex, tol: float) -> bool:
    """Do the closed segments p1p2 and q1q2 touch (including collinear overlap)?"""
    d1, d2 = _orient(q1, q2, p1), _orient(q1, q2, p2)
    d3, d4 = _orient(p1, p2, q1), _orient(p1, p2, q2)
    scale = tol * max(abs(p2 - p1), abs(q2 - q1), 1e-300)
    if ((d1 > scale and d2 < -scale) or (d1 < -scale and d2 > scale)) and (
        (d3 > scale and d4 < -scale) or (d3 < -scale and d4 > scale)
    ):
        return True
    return ((abs(d1) <= scale and _on_seg(q1, q2, p1, tol)) or (abs(d2) <= scale and _on_seg(q1, q2, p2, tol))
            or (abs(d3) <= scale and _on_seg(p1, p2, q1, tol)) or (abs(d4) <= scale and _on_seg(p1, p2, q2, tol)))


@njit(cache=True, error_model="numpy")
def polygon_defect(w: np.ndarray) -> tuple[int, int, int]:
    """What is wrong with polygon ``w`` (complex vertices), as ``(code, i, j)``: 0 nothing; 1 vertex i not finite;
    2 vertices i and j coincide; 3 edge i-(i+1) meets edge j-(j+1); 4 clockwise; 5 zero area; 6 vertex i a spike
    (a zero or full interior angle). ``transfer.scm.geometry.check_polygon`` words them."""
    n = w.shape[0]
    for k in range(n):
        if not (math.isfinite(w[k].real) and math.isfinite(w[k].imag)):
            return 1, k, 0
    diam = 0.0
    for i in range(n):
        for j in range(n):
            diam = max(diam, abs(w[i] - w[j]))
    tol = 1e-12 * max(diam, 1e-300)
    for i in range(n):
        for j in range(i + 1, n):
            if abs(w[i] - w[j]) <= tol:
                return 2, i, j
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # adjacent edges share a vertex
            if segments_cross(w[i], w[(i + 1) % n], w[j], w[(j + 1) % n], 1e-12):
                return 3, i, j
    area2 = 0.0
    for k in range(n):
        a, b = w[k], w[(k + 1) % n]
        area2 += a.real * b.imag - b.real * a.imag
    if area2 < 0:
        return 4, 0, 0
    if area2 <= 1e-14 * diam * diam:
        return 5, 0, 0
    for k in range(n):
        turn = (w[(k + 1) % n] - w[k]) / (w[k] - w[k - 1])
        alpha = 1.0 - math.atan2(turn.imag, turn.real) / PI
        if alpha < 1e-9 or alpha > 2.0 - 1e-9:
            return 6, k, 0
    return 0, 0, 0


@njit(cache=True, error_model="numpy")
def _smallest_angle(q: np.ndarray) -> float:
    """Smallest interior angle (radians) of a counter-clockwise polygon given as (n, 2) floats: pi less each
    vertex's turn, the turn from the dot and cross products of its edges."""
    n = q.shape[0]
    best = math.inf
    for k in range(n):
        px, py = q[k, 0] - q[k - 1, 0], q[k, 1] - q[k - 1, 1]  # the edge into vertex k
        nx, ny = q[(k + 1) % n, 0] - q[k, 0], q[(k + 1) % n, 1] - q[k, 1]  # the edge out of it
        best = min(best, PI - math.atan2(px * ny - py * nx, px * nx + py * ny))
    return best


@njit(cache=True, error_model="numpy")
def quad_pair_score(t: np.ndarray, lrn: np.ndarray) -> float:
    """The shape score of a mapping region: the smaller of the smallest interior angles of its teacher and its
    learner polygon ((n, 2) floats each), or -1.0 when either is not a valid polygon (:func:`polygon_defect`)."""
    n = t.shape[0]
    w = np.empty(n, dtype=np.complex128)
    for q in (t, lrn):
        for k in range(n):
            w[k] = complex(q[k, 0], q[k, 1])
        if n < 4 or polygon_defect(w)[0] != 0:
            return -1.0
    return min(_smallest_angle(t), _smallest_angle(lrn))


@njit(cache=True, error_model="numpy")
def points_in_polygon(p: np.ndarray, w: np.ndarray, tol: float) -> np.ndarray:
    """True where p is inside the closed polygon w (points within tol of an edge count as inside)."""
    n = w.shape[0]
    out = np.zeros(p.shape[0], dtype=np.bool_)
    for i in range(p.shape[0]):
        x = p[i].real
        y = p[i].imag
        inside = False
        on_edge = False
        for j in range(n):
            a = w[j]
            b = w[(j + 1) % n]
            ab = b - a
            L2 = ab.real * ab.real + ab.imag * ab.imag
            t = ((p[i] - a).real * ab.real + (p[i] - a).imag * ab.imag) / L2
            t = min(max(t, 0.0), 1.0)
            if abs(p[i] - (a + t * ab)) <= tol:
                on_edge = True
                break
            if (a.imag > y) != (b.imag > y):
                xc = a.real + (y - a.imag) * ab.real / ab.imag
                if x < xc:
                    inside = not inside
        out[i] = inside or on_edge
    return out

