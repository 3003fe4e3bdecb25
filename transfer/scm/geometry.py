"""Polygon checks shared by the SC maps and the mapping-region selection: one place that says what a valid
polygon is (at least 4 distinct finite vertices, simple, counter-clockwise, no zero or full turn)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray


def as_complex(points: ArrayLike, what: str = "points") -> NDArray[np.complex128]:
    """Complex array from complex numbers or an (..., 2) float array (x = real part, y = imaginary part)."""
    a = np.asarray(points)
    if np.iscomplexobj(a):
        return a.astype(np.complex128)
    a = a.astype(float)
    if a.ndim >= 1 and a.shape[-1] == 2:
        return a[..., 0] + 1j * a[..., 1]
    if a.ndim == 0 or a.ndim >= 1:
        return a.astype(np.complex128)
    raise ValueError(f"{what}: expected complex numbers or an (..., 2) array, got shape {a.shape}")


def _segments_cross(p1: complex, p2: complex, q1: complex, q2: complex, tol: float) -> bool:
    """Do the closed segments p1p2 and q1q2 touch (including collinear overlap)?"""

    def orient(a: complex, b: complex, c: complex) -> float:
        return (b - a).real * (c - a).imag - (b - a).imag * (c - a).real

    def on_seg(a: complex, b: complex, c: complex) -> bool:
        return (
            min(a.real, b.real) - tol <= c.real <= max(a.real, b.real) + tol
            and min(a.imag, b.imag) - tol <= c.imag <= max(a.imag, b.imag) + tol
        )

    d1, d2 = orient(q1, q2, p1), orient(q1, q2, p2)
    d3, d4 = orient(p1, p2, q1), orient(p1, p2, q2)
    scale = tol * max(abs(p2 - p1), abs(q2 - q1), 1e-300)
    if ((d1 > scale and d2 < -scale) or (d1 < -scale and d2 > scale)) and (
        (d3 > scale and d4 < -scale) or (d3 < -scale and d4 > scale)
    ):
        return True
    return (
        (abs(d1) <= scale and on_seg(q1, q2, p1))
        or (abs(d2) <= scale and on_seg(q1, q2, p2))
        or (abs(d3) <= scale and on_seg(p1, p2, q1))
        or (abs(d4) <= scale and on_seg(p1, p2, q2))
    )


def turning_exponents(w: NDArray[np.complex128]) -> NDArray[np.float64]:
    """beta_j = interior angle / pi - 1 (= -turn_j / pi) of a counter-clockwise polygon."""
    nxt = np.concatenate((w[1:], w[:1])) - w  # np.roll's result, without its generality's cost (a hot path)
    prev = np.concatenate((nxt[-1:], nxt[:-1]))
    return -np.angle(nxt / prev) / np.pi


def check_polygon(vertices: ArrayLike, *, min_vertices: int = 4) -> NDArray[np.complex128]:
    """Validate a polygon and return its vertices as a complex array; ValueError naming the problem otherwise."""
    w = as_complex(vertices, "vertices").ravel() if np.iscomplexobj(np.asarray(vertices)) else as_complex(vertices)
    w = np.asarray(w, dtype=np.complex128).ravel()
    if w.size < min_vertices:
        raise ValueError(f"a polygon needs at least {min_vertices} vertices, got {w.size}")
    if not np.all(np.isfinite(w)):
        raise ValueError("vertices contain non-finite numbers (NaN or inf)")
    n = w.size
    diam = float(np.max(np.abs(w[:, None] - w[None, :])))
    tol = 1e-12 * max(diam, 1e-300)
    for i in range(n):
        for j in range(i + 1, n):
            if abs(w[i] - w[j]) <= tol:
                raise ValueError(f"repeated vertices: vertex {i} and vertex {j} coincide")
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # adjacent edges share a vertex
            if _segments_cross(w[i], w[(i + 1) % n], w[j], w[(j + 1) % n], 1e-12):
                raise ValueError(f"self-crossing polygon: edge {i}-{(i + 1) % n} meets edge {j}-{(j + 1) % n}")
    after = np.concatenate((w[1:], w[:1]))
    area2 = float(np.sum(w.real * after.imag - after.real * w.imag))
    if area2 < 0:
        raise ValueError("vertices are in clockwise order; give them counter-clockwise")
    if area2 <= 1e-14 * diam * diam:
        raise ValueError("degenerate polygon with zero area")
    alpha = turning_exponents(w) + 1.0
    bad = np.where((alpha < 1e-9) | (alpha > 2.0 - 1e-9))[0]
    if bad.size:
        raise ValueError(f"vertex {int(bad[0])} has a zero or full interior angle (a spike)")
    return w


def is_simple_ccw(vertices: ArrayLike) -> bool:
    """True when :func:`check_polygon` accepts the polygon (cheap boolean form for region selection)."""
    try:
        check_polygon(vertices)
    except ValueError:
        return False
    return True


def check_corners(corners: Sequence[int], n: int) -> tuple[int, int, int, int]:
    """Four distinct, strictly increasing vertex indices in [0, n)."""
    try:
        cs = tuple(int(c) for c in corners)
    except (TypeError, ValueError):
        raise ValueError(f"corners must be 4 integer vertex indices, got {corners!r}") from None
    if len(cs) != 4:
        raise ValueError(f"corners must be 4 vertex indices, got {len(cs)}")
    if any(int(c) != c for c in corners):
        raise ValueError(f"corners must be integers, got {corners!r}")
    if not all(0 <= c < n for c in cs):
        raise ValueError(f"corners {cs} must be vertex indices in [0, {n})")
    if not all(cs[i] < cs[i + 1] for i in range(3)):
        raise ValueError(f"corners {cs} must be 4 distinct increasing vertex indices")
    return cs  # type: ignore[return-value]
