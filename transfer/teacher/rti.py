"""The teacher's MPC by real-time iteration (``MpcConfig.solver`` ``rti-qpoases`` / ``rti-daqp``; the module
docstring of :mod:`transfer.teacher.mpc` and docs/ARCHITECTURE.md, "The teacher's MPC"): the linearisation and the
rollout as CasADi functions (interpreted, or compiled by a caller's ``compiler``), evaluated in place on numpy
arrays, and one dense QP per tick.

Pure: no clocks, no files.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Protocol

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from transfer.domain import Bounds
from transfer.teacher.unicycle import euler

#: turns CasADi functions into faster equivalents (generated, compiled code) or returns None to keep them as they are
Compiler = Callable[[Sequence[ca.Function]], "Sequence[ca.Function] | None"]


class MpcConfig(Protocol):
    """What the real-time iteration reads of its configuration: a :class:`transfer.teacher.mpc.MpcConfig` (which
    imports this module)."""

    N: int
    dt: float
    q_pos: float
    q_heading: float
    q_terminal: float
    r_u: float
    r_du: float
    du_max: tuple[float, float]
    obstacle_margin: float
    max_obstacles: int
    state_box: tuple[float, float, float, float]
    solver: str
    max_iter: int
    slack_weight: float
    rti_cold_iters: int
    turn_needs_speed: bool


def _turn_rows(u, kappa) -> tuple:
    """A learner that cannot turn in place: the rows ``omega - k_hi v`` (<= 0) and ``omega - k_lo v`` (>= 0) of one
    stage's input ``u``, each scaled to a unit normal (a side not learned yet has a slope of
    :data:`transfer.teacher.mpc.CURVATURE_FREE`: its row stays well conditioned, and inactive)."""
    return tuple((u[1] - kappa[i] * u[0]) / ca.sqrt(1.0 + kappa[i] ** 2) for i in (1, 0))


def _build_rti(cfg: MpcConfig) -> tuple[ca.Function, ...]:
    """The real-time iteration's functions (:func:`_rti_problem`): a linearisation per QP size, then the rollout."""
    return _rti_problem(cfg)[0]


