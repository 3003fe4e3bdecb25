"""Polygon checks shared by the SC maps and the mapping-region selection: one place that says what a valid
polygon is (at least 4 distinct finite vertices, simple, counter-clockwise, no zero or full turn)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.scm._polygon import polygon_defect

#: the words for each defect code of :func:`transfer.scm._polygon.polygon_defect`
_DEFECTS = {
    1: "vertices contain non-finite numbers (NaN or inf)",
    2: "repeated vertices: vertex {i} and vertex {j} coincide",
    3: "self-crossing polygon: edge {i}-{i1} meets edge {j}-{j1}",
    4: "vertices are in clockwise order; give them counter-clockwise",
    5: "degenerate polygon with zero area",
    6: "vertex {i} has a zero or full interior angle (a spike)",
}


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


def turning_exponents(w: NDArray[np.complex128]) -> NDArray[np.float64]:
    """beta_j = interior angle / pi - 1 (= -turn_j / pi) of a counter-clockwise polygon."""
    nxt = np.concatenate((w[1:], w[:1])) - w  # np.roll's result, without its generality's cost (a hot path)
    prev = np.concatenate((nxt[-1:], nxt[:-1]))
    return -np.angle(nxt / prev) / np.pi


def check_polygon(vertices: ArrayLike, *, min_vertices: int = 4) -> NDArray[np.complex128]:
    """Validate a polygon and return its vertices as a complex array; ValueError naming the problem otherwise."""
    w = _vertices(vertices)
    if w.size < min_vertices:
        raise ValueError(f"a polygon needs at least {min_vertices} vertices, got {w.size}")
    code, i, j = polygon_defect(w)
    if code:
        raise ValueError(_DEFECTS[code].format(i=i, j=j, i1=(i + 1) % w.size, j1=(j + 1) % w.size))
    return w


def is_simple_ccw(vertices: ArrayLike) -> bool:
    """True when :func:`check_polygon` accepts the polygon (cheap boolean form for region selection)."""
    try:
        w = _vertices(vertices)
    except (TypeError, ValueError):
        return False
    return w.size >= 4 and polygon_defect(w)[0] == 0


def _vertices(vertices: ArrayLike) -> NDArray[np.complex128]:
    """A polygon's vertices (complex numbers or (N, 2) floats) as a flat complex array."""
    return np.asarray(as_complex(vertices), dtype=np.complex128).ravel()


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
