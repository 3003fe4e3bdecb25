"""A learner that changes under the transfer: ``scmbridge sim drift --scenario battery|payload|wheel|floor``.

The paper learns a fixed learner. A real robot changes during a run: a battery sags and the top speed drops, a payload
slows its acceleration, a wheel starts to drag and the robot yaws, it drives onto another floor. Each scenario runs the
paper's full-size MPC world laid end to end (:data:`TILES` S-paths, so there is time before and after the change) with
the paper's cubic learner, and changes the learner mid-run:

- ``battery``: from :data:`T_CHANGE` the learner's top speed and its yaw-rate limits fall linearly, by 30 % over 60 s
  (what it really does under a command is capped; the commands it accepts are the same);
- ``payload``: the learner has an acceleration limit (:data:`ACCEL`, :data:`ANG_ACCEL`; the paper's learner has none,
  so this scenario's learner is the paper's with one), halved at :data:`T_CHANGE` at once;
- ``wheel``: from :data:`T_CHANGE` a constant yaw-rate bias of 15 % of the learner's yaw-rate range (a dragging wheel);
- ``floor``: when the robot passes :data:`FLOOR_AT` of the path its response curves change shape (speed: cubic ->
  quadratic; yaw rate: a flatter cubic), as from carpet onto tiles.

Every run is made twice on the same seed: with the store's change detection (:class:`transfer.store.PairStore`,
``adapt=True``, the default) and with the paper's never-forgetting store (``adapt=False``: the ``baseline``). The JSON
summary says, for each: ``dev_before_m`` (mean distance to the path over the 20 s before the change starts),
``dev_after_m`` (from 15 s after the change ends to the end of the run), ``recover_s`` (from the change's end until
the mean deviation over the next 5 s is within 1.2x ``dev_before_m``; null if never), ``reached_goal``, ``collisions``,
``relearned`` (cells the store re-learned) and ``edges_relearned`` (learned limits' edges it learned again, their own
change test: ``transfer/limits.py``). Deviation is measured from the poses of the run, every 0.1 s.
``cmd_err_before`` / ``cmd_err_after`` (same windows) are the transfer's own error: the mean distance between what the
learner did and what the teacher asked, normalised by the teacher's range. The path deviation also holds what the
learner can no longer do at all, and the MPC's feedback hides part of a wrong map on the straights; the command error
shows the map itself.

The teacher's MPC slows down for a bend the learned yaw-rate limit cannot turn at the top speed
(:data:`CURVE_MARGIN`, ``--curve-margin``; the station's ``[teacher] curve_margin``) where the learned limits need it:
once a yaw-rate edge has come inside the widest it held (:meth:`transfer.limits.LearnerLimits.turn_lost`), under
either store. A dragging wheel takes part of
the learner's right turn away: under the paper's MPC (``--curve-margin 0``), whose references keep the top speed, the
S's right bends are driven wide whatever the map and the store (docs/PAPER.md, "Beyond the paper", has the figures).
The MPC is the paper's, solved to convergence by IPOPT, unless ``--solver`` names the real-time iteration a station runs
(``[teacher] mpc_solver``; docs/ARCHITECTURE.md, "The teacher's MPC"); each summary names it (``mpc_solver``).

``--reloaded``: the other case a station meets, a store learned on another day. A first run learns a store from no pairs
on the unchanged learner (the paper's store); the next day's learner has changed meanwhile (the scenario's change, whole
from the start of the run: the battery at its end, the wheel dragging, the new floor, the payload scenario's learner
after its change, whose acceleration is limited where yesterday's was not; ``none``: unchanged) and drives the same
world from that store twice, re-learning its changed cells (a station's default, ``[transfer] adapt``, for a store it
reloads as for one it learns from no pairs) and not (the paper's store). Its summary gives each run's ``dev_m`` and
``dev_last_half_m`` (mean distance to the path over the run and over its second half), ``time_s``, ``reached_goal``,
``collisions`` and ``relearned`` (and ``edges_relearned``).
"""

from __future__ import annotations

