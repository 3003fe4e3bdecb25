"""The teacher's MPC (paper Section 5.2, Eq. MPC_OCP), with CasADi.

Unicycle model (Euler, step ``dt``), horizon ``N``, quadratic tracking cost on position and heading, a penalty on
input changes, circular obstacle constraints (softened by a slack per stage), state bounds, input bounds equal to the
*current learned limits* and an input-rate bound. The problem is built once per configuration; the input bounds are
passed at every solve, and the obstacles, the references, the start and the previous input are parameters, so a
change of learned limits never rebuilds it.

Two ways to solve the same problem (``MpcConfig.solver``, docs/ARCHITECTURE.md "The teacher's MPC"):

- ``ipopt``: the full nonlinear program to convergence (IPOPT over the stage-wise NLP); the reference.
- ``rti-qpoases`` / ``rti-daqp``: real-time iteration. Each tick linearises the problem once around the previous
  plan shifted by one step (single shooting over the inputs and one obstacle slack, Gauss-Newton Hessian of
  the least-squares cost, obstacle rows linearised) and solves one dense QP with an active-set solver that keeps its
  working set from tick to tick. A cold start (the first tick, after ``reset``) iterates up to ``rti_cold_iters``
  times. The QP's data come from a CasADi function that a caller may hand to a ``compiler`` (generated C, built once
  and cached by :mod:`bridge.teacher.codegen`); without one it runs in CasADi's virtual machine.

References are sampled along the path from the point closest to the vehicle, spaced by the distance the teacher
covers in one step at the top of its current speed bound, or slower where a bend within the horizon's reach is
sharper than the yaw-rate bound on the bend's side can turn at that speed: a learner whose turn rate is bounded
(learned limits narrower than the teacher's, a dragging wheel that takes a side's turn away) is asked to slow down
for the bend, as a driver does, instead of falling behind references it cannot follow and cutting the bend wide
(``MpcConfig.curve_margin``: the share of the yaw-rate bound the slower speed uses, the rest is left for the
correction; 0, the default, is the paper's MPC, references at the top speed everywhere; the station's
``[teacher] curve_margin``). Why (``sim drift --scenario wheel``): with a wheel dragging part of the
learner's yaw-rate range away, the learned limits follow it, but references at the top speed keep the bends on that
side out of reach (docs/PAPER.md, "Beyond the paper", has the figures). It is not the default because it changes
the paper's experiment: the ideal teacher tracks the path far closer with it, so the paper's ratio to the teacher
is no longer the paper's (docs/PAPER.md). The obstacles the problem's slots hold are the nearest
within the horizon's reach. A learner that cannot turn in place (``MpcConfig.turn_needs_speed``) adds the learned
curvatures as two linear rows a stage, ``k_lo v <= omega <= k_hi v`` (docs/ARCHITECTURE.md, "The teacher's MPC").
A failed solve never yields garbage: the shifted previous plan is used if there is one
(and the result says ``fallback=True``), else a stop.

Pure: no clocks, no files; the caller times ``solve``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from transfer.domain import Bounds, clamp
from transfer.teacher import _refs
from transfer.teacher.path import Polyline
from transfer.teacher.rti import Compiler, _Rti, _turn_rows
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
    max_obstacles: int = 12  # obstacle slots: the nearest within the horizon's reach are kept
    state_box: tuple[float, float, float, float] = (-50.0, 50.0, -50.0, 50.0)  # x_min, x_max, y_min, y_max
    solver: str = "ipopt"  # one of SOLVERS
    max_iter: int = 60  # IPOPT's iteration cap; the QP solvers' working-set changes are capped at 10x this
    slack_weight: float = 1e5  # penalty on obstacle-constraint violation (m^2), exact for large enough weights
    rti_cold_iters: int = 5  # real-time iteration: QPs on a cold start (no previous plan); 1 per tick after
    #: the references slow down for a bend the yaw-rate bound cannot turn at the top speed (module docstring), leaving
    #: this share of the bound for the correction; 0 (the paper's MPC) keeps them at the top speed everywhere
    curve_margin: float = 0.0
    #: a learner that cannot turn in place (an Ackermann rover): the inputs also obey ``k_lo v <= omega <= k_hi v``,
    #: the learned curvatures given to :meth:`MpcTeacher.solve` (two linear rows a stage; without it the problem has
    #: none of them, and costs what it did)
    turn_needs_speed: bool = False

    def __post_init__(self) -> None:
        if self.solver not in SOLVERS:
            raise ValueError(f"unknown MPC solver {self.solver!r}; known: {', '.join(SOLVERS)}")
        if self.N < 2 or self.max_obstacles < 0 or self.dt <= 0 or self.rti_cold_iters < 1:
            raise ValueError(f"MPC needs N >= 2, dt > 0, max_obstacles >= 0, rti_cold_iters >= 1: {self}")
        if not 0.0 <= self.curve_margin <= 1.0:
            raise ValueError(f"MPC curve_margin must be in [0, 1] (0: references at the top speed), got {self}")


#: a curvature this large (rad/m) bounds nothing a teacher's range allows: an unknown side (infinite) is given as it
CURVATURE_FREE = 1e3

#: an obstacle list with none in it (rows x, y, radius)
_NO_OBSTACLES = np.zeros((0, 3))

#: the ways to solve the MPC (module docstring); "ipopt" is the reference
SOLVERS = ("ipopt", "rti-qpoases", "rti-daqp")



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
    kappa = ca.SX.sym("kappa", 2 if cfg.turn_needs_speed else 0)  # the learned curvatures (k_lo, k_hi), rad/m
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
            if cfg.turn_needs_speed:  # omega - k_hi v <= 0 <= omega - k_lo v
                rows.add(ca.vertcat(*_turn_rows(U[:, k], kappa)), [-ca.inf, 0.0], [0.0, ca.inf])
            xn = ca.vertcat(*euler(X[0, k], X[1, k], X[2, k], U[0, k], U[1, k], cfg.dt, ca.cos, ca.sin))
            rows.add(X[:, k + 1] - xn, [0.0] * 3, [0.0] * 3)
    p = ca.vertcat(x0, ca.vec(refs), u_prev, ca.vec(obs), kappa)
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


def _ipopt(cfg: MpcConfig, nlp: dict):
    opts = {"print_time": False, "ipopt": {"print_level": 0, "max_iter": cfg.max_iter, "tol": 1e-6,
            "acceptable_tol": 1e-4, "warm_start_init_point": "yes", "sb": "yes", "mu_strategy": "adaptive",
            "warm_start_bound_push": 1e-6, "warm_start_mult_bound_push": 1e-6, "mu_init": 1e-3}}
    return ca.nlpsol("mpc", "ipopt", nlp, opts)


def _copy(a: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
    return None if a is None else a.copy()


class _Ipopt:
    """The reference: the stage-wise NLP solved to convergence, warm-started with the previous primal-dual point."""

    def __init__(self, cfg: MpcConfig) -> None:
        nlp, rows = _build_nlp(cfg)
        self.cfg, self.solver = cfg, _ipopt(cfg, nlp)
        self.nx = 3 * (cfg.N + 1) + 2 * cfg.N + cfg.N
        self.lbg, self.ubg = np.array(rows.lb), np.array(rows.ub)
        self.ix, self.iu, self.islack = _layout(cfg.N)
        self.lam_g: NDArray[np.float64] | None = None

    def reset(self) -> None:
        self.lam_g = None

    def warm_start(self) -> NDArray[np.float64] | None:
        """The multipliers the next solve starts from (None: from none)."""
        return _copy(self.lam_g)

    def set_warm_start(self, lam_g: NDArray[np.float64] | None) -> None:
        self.lam_g = _copy(lam_g)

    def solve(self, p: NDArray[np.float64], state: NDArray[np.float64], U0: NDArray[np.float64], limits: Bounds,
              cold: bool, slots: int | None = None) -> tuple[bool, str, int, NDArray[np.float64], NDArray[np.float64]]:
        """The NLP from ``U0`` (``slots``, the obstacle slots in use, is the real-time iteration's concern: every
        slot's rows are in the NLP)."""
        cfg = self.cfg
        X0 = np.zeros((cfg.N + 1, 3))
        X0[0] = state
        for k in range(cfg.N):
            X0[k + 1] = step(X0[k], U0[k], cfg.dt)
        lbx, ubx = np.full(self.nx, -np.inf), np.full(self.nx, np.inf)
        xb = cfg.state_box
        lbx[self.ix[:, 0]], ubx[self.ix[:, 0]] = xb[0], xb[1]
        lbx[self.ix[:, 1]], ubx[self.ix[:, 1]] = xb[2], xb[3]
        lbx[self.iu[:, 0]], ubx[self.iu[:, 0]] = limits.v
        lbx[self.iu[:, 1]], ubx[self.iu[:, 1]] = limits.w
        lbx[self.islack] = 0.0
        x_init = np.zeros(self.nx)
        x_init[self.ix], x_init[self.iu] = X0, U0
        args = {"x0": x_init, "p": p, "lbx": lbx, "ubx": ubx, "lbg": self.lbg, "ubg": self.ubg}
        if self.lam_g is not None and not cold:
            args["lam_g0"] = self.lam_g
        try:
            sol = self.solver(**args)
        except RuntimeError as exc:  # CasADi raises on solver errors
            return False, f"error: {exc}", 0, U0, X0
        stats = self.solver.stats()
        xopt = np.asarray(sol["x"]).ravel()
        ok = bool(stats.get("success", False)) and bool(np.all(np.isfinite(xopt)))
        if ok:
            self.lam_g = np.asarray(sol["lam_g"]).ravel()
        return ok, str(stats.get("return_status", "")), int(stats.get("iter_count", 0)), xopt[self.iu], xopt[self.ix]


class MpcTeacher:
    """Step-wise MPC: ``solve(state, path, limits)`` each control tick (see the module docstring). ``compiler``
    (real-time iteration only) builds the QP's data function into generated code once."""

    def __init__(self, config: MpcConfig | None = None, compiler: Compiler | None = None) -> None:
        self.cfg = cfg = config or MpcConfig()
        self._backend: _Ipopt | _Rti = _Ipopt(cfg) if cfg.solver == "ipopt" else _Rti(cfg, compiler)
        # the compiled loops a solve calls loaded (or compiled, once per machine) now, not in the first tick
        _refs.warm(curve=cfg.curve_margin > 0.0)
        #: the path's segment closest to the last solve's state: where the next solve's search for it starts
        #: (:func:`transfer.teacher._refs.closest_near`: the same point, found in a few microseconds)
        self._near = 0
        self._prev_pred: NDArray[np.float64] | None = None
        self._prev_u: NDArray[np.float64] | None = None
        self.u_last = np.zeros(2)
        # the parameter vector p = [x0, refs, u_prev, obstacles, curvatures if turn_needs_speed] (the layout of
        # _build_nlp), refilled each solve
        N, K = cfg.N, cfg.max_obstacles
        nk = 2 if cfg.turn_needs_speed else 0
        self._p = np.empty(3 + 3 * (N + 1) + 2 + 3 * K + nk)
        self._p_refs = self._p[3: 3 + 3 * (N + 1)].reshape(N + 1, 3)
        self._p_uprev = self._p[3 + 3 * (N + 1): 5 + 3 * (N + 1)]
        self._p_obs = self._p[5 + 3 * (N + 1): 5 + 3 * (N + 1) + 3 * K].reshape(K, 3)  # a row per slot: x, y, radius
        self._p_kappa = self._p[5 + 3 * (N + 1) + 3 * K:]  # the curvatures (turn_needs_speed)

    @property
    def compiled(self) -> bool:
        """Whether the solve runs generated, compiled code (real-time iteration with a working compiler)."""
        return isinstance(self._backend, _Rti) and self._backend.compiled

    def kernels(self) -> list[ca.Function]:
        """The functions a compiler may turn into compiled code (empty for IPOPT): hand the result to
        :meth:`use_compiled`, e.g. from a build in the background."""
        return list(self._backend.functions) if isinstance(self._backend, _Rti) else []

    def use_compiled(self, functions: Sequence[ca.Function]) -> None:
        """Solve with compiled equivalents of :meth:`kernels` from now on (call between two solves)."""
        if not isinstance(self._backend, _Rti):
            raise ValueError("only the real-time iteration has kernels to compile")
        self._backend.use(functions)

    def reset(self) -> None:
        self._prev_pred = self._prev_u = None
        self._backend.reset()
        self.u_last = np.zeros(2)

    def warm_start(self) -> tuple:
        """All the next solve starts from (the last plan and its prediction, the last command, the path segment the
        search for the closest point starts at, the NLP's multipliers): :meth:`set_warm_start` with it later, and the
        next solve is the one that would have come now. IPOPT only (the real-time iteration's QP solvers keep working
        sets of their own)."""
        if not isinstance(self._backend, _Ipopt):
            raise ValueError("only IPOPT's warm start can be taken and given back")
        return (self._near, _copy(self._prev_pred), _copy(self._prev_u), self.u_last.copy(),
                self._backend.warm_start())

    def set_warm_start(self, warm: tuple) -> None:
        """Start the next solve from ``warm`` (:meth:`warm_start` of this MPC)."""
        if not isinstance(self._backend, _Ipopt):
            raise ValueError("only IPOPT's warm start can be taken and given back")
        self._near, pred, u, last, lam_g = warm
        self._prev_pred, self._prev_u, self.u_last = _copy(pred), _copy(u), last.copy()
        self._backend.set_warm_start(lam_g)

    def references(self, state: NDArray[np.float64], path: Polyline, v_ref: float) -> NDArray[np.float64]:
        """N + 1 references from the closest path point, spaced by ``v_ref * dt`` (headings unwrapped)."""
        x, y, th = np.asarray(state, dtype=float).tolist()
        return _refs.references(path.points, path.s, path.seg_len, path.heading, x, y, th,
                                float(v_ref * self.cfg.dt), self.cfg.N + 1)

    def obstacles_that_matter(self, state: NDArray[np.float64], obstacles: NDArray[np.float64] | None,
                              limits: Bounds) -> tuple[NDArray[np.float64], int]:
        """The obstacles the NLP's ``max_obstacles`` slots hold: the nearest (by clearance) of those within reach
        of this horizon (the distance the top speed covers in N steps, plus the margin), and how many obstacles
        within reach did not fit (the caller reports them; none is ever dropped silently)."""
        slots = np.empty((self.cfg.max_obstacles, 3))
        kept, dropped = self._nearest(state, obstacles, limits, slots)
        return slots[:kept], dropped

    def _nearest(self, state: NDArray[np.float64], obstacles: NDArray[np.float64] | None, limits: Bounds,
                 slots: NDArray[np.float64]) -> tuple[int, int]:
        """:meth:`obstacles_that_matter` written into ``slots`` (the parameter vector's rows; the unused ones
        marked), in one compiled loop: (how many were kept, how many were dropped)."""
        reach = self.cfg.N * self.cfg.dt * max(abs(limits.v[0]), abs(limits.v[1])) + self.cfg.obstacle_margin
        o = _NO_OBSTACLES if obstacles is None else np.asarray(obstacles, dtype=float).reshape(-1, 3)
        return _refs.nearest_obstacles(np.ascontiguousarray(o), float(state[0]), float(state[1]), reach, slots)

    def solve(
        self,
        state: NDArray[np.float64],
        path: Polyline,
        limits: Bounds,
        obstacles: NDArray[np.float64] | None = None,
        v_ref: float | None = None,
        curvature: tuple[float, float] | None = None,
        slow_for_bends: bool = True,
        closest: tuple[float, int] | None = None,
    ) -> MpcResult:
        """One MPC solve from ``state``; inputs bounded by ``limits`` (the learned limits) and, with
        ``turn_needs_speed``, by ``curvature`` (``(k_lo, k_hi)``, rad/m: ``k_lo v <= omega <= k_hi v``; an infinite
        side or None leaves that side to the box). ``slow_for_bends`` False: the references at the top speed this
        solve, whatever ``curve_margin`` (the caller's learned limits do not need the slowing:
        :meth:`transfer.limits.LearnerLimits.turn_lost`). ``closest``: the path's point closest to ``state`` as
        :func:`transfer.teacher._refs.closest_near` gives it (arc length, segment), where the caller found it
        already for the same state and path (the station, for its off-path verdict): not searched again."""
        cfg = self.cfg
        N = cfg.N
        state = np.asarray(state, dtype=float)
        xs = state.tolist() if state.shape == (3,) else None
        if xs is None or not (math.isfinite(xs[0]) and math.isfinite(xs[1]) and math.isfinite(xs[2])):
            raise ValueError(f"MPC state must be three finite numbers, got {state}")
        # the closest point of the path once for the slowing and the references (each found it again before)
        if closest is not None:
            s0, self._near = closest
        else:
            s0, _, self._near = _refs.closest_near(path.points, path.s, path.seg_len, xs[0], xs[1], self._near)
        if v_ref is not None:
            v = v_ref
        elif cfg.curve_margin > 0.0 and slow_for_bends:
            v_top = limits.v[1]
            v = _refs.curve_speed_from(path.s, path.curvature, s0, v_top,
                                       limits.v[0] if limits.v[0] > 0.0 else 0.25 * v_top, limits.w[0], limits.w[1],
                                       cfg.curve_margin, N * cfg.dt)
        else:
            v = limits.v[1]
        refs = _refs.references_from(path.points, path.s, path.seg_len, path.heading, s0, xs[2], float(v * cfg.dt),
                                     N + 1)  # = self.references(state, path, v)
        # p = [x0, refs, u_prev, obstacles], column-major as _build_nlp lays it out: refs and obstacles by rows
        p = self._p
        p[:3] = state
        self._p_refs[:] = refs
        np.minimum(np.maximum(self.u_last, limits.lo), limits.hi, out=self._p_uprev)
        kept, dropped = self._nearest(state, obstacles, limits, self._p_obs)  # the slots: the nearest within reach
        if cfg.turn_needs_speed:
            k_lo, k_hi = curvature if curvature is not None else (-math.inf, math.inf)
            if not (k_lo <= 0.0 <= k_hi):  # straight ahead stays feasible (NaN fails too)
                raise ValueError(f"MPC curvature must be (k_lo <= 0, k_hi >= 0), got {curvature}")
            self._p_kappa[0], self._p_kappa[1] = max(k_lo, -CURVATURE_FREE), min(k_hi, CURVATURE_FREE)
        cold = self._prev_u is None
        ok, status, iters, U, Xp = self._backend.solve(p, state, self._warm(limits), limits, cold, kept)
        if ok:
            u = clamp(U[0], limits.lo, limits.hi)
            self._prev_u, self._prev_pred = U, Xp
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

    def _warm(self, limits: Bounds) -> NDArray[np.float64]:
        """The inputs to start from: the previous plan's shifted one step, or half the top speed straight ahead."""
        if self._prev_u is not None:
            U = np.empty_like(self._prev_u)
            U[:-1], U[-1] = self._prev_u[1:], self._prev_u[-1]
        else:
            U = np.tile([limits.v[1] * 0.5, 0.0], (self.cfg.N, 1))
        return clamp(U, limits.lo, limits.hi)
