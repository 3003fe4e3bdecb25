"""``scmbridge bench mpc``: every way of solving the teacher's MPC, measured in one run (JSON).

For each solver (IPOPT, the reference; the real-time iteration over qpOASES and over DAQP, from compiled code):

- ``N20`` (and ``N10``): the time of each ``solve`` call (references, obstacles, the solve, the plan) while the
  ideal teacher (the teacher model bounded by the learner's true range) drives the full-size MPC world with
  ``--slots`` obstacle slots; median, p99, max, failures and the ticks it took.
- ``closed_loop``: the MPC case's seed sweep (``scmbridge sim mpc``) with this solver: the SCM learner's median time
  and last-half deviation ratios to the ideal teacher, the seeds that collided or missed the goal, and the ideal
  teacher's own figures. ``--seeds`` defaults to seeds the test suite does not use.

The compiled code is built (or loaded from the cache) before timing; ``build_s`` says how long that took.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.common import emit


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--steps", type=int, default=600, help="closed-loop ticks at most per timing run")
    ap.add_argument("--slots", type=int, default=8, help="obstacle slots of the timed MPC")
    ap.add_argument("--solvers", default="ipopt,rti-qpoases,rti-daqp", help="comma-separated (transfer.teacher.mpc)")
    ap.add_argument("--seeds", default="100-104", help="the closed-loop sweep's seeds (see scmbridge sim mpc)")
    ap.add_argument("--full", action="store_true", help="the closed-loop sweep on the full-size world (slow)")
    ap.add_argument("--no-sweep", action="store_true", help="timing only")


def _timing(solver: str, N: int, slots: int, steps: int) -> dict:
    from bridge.teacher.codegen import build_mpc
    from sim_learner.dynamics import MPC_LEARNER_V, MPC_LEARNER_W
    from sim_learner.runs import Run, mean_dev_last_half
    from sim_learner.worlds import mpc_world
    from transfer.domain import Bounds
    from transfer.teacher.mpc import MpcConfig
    from transfer.teacher.unicycle import step

    world = mpc_world()
    limits = Bounds(MPC_LEARNER_V, MPC_LEARNER_W)
    t0 = time.perf_counter()
    mpc = build_mpc(MpcConfig(N=N, max_obstacles=slots, solver=solver), compile=True)
    build_s = time.perf_counter() - t0
    x, run, times, fails, collided = world.start.copy(), Run(solver), [], 0, False
    run.poses.append(x.copy())
    for _ in range(steps):
        t = time.perf_counter()
        r = mpc.solve(x, world.path, limits, world.obstacles)
        times.append(time.perf_counter() - t)
        fails += int(not r.ok)
        x = step(x, r.u, mpc.cfg.dt)
        run.poses.append(x.copy())
        collided |= world.collides(x[:2], 0.1)
        if world.reached(x):
            run.reached = True
            break
    ms = np.array(times[1:]) * 1e3  # the first solve of a run is a cold start
    return {"median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max()),
            "failures": fails, "ticks": len(times), "reached": run.reached, "collided": bool(collided),
            "dev_last_half_m": mean_dev_last_half(run, world), "compiled": mpc.compiled, "build_s": build_s}


def _closed_loop(solver: str, seeds: list[int], quick: bool) -> dict:
    from sim_learner.experiments import sweep_mpc

    t0 = time.perf_counter()
    sweep = sweep_mpc(seeds, quick=quick, explorations=("guided",), workers=1, progress=False, solver=solver).summary
    stats = sweep["policies"]["guided"]["stats"]
    teacher = sweep["references"]["teacher"]
    return {"seeds": seeds, "quick": quick, "time_ratio_median": stats["scm_time_ratio"]["median"],
            "dev_ratio_median": stats["scm_dev_ratio"]["median"], "collided_seeds": stats["collided_seeds"],
            "no_goal_seeds": stats["no_goal_seeds"], "teacher_time_s": teacher["time_s"],
            "teacher_dev_last_half_m": teacher["dev_last_half_m"], "teacher_collided": teacher["collided"],
            "wall_s": time.perf_counter() - t0}


def run(args: argparse.Namespace) -> int:
    from sim_learner.experiments import parse_seeds
    from transfer.teacher.mpc import SOLVERS

    solvers = [s.strip() for s in args.solvers.split(",") if s.strip()]
    unknown = [s for s in solvers if s not in SOLVERS]
    if unknown:
        from bridge.core.errors import UsageError

        raise UsageError(f"--solvers: unknown {', '.join(unknown)}; known: {', '.join(SOLVERS)}")
    seeds = parse_seeds(args.seeds)
    out: dict = {"slots": args.slots, "solvers": {}}
    for solver in solvers:
        res = {f"N{N}": _timing(solver, N, args.slots, args.steps) for N in (20, 10)}
        if not args.no_sweep:
            res["closed_loop"] = _closed_loop(solver, seeds, quick=not args.full)
        out["solvers"][solver] = res
    ref = out["solvers"].get("ipopt")
    if ref is not None:
        out["speedup_vs_ipopt"] = {s: ref["N20"]["median_ms"] / r["N20"]["median_ms"]
                                   for s, r in out["solvers"].items() if s != "ipopt"}
    out["target"] = {"N20_median_ms": 0.3, "N20_p99_ms": 1.0, "slots": 8}
    emit(out)
    return 0