import argparse
import copy
import functools
import json
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bridge.core.logsink import print_line
from sim_learner.dynamics import LearnerModel, mpc_learner
from sim_learner.experiments import VEHICLE_RADIUS, parse_seeds, scm_start
from sim_learner.runs import DT, mpc_teacher
from sim_learner.worlds import mpc_world
from transfer.domain import Bounds
from transfer.mission import Mission
from transfer.pairs import teacher_equivalent
from transfer.paper import MPC_TEACHER_V, MPC_TEACHER_W
from transfer.policy import make_policy
from transfer.step import TransferStep
from transfer.store import CHANGE_TOL, PairStore
from transfer.teacher.mpc import SOLVERS, MpcTeacher
from transfer.teacher.unicycle import step as unicycle_step

SCENARIOS = ("battery", "payload", "wheel", "floor")
#: ``none``: the same run with no change (the false-alarm rate: noise or nothing must never re-learn a cell)
CONTROL = "none"
#: S-paths laid end to end: about 150 s of driving, time for 20 s before a change and 45 s after the battery's
TILES = 4
#: when a time-driven change starts, s of the run
T_CHANGE = 40.0
#: the battery's fall: 30 % of the top speed and yaw-rate limits, over this many seconds
BATTERY_FALL, BATTERY_S = 0.3, 60.0
#: the payload learner's acceleration limits before the change (halved by it), m/s^2 and rad/s^2: the paper's learner
#: reaches any command within a tick; with these a step across its whole speed range takes 0.17 s
ACCEL, ANG_ACCEL = 1.5, 3.0
#: the dragging wheel's yaw-rate bias, as a share of the learner's yaw-rate range
WHEEL_BIAS = 0.15
#: where on the path (share of its length) the floor changes
FLOOR_AT = 0.3
#: the windows of the summary, s: before the change, after its end (settling), the recovery's moving mean
BEFORE_S, SETTLE_S, RECOVER_WINDOW_S = 20.0, 15.0, 5.0
#: recovered: the moving mean of the deviation within this factor of the deviation before the change
RECOVER_FACTOR = 1.2
#: the teacher MPC's ``curve_margin`` in these runs (:class:`transfer.teacher.mpc.MpcConfig`): it slows down for a bend
#: the learned yaw-rate limit cannot turn at the top speed. A learner that changed may turn less than it did; the
#: paper's MPC (0) keeps asking for the bend at the top speed, which the changed learner cannot turn (the module
#: docstring). Both stores of a run drive under the same teacher, which slows only once its learned limits lost reach.
CURVE_MARGIN = 0.9
#: the corridor of these runs, m (the station's default ``[station] corridor_m``): a side of the learned limits whose
#: edge is unknown after a change is probed again only inside a share of it (:class:`transfer.step.TransferStep`)
CORRIDOR_M = 1.0


