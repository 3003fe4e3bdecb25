"""Motion-primitive planning for the teacher (paper Section 5.1, Eq. differencePrimitivePathPlanning).

A primitive is a fixed teacher command held for ``duration`` seconds; the library is an n x n grid over the
teacher's command range. Transferring the planner to a learner means filtering the library by the learner's
limits on the teacher domain (the hull of the calibration pairs). The planner scores every sequence of
``horizon`` primitives against the desired path by ``k_d * DTW + k_theta * |heading error|`` and returns the best;
the caller replans when the learner strays from the local plan by more than ``epsilon`` (event-triggered), with
``epsilon = eta * min distance to the obstacles in the field of view`` or ``eps_max`` when none is in view.

Vectorised over all candidate sequences (numpy); pure.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from transfer.domain import Bounds
from transfer.teacher.path import Polyline
from transfer.teacher.unicycle import step, wrap_angle


@dataclass(frozen=True)
class Plan:
    """The chosen primitive sequence: its commands, its trajectory (world frame) and its score."""

    commands: NDArray[np.float64]  # (horizon, 2)
    trajectory: NDArray[np.float64]  # (horizon * steps + 1, 3)
    cost: float
    index: tuple[int, ...]


class PrimitiveLibrary:
    """An n x n grid of teacher commands over ``bounds``, each held ``duration`` s (Euler steps of ``dt``)."""

    def __init__(self, bounds: Bounds, n: int = 11, duration: float = 1.0, dt: float = 0.1) -> None:
        g = np.linspace(0.0, 1.0, n)
        V, W = np.meshgrid(g, g, indexing="ij")
        self.commands = bounds.denormalise(np.stack([V.ravel(), W.ravel()], axis=-1))
        self.duration = float(duration)
        self.dt = float(dt)
        self.steps = int(round(duration / dt))

    def __len__(self) -> int:
        return self.commands.shape[0]

    def relative_trajectories(self, idx: NDArray[np.int64] | None = None) -> NDArray[np.float64]:
        """Poses (len, steps + 1, 3) of each primitive started at the origin facing +x (exact Euler rollout)."""
        c = self.commands if idx is None else self.commands[idx]
        out = np.zeros((c.shape[0], self.steps + 1, 3))
        for k in range(self.steps):
            out[:, k + 1] = step(out[:, k], c, self.dt)
        return out


def _compose(start: NDArray[np.float64], rel: NDArray[np.float64]) -> NDArray[np.float64]:
    """Place relative poses (..., 3) after the pose ``start`` (..., 3)."""
    c, s = np.cos(start[..., 2]), np.sin(start[..., 2])
    x = start[..., 0, None] + c[..., None] * rel[..., 0] - s[..., None] * rel[..., 1]
    y = start[..., 1, None] + s[..., None] * rel[..., 0] + c[..., None] * rel[..., 1]
    return np.stack([x, y, start[..., 2, None] + rel[..., 2]], axis=-1)


def dtw(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Dynamic-time-warping distance between point sequences a (C, n, 2) and b (m, 2), for all C at once."""
    C, n = a.shape[0], a.shape[1]
    m = b.shape[0]
    d = np.hypot(a[:, :, None, 0] - b[None, None, :, 0], a[:, :, None, 1] - b[None, None, :, 1])
    D = np.full((C, n + 1, m + 1), np.inf)
    D[:, 0, 0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            D[:, i, j] = d[:, i - 1, j - 1] + np.minimum(np.minimum(D[:, i - 1, j], D[:, i, j - 1]), D[:, i - 1, j - 1])
    return D[:, n, m]


class PrimitivePlanner:
    """Scores every sequence of ``horizon`` allowed primitives against the path ahead (see module docstring)."""

    def __init__(self, library: PrimitiveLibrary, k_d: float = 1.0, k_theta: float = 2.0, horizon: int = 2,
                 samples: int = 10) -> None:
        self.lib = library
        self.k_d = float(k_d)
        self.k_theta = float(k_theta)
        self.horizon = int(horizon)
        self.samples = int(samples)

    def plan(self, state: NDArray[np.float64], path: Polyline, allowed: NDArray[np.bool_]) -> Plan:
        """The best sequence of allowed primitives from ``state``."""
        idx = np.flatnonzero(allowed)
        if idx.size == 0:
            raise ValueError("no primitive is allowed: the learner's limits exclude the whole library")
        rel = self.lib.relative_trajectories(idx)  # (K, steps + 1, 3)
        seqs = np.array(list(itertools.product(range(idx.size), repeat=self.horizon)))  # (C, horizon)
        # chain the primitives: each starts where the previous ended
        traj = [_compose(np.repeat(state[None], len(seqs), axis=0), rel[seqs[:, 0]])]
        for h in range(1, self.horizon):
            traj.append(_compose(traj[-1][:, -1], rel[seqs[:, h]])[:, 1:])
        full = np.concatenate(traj, axis=1)  # (C, horizon * steps + 1, 3)
        # the desired path ahead, as long as the fastest allowed sequence can go
        s0, _ = path.project(state[:2])
        vmax = float(np.max(np.abs(self.lib.commands[idx, 0])))
        reach = max(vmax * self.lib.duration * self.horizon, 1e-3)
        ahead = path.at(s0 + np.linspace(0.0, reach, self.samples + 1)[1:])
        pick = np.linspace(1, full.shape[1] - 1, self.samples).round().astype(int)
        e_d = dtw(full[:, pick, :2], ahead[:, :2])
        # heading error at the end of the sequence against the path heading at the nearest point ahead
        ends = full[:, -1]
        window = path.at(s0 + np.linspace(0.0, 1.5 * reach, 3 * self.samples))
        dd = (ends[:, None, 0] - window[None, :, 0]) ** 2 + (ends[:, None, 1] - window[None, :, 1]) ** 2
        th_p = window[np.argmin(dd, axis=1), 2]
        e_th = np.abs(np.asarray(wrap_angle(th_p - ends[:, 2])))
        cost = self.k_d * e_d + self.k_theta * e_th
        best = int(np.argmin(cost))
        chosen = idx[seqs[best]]
        return Plan(self.lib.commands[chosen], full[best], float(cost[best]), tuple(int(i) for i in chosen))


def replan_threshold(pose: NDArray[np.float64], obstacles: NDArray[np.float64], eta: float = 0.3,
                     eps_max: float = 0.5, fov: float = math.radians(120), view_range: float = 6.0) -> float:
    """The event-triggered replanning threshold: eta * distance to the nearest obstacle in the field of view,
    else eps_max (paper Section 5.1)."""
    if obstacles.size == 0:
        return eps_max
    d = obstacles[:, :2] - pose[:2]
    dist = np.hypot(d[:, 0], d[:, 1]) - obstacles[:, 2]
    bearing = np.abs(np.asarray(wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - pose[2])))
    seen = (bearing <= fov / 2) & (dist <= view_range)
    if not seen.any():
        return eps_max
    return float(min(eps_max, eta * max(float(dist[seen].min()), 0.0)))