@functools.lru_cache(maxsize=8)
def _rti_problem(cfg: MpcConfig) -> tuple[tuple[ca.Function, ...], NDArray[np.float64]]:
    """The real-time iteration's two functions over z = [u_0 .. u_{N-1}, s] (single shooting) and the parameters p
    of :func:`transfer.teacher.mpc._build_nlp` (built once per configuration and shared by every MPC of a process).
    One slack s softens every obstacle row (it is the largest violation; IPOPT's problem has one per stage): with
    the same exact penalty both problems have the same solution wherever the obstacles can be avoided, and a third
    fewer QP variables make the QP about twice as fast.

    - ``mpc_rti_lin<k>(z, p) -> (sqrt(2) Jr, g, Jc, lba, uba)``, one for each QP's number k of obstacle slots
      (:func:`slot_sizes`), over its rows only: the QP's data at z but its Hessian: the Jacobian of the
      cost's tracking residuals r (cost = |r|^2 + the slack penalty; the heading term 1 - cos e is 2 sin^2(e/2))
      scaled so that their Gauss-Newton Hessian is its square, the QP's gradient g, the Jacobian Jc of the rows c (input
      rates, state box, curvatures if any, then the obstacles slot by slot) and the bounds of the linearised rows,
      lo - c + Jc z <= Jc z' <= hi - c + Jc z (an unused obstacle slot, radius <= 0, gets lo = -inf); dense.
    - ``mpc_rti_roll(z, p) -> X``: the (N + 1) x 3 states the inputs of z give from the start.

    And the Hessian's fixed part: the input and input-rate residuals are linear in z, so their part of the
    Gauss-Newton Hessian (and the slack penalty's) is the same at every z; ``sqrt(2) Jr`` holds only the tracking
    residuals' rows, whose part changes. :class:`_Rti` forms the QP from them: the Hessian as one BLAS product of
    those rows plus the fixed part, the rest as the function gives it, in place.
    """
    N, K = cfg.N, cfg.max_obstacles
    U, S = ca.SX.sym("U", 2, N), ca.SX.sym("S")
    x0, refs, u_prev = ca.SX.sym("x0", 3), ca.SX.sym("refs", 3, N + 1), ca.SX.sym("u_prev", 2)
    obs = ca.SX.sym("obs", 3, K)
    kappa = ca.SX.sym("kappa", 2 if cfg.turn_needs_speed else 0)
    z = ca.vertcat(ca.vec(U), S)
    p = ca.vertcat(x0, ca.vec(refs), u_prev, ca.vec(obs), kappa)
    X = [x0]
    for k in range(N):
        X.append(ca.vertcat(*euler(X[-1][0], X[-1][1], X[-1][2], U[0, k], U[1, k], cfg.dt, ca.cos, ca.sin)))
    res, rate = [], []
    for k in range(1, N + 1):
        q = math.sqrt(cfg.q_terminal if k == N else cfg.q_pos)
        res += [q * (X[k][0] - refs[0, k]), q * (X[k][1] - refs[1, k]),
                math.sqrt(2 * cfg.q_heading) * ca.sin((X[k][2] - refs[2, k]) / 2)]
    for k in range(N):
        du = U[:, k] - (u_prev if k == 0 else U[:, k - 1])
        res += [math.sqrt(cfg.r_u) * U[0, k], math.sqrt(cfg.r_u) * U[1, k],
                math.sqrt(cfg.r_du) * du[0], math.sqrt(cfg.r_du) * du[1]]
        rate += [du[0], du[1]]
    r = ca.vertcat(*res)
    # the obstacle rows last and slot by slot (slot j's N stages together): the rows of the first k slots are the
    # first rows of c, and a QP over the slots in use takes only those (_Rti)
    obstacle, obstacle_lo = [], []
    for j in range(K):
        rr = obs[2, j] + cfg.obstacle_margin
        for k in range(1, N + 1):
            obstacle.append((X[k][0] - obs[0, j]) ** 2 + (X[k][1] - obs[1, j]) ** 2 + S)
            obstacle_lo.append(ca.if_else(obs[2, j] > 0, rr**2, -ca.inf))
    box = [c for k in range(1, N + 1) for c in (X[k][0], X[k][1])]
    # a learner that cannot turn in place: omega - k_hi v <= 0 <= omega - k_lo v at every stage
    turn = [c for k in range(N) for c in _turn_rows(U[:, k], kappa)] if cfg.turn_needs_speed else []
    c = ca.vertcat(*rate, *box, *turn, *obstacle)
    dmax = np.tile(np.asarray(cfg.du_max, dtype=float), N)
    xb = cfg.state_box
    lo = ca.vertcat(ca.DM(-dmax), ca.DM(np.tile([xb[0], xb[2]], N)), ca.DM(np.tile([-np.inf, 0.0], N if turn else 0)),
                    *obstacle_lo)
    hi = ca.vertcat(ca.DM(dmax), ca.DM(np.tile([xb[1], xb[3]], N)), ca.DM(np.tile([0.0, np.inf], N if turn else 0)),
                    ca.inf * ca.DM.ones(K * N))
    # the QP's data at z, all but the Hessian (one BLAS product of the scaled Jacobian, in numpy):
    # cost |r|^2 + w s + w s^2 ~ 1/2 z'Hz + g'z with H = 2 Jr'Jr (Gauss-Newton) + 2w e e', g = 2 Jr'(r - Jr z) + w e
    # (e: the slack's unit vector); rows c(z') ~ c(z) + Jc (z' - z), so lo <= c <= hi bound Jc z' by lo - c + Jc z
    jr = ca.jacobian(r, z)
    e = ca.DM.zeros(2 * N + 1)
    e[2 * N] = cfg.slack_weight
    # by forward and reverse sweeps (jtimes), not as products of the Jacobians: far less generated code
    g = 2.0 * ca.jtimes(r, z, r - ca.jtimes(r, z, z), True) + e
    track = 3 * N  # the tracking residuals come first; the input and input-rate ones, linear in z, after them
    jr2 = math.sqrt(2.0) * ca.densify(jr[:track, :])
    fixed_rows = c.numel() - K * N
    lins = []
    for k in slot_sizes(K):  # a linearisation per QP, of its rows only: the generated code of fewer slots is smaller
        n = fixed_rows + k * N
        ck = c[:n]
        jcz = ca.jtimes(ck, z, z) - ck
        out = [jr2, g, ca.densify(ca.jacobian(ck, z)), lo[:n] + jcz, hi[:n] + jcz]
        lins.append(ca.Function(f"mpc_rti_lin{k}", [z, p], out, ["z", "p"], ["jr2", "g", "jc", "lba", "uba"]))
    roll = ca.Function("mpc_rti_roll", [z, p], [ca.horzcat(*X).T], ["z", "p"], ["x"])
    fixed = ca.Function("mpc_rti_fixed", [z, p], [ca.densify(jr[track:, :])])
    j_in = np.asarray(fixed(np.zeros(z.numel()), np.zeros(p.numel())))  # constant: the same at any z and p
    h_fixed = 2.0 * j_in.T @ j_in
    h_fixed[-1, -1] += 2.0 * cfg.slack_weight
    return (*lins, roll), h_fixed