def h_v_floor(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """The new floor's speed response: quadratic (more grip at mid commands than the carpet's cubic)."""
    return v**2


def h_w_floor(w: NDArray[np.float64]) -> NDArray[np.float64]:
    """The new floor's yaw-rate response: a flatter cubic, ``2 (w - 0.5)^3 + 0.5 (w - 0.5) + 0.5`` (still 0 and 1 at
    the ends)."""
    return 2.0 * (w - 0.5) ** 3 + 0.5 * (w - 0.5) + 0.5


def tiled(world: Mission, tiles: int) -> Mission:
    """The mission's path and obstacles laid end to end ``tiles`` times along x (the start stays)."""
    pts = world.path.points
    dx = float(pts[-1][0] - pts[0][0])
    path = np.vstack([pts] + [pts[1:] + np.array([k * dx, 0.0]) for k in range(1, tiles)])
    obs = np.vstack([world.obstacles + np.array([k * dx, 0.0, 0.0]) for k in range(tiles)])
    return Mission(f"{world.name}-x{tiles}", type(world.path)(path), obs, world.goal_tolerance, world.start,
                   world.frame)


@dataclass
class ChangingLearner:
    """The paper's cubic learner, changed by a scenario: ``response(u, t, progress)`` is what it really does under
    command ``u`` at time ``t`` (s of the run) with ``progress`` (share of the path covered). Keeps its own velocity
    for the acceleration limit of the ``payload`` scenario."""

    scenario: str
    changed: bool = False  # changed before the run began (a store reloaded the next day): the change is whole at once
    model: LearnerModel = field(default_factory=mpc_learner)
    vel: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2))
    floor_t: float | None = None  # when the floor changed (the floor scenario's change time)

    def __post_init__(self) -> None:
        if self.scenario not in (*SCENARIOS, CONTROL):
            raise ValueError(f"unknown scenario {self.scenario!r}; known: {', '.join(SCENARIOS)}")
        self.floor = LearnerModel(self.model.v_range, self.model.w_range, h_v_floor, h_w_floor, name="floor")
        if self.changed and self.scenario == "floor":
            self.floor_t = 0.0

    def change(self) -> tuple[float | None, float | None]:
        """(start, end) of the change in s of the run; None for the floor's before the robot got there."""
        if self.changed:
            return None, None
        if self.scenario == "battery":
            return T_CHANGE, T_CHANGE + BATTERY_S
        if self.scenario == "floor":
            return self.floor_t, self.floor_t
        if self.scenario == CONTROL:
            return None, None
        return T_CHANGE, T_CHANGE

    def response(self, u: NDArray[np.float64], t: float, progress: float) -> NDArray[np.float64]:
        m = self.model
        if self.changed:
            t += T_CHANGE + BATTERY_S  # every time-driven change has ended
        if self.scenario == "floor":
            if self.floor_t is None and progress >= FLOOR_AT:
                self.floor_t = t
            out = (self.floor if self.floor_t is not None else m).response(u)
        else:
            out = m.response(u)
        if self.scenario == "battery":
            f = 1.0 - BATTERY_FALL * float(np.clip((t - T_CHANGE) / BATTERY_S, 0.0, 1.0))
            out = np.array([min(out[0], f * m.v_range[1]), np.clip(out[1], f * m.w_range[0], f * m.w_range[1])])
        elif self.scenario == "wheel" and t >= T_CHANGE:
            out = out + np.array([0.0, WHEEL_BIAS * (m.w_range[1] - m.w_range[0])])
        elif self.scenario == "payload":
            k = 0.5 if t >= T_CHANGE else 1.0
            lim = np.array([ACCEL, ANG_ACCEL]) * k * DT
            out = self.vel + np.clip(out - self.vel, -lim, lim)
        self.vel = np.asarray(out, dtype=float)
        return self.vel


@dataclass
class DriftRun:
    """One run: the time of each pose, the poses' distance to the path and progress, and the run's outcome."""

    t: list[float] = field(default_factory=list)
    dev: list[float] = field(default_factory=list)
    progress: list[float] = field(default_factory=list)
    methods: list[str] = field(default_factory=list)
    cmd_err: list[float] = field(default_factory=list)  # |what the learner did - what the teacher asked| (normalised)
    reached: bool = False
    collided: bool = False
    relearned: int = 0
    edges_relearned: int = 0  # learned limits' edges the store learned again (transfer/limits.py)
    time_s: float | None = None
    store: PairStore | None = None  # what the run's store learned


@dataclass
class _Loop:
    """A run's closed loop between two ticks (the MPC's warm start aside): what a copy needs to go on alike."""

    world: Mission
    learner: ChangingLearner
    store: PairStore
    step: TransferStep
    run: DriftRun
    x: NDArray[np.float64]
    prev: NDArray[np.float64] | None = None  # the learner command before this tick's (transfer/limits_watch.py)
    k: int = 0
    ended: bool = False


def _start(scenario: str, seed: int, adapt: bool, tiles: int, change_tol: float, reloaded: PairStore | None,
           spread: bool) -> _Loop:
    world = tiled(mpc_world(), tiles)
    learner = ChangingLearner(scenario, changed=reloaded is not None)
    m = learner.model
    if reloaded is None:
        store = PairStore(Bounds(m.v_range, m.w_range), Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=5, adapt=adapt,
                          change_tol=change_tol)
    else:  # as a station reloads it: its configuration decides whether it adapts
        store = PairStore.from_bytes(reloaded.to_bytes())
        store.set_adapt(adapt)
        store.change.change_tol = change_tol
    store.spreading.set(spread and adapt)
    step = TransferStep(make_policy(store, "scm", np.random.default_rng(seed)), dt=DT)
    return _Loop(world, learner, store, step, DriftRun(), scm_start(world, seed))


