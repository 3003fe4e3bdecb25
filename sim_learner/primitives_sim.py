"""``scmbridge sim primitives``: the paper's motion-primitive case (Section 5.1, Table 1).

Calibration first: a 5 x 5 grid of learner commands (extremes included), each driven for one primitive duration,
gives the command pairs and so the learner's limits on the teacher domain; the 121 teacher primitives are filtered
by those limits. Then the SCM learner (primitive commands mapped by the SC transfer) and the baseline learner
(primitive commands applied directly, full library: it knows nothing of its limits) follow the S-path with
event-triggered replanning. The learner is the per-axis scaled learner of :func:`sim_learner.dynamics.scaled_learner`
with position measurement noise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim_learner.dynamics import PRIM_TEACHER_V, PRIM_TEACHER_W, LearnerModel, scaled_learner
from sim_learner.runs import DT, Progress
from sim_learner.worlds import World, primitives_world
from transfer.domain import Bounds
from transfer.limits import calibration_commands
from transfer.pairs import teacher_equivalent
from transfer.policy import make_policy
from transfer.step import TransferStep
from transfer.store import PairStore
from transfer.teacher.primitives import PrimitiveLibrary, PrimitivePlanner, replan_threshold

NOISE_STD = 0.05  # m, measurement noise on the learner's position (the paper: "G ~ N(0, 0.1)"; see docs/PAPER.md)
VEHICLE_RADIUS = 0.3


def calibrate(learner: LearnerModel, store: PairStore, duration: float) -> None:
    """Drive each calibration command for one primitive duration; pair every control interval of it (the
    teacher model is the Euler step of DT: pairing over the whole second would mistake the arc for its chord)."""
    LB = store.learner_bounds
    for u in calibration_commands(LB, 5):
        x = np.zeros(3)
        for _ in range(int(round(duration / DT))):
            x1 = learner.step(x, u, DT)
            store.add(teacher_equivalent(x, x1, DT), u)
            x = x1


def follow(name: str, world: World, learner: LearnerModel, planner: PrimitivePlanner, allowed, to_learner,
           rng: np.random.Generator, t_max: float, bar: Progress | None) -> dict:
    """Closed loop: plan, execute the first primitive tick by tick, replan at its end or on deviation.
    ``to_learner(u_T, pose)``: the learner command for a primitive's command planned from the measured pose."""
    x = world.start.astype(float).copy()
    poses, cmds, plans = [x.copy()], [], []
    replans = events = 0
    collided = reached = False
    t_goal = None
    steps = planner.lib.steps
    k = 0
    max_ticks = int(round(t_max / DT))
    while k < max_ticks and not reached:
        meas = x.copy()
        meas[:2] += rng.normal(0.0, NOISE_STD, 2)
        plan = planner.plan(meas, world.path, allowed)
        plans.append(plan.trajectory[:, :2])
        replans += 1
        u_T = plan.commands[0]
        u_L = to_learner(u_T, meas)
        for j in range(steps):
            x = learner.step(x, u_L, DT)
            k += 1
            poses.append(x.copy())
            cmds.append(u_L)
            if world.collides(x[:2], VEHICLE_RADIUS):
                collided = True
            if world.reached(x):  # the one goal rule (transfer.mission)
                reached, t_goal = True, k * DT
                break
            # event trigger: the learner left the local plan by more than epsilon
            meas = x.copy()
            meas[:2] += rng.normal(0.0, NOISE_STD, 2)
            planned = plan.trajectory[min(j + 1, len(plan.trajectory) - 1), :2]
            if np.hypot(*(meas[:2] - planned)) > replan_threshold(meas, world.obstacles) + 2 * NOISE_STD:
                events += 1
                break
        if bar is not None:
            bar(world.path.project(x[:2])[0] / world.path.length, name)
    P = np.array(poses)
    dev = np.array([world.path.project(p[:2])[1] for p in P])
    return {"poses": P, "commands": np.array(cmds).reshape(-1, 2), "plans": plans, "reached": reached,
            "collided": collided, "time_s": t_goal, "replans": replans, "event_replans": events,
            "max_dev_m": float(dev.max()), "mean_dev_m": float(dev.mean())}


def run_primitives(seed: int = 0, quick: bool = False, out: Path | None = None, progress: bool = True,
                   exploration: str = "guided") -> dict:
    """Paper Section 5.1: calibration, the learner's limits filter the library, SCM learner vs baseline learner."""
    world = primitives_world()
    learner = scaled_learner()
    TB = Bounds(PRIM_TEACHER_V, PRIM_TEACHER_W)
    LB = Bounds(learner.v_range, learner.w_range)
    lib = PrimitiveLibrary(TB, 11, duration=1.0, dt=DT)
    store = PairStore(LB, TB, grid=(11, 11), k_min=1)
    calibrate(learner, store, lib.duration)
    kept = np.asarray(store.limits.contains(lib.commands, use_hull=True, tol=1e-6))
    planner = PrimitivePlanner(lib, k_d=1.0, k_theta=2.0, horizon=2)
    step = TransferStep(make_policy(store, "scm", np.random.default_rng(seed), exploration=exploration), dt=DT)
    bar = Progress("primitives") if progress else None
    t_max = 90.0 if quick else 150.0
    rng = np.random.default_rng(seed)
    scm = follow("scm", world, learner, planner, kept, lambda u, x: step.map(u, x, world).u_L, rng, t_max, bar)
    base = follow("baseline", world, learner, planner, np.ones(len(lib), dtype=bool), lambda u, x: learner.clamp(u),
                  np.random.default_rng(seed), t_max, bar)
    if bar:
        bar.done()
    summary = {
        "experiment": "primitives",
        "quick": quick,
        "exploration": exploration,
        "kept_primitives": int(kept.sum()),
        "total_primitives": len(lib),
        "learned_limits": store.limits.box.as_list(),
        "scm_reached_goal": scm["reached"],
        "scm_collisions": scm["collided"],
        "scm_max_dev_m": scm["max_dev_m"],
        "scm_mean_dev_m": scm["mean_dev_m"],
        "scm_time_s": scm["time_s"],
        "scm_replans": scm["replans"],
        "scm_event_replans": scm["event_replans"],
        "baseline_reached_goal": base["reached"],
        "baseline_collisions": base["collided"],
        "baseline_max_dev_m": base["max_dev_m"],
        "baseline_mean_dev_m": base["mean_dev_m"],
        "baseline_time_s": base["time_s"],
        "baseline_replans": base["replans"],
        "noise_std_m": NOISE_STD,
    }
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "primitives_runs.npz", scm_poses=scm["poses"], scm_commands=scm["commands"],
                            baseline_poses=base["poses"], baseline_commands=base["commands"], kept=kept,
                            library=lib.commands)
        from sim_learner.figures import primitives_figures

        summary["figures"] = primitives_figures(out, world, scm, base, lib, kept, store)
    return summary
