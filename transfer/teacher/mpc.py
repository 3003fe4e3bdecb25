"""The teacher's MPC (paper Section 5.2, Eq. MPC_OCP), with CasADi.

Unicycle model (Euler, step ``dt``), horizon ``N``, quadratic tracking cost on position and heading, a penalty on
input changes, circular obstacle constraints, state bounds, input bounds equal to the *current learned limits* and
an input-rate bound. The NLP is built once per (N, number of obstacle slots); the input bounds are variable bounds
passed at every solve (``lbx``/``ubx``), and the obstacles, the references, the start and the previous input are
parameters, so a change of learned limits never rebuilds the problem.

References are sampled along the path from the point closest to the vehicle, spaced by the distance the teacher
covers in one step at the top of its current speed bound. The solver is warm-started from the previous solution
shifted by one step. A failed solve never yields garbage: the shifted previous plan is used if there is one (and
the result says ``fallback=True``), else a stop.

Pure: no clocks; the caller times ``solve``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from transfer.domain import Bounds
from transfer.teacher.path import Polyline
from transfer.teacher.unicycle import euler, step


@dataclass(frozen=True)
class MpcConfig:
    """Weights and limits of the MPC (defaults tuned for the paper's MPC case: v <= 0.6 m/s, |omega| <= pi/4)."""

    N: int = 20
    dt: float = 0.1
    q_pos: float = 10.0
    q_heading: float = 0.5
    q_terminal: float = 20.0
    r_u: float = 0.05
    r_du: float = 1.0
    du_max: tuple[float, float] = (0.3, 1.2)  # max change of (v, omega) per step
    obstacle_margin: float = 0.15  # vehicle radius + safety, m
    max_obstacles: int = 6
    state_box: tuple[float, float, float, float] = (-50.0, 50.0, -50.0, 50.0)  # x_min, x_max, y_min, y_max
    solver: str = "ipopt"  # IPOPT (mumps); fatrop needs a different constraint order, not wired up
    max_iter: int = 60
    slack_weight: float = 1e5  # penalty on obstacle-constraint violation (m^2), exact for large enough weights


@dataclass
class MpcResult:
    """The command to apply and what it is based on."""

    u: NDArray[np.float64]
    ok: bool
    status: str
    predicted: NDArray[np.float64]  # (N + 1, 3)
    fallback: bool = False
    solver: str = ""
    iterations: int = 0
    obstacles_dropped: int = 0  # obstacles within the horizon's reach that did not fit the NLP's slots
    refs: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))


class _Rows:
    """Constraint rows g with their bounds, appended stage by stage."""

    def __init__(self) -> None:
        self.g: list = []
        self.lb: list[float] = []
        self.ub: list[float] = []

    def add(self, expr, lo, hi) -> None:
        self.g.append(expr)
        self.lb += list(lo)
        self.ub += list(hi)


def _build_nlp(cfg: MpcConfig) -> tuple[dict, _Rows]:
    """The NLP in stage-wise variable order [x0, u0, x1, s1, u1, ..., xN, sN] (banded KKT systems for the sparse
    solver): tracking cost, input-rate cost and bounds, Euler dynamics, softened obstacle constraints."""
    N, K = cfg.N, cfg.max_obstacles
    X = ca.SX.sym("X", 3, N + 1)
    U = ca.SX.sym("U", 2, N)
    x0 = ca.SX.sym("x0", 3)
    refs = ca.SX.sym("refs", 3, N + 1)
    u_prev = ca.SX.sym("u_prev", 2)
    obs = ca.SX.sym("obs", 3, K)  # x, y, radius (radius <= 0: unused slot)
    w, rows, cost = [], _Rows(), 0
    for k in range(N + 1):
        w.append(X[:, k])
        if k == 0:
            rows.add(X[:, 0] - x0, [0.0] * 3, [0.0] * 3)
        eth = 1 - ca.cos(X[2, k] - refs[2, k])
        qp = cfg.q_terminal if k == N else cfg.q_pos
        cost += qp * ((X[0, k] - refs[0, k]) ** 2 + (X[1, k] - refs[1, k]) ** 2) + cfg.q_heading * eth
        if k >= 1:
            sk = ca.SX.sym(f"s{k}")
            w.append(sk)
            cost += cfg.slack_weight * sk + cfg.slack_weight * sk**2
            _obstacle_rows(rows, cfg, X[:, k], sk, obs)
        if k < N:
            w.append(U[:, k])
            du = U[:, k] - (u_prev if k == 0 else U[:, k - 1])
            cost += cfg.r_u * ca.sumsqr(U[:, k]) + cfg.r_du * ca.sumsqr(du)
            rows.add(du, [-cfg.du_max[0], -cfg.du_max[1]], [cfg.du_max[0], cfg.du_max[1]])
            xn = ca.vertcat(*euler(X[0, k], X[1, k], X[2, k], U[0, k], U[1, k], cfg.dt, ca.cos, ca.sin))
            rows.add(X[:, k + 1] - xn, [0.0] * 3, [0.0] * 3)
    p = ca.vertcat(x0, ca.vec(refs), u_prev, ca.vec(obs))
    return {"x": ca.vertcat(*w), "f": cost, "g": ca.vertcat(*rows.g), "p": p}, rows