def _go(loop: _Loop, mpc: MpcTeacher, tiles: int, until: Callable[[float, float], bool] | None = None) -> None:
    """Tick ``loop`` to its run's end, or to the first tick at whose start ``until(t, progress)`` holds (not driven)."""
    world, learner, store, step, run = loop.world, loop.learner, loop.store, loop.step, loop.run
    x, prev = loop.x, loop.prev
    for k in range(loop.k, int(round(120.0 * tiles / DT))):
        t = k * DT
        s, d = world.path.project(x[:2])
        prog = s / world.path.length
        if until is not None and until(t, prog):
            loop.x, loop.prev, loop.k = x, prev, k
            return
        run.t.append(t)
        run.dev.append(float(d))
        run.progress.append(float(prog))
        res = mpc.solve(x, world.path, store.limits.box, world.obstacles, slow_for_bends=store.slows_for_bends())
        mapped = step.map(res.u, x, world, res.predicted, corridor_m=CORRIDOR_M)
        did = learner.response(mapped.u_L, t, prog)
        run.cmd_err.append(float(np.hypot(*((did - res.u) / store.teacher_bounds.span))))
        x1 = unicycle_step(x, did, DT)
        store.add(teacher_equivalent(x, x1, DT), mapped.u_L, stamp=t + DT, prev_u_L=prev)
        prev = mapped.u_L
        run.methods.append(mapped.method)
        x = x1
        if world.collides(x[:2], VEHICLE_RADIUS):
            run.collided = True
        if world.reached(x):
            run.reached, run.time_s = True, (k + 1) * DT
            break
    loop.x, loop.prev, loop.ended = x, prev, True
    run.relearned, run.edges_relearned, run.store = store.relearned, store.limits.relearned, store


def drive(scenario: str, seed: int, adapt: bool, tiles: int = TILES, solver: str = "ipopt",
          change_tol: float = CHANGE_TOL, curve_margin: float = CURVE_MARGIN,
          reloaded: PairStore | None = None, spread: bool = False) -> tuple[DriftRun, ChangingLearner]:
    """The SCM learner from no pairs on the tiled world under ``scenario``, the store adapting (with ``change_tol``)
    or not, the teacher's MPC slowing for bends at ``curve_margin`` (0: the paper's MPC). ``reloaded``: from a copy
    of that store instead, the learner changed before the run began (``--reloaded``). ``spread``: the adapting store
    spreads a change to the cells not driven since (``transfer/store_spread.py``; off by default)."""
    loop = _start(scenario, seed, adapt, tiles, change_tol, reloaded, spread)
    mpc = mpc_teacher(solver, curve_margin)
    mpc.reset()
    _go(loop, mpc, tiles)
    return loop.run, loop.learner


#: the scenarios whose learner is the unchanged one until its change begins (the battery's caps and the payload's
#: acceleration limit act from the start): their runs on one seed and store drive the same ticks until then
UNCHANGED_UNTIL_CHANGE = ("wheel", "floor", CONTROL)
#: :func:`drive_shared` parts the runs from this long before the first change begins on (s, and the share of the path
#: the floor's is at): a tick at which no hole search is under way (a search is a generator, a step per command, and
#: a copy cannot carry it on)
FORK_LEAD_S, FORK_LEAD_PROGRESS = 3.0, 0.03


def _begins(scenario: str, t: float, progress: float) -> bool:
    """Whether ``scenario``'s learner may answer unlike the unchanged one from the tick at (``t``, ``progress``) on."""
    return (scenario == "wheel" and t >= T_CHANGE) or (scenario == "floor" and progress >= FLOOR_AT)