class _Buffered:
    """A CasADi function evaluated in place on numpy arrays (``Function.buffer``): no conversion per call, which
    costs more than the evaluation itself for matrices of this size."""

    def __init__(self, fn: ca.Function) -> None:
        self.fn = fn
        self.args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self.res = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        self._buf, self._eval = fn.buffer()
        for i, a in enumerate(self.args):
            self._buf.set_arg(i, memoryview(a))
        for i, a in enumerate(self.res):
            self._buf.set_res(i, memoryview(a))

    def rebind(self, i: int, array: NDArray[np.float64]) -> None:
        """Make input ``i`` read ``array`` (another buffer's array: no copy between the two)."""
        if array.size != self.args[i].size:
            raise ValueError(f"input {i} of {self.fn.name()} holds {self.args[i].size} numbers, not {array.size}")
        self.args[i] = array
        self._buf.set_arg(i, memoryview(array))

    def __call__(self) -> None:
        self._eval()

    def stats(self) -> dict:
        """The solver's statistics of the last evaluation (``success``, ``return_status``, ...)."""
        return self._buf.stats()

    def ret(self) -> int:
        """The last evaluation's return flag: 0 when it succeeded. For qpOASES it is non-zero exactly when its
        statistics say ``success`` false (a QP not solved, the working-set changes used up); reading it costs far
        less than :meth:`stats`, which builds a dictionary of the solver's statistics each call."""
        return self._buf.ret()


#: the obstacle slots a QP may hold: the QP of a tick holds the fewest of these that fit the slots in use (up to
#: the configuration's ``max_obstacles``, always one of them). Each is a solver of its own, made with the MPC (about
#: 0.15-0.3 MB each), and a linearisation of its own: few sizes, for the common cases (no obstacle within the
#: horizon's reach, or one or two)
SLOT_SIZES = (0, 2)


def slot_sizes(max_obstacles: int) -> tuple[int, ...]:
    """The obstacle slots of each QP of an MPC with ``max_obstacles`` slots (:data:`SLOT_SIZES`), fewest first."""
    return tuple(sorted({k for k in SLOT_SIZES if k < max_obstacles} | {max_obstacles}))


class _Qp:
    """One dense QP solver over the first ``rows`` rows of the linearisation (the fixed rows and the first slots'
    obstacle rows), its data written in place into its input arrays (CasADi's dense matrices are column-major:
    the numpy views are transposes of the flat buffers). Each keeps its own working set from solve to solve."""

    def __init__(self, plugin: str, opts: dict, nz: int, rows: int) -> None:
        self.rows = rows
        self.fn = ca.conic(f"mpc_rti_{rows}", plugin,
                           {"h": ca.Sparsity.dense(nz, nz), "a": ca.Sparsity.dense(rows, nz)}, opts)
        self.buf = _Buffered(self.fn)
        arg = {name: self.buf.args[self.fn.index_in(name)] for name in ("h", "lbx", "ubx")}
        self.H = arg["h"].reshape(nz, nz)  # symmetric: its layout does not matter
        self.lbx, self.ubx = arg["lbx"], arg["ubx"]
        self.x = self.buf.res[0]
        self.lin: _Buffered | None = None  # the linearisation of these rows (bind)
        self.JrT = np.zeros((nz, 0))
        self.bounds_of: tuple | None = None

    def bind(self, lin: ca.Function, z: NDArray[np.float64], p: NDArray[np.float64]) -> None:
        """Linearise with ``lin`` (this QP's rows) at the start ``z`` for the parameters ``p``, and read A, the
        gradient and the rows' bounds straight from its outputs (no copy)."""
        self.lin = _Buffered(lin)
        self.lin.rebind(0, z)
        self.lin.rebind(1, p)
        self.JrT = self.lin.res[0].reshape(z.size, lin.size1_out(0))  # sqrt(2) Jr transposed: BLAS reads it as it is
        self.buf.rebind(self.fn.index_in("x0"), z)
        for name, i in (("g", 1), ("a", 2), ("lba", 3), ("uba", 4)):
            self.buf.rebind(self.fn.index_in(name), self.lin.res[i])