def _obstacle_rows(rows: _Rows, cfg: MpcConfig, xk, sk, obs) -> None:
    """Obstacle constraints of one stage, softened by the stage's slack (an exact L1 penalty): a vehicle that
    cannot stop (v_min > 0) must still get the least-bad plan, not an infeasible problem. An unused slot has
    radius <= 0 and its row becomes d2 >= -1 (always true)."""
    for j in range(cfg.max_obstacles):
        d2 = (xk[0] - obs[0, j]) ** 2 + (xk[1] - obs[1, j]) ** 2
        rr = obs[2, j] + cfg.obstacle_margin
        rows.add(d2 + sk - ca.if_else(obs[2, j] > 0, rr**2, -1.0), [0.0], [ca.inf])


def _layout(N: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Indices of every state, input and slack in the stage-wise variable vector."""
    idx_x, idx_u, idx_s, pos = [], [], [], 0
    for k in range(N + 1):
        idx_x.append(np.arange(pos, pos + 3))
        pos += 3
        if k >= 1:
            idx_s.append(pos)
            pos += 1
        if k < N:
            idx_u.append(np.arange(pos, pos + 2))
            pos += 2
    return np.array(idx_x), np.array(idx_u), np.array(idx_s)


def _solver(cfg: MpcConfig, nlp: dict):
    if cfg.solver != "ipopt":
        raise ValueError(f"unknown MPC solver {cfg.solver!r}: only ipopt is wired up")
    opts = {"print_time": False, "ipopt": {"print_level": 0, "max_iter": cfg.max_iter, "tol": 1e-6,
            "acceptable_tol": 1e-4, "warm_start_init_point": "yes", "sb": "yes", "mu_strategy": "adaptive",
            "warm_start_bound_push": 1e-6, "warm_start_mult_bound_push": 1e-6, "mu_init": 1e-3}}
    return ca.nlpsol("mpc", "ipopt", nlp, opts)


class MpcTeacher:
    """Step-wise MPC: ``solve(state, path, limits)`` each control tick (see the module docstring)."""

    def __init__(self, config: MpcConfig | None = None) -> None:
        self.cfg = cfg = config or MpcConfig()
        nlp, rows = _build_nlp(cfg)
        self._solver = _solver(cfg, nlp)
        self._nx = 3 * (cfg.N + 1) + 2 * cfg.N + cfg.N
        self._lbg, self._ubg = np.array(rows.lb), np.array(rows.ub)
        self._ix, self._iu, self._is = _layout(cfg.N)
        self._prev: NDArray[np.float64] | None = None
        self._prev_pred: NDArray[np.float64] | None = None
        self._prev_u: NDArray[np.float64] | None = None
        self._lam_g: NDArray[np.float64] | None = None
        self.u_last = np.zeros(2)

    def reset(self) -> None:
        self._prev = self._prev_pred = self._prev_u = self._lam_g = None
        self.u_last = np.zeros(2)

    def references(self, state: NDArray[np.float64], path: Polyline, v_ref: float) -> NDArray[np.float64]:
        """N + 1 references from the closest path point, spaced by ``v_ref * dt`` (headings unwrapped)."""
        s0, _ = path.project(state[:2])
        ss = s0 + v_ref * self.cfg.dt * np.arange(self.cfg.N + 1)
        r = path.at(ss)
        # unwrap the reference heading next to the vehicle's heading so the cost sees no 2 pi jumps
        rel = np.unwrap(r[:, 2] - state[2])
        r[:, 2] = state[2] + rel - 2 * math.pi * np.round(rel[0] / (2 * math.pi))
        return r

    def obstacles_that_matter(self, state: NDArray[np.float64], obstacles: NDArray[np.float64] | None,
                              limits: Bounds) -> tuple[NDArray[np.float64], int]:
        """The obstacles the NLP's ``max_obstacles`` slots hold: the nearest (by clearance) of those within reach
        of this horizon (the distance the top speed covers in N steps, plus the margin), and how many obstacles
        within reach did not fit (the caller reports them; none is ever dropped silently)."""
        if obstacles is None or len(obstacles) == 0:
            return np.zeros((0, 3)), 0
        o = np.asarray(obstacles, dtype=float).reshape(-1, 3)
        clearance = np.hypot(o[:, 0] - state[0], o[:, 1] - state[1]) - o[:, 2]
        reach = self.cfg.N * self.cfg.dt * max(abs(limits.v[0]), abs(limits.v[1])) + self.cfg.obstacle_margin
        near = np.flatnonzero(clearance <= reach)
        near = near[np.argsort(clearance[near], kind="stable")]
        keep = near[: self.cfg.max_obstacles]
        return o[keep], int(near.size - keep.size)

    def solve(
        self,
        state: NDArray[np.float64],
        path: Polyline,
        limits: Bounds,
        obstacles: NDArray[np.float64] | None = None,
        v_ref: float | None = None,
    ) -> MpcResult:
        """One MPC solve from ``state``; inputs bounded by ``limits`` (the learned limits)."""
        cfg = self.cfg
        N = cfg.N
        state = np.asarray(state, dtype=float)
        if not np.all(np.isfinite(state)):
            raise ValueError(f"MPC state must be finite, got {state}")
        refs = self.references(state, path, limits.v[1] if v_ref is None else v_ref)
        obs = np.zeros((3, cfg.max_obstacles))
        obs[2, :] = -1.0
        o, dropped = self.obstacles_that_matter(state, obstacles, limits)
        obs[:, : o.shape[0]] = o.T
        u_prev = np.clip(self.u_last, limits.lo, limits.hi)
        p = np.concatenate([state, refs.T.ravel(order="F"), u_prev, obs.ravel(order="F")])
        lbx = np.full(self._nx, -np.inf)
        ubx = np.full(self._nx, np.inf)
        xb = cfg.state_box
        lbx[self._ix[:, 0]], ubx[self._ix[:, 0]] = xb[0], xb[1]
        lbx[self._ix[:, 1]], ubx[self._ix[:, 1]] = xb[2], xb[3]
        lbx[self._iu[:, 0]], ubx[self._iu[:, 0]] = limits.v
        lbx[self._iu[:, 1]], ubx[self._iu[:, 1]] = limits.w
        lbx[self._is] = 0.0
        x_init = self._warm(state, refs, limits)
        args = {"x0": x_init, "p": p, "lbx": lbx, "ubx": ubx, "lbg": self._lbg, "ubg": self._ubg}
        if self._lam_g is not None and cfg.solver == "ipopt":
            args["lam_g0"] = self._lam_g
        try:
            sol = self._solver(**args)
            stats = self._solver.stats()
            ok = bool(stats.get("success", False))
            status = str(stats.get("return_status", ""))
            iters = int(stats.get("iter_count", 0))
            xopt = np.asarray(sol["x"]).ravel()
            if not np.all(np.isfinite(xopt)):
                ok = False
        except RuntimeError as exc:  # CasADi raises on solver errors
            ok, status, iters, xopt = False, f"error: {exc}", 0, x_init
        if ok:
            U = xopt[self._iu]
            Xp = xopt[self._ix]
            u = np.clip(U[0], limits.lo, limits.hi)
            self._prev = xopt
            self._prev_u, self._prev_pred = U, Xp
            self._lam_g = np.asarray(sol["lam_g"]).ravel()
            self.u_last = u
            return MpcResult(u, True, status, Xp, False, cfg.solver, iters, dropped, refs)
        # fallback: the previous plan shifted by one step, or a stop
        if self._prev_u is not None and self._prev_u.shape[0] > 1:
            u = np.clip(self._prev_u[1], limits.lo, limits.hi)
            self._prev_u = np.vstack([self._prev_u[1:], self._prev_u[-1:]])
            pred = np.vstack([self._prev_pred[1:], self._prev_pred[-1:]])
            self._prev_pred = pred
            self.u_last = u
            return MpcResult(u, False, status, pred, True, cfg.solver, iters, dropped, refs)
        stop = np.array([max(limits.v[0], 0.0) if limits.v[0] > 0 else 0.0, 0.0])
        stop = np.clip(stop, limits.lo, limits.hi)
        self.u_last = stop
        return MpcResult(stop, False, status, np.repeat(state[None], N + 1, axis=0), True, cfg.solver, iters, dropped,
                         refs)

    def _warm(self, state: NDArray[np.float64], refs: NDArray[np.float64], limits: Bounds) -> NDArray[np.float64]:
        """Initial guess: the previous solution shifted one step, or a rollout along the references."""
        x = np.zeros(self._nx)
        if self._prev_u is not None:
            U = np.vstack([self._prev_u[1:], self._prev_u[-1:]])
        else:
            U = np.tile(np.clip([limits.v[1] * 0.5, 0.0], limits.lo, limits.hi), (self.cfg.N, 1))
        U = np.clip(U, limits.lo, limits.hi)
        X = np.zeros((self.cfg.N + 1, 3))
        X[0] = state
        for k in range(self.cfg.N):
            X[k + 1] = step(X[k], U[k], self.cfg.dt)
        x[self._ix] = X
        x[self._iu] = U
        return x