def drive_shared(scenarios: Sequence[str], seed: int, adapt: bool, tiles: int = TILES, solver: str = "ipopt",
                 change_tol: float = CHANGE_TOL, curve_margin: float = CURVE_MARGIN,
                 spread: bool = False) -> list[tuple[DriftRun, ChangingLearner]]:
    """:func:`drive` of each of ``scenarios`` on one seed and store, the same runs: the ticks they share driven once,
    up to a tick shortly before the first of their changes begins (:data:`FORK_LEAD_S`) at which the loop can be
    copied, then each scenario's run from a copy of that loop and the MPC's warm start. Scenarios outside
    :data:`UNCHANGED_UNTIL_CHANGE`, another solver than IPOPT (whose warm start cannot be taken whole), or a loop
    that cannot be copied before a change begins: each run driven from the start."""
    def alone() -> list[tuple[DriftRun, ChangingLearner]]:
        return [drive(sc, seed, adapt, tiles, solver, change_tol, curve_margin, spread=spread) for sc in scenarios]

    if solver != "ipopt" or len(scenarios) < 2 or not set(scenarios) <= set(UNCHANGED_UNTIL_CHANGE):
        return alone()

    def begins(t: float, progress: float) -> bool:
        return any(_begins(sc, t, progress) for sc in scenarios)

    shared = _start(CONTROL, seed, adapt, tiles, change_tol, None, spread)
    mpc = mpc_teacher(solver, curve_margin)
    mpc.reset()
    _go(shared, mpc, tiles, until=lambda t, progress: begins(t + FORK_LEAD_S, progress + FORK_LEAD_PROGRESS))
    while True:
        try:
            loops = [copy.deepcopy(shared, memo={id(shared.world): shared.world}) for _ in scenarios]
            break
        except TypeError:  # a hole search under way: one tick more, if no change begins at it
            k = shared.k
            if not shared.ended:
                _go(shared, mpc, tiles, until=lambda t, progress, k=k: t > (k + 0.5) * DT or begins(t, progress))
            if shared.ended or shared.k == k:
                return alone()
    warm = mpc.warm_start()
    for sc, loop in zip(scenarios, loops):
        loop.learner.scenario = sc
        if not loop.ended:
            mpc.set_warm_start(warm)
            _go(loop, mpc, tiles)
    return [(loop.run, loop.learner) for loop in loops]


def figures(run: DriftRun, change: tuple[float | None, float | None]) -> dict:
    """The summary's figures of one run (module docstring)."""
    t, dev = np.asarray(run.t), np.asarray(run.dev)
    t0, t1 = change
    out: dict = {"reached_goal": run.reached, "collisions": run.collided, "relearned": run.relearned,
                 "edges_relearned": run.edges_relearned, "time_s": run.time_s,
                 "driving_s": round(len(run.t) * DT, 1), "dev_before_m": None, "dev_after_m": None, "recover_s": None,
                 "cmd_err_before": None, "cmd_err_after": None, "change_s": [t0, t1]}
    if t0 is None or t1 is None:
        return out
    before = (t >= t0 - BEFORE_S) & (t < t0)
    after = t >= t1 + SETTLE_S
    err = np.asarray(run.cmd_err)
    if before.any():
        out["dev_before_m"] = float(dev[before].mean())
        out["cmd_err_before"] = float(err[before[:len(err)]].mean())
    if after.any():
        out["dev_after_m"] = float(dev[after].mean())
        out["cmd_err_after"] = float(err[after[:len(err)]].mean())
    if out["dev_before_m"] is not None:
        bound = RECOVER_FACTOR * out["dev_before_m"]
        n = int(round(RECOVER_WINDOW_S / DT))
        for i in np.flatnonzero(t >= t1):
            if i + n > len(dev):
                break
            if dev[i:i + n].mean() <= bound:
                out["recover_s"] = round(float(t[i] - t1), 2)
                break
    return out


def drift_summary(scenario: str, seed: int, tiles: int = TILES, solver: str = "ipopt", change_tol: float = CHANGE_TOL,
                  baseline: bool = True, curve_margin: float = CURVE_MARGIN, spread: bool = False) -> dict:
    """One scenario on one seed: the adapting store's figures and the never-forgetting baseline's on the same run
    (``baseline=False``: the adapting store's alone, e.g. for the false-alarm rate of ``none``)."""
    return drift_summaries([scenario], seed, tiles, solver, change_tol, baseline, curve_margin, spread)[0]


