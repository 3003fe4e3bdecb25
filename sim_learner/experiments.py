"""The paper's simulations, in-process: ``scmbridge sim mpc|grid|primitives --out DIR``.

Each prints one JSON summary on stdout and writes PNG figures and the raw trajectories (``.npz``) into DIR. The
learner is a black box here exactly as on a robot: the loop only sends it commands and reads its poses; the
transfer code (``transfer/``) is the same the live station runs.

- ``mpc``: from no pairs at all, the ideal teacher, the SCM learner and the baseline learner follow the S-path with
  the teacher's MPC (paper Section 5.2).
- ``grid``: the exhaustive test of the paper: a dense grid of teacher commands inside the learned limits, each
  applied 0.1 s from the same pose to the teacher, the baseline, the SCM learner and each alternative mapper.
- ``primitives``: the motion-primitive planner (paper Section 5.1) after a 5 x 5 calibration.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path as FsPath

import numpy as np
from numpy.typing import NDArray

from sim_learner.dynamics import MPC_TEACHER_V, MPC_TEACHER_W, LearnerModel, mpc_learner
from sim_learner.runs import DT, Progress
from sim_learner.worlds import World, mpc_world
from transfer.domain import Bounds
from transfer.pairs import teacher_equivalent
from transfer.policy import TransferPolicy
from transfer.store import PairStore
from transfer.teacher.mpc import MpcConfig, MpcTeacher
from transfer.teacher.unicycle import step as teacher_step

VEHICLE_RADIUS = 0.1  # m, for collision checks


@dataclass
class Run:
    """One closed-loop run: poses, commands sent, methods, whether and when it reached the goal."""

    name: str
    poses: list[NDArray[np.float64]] = field(default_factory=list)
    commands: list[NDArray[np.float64]] = field(default_factory=list)
    teacher_cmds: list[NDArray[np.float64]] = field(default_factory=list)
    methods: list[str] = field(default_factory=list)
    reached: bool = False
    collided: bool = False
    time_s: float | None = None
    solve_s: list[float] = field(default_factory=list)
    failures: int = 0

    def arrays(self) -> dict[str, NDArray]:
        return {
            f"{self.name}_poses": np.array(self.poses),
            f"{self.name}_commands": np.array(self.commands).reshape(-1, 2),
            f"{self.name}_teacher": np.array(self.teacher_cmds).reshape(-1, 2),
        }


def _deviation_profile(run: Run, world: World) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(progress in [0, 1], distance to the path) for every pose of a run."""
    prog, dev = [], []
    for p in run.poses:
        s, d = world.path.project(p[:2])
        prog.append(s / world.path.length)
        dev.append(d)
    return np.array(prog), np.array(dev)


def _mean_dev_last_half(run: Run, world: World) -> float | None:
    prog, dev = _deviation_profile(run, world)
    m = prog >= 0.5
    return float(dev[m].mean()) if m.any() else None


def closed_loop_mpc(
    name: str,
    world: World,
    mpc: MpcTeacher,
    bounds_fn,
    apply_fn,
    t_max: float,
    progress: Progress | None = None,
) -> Run:
    """Drive one vehicle along the world's path: each tick the MPC (bounded by ``bounds_fn()``) proposes a
    teacher command, ``apply_fn(state, u_T)`` turns it into motion and returns (next_state, command, method)."""
    mpc.reset()
    run = Run(name)
    x = world.start.astype(float).copy()
    run.poses.append(x.copy())
    steps = int(round(t_max / DT))
    for k in range(steps):
        t0 = time.perf_counter()
        res = mpc.solve(x, world.path, bounds_fn(), world.obstacles)
        run.solve_s.append(time.perf_counter() - t0)
        run.failures += int(not res.ok)
        x, u_sent, method = apply_fn(x, res.u)
        run.poses.append(x.copy())
        run.commands.append(u_sent)
        run.teacher_cmds.append(res.u)
        run.methods.append(method)
        if world.collides(x[:2], VEHICLE_RADIUS):
            run.collided = True
        s, _ = world.path.project(x[:2])
        if progress is not None and k % 10 == 0:
            progress(s / world.path.length, name)
        at_end = s >= world.path.length - 1e-6 or np.hypot(*(x[:2] - world.goal)) < world.goal_radius
        if at_end and s >= 0.9 * world.path.length:
            run.reached = True
            run.time_s = (k + 1) * DT
            break
    return run