class _Rti:
    """Real-time iteration (module docstring): one QP per tick on the problem linearised at the shifted plan. The
    QP holds the fixed rows and the obstacle rows of the slots in use only (the fewest :data:`SLOT_SIZES` that fit
    them): an unused slot's rows are never active (-inf <= row), so the solution is the same, and a QP without
    them costs the active-set solver far less (most ticks have no obstacle or one within the horizon's reach)."""

    def __init__(self, cfg: MpcConfig, compiler: Compiler | None) -> None:
        N, K = cfg.N, cfg.max_obstacles
        self.cfg, self.nz = cfg, 2 * N + 1
        functions, self.h_fixed = _rti_problem(cfg)
        self.functions = list(functions)
        compiled = compiler(self.functions) if compiler is not None else None
        self.compiled = compiled is not None
        plugin = cfg.solver.split("-", 1)[1]
        opts: dict = {"error_on_fail": False}
        if plugin == "qpoases":
            opts.update({"printLevel": "none", "sparse": False, "nWSR": 10 * cfg.max_iter})
        elif plugin == "daqp":
            opts.update({"daqp": {"iter_limit": 10 * cfg.max_iter}})
        self.sizes = slot_sizes(K)
        self.qps = {k: _Qp(plugin, opts, self.nz, lin.size1_out(2)) for k, lin in zip(self.sizes, self.functions)}
        self.z, self.p = np.zeros(self.nz), np.zeros(self.functions[0].nnz_in(1))  # every linearisation's inputs
        #: success read from the return flag (qpOASES sets it; DAQP's plugin returns 0 on a failure too, so its
        #: statistics are read instead)
        self._flag_says = plugin == "qpoases"
        self._bind(compiled or self.functions)
        self._step = np.empty(self.nz)  # scratch: the step of each QP

    def _bind(self, functions: Sequence[ca.Function]) -> None:
        """Evaluate the linearisations and the rollout with ``functions`` (interpreted or compiled: same results);
        each QP reads its linearisation's outputs, the start of each QP is the linearisation point."""
        *lins, roll = functions
        for qp, lin in zip(self.qps.values(), lins):
            qp.bind(lin, self.z, self.p)
        self.roll = _Buffered(roll)
        self.roll.rebind(0, self.z)  # the plan: z holds the last QP's solution when the rollout runs
        self.roll.rebind(1, self.p)

    def use(self, functions: Sequence[ca.Function]) -> None:
        """Switch to compiled equivalents of :attr:`functions` (between two solves)."""
        self._bind(functions)  # the QPs read the new linearisation's buffers
        self.compiled = True

    def reset(self) -> None:
        """Nothing to forget: the solvers' working sets are only starting guesses."""

    def _bounds(self, qp: _Qp, limits: Bounds) -> None:
        key = (limits.v, limits.w)
        if key != qp.bounds_of:  # the learned limits moved (often while the store fills)
            N = self.cfg.N
            qp.lbx[: 2 * N].reshape(N, 2)[:] = limits.lo  # = np.tile(limits.lo, N), in place
            qp.ubx[: 2 * N].reshape(N, 2)[:] = limits.hi
            qp.lbx[2 * N:], qp.ubx[2 * N:] = 0.0, np.inf
            qp.bounds_of = key

    def solve(self, p: NDArray[np.float64], state: NDArray[np.float64], U0: NDArray[np.float64], limits: Bounds,
              cold: bool, slots: int | None = None) -> tuple[bool, str, int, NDArray[np.float64], NDArray[np.float64]]:
        """One real-time iteration (``rti_cold_iters`` QPs on a cold start) from the inputs ``U0``; ``slots``: how
        many obstacle slots of ``p`` are in use (the first ones; None: all of them)."""
        N, z = self.cfg.N, self.z
        need = self.cfg.max_obstacles if slots is None else slots
        qp = self.qps[next(k for k in self.sizes if k >= need)]
        x, H, lin = qp.x, qp.H, qp.lin
        assert lin is not None
        self._bounds(qp, limits)
        self.p[:] = p
        z[: 2 * N] = U0.ravel()
        z[2 * N] = 0.0
        np.minimum(np.maximum(z, qp.lbx, out=z), qp.ubx, out=z)  # = np.clip, without its wrapper
        status, iters = "", 0
        for _ in range(self.cfg.rti_cold_iters if cold else 1):
            lin()
            # the QP's Hessian: 2 Jr'Jr of the tracking rows (Gauss-Newton) + the fixed part (the inputs' rows, the
            # slack's penalty); the rest is the function's output
            np.dot(qp.JrT, qp.JrT.T, out=H)
            H += self.h_fixed
            try:
                qp.buf()
            except RuntimeError as exc:  # CasADi refuses an ill-posed QP (bounds crossed by a bad linearisation)
                return False, f"QP: {str(exc).splitlines()[-1][:120]}", iters, U0, np.zeros((N + 1, 3))
            iters += 1
            solved = qp.buf.ret() == 0 if self._flag_says else bool(qp.buf.stats().get("success", False))
            if solved:
                d = np.subtract(x, z, out=self._step)
                moved = float(np.abs(d, out=d).max())  # not finite exactly when x is not (z is finite)
            if not solved or not math.isfinite(moved):
                why = qp.buf.stats().get("return_status", "failed") if not solved else "not finite"
                return False, f"QP: {why}", iters, U0, np.zeros((N + 1, 3))
            z[:] = x
            if moved < 1e-5:
                break
        status = f"rti cold ({iters} QPs)" if cold else "rti"
        self.roll()
        return True, status, iters, z[: 2 * N].reshape(N, 2).copy(), self.roll.res[0].reshape(3, N + 1).T.copy()