def drift_summaries(scenarios: Sequence[str], seed: int, tiles: int = TILES, solver: str = "ipopt",
                    change_tol: float = CHANGE_TOL, baseline: bool = True, curve_margin: float = CURVE_MARGIN,
                    spread: bool = False) -> list[dict]:
    """:func:`drift_summary` of each of ``scenarios`` on one seed, the ticks their runs share driven once
    (:func:`drive_shared`)."""
    runs = drive_shared(scenarios, seed, True, tiles, solver, change_tol, curve_margin, spread)
    bases = drive_shared(scenarios, seed, False, tiles, solver, curve_margin=curve_margin) if baseline else None
    out = []
    for i, (sc, (run, learner)) in enumerate(zip(scenarios, runs)):
        row = {"experiment": "drift", "scenario": sc, "seed": seed, "tiles": tiles, "change_tol": change_tol,
               "curve_margin": curve_margin, "mpc_solver": solver, **({"spread": True} if spread else {}),
               **figures(run, learner.change())}
        if bases is not None:
            base, base_learner = bases[i]
            row["baseline"] = figures(base, base_learner.change())
        out.append(row)
    return out


def reloaded_figures(run: DriftRun) -> dict:
    """A reloaded run's figures: the mean deviation over the run and over its second half (by time)."""
    t, dev = np.asarray(run.t), np.asarray(run.dev)
    half = t >= t[-1] / 2.0
    return {"reached_goal": run.reached, "collisions": run.collided, "relearned": run.relearned,
            "edges_relearned": run.edges_relearned, "time_s": run.time_s, "dev_m": float(dev.mean()),
            "dev_last_half_m": float(dev[half].mean())}


@functools.lru_cache(maxsize=8)
def _first_run(seed: int, tiles: int, solver: str, curve_margin: float) -> DriftRun:
    """``--reloaded``'s first run (the unchanged learner from no pairs), the same for every scenario reloaded from it:
    deterministic, so driven once per process and shared (each reloaded run drives a copy of its store)."""
    first, _ = drive(CONTROL, seed, adapt=False, tiles=tiles, solver=solver, curve_margin=curve_margin)
    return first


def reloaded_summary(scenario: str, seed: int, tiles: int = TILES, solver: str = "ipopt",
                     change_tol: float = CHANGE_TOL, curve_margin: float = CURVE_MARGIN) -> dict:
    """``--reloaded`` (module docstring) on one seed: the first run's store, then the changed learner driven from it
    re-learning its changed cells (``adaptive``) and not (``baseline``)."""
    first = _first_run(seed, tiles, solver, curve_margin)
    assert first.store is not None
    out = {"experiment": "drift-reloaded", "scenario": scenario, "seed": seed, "tiles": tiles, "change_tol": change_tol,
           "curve_margin": curve_margin, "mpc_solver": solver,
           "learned": {"refined_pairs": first.store.n_configured(), **reloaded_figures(first)}}
    for name, adapt in (("adaptive", True), ("baseline", False)):
        run, _ = drive(scenario, seed, adapt=adapt, tiles=tiles, solver=solver, change_tol=change_tol,
                       curve_margin=curve_margin, reloaded=first.store)
        out[name] = reloaded_figures(run)
    return out


def reloaded_stats(rows: list[dict]) -> dict:
    """Per scenario: the median last-half deviation of each store, the median of their ratio seed by seed and on how
    many seeds re-learning was worse, goals, collisions and the cells re-learned."""
    out: dict = {}
    for sc in sorted({r["scenario"] for r in rows}):
        rs = [r for r in rows if r["scenario"] == sc]
        ratio = [r["adaptive"]["dev_last_half_m"] / r["baseline"]["dev_last_half_m"] for r in rs
                 if r["baseline"]["dev_last_half_m"] > 0]
        out[sc] = {**{f"{k}_dev_last_half_m": _median([r[k]["dev_last_half_m"] for r in rs])
                      for k in ("adaptive", "baseline")},
                   "adaptive_to_baseline": _median(ratio), "adaptive_to_baseline_q": _quartiles(ratio),
                   "adaptive_worse": sum(x > 1.0 for x in ratio),
                   "reached_goal": [sum(bool(r[k]["reached_goal"]) for r in rs) for k in ("adaptive", "baseline")],
                   "collisions": [sum(bool(r[k]["collisions"]) for r in rs) for k in ("adaptive", "baseline")],
                   "relearned": _median([r["adaptive"]["relearned"] for r in rs]), "seeds": len(rs)}
    return out


