"""Command pairing: the teacher command that reproduces an observed learner motion (paper Eq. commandPairs).

A command pair is ``<u_T_bar, u_L>``: the learner command ``u_L`` applied from ``x_L(t)`` to ``x_L(t + dt)`` and
``u_T_bar = f_T^-1(x_L(t), x_L(t + dt))``, the command under which the teacher (the Euler unicycle of
:mod:`transfer.teacher.unicycle`) would have made the same move.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.teacher.unicycle import wrap_angle


def teacher_equivalent(x0: ArrayLike, x1: ArrayLike, dt: float) -> NDArray[np.float64]:
    """f_T^-1 of one Euler step: the (v, omega) minimising the teacher's one-step pose error to ``x1``.

    The Euler unicycle moves along its *initial* heading, so the heading rate is matched exactly,
    ``omega = wrap(theta1 - theta0) / dt``, and v is the least-squares fit of the displacement onto the heading,
    ``v = <p1 - p0, (cos theta0, sin theta0)> / dt``: a backward move gives a negative v (reversing), a sideways
    drift that no unicycle command reproduces is the least-squares residual. Exact for teacher-generated motion.
    """
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"dt must be a positive finite number, got {dt}")
    if isinstance(x0, np.ndarray) and isinstance(x1, np.ndarray) and x0.shape == x1.shape == (3,):
        return _one_pair(x0.tolist(), x1.tolist(), dt)  # the live pairer's case, once per pair: scalar maths
    a = np.asarray(x0, dtype=float)
    b = np.asarray(x1, dtype=float)
    if a.shape[-1] != 3 or b.shape[-1] != 3:
        raise ValueError("poses must be (..., 3) arrays of (x, y, theta)")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("poses must be finite")
    th = a[..., 2]
    d = b[..., :2] - a[..., :2]
    v = (d[..., 0] * np.cos(th) + d[..., 1] * np.sin(th)) / dt
    w = np.asarray(wrap_angle(b[..., 2] - th)) / dt
    return np.stack([v, w], axis=-1)


def _one_pair(a: list[float], b: list[float], dt: float) -> NDArray[np.float64]:
    """:func:`teacher_equivalent` of two single poses, in scalar arithmetic (the same formulas)."""
    if not all(math.isfinite(c) for c in (*a, *b)):
        raise ValueError("poses must be finite")
    th = a[2]
    v = ((b[0] - a[0]) * math.cos(th) + (b[1] - a[1]) * math.sin(th)) / dt
    w = wrap_angle(b[2] - th) / dt
    return np.array([v, w])


def planned_commands(predicted: ArrayLike, dt: float, k: int = 10) -> NDArray[np.float64]:
    """The teacher's next ``k`` planned commands after the one it sends, from its predicted states ``(N + 1, 3)``
    (an MPC's plan of the teacher's own Euler model: f_T^-1 of consecutive predicted states is exactly its input)."""
    pred = np.asarray(predicted, dtype=float)
    if pred.ndim != 2 or pred.shape[0] < 3 or pred.shape[1] != 3 or not np.all(np.isfinite(pred)):
        return np.zeros((0, 2))
    return teacher_equivalent(pred[:-1], pred[1:], dt)[1:1 + k]
