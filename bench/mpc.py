"""``scmbridge bench mpc``: MPC solve time per closed-loop step on the S-path with obstacles (JSON).

The teacher model follows the MPC world's path with inputs bounded by the learner's true range (the ideal
teacher of ``scmbridge sim mpc``), once with N = 10 and once with N = 20. Failed or non-converged solves are
counted; their commands are never the raw solver output (the MPC falls back to its shifted plan or a stop).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.common import emit


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--steps", type=int, default=400, help="closed-loop steps per horizon")


def run(args: argparse.Namespace) -> int:
    from sim_learner.dynamics import MPC_LEARNER_V, MPC_LEARNER_W
    from sim_learner.worlds import mpc_world
    from transfer.domain import Bounds
    from transfer.teacher.mpc import MpcConfig, MpcTeacher
    from transfer.teacher.unicycle import step

    world = mpc_world()
    limits = Bounds(MPC_LEARNER_V, MPC_LEARNER_W)
    out: dict = {"solve_ms": {}, "failures": {}, "solver": "ipopt (mumps)", "steps": {}}
    for N in (10, 20):
        mpc = MpcTeacher(MpcConfig(N=N))
        x = world.start.copy()
        times, fails = [], 0
        for _ in range(args.steps):
            t = time.perf_counter()
            r = mpc.solve(x, world.path, limits, world.obstacles)
            times.append(time.perf_counter() - t)
            fails += int(not r.ok)
            x = step(x, r.u, mpc.cfg.dt)
            if world.reached(x):
                break
        ms = np.array(times) * 1e3
        out["solve_ms"][f"N{N}"] = {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95))}
        out["failures"][f"N{N}"] = fails
        out["steps"][f"N{N}"] = len(times)
    out["target"] = {"N20_median_ms": 5.0}
    emit(out)
    return 0
