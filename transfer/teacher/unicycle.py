"""The teacher's model: the paper's Euler-discretised unicycle (Eq. motion_primitives_dynamicmodel).

State ``(x, y, theta)``, command ``(v, omega)``: x_{k+1} = x_k + dt * (v cos theta, v sin theta, omega).
Vectorised over leading axes so a batch of poses or commands steps at once.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray


def wrap_angle(a: ArrayLike) -> NDArray[np.float64] | float:
    """Angle(s) wrapped to [-pi, pi)."""
    if type(a) is float:  # one angle (the live pairer's, once per pair): the same arithmetic without numpy's calls
        return (a + math.pi) % (2.0 * math.pi) - math.pi
    out = (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi
    return float(out) if out.ndim == 0 else out


def euler(x: Any, y: Any, th: Any, v: Any, w: Any, dt: Any, cos: Callable = np.cos, sin: Callable = np.sin
          ) -> tuple[Any, Any, Any]:
    """The one Euler step of the unicycle, on anything with arithmetic: floats, numpy arrays, CasADi symbols
    (pass ``ca.cos``/``ca.sin``). Every model in the project (teacher, learner, MPC, emulated vehicle) steps here."""
    return x + dt * v * cos(th), y + dt * v * sin(th), th + dt * w


def step(state: ArrayLike, u: ArrayLike, dt: float) -> NDArray[np.float64]:
    """One Euler step of the unicycle; ``state[..., 3]``, ``u[..., 2]`` broadcast against each other."""
    s = np.asarray(state, dtype=float)
    c = np.asarray(u, dtype=float)
    return np.stack(euler(s[..., 0], s[..., 1], s[..., 2], c[..., 0], c[..., 1], dt), axis=-1)


def rollout(state: ArrayLike, u: ArrayLike, dt: float, steps: int) -> NDArray[np.float64]:
    """Hold command ``u`` for ``steps`` Euler steps from ``state``; returns ``(steps + 1, ..., 3)`` poses."""
    s = np.asarray(state, dtype=float)
    out = [s]
    for _ in range(int(steps)):
        s = step(s, u, dt)
        out.append(s)
    return np.stack(out, axis=0)