def run_mpc(seed: int = 0, quick: bool = False, out: FsPath | None = None, progress: bool = True) -> dict:
    """Paper Section 5.2: ideal teacher vs SCM learner vs baseline learner, no command pairs at the start."""
    world = mpc_world(0.6 if quick else 1.0)
    learner = mpc_learner()
    TB = Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
    LB = Bounds(learner.v_range, learner.w_range)
    # the learner's true command range mapped onto the teacher domain: its extremes are fixed points of h, so
    # the teacher equivalents of the learner's extreme commands are the same numbers
    true_box = Bounds(tuple(learner.response(LB.lo)[:1].tolist() + learner.response(LB.hi)[:1].tolist()),
                      (float(learner.response(LB.lo)[1]), float(learner.response(LB.hi)[1])))
    mpc = MpcTeacher(MpcConfig(N=20, dt=DT))
    bar = Progress("mpc") if progress else None
    t_max = 120.0 if not quick else 60.0

    def ideal(x, u):
        return teacher_step(x, u, DT), u, "teacher"

    teacher = closed_loop_mpc("teacher", world, mpc, lambda: true_box, ideal, t_max, bar)

    store = PairStore(LB, TB, k_min=5)
    policy = TransferPolicy(store, "scm", rng=np.random.default_rng(seed))

    def scm(x, u):
        m = policy.map(u)
        x1 = learner.step(x, m.u_L, DT)
        store.add(teacher_equivalent(x, x1, DT), m.u_L)
        return x1, m.u_L, m.method

    scm_run = closed_loop_mpc("scm", world, mpc, lambda: store.limits.box, scm, t_max, bar)

    def baseline(x, u):
        return learner.step(x, u, DT), learner.clamp(u), "direct"

    base_t_max = 2.5 * (teacher.time_s or t_max / 2)
    base = closed_loop_mpc("baseline", world, mpc, lambda: TB, baseline, base_t_max, bar)
    if bar:
        bar.done()

    learned = store.limits.box
    rel = [
        abs(learned.v[0] - true_box.v[0]) / (true_box.v[1] - true_box.v[0]),
        abs(learned.v[1] - true_box.v[1]) / (true_box.v[1] - true_box.v[0]),
        abs(learned.w[0] - true_box.w[0]) / (true_box.w[1] - true_box.w[0]),
        abs(learned.w[1] - true_box.w[1]) / (true_box.w[1] - true_box.w[0]),
    ]
    counts = {m: scm_run.methods.count(m) for m in ("scm", "direct", "perturb")}
    solve = np.array(teacher.solve_s + scm_run.solve_s + base.solve_s) * 1e3
    summary = {
        "experiment": "mpc",
        "quick": quick,
        "seed": seed,
        "teacher_time_s": teacher.time_s,
        "scm_time_s": scm_run.time_s,
        "baseline_time_s": base.time_s,
        "baseline_reached_goal": base.reached,
        "teacher_dev_last_half_m": _mean_dev_last_half(teacher, world),
        "scm_dev_last_half_m": _mean_dev_last_half(scm_run, world),
        "baseline_dev_last_half_m": _mean_dev_last_half(base, world),
        "collisions": {"teacher": teacher.collided, "scm": scm_run.collided, "baseline": base.collided},
        "limits_rel_err": float(max(rel)),
        "learned_limits": learned.as_list(),
        "true_limits": true_box.as_list(),
        "method_counts": counts,
        "refined_pairs": len(store.refined()),
        "raw_pairs": store.raw_count,
        "mpc_solve_ms": {"median": float(np.median(solve)), "p95": float(np.percentile(solve, 95))},
        "mpc_failures": teacher.failures + scm_run.failures + base.failures,
    }
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "mpc_runs.npz", **teacher.arrays(), **scm_run.arrays(), **base.arrays(),
                            scm_methods=np.array(scm_run.methods), store=np.frombuffer(store.to_bytes(), np.uint8))
        from sim_learner.figures import mpc_figures

        summary["figures"] = mpc_figures(out, world, [teacher, scm_run, base], store, true_box, TB, LB)
    summary["_store"] = store
    return summary