def _task(args: tuple[str, int, int, str, float, bool, float, bool]) -> dict:
    return drift_summary(*args)


def _reloaded_task(args: tuple[str, int, int, str, float, float]) -> dict:
    return reloaded_summary(*args)


def sweep(scenarios: Sequence[str], seeds: Sequence[int], tiles: int = TILES, workers: int = 2,
          change_tol: float = CHANGE_TOL, baseline: bool = True, curve_margin: float = CURVE_MARGIN,
          spread: bool = False, solver: str = "ipopt") -> list[dict]:
    """Every scenario on every seed (at most ``workers`` processes); the baseline runs only where a change is (the
    never-forgetting store has nothing to compare with on ``none``)."""
    return _run(_task, [(sc, s, tiles, solver, change_tol, baseline and sc != CONTROL, curve_margin, spread)
                        for sc in scenarios for s in seeds], workers)


def sweep_reloaded(scenarios: Sequence[str], seeds: Sequence[int], tiles: int = TILES, workers: int = 2,
                   change_tol: float = CHANGE_TOL, curve_margin: float = CURVE_MARGIN,
                   solver: str = "ipopt") -> list[dict]:
    """``--reloaded`` for every scenario and seed (at most ``workers`` processes)."""
    return _run(_reloaded_task, [(sc, s, tiles, solver, change_tol, curve_margin) for sc in scenarios for s in seeds],
                workers)


def _run(task: Callable[[Any], dict], tasks: list[tuple], workers: int) -> list[dict]:
    """``task`` of each of ``tasks``, in order: in this process, or in at most ``workers`` processes."""
    if workers <= 1 or len(tasks) == 1:
        return [task(a) for a in tasks]
    with ProcessPoolExecutor(max_workers=workers) as ex:
        return list(ex.map(task, tasks))


def _median(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.median(vals)) if vals else None


def _quartiles(values: list[float | None]) -> list[float] | None:
    vals = [v for v in values if v is not None]
    return [round(float(q), 3) for q in np.percentile(vals, (25, 75))] if vals else None


def _ratio(s: dict) -> float | None:
    return None if s["dev_after_m"] is None or not s["dev_before_m"] else s["dev_after_m"] / s["dev_before_m"]


