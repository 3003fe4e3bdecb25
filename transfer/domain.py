"""Command domains: the box of (v, omega) commands a vehicle accepts, and the normalisation onto [0, 1]^2.

Both sides of the transfer are normalised by their own bounds before any geometry is done (Delaunay, SC maps):
v (m/s) and omega (rad/s) have different scales, and the paper draws and clusters in normalised coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


def clamp(a: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> NDArray[np.float64]:
    """``np.clip(a, lo, hi)`` (NaN stays NaN) without numpy's Python-level wrapper, which costs more than the clip on
    the two-element arrays of the per-command path."""
    return np.minimum(np.maximum(a, lo), hi)


@dataclass(frozen=True)
class Bounds:
    """Axis-aligned command box: ``v = (v_min, v_max)`` m/s, ``w = (omega_min, omega_max)`` rad/s."""

    v: tuple[float, float]
    w: tuple[float, float]

    def __post_init__(self) -> None:
        for name, (lo, hi) in (("v", self.v), ("w", self.w)):
            if not (math.isfinite(lo) and math.isfinite(hi)):  # scalars: math, not numpy (a box is made per tick)
                raise ValueError(f"bounds {name}=({lo}, {hi}) must be finite")
            if not lo < hi:
                raise ValueError(f"bounds {name}=({lo}, {hi}) must have min < max")
        object.__setattr__(self, "v", (float(self.v[0]), float(self.v[1])))
        object.__setattr__(self, "w", (float(self.w[0]), float(self.w[1])))
        # built once (every command of every tick reads them), and read-only: a caller cannot change the bounds
        lo, hi = np.array([self.v[0], self.w[0]]), np.array([self.v[1], self.w[1]])
        span = hi - lo
        for name, a in (("_lo", lo), ("_hi", hi), ("_span", span)):
            a.flags.writeable = False
            object.__setattr__(self, name, a)

    @property
    def lo(self) -> NDArray[np.float64]:
        return self._lo  # type: ignore[attr-defined]

    @property
    def hi(self) -> NDArray[np.float64]:
        return self._hi  # type: ignore[attr-defined]

    @property
    def span(self) -> NDArray[np.float64]:
        return self._span  # type: ignore[attr-defined]

    def normalise(self, u: ArrayLike) -> NDArray[np.float64]:
        """(..., 2) commands -> [0, 1]^2 (values outside the box map outside [0, 1])."""
        return (np.asarray(u, dtype=float) - self.lo) / self.span

    def denormalise(self, n: ArrayLike) -> NDArray[np.float64]:
        return self.lo + np.asarray(n, dtype=float) * self.span

    def clip(self, u: ArrayLike) -> NDArray[np.float64]:
        return clamp(np.asarray(u, dtype=float), self.lo, self.hi)  # several commands a tick go through here

    def contains(self, u: ArrayLike, tol: float = 1e-12) -> bool | NDArray[np.bool_]:
        a = np.asarray(u, dtype=float)
        inside = np.all((a >= self.lo - tol * self.span) & (a <= self.hi + tol * self.span), axis=-1)
        return bool(inside) if np.ndim(inside) == 0 else inside

    def corners(self) -> NDArray[np.float64]:
        """The four corners, counter-clockwise from (v_min, omega_min)."""
        (v0, v1), (w0, w1) = self.v, self.w
        return np.array([[v0, w0], [v1, w0], [v1, w1], [v0, w1]])

    def as_list(self) -> list[float]:
        """``[v_min, v_max, omega_min, omega_max]``."""
        return [self.v[0], self.v[1], self.w[0], self.w[1]]

    @staticmethod
    def from_list(x: ArrayLike) -> Bounds:
        a = [float(t) for t in np.asarray(x, dtype=float).ravel()]
        if len(a) != 4:
            raise ValueError(f"bounds need 4 numbers [v_min, v_max, w_min, w_max], got {len(a)}")
        return Bounds((a[0], a[1]), (a[2], a[3]))