class PrimitiveFollower:
    """The paper's execution of primitive plans, one control tick at a time (Section 5.1): plan, send the first
    primitive's command for its duration, replan at its end or as soon as the vehicle strays from the local plan
    by more than the event threshold (:func:`replan_threshold`, plus ``noise_margin`` for pose noise)."""

    def __init__(self, planner: PrimitivePlanner, noise_margin: float = 0.0) -> None:
        self.planner = planner
        self.noise_margin = float(noise_margin)
        self.plan: Plan | None = None
        self.j = 0  # control ticks of the current primitive already sent
        self.replans = self.events = 0

    def reset(self) -> None:
        self.plan, self.j = None, 0

    def step(self, state: NDArray[np.float64], path: Polyline, allowed: NDArray[np.bool_],
             obstacles: NDArray[np.float64]) -> NDArray[np.float64]:
        """The teacher command for this tick (replanning first when the primitive ended or the vehicle strayed)."""
        x = np.asarray(state, dtype=float)
        strayed = False
        if self.plan is not None and self.j < self.planner.lib.steps:
            planned = self.plan.trajectory[min(self.j, len(self.plan.trajectory) - 1), :2]
            strayed = float(np.hypot(*(x[:2] - planned))) > replan_threshold(x, obstacles) + self.noise_margin
            self.events += int(strayed)
        if self.plan is None or self.j >= self.planner.lib.steps or strayed:
            self.plan, self.j = self.planner.plan(x, path, allowed), 0
            self.replans += 1
        self.j += 1
        return self.plan.commands[0].copy()