def sweep_stats(rows: list[dict]) -> dict:
    """Per scenario, for the adapting store and the baseline: the median deviation after the change over before it
    (with its quartiles), the median time to recover (never counts as the run's rest), how many seeds recovered
    within 15 s, reached the goal and collided, the median cells re-learned; how many seeds the baseline ended worse
    (a larger deviation after). For ``none``: the re-learnings per hour of driving, and when there were none the
    95 % upper bound of that rate (3 / hours driven: no event in T hours)."""
    out: dict = {}
    for sc in sorted({r["scenario"] for r in rows}):
        rs = [r for r in rows if r["scenario"] == sc]
        if sc == CONTROL:
            hours = sum(r["driving_s"] for r in rs) / 3600.0
            n = sum(r["relearned"] for r in rs)
            out[sc] = {"relearned": n, "driving_h": round(hours, 3), "relearned_per_h": round(n / hours, 3),
                       "edges_relearned": sum(r["edges_relearned"] for r in rs),
                       "upper_95_per_h": round(3.0 / hours, 3) if n == 0 else None,
                       "reached_goal": sum(bool(r["reached_goal"]) for r in rs),
                       "collisions": sum(bool(r["collisions"]) for r in rs), "seeds": len(rs)}
            continue

        def stats(get, rs: list[dict] = rs) -> dict:
            sel = [get(r) for r in rs]
            ratio = [_ratio(s) for s in sel]
            rec = [s["recover_s"] if s["recover_s"] is not None else
                   (s["driving_s"] - s["change_s"][1] if s["change_s"][1] is not None else None) for s in sel]
            return {"dev_after_to_before": _median(ratio), "dev_after_to_before_q": _quartiles(ratio),
                    "recover_s": _median(rec), "recover_s_q": _quartiles(rec),
                    "recovered_within_15s": sum(s["recover_s"] is not None and s["recover_s"] <= 15.0 for s in sel),
                    "reached_goal": sum(bool(s["reached_goal"]) for s in sel),
                    "collisions": sum(bool(s["collisions"]) for s in sel),
                    "relearned": _median([s["relearned"] for s in sel]),
                    "edges_relearned": _median([s["edges_relearned"] for s in sel]),
                    "time_s": _median([s["time_s"] for s in sel]), "seeds": len(sel)}

        out[sc] = {"adaptive": stats(lambda r: r)}
        if all("baseline" in r for r in rs):
            out[sc]["baseline"] = stats(lambda r: r["baseline"])
            out[sc]["baseline_worse"] = sum(
                (_ratio(r["baseline"]) or 0.0) > (_ratio(r) or 0.0) for r in rs)
    return out


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scenario", choices=[*SCENARIOS, CONTROL, "all"], default="all",
                    help="what changes (default: all four; none: no change, the false-alarm rate)")
    ap.add_argument("--seed", type=int, default=0, help="the run's seed (exploration ties, the start's jitter)")
    ap.add_argument("--seeds", type=parse_seeds, default=None, help="a sweep instead: 0-9, or 0,3,5")
    ap.add_argument("--tiles", type=int, default=TILES, help="S-paths laid end to end (the run's length)")
    ap.add_argument("--out", default=None, help="directory for the summaries (drift.json)")
    ap.add_argument("--change-tol", type=float, default=CHANGE_TOL,
                    help="the store's change tolerance (share of the teacher's range; [transfer] change_tol)")
    ap.add_argument("--workers", type=int, default=2, help="processes of a sweep (default 2)")
    ap.add_argument("--reloaded", action="store_true",
                    help="a store learned on the unchanged learner the day before, the learner changed since: "
                         "driven from it re-learning its changed cells and not (module docstring)")
    ap.add_argument("--curve-margin", type=float, default=CURVE_MARGIN,
                    help="the teacher MPC slows for a bend the learned yaw-rate limit cannot turn at its top speed, "
                         f"using this share of the limit (default {CURVE_MARGIN}; 0: the paper's MPC; "
                         "[teacher] curve_margin)")
    ap.add_argument("--solver", choices=SOLVERS, default="ipopt",
                    help="how the teacher's MPC is solved: ipopt, the paper's MPC (default); rti-qpoases / rti-daqp, "
                         "the real-time iteration a station runs ([teacher] mpc_solver)")
    ap.add_argument("--spread", action="store_true",
                    help="the adapting store spreads a change to the cells not driven since (transfer/store_spread.py; "
                         "off by default: docs/PAPER.md has what it gains and costs)")


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    scenarios = list(SCENARIOS) if args.scenario == "all" else [args.scenario]
    seeds = args.seeds if args.seeds is not None else [args.seed]
    if not 0.0 <= args.curve_margin <= 1.0:
        raise SystemExit(f"--curve-margin must be in [0, 1], got {args.curve_margin}")
    if args.reloaded and args.spread:
        raise SystemExit("--spread is for a run from no pairs, not --reloaded")
    if args.reloaded:
        rows = sweep_reloaded(scenarios, seeds, args.tiles, workers=args.workers, change_tol=args.change_tol,
                              curve_margin=args.curve_margin, solver=args.solver)
        stats, kind = (reloaded_stats(rows) if len(rows) > 1 else None), "drift-reloaded-sweep"
    else:
        rows = sweep(scenarios, seeds, args.tiles, workers=args.workers, change_tol=args.change_tol,
                     curve_margin=args.curve_margin, spread=args.spread, solver=args.solver)
        stats, kind = (sweep_stats(rows) if len(rows) > 1 else None), "drift-sweep"
    for r in rows:
        print_line(json.dumps(r))
    if stats is not None:
        print_line(json.dumps({"experiment": kind, "seeds": list(seeds), "stats": stats,
                               "wall_s": round(time.perf_counter() - t0, 1)}))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "drift.json").write_text(json.dumps(rows, indent=1))
    return 0


__all__ = ["SCENARIOS", "ChangingLearner", "drift_summary", "drive", "figures", "reloaded_summary", "tiled"]