def run_grid(seed: int = 0, quick: bool = False, out: FsPath | None = None, progress: bool = True,
             store: PairStore | None = None) -> dict:
    """The paper's exhaustive test: a dense grid of teacher commands inside the learned limits, 0.1 s each."""
    if store is None:
        store = run_mpc(seed, quick, None, progress)["_store"]
    learner = mpc_learner()
    box = store.limits.box
    n = 25 if quick else 60
    gv = np.linspace(box.v[0], box.v[1], n)
    gw = np.linspace(box.w[0], box.w[1], n)
    V, W = np.meshgrid(gv, gw, indexing="ij")
    cmds = np.stack([V.ravel(), W.ravel()], axis=-1)
    x0 = np.array([0.0, 0.0, 0.0])
    target = teacher_step(x0, cmds, DT)
    names = ["scm", "identity", "affine", "barycentric"]
    pos_err = {k: np.zeros(len(cmds)) for k in names}
    ang_err = {k: np.zeros(len(cmds)) for k in names}
    method = np.empty(len(cmds), dtype=object)
    for name in names:
        pol = TransferPolicy(store, name, rng=np.random.default_rng(seed))
        for i, u in enumerate(cmds):
            m = pol.map(u)
            if name == "scm":
                method[i] = m.method
            x1 = learner.step(x0, m.u_L, DT)
            pos_err[name][i] = np.hypot(*(x1[:2] - target[i, :2]))
            ang_err[name][i] = abs(math.remainder(x1[2] - target[i, 2], 2 * math.pi))
    region = method == "scm"

    def stats(a: NDArray[np.float64], mask: NDArray[np.bool_]) -> dict | None:
        if not mask.any():
            return None
        return {"median": float(np.median(a[mask])), "p95": float(np.percentile(a[mask], 95))}

    per_method = {}
    for meth in ("scm", "direct", "perturb"):
        mask = method == meth
        per_method[meth] = {"count": int(mask.sum()), "scm_pos_err_m": stats(pos_err["scm"], mask),
                            "baseline_pos_err_m": stats(pos_err["identity"], mask)}
    summary = {
        "experiment": "grid",
        "quick": quick,
        "commands": len(cmds),
        "scm_region_fraction": float(region.mean()),
        "scm_region_median_pos_err_m": float(np.median(pos_err["scm"][region])) if region.any() else None,
        "baseline_median_pos_err_m": float(np.median(pos_err["identity"][region])) if region.any() else None,
        "scm_region_median_ang_err_rad": float(np.median(ang_err["scm"][region])) if region.any() else None,
        "baseline_median_ang_err_rad": float(np.median(ang_err["identity"][region])) if region.any() else None,
        "mappers": {
            k: {"region_median_pos_err_m": float(np.median(pos_err[k][region])) if region.any() else None,
                "region_p95_pos_err_m": float(np.percentile(pos_err[k][region], 95)) if region.any() else None,
                "region_median_ang_err_rad": float(np.median(ang_err[k][region])) if region.any() else None}
            for k in names
        },
        "per_method_region": per_method,
        "baseline_region_median_pos_err_m_all": float(np.median(pos_err["identity"])),
    }
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "grid.npz", commands=cmds, method=method.astype(str),
                            **{f"pos_err_{k}": v for k, v in pos_err.items()},
                            **{f"ang_err_{k}": v for k, v in ang_err.items()})
        from sim_learner.figures import grid_figures

        summary["figures"] = grid_figures(out, store, cmds, n, method, pos_err, ang_err)
    return summary


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scmbridge sim", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiment", choices=["mpc", "grid", "primitives"])
    ap.add_argument("--out", type=FsPath, default=FsPath("out"), help="directory for figures and trajectories")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="a shortened run (what the tests use)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if args.experiment == "mpc":
        summary = run_mpc(args.seed, args.quick, args.out)
    elif args.experiment == "grid":
        summary = run_grid(args.seed, args.quick, args.out)
    else:
        from sim_learner.primitives_sim import run_primitives

        summary = run_primitives(args.seed, args.quick, args.out)
    summary.pop("_store", None)
    summary["wall_s"] = time.perf_counter() - t0
    json.dump(summary, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


__all__ = ["LearnerModel", "main", "run_grid", "run_mpc"]
