"""The paper's simulations, in-process: ``scmbridge sim mpc|grid|primitives --out DIR``.

Each prints one JSON summary on stdout and writes PNG figures and the raw trajectories (``.npz``) into DIR. The
learner is a black box here exactly as on a robot: the loop only sends it commands and reads its poses; the
transfer code (``transfer/``) is the same the live station runs.

- ``mpc``: from no pairs at all, the ideal teacher, the SCM learner and two baseline learners follow the S-path with
  the teacher's MPC (paper Section 5.2). ``--seeds 0-9`` (or ``0,3,5``) runs a seed sweep instead (at most two
  worker processes) and prints, for every claim figure, the median, the spread and the worst seed, for each
  exploration policy (``--policy guided|paper``, default both).
- ``grid``: the exhaustive test of the paper: a dense grid of teacher commands inside the learned limits, each
  applied 0.1 s from the same pose to the teacher, the baseline, the SCM learner and each alternative mapper.
- ``primitives``: the motion-primitive planner (paper Section 5.1) after a 5 x 5 calibration.

The two baselines of the MPC case, both applying the teacher's commands to the learner as they are (clipped by the
learner): ``teacher_range``, the MPC bounded by the teacher's own range (what the paper's baseline does, since it
knows nothing of the learner); ``true_range``, the MPC bounded by the learner's true range (the commands the ideal
teacher sends, closed-loop on the learner's poses). Only the SCM learner depends on the seed: its exploration's
random samples and tie-breaks, and its start, moved by up to 1 mm and 1 mrad (:data:`START_JITTER`). The guided
policy uses its random generator only for exact ties, so without the jitter every seed would give the same run; the
jitter, far below anything physical, makes a sweep sample how the closed loop (its discrete choices: which cell,
which region) amplifies tiny differences, as another CPU's floating point does. The ideal teacher and the baselines
start at the world's start, are deterministic and are computed once per process.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import multiprocessing
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from bridge.core.errors import UsageError
from sim_learner.dynamics import MPC_TEACHER_V, MPC_TEACHER_W, LearnerModel, mpc_learner
from sim_learner.runs import DT, Progress, Run, mean_dev_last_half, mpc_teacher
from sim_learner.worlds import World, mpc_world
from transfer.domain import Bounds
from transfer.pairs import teacher_equivalent
from transfer.policy import EXPLORATIONS, make_policy
from transfer.step import TransferStep
from transfer.store import PairStore
from transfer.teacher.mpc import MpcResult, MpcTeacher
from transfer.teacher.unicycle import step as teacher_step

VEHICLE_RADIUS = 0.1  # m, for collision checks
START_JITTER = (1e-3, 1e-3)  # m, rad: the seed's offset of the SCM learner's start (module docstring)

ApplyFn = Callable[[NDArray[np.float64], MpcResult], tuple[NDArray[np.float64], NDArray[np.float64], str]]


@dataclass(frozen=True)
class MpcCase:
    """The MPC case's fixed parts: world, learner, both command boxes, the learner's true range on the teacher
    domain and the time limit."""

    world: World
    learner: LearnerModel
    teacher_bounds: Bounds
    learner_bounds: Bounds
    true_box: Bounds
    t_max: float


def mpc_case(quick: bool) -> MpcCase:
    """The paper's MPC case, shortened (world scaled by 0.6) when ``quick``."""
    learner = mpc_learner()
    LB = Bounds(learner.v_range, learner.w_range)
    lo, hi = learner.response(LB.lo), learner.response(LB.hi)
    # the learner's true command range mapped onto the teacher domain: its extremes are fixed points of h, so
    # the teacher equivalents of the learner's extreme commands are the same numbers
    true_box = Bounds((float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])))
    return MpcCase(mpc_world(0.6 if quick else 1.0), learner, Bounds(MPC_TEACHER_V, MPC_TEACHER_W), LB, true_box,
                   60.0 if quick else 120.0)


def closed_loop_mpc(name: str, world: World, mpc: MpcTeacher, bounds_fn: Callable[[], Bounds], apply_fn: ApplyFn,
                    t_max: float, progress: Progress | None = None, start: NDArray[np.float64] | None = None) -> Run:
    """Drive one vehicle along the world's path from ``start`` (default the world's): each tick the MPC (bounded
    by ``bounds_fn()``) proposes a teacher command, ``apply_fn(state, result)`` turns it into motion and returns
    (next_state, command, method)."""
    mpc.reset()
    run = Run(name)
    x = np.array(world.start if start is None else start, dtype=float)
    run.poses.append(x.copy())
    steps = int(round(t_max / DT))
    for k in range(steps):
        t0 = time.perf_counter()
        res = mpc.solve(x, world.path, bounds_fn(), world.obstacles)
        run.solve_s.append(time.perf_counter() - t0)
        run.failures += int(not res.ok)
        x, u_sent, method = apply_fn(x, res)
        run.poses.append(x.copy())
        run.commands.append(u_sent)
        run.teacher_cmds.append(res.u)
        run.methods.append(method)
        if world.collides(x[:2], VEHICLE_RADIUS):
            run.collided = True
        if progress is not None and k % 10 == 0:
            progress(world.progress(x[:2]), name)
        if world.reached(x):  # the one goal rule (transfer.mission)
            run.reached = True
            run.time_s = (k + 1) * DT
            break
    return run


# ------------------------------------------------------------------------------------------ the MPC case
@dataclass(frozen=True)
class References:
    """The seed-independent runs of the MPC case: the ideal teacher and the two baselines."""

    teacher: Run
    baseline_teacher_range: Run
    baseline_true_range: Run


_REFERENCES: dict[tuple[bool, str], References] = {}


def mpc_references(quick: bool, progress: bool = False, solver: str = "ipopt") -> References:
    """Ideal teacher (the teacher model under the MPC bounded by the learner's true range) and the two baselines
    (module docstring); deterministic, so computed once per process and shared by every seed."""
    if (quick, solver) not in _REFERENCES:
        _REFERENCES[quick, solver] = _compute_references(quick, progress, solver)
    return _REFERENCES[quick, solver]


def _compute_references(quick: bool, progress: bool, solver: str = "ipopt") -> References:
    case = mpc_case(quick)
    world, learner = case.world, case.learner
    mpc = mpc_teacher(solver)
    bar = Progress("refs") if progress else None

    def ideal(x, res):
        return teacher_step(x, res.u, DT), res.u, "teacher"

    def direct(x, res):
        return learner.step(x, res.u, DT), learner.clamp(res.u), "direct"

    teacher = closed_loop_mpc("teacher", world, mpc, lambda: case.true_box, ideal, case.t_max, bar)
    base_t_max = 2.5 * (teacher.time_s or case.t_max / 2)
    base = closed_loop_mpc("baseline", world, mpc, lambda: case.teacher_bounds, direct, base_t_max, bar)
    base_true = closed_loop_mpc("baseline_true", world, mpc, lambda: case.true_box, direct, base_t_max, bar)
    if bar:
        bar.done()
    return References(teacher, base, base_true)


def scm_start(world: World, seed: int, jitter: tuple[float, float] = START_JITTER) -> NDArray[np.float64]:
    """The SCM learner's start for a seed: the world's, moved uniformly within +-jitter (m in x and y, rad)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(2)[1])
    j = np.array([jitter[0], jitter[0], jitter[1]], dtype=float)
    return world.start.astype(float) + rng.uniform(-1.0, 1.0, 3) * j


def run_scm(seed: int, quick: bool, exploration: str = "guided",
            progress: Progress | None = None, solver: str = "ipopt", adapt: bool = False,
            calibrated: bool = False) -> tuple[Run, PairStore]:
    """The SCM learner from no pairs at all: the MPC bounded by the learned limits, each command mapped by the
    transfer step the station uses (:class:`transfer.step.TransferStep`: the policy explores by its own rule, never
    near an obstacle; the guided policy is steered by the teacher's plan), each control interval paired and added to
    the store. The seed drives the policy's random generator and the start's sub-millimetre jitter
    (:func:`scm_start`). ``adapt``: the store with change detection (the station's ``[transfer] adapt``), on a
    learner that does not change. ``calibrated``: the paper's calibrated start instead (its Jackal run): the 5 x 5
    grid of ``scmbridge calibrate`` driven first, each command for ``k_min`` control intervals, and commands at a
    driven limit mapped by the region just inside it (``[transfer] at_limit = "region"``)."""
    case = mpc_case(quick)
    world, learner = case.world, case.learner
    store = PairStore(case.learner_bounds, case.teacher_bounds, k_min=5, adapt=adapt)
    if calibrated:
        from sim_learner.primitives_sim import calibrate

        calibrate(learner, store, store.k_min * DT)
    step = TransferStep(make_policy(store, "scm", np.random.default_rng(seed), exploration=exploration,
                                    at_limit="region" if calibrated else "row"), dt=DT)

    regions: list[tuple[int, ...]] = []

    def scm(x, res):
        m = step.map(res.u, x, world, res.predicted)
        x1 = learner.step(x, m.u_L, DT)
        store.add(teacher_equivalent(x, x1, DT), m.u_L)
        regions.append(m.region)
        return x1, m.u_L, m.method

    run = closed_loop_mpc("scm", world, mpc_teacher(solver), lambda: store.limits.box, scm, case.t_max, progress,
                          scm_start(world, seed))
    run.regions = regions
    return run, store


def _run_figures(run: Run, world: World) -> dict:
    """Time, goal, last-half deviation and collision of one run."""
    return {"time_s": run.time_s, "reached_goal": run.reached, "dev_last_half_m": mean_dev_last_half(run, world),
            "collided": run.collided}


def _with_ratios(fig: dict, ref: dict) -> dict:
    """A run's figures with its time and last-half deviation as ratios to the ideal teacher's."""
    def ratio(num: float | None, den: float | None) -> float | None:
        return None if num is None or not den else float(num / den)

    return {**fig, "time_ratio": ratio(fig["time_s"], ref["time_s"]),
            "dev_ratio": ratio(fig["dev_last_half_m"], ref["dev_last_half_m"])}


def reference_figures(quick: bool, progress: bool = False, solver: str = "ipopt") -> dict:
    """The ideal teacher's and both baselines' figures (JSON-ready; seed-independent)."""
    refs = mpc_references(quick, progress, solver)
    world = mpc_case(quick).world
    teacher = _run_figures(refs.teacher, world)
    return {"teacher": teacher,
            "baselines": {"teacher_range": _with_ratios(_run_figures(refs.baseline_teacher_range, world), teacher),
                          "true_range": _with_ratios(_run_figures(refs.baseline_true_range, world), teacher)}}


def scm_figures(run: Run, store: PairStore, quick: bool) -> dict:
    """The SCM learner's figures (JSON-ready) without the ratios to the teacher."""
    case = mpc_case(quick)
    learned, true_box = store.limits.box, case.true_box
    sv, sw = true_box.span
    rel = [abs(learned.v[0] - true_box.v[0]) / sv, abs(learned.v[1] - true_box.v[1]) / sv,
           abs(learned.w[0] - true_box.w[0]) / sw, abs(learned.w[1] - true_box.w[1]) / sw]
    counts = run.method_counts()
    solve = np.array(run.solve_s) * 1e3
    return {**_run_figures(run, case.world),
            "perturb_share": counts["perturb"] / max(len(run.methods), 1),
            # guided "direct" anchored on the learned region (the paper's "direct" has no region)
            "direct_from_region": sum(1 for m, r in zip(run.methods, run.regions) if m == "direct" and r),
            "limits_rel_err": float(max(rel)),
            "learned_limits": learned.as_list(),
            "true_limits": true_box.as_list(),
            "method_counts": counts,
            "refined_pairs": len(store.refined()),
            "raw_pairs": store.raw_count,
            "mpc_solve_ms": {"median": float(np.median(solve)), "p95": float(np.percentile(solve, 95))},
            "mpc_failures": run.failures,
            # a fingerprint of every command sent: equal digests mean bit-identical runs (determinism checks)
            "commands_digest": hashlib.sha256(np.array(run.commands, dtype=float).tobytes()).hexdigest()[:16]}


def mpc_summary(seed: int, quick: bool, exploration: str, scm: dict, refs: dict) -> dict:
    """The JSON summary of one MPC experiment from the SCM learner's and the references' figures."""
    s = _with_ratios(scm, refs["teacher"])
    return {
        "experiment": "mpc",
        "quick": quick,
        "seed": seed,
        "exploration": exploration,
        "teacher_time_s": refs["teacher"]["time_s"],
        "teacher_dev_last_half_m": refs["teacher"]["dev_last_half_m"],
        "scm_time_s": s["time_s"],
        "scm_reached_goal": s["reached_goal"],
        "scm_dev_last_half_m": s["dev_last_half_m"],
        "scm_time_ratio": s["time_ratio"],
        "scm_dev_ratio": s["dev_ratio"],
        "perturb_share": s["perturb_share"],
        "collisions": {"teacher": refs["teacher"]["collided"], "scm": s["collided"],
                       **{f"baseline_{k}": b["collided"] for k, b in refs["baselines"].items()}},
        "baselines": refs["baselines"],
        **{k: s[k] for k in ("direct_from_region", "limits_rel_err", "learned_limits", "true_limits",
                             "method_counts", "refined_pairs", "raw_pairs", "mpc_solve_ms", "mpc_failures",
                             "commands_digest")},
    }


@dataclass(frozen=True)
class MpcOutcome:
    """One MPC experiment: its JSON-ready summary and the learned pair store (for the grid test)."""

    summary: dict
    store: PairStore


def mpc_experiment(seed: int = 0, quick: bool = False, out: Path | None = None, progress: bool = True,
            exploration: str = "guided", adapt: bool = False) -> MpcOutcome:
    """Paper Section 5.2: ideal teacher vs SCM learner vs the two baselines, no command pairs at the start."""
    case = mpc_case(quick)
    bar = Progress("mpc") if progress else None
    refs = reference_figures(quick, progress)
    scm_run, store = run_scm(seed, quick, exploration, bar, adapt=adapt)
    if bar:
        bar.done()
    summary = mpc_summary(seed, quick, exploration, scm_figures(scm_run, store, quick), refs)
    summary["adapt"] = adapt
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        r = mpc_references(quick)
        runs = [r.teacher, scm_run, r.baseline_teacher_range, r.baseline_true_range]
        np.savez_compressed(out / "mpc_runs.npz", **{k: v for run in runs for k, v in run.arrays().items()},
                            scm_methods=np.array(scm_run.methods), store=np.frombuffer(store.to_bytes(), np.uint8))
        from sim_learner.figures import mpc_figures

        summary["figures"] = mpc_figures(out, case.world, runs, store, case.true_box, case.teacher_bounds,
                                         case.learner_bounds)
    return MpcOutcome(summary, store)


# --------------------------------------------------------------------------------------------- the sweep
#: the per-seed figures a sweep summarises (all "lower is better"; the worst seed is the one with the largest)
SWEEP_FIGURES = ("scm_time_ratio", "scm_dev_ratio", "perturb_share", "limits_rel_err")


def parse_seeds(text: str) -> list[int]:
    """``"0-9"`` -> 0..9, ``"0,3,5"`` -> [0, 3, 5]; ranges and lists combine (``"0-2,7"``)."""
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            a, b = part.split("-", 1)
            lo, hi = int(a), int(b)
            if hi < lo:
                raise ValueError(f"seed range {part!r} is empty")
            seeds.extend(range(lo, hi + 1))
        else:
            seeds.append(int(part))
    if not seeds:
        raise ValueError(f"no seeds in {text!r}")
    return sorted(set(seeds))


def figure_stats(values: dict[int, float | None]) -> dict:
    """Median, min, max and worst seed of a per-seed figure (None: the run did not produce it, e.g. no goal:
    counted as worst, listed in ``missing``, and the median is None if they are half or more)."""
    seeds = sorted(values)
    arr = np.array([np.inf if values[s] is None else float(values[s]) for s in seeds])
    med = float(np.median(arr))
    finite = arr[np.isfinite(arr)]
    return {"median": med if math.isfinite(med) else None,
            "min": float(finite.min()) if finite.size else None,
            "max": float(arr.max()) if np.isfinite(arr.max()) else None,
            "worst_seed": seeds[int(np.argmax(arr))],
            "missing": [s for s in seeds if values[s] is None]}


def summarise_sweep(per_seed: Sequence[dict]) -> dict:
    """Statistics over the per-seed summaries of one exploration policy."""
    stats = {f: figure_stats({s["seed"]: s[f] for s in per_seed}) for f in SWEEP_FIGURES}
    stats["collided_seeds"] = [s["seed"] for s in per_seed if s["collisions"]["scm"]]
    stats["no_goal_seeds"] = [s["seed"] for s in per_seed if not s["scm_reached_goal"]]
    return stats


def _sweep_task(task: tuple) -> tuple[dict, bytes | None]:
    """One unit of a sweep, in a worker: the references' figures, or one seed's SCM figures and learned store."""
    if task[0] == "refs":
        return reference_figures(task[1], solver=task[2]), None
    _, seed, quick, exploration, solver, adapt = task
    run, store = run_scm(seed, quick, exploration, solver=solver, adapt=adapt)
    return scm_figures(run, store, quick), store.to_bytes()


def _compact(s: dict) -> dict:
    keys = ("seed", "scm_time_s", "scm_reached_goal", "scm_time_ratio", "scm_dev_last_half_m", "scm_dev_ratio",
            "perturb_share", "limits_rel_err", "method_counts", "direct_from_region", "refined_pairs",
            "commands_digest")
    return {**{k: s[k] for k in keys}, "collided": s["collisions"]["scm"]}


@dataclass(frozen=True)
class SweepOutcome:
    """A seed sweep: its JSON-ready summary and the pair store each (exploration, seed) learned."""

    summary: dict
    stores: dict[tuple[str, int], PairStore]


def sweep_mpc(seeds: Sequence[int], quick: bool = True, explorations: Sequence[str] = EXPLORATIONS,
              workers: int = 2, progress: bool = True, solver: str = "ipopt", adapt: bool = False,
              references: bool = True) -> SweepOutcome:
    """The MPC case for every seed and exploration policy: per-seed figures, their median, spread and worst seed,
    and the seed-independent references (ideal teacher, both baselines; ``references=False``: the stores alone, the
    summary empty). ``workers`` > 1: a process pool (spawned, at most 2; a script calling this needs the ``if
    __name__ == "__main__"`` guard); 1 runs in this process."""
    for e in explorations:
        if e not in EXPLORATIONS:
            raise ValueError(f"unknown exploration {e!r}; known: {', '.join(EXPLORATIONS)}")
    tasks: list[tuple] = ([("refs", quick, solver)] if references else []) + [
        ("scm", s, quick, e, solver, adapt) for e in explorations for s in seeds]
    workers = max(1, min(int(workers), 2))
    bar = Progress("sweep") if progress else None
    results: list[tuple[dict, bytes | None]] = []
    if workers == 1:
        for i, t in enumerate(tasks):
            results.append(_sweep_task(t))
            if bar:
                bar((i + 1) / len(tasks), str(t[1:]))
    else:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            for i, r in enumerate(pool.map(_sweep_task, tasks)):
                results.append(r)
                if bar:
                    bar((i + 1) / len(tasks), str(tasks[i][1:]))
    if bar:
        bar.done()
    stores = {(t[3], t[1]): PairStore.from_bytes(r[1]) for t, r in zip(tasks, results) if r[1] is not None}
    if not references:
        return SweepOutcome({}, stores)
    refs, policies = results[0][0], {}
    for e in explorations:
        per = [mpc_summary(t[1], quick, e, r[0], refs) for t, r in zip(tasks[1:], results[1:]) if t[3] == e]
        policies[e] = {"stats": summarise_sweep(per), "per_seed": [_compact(s) for s in per]}
    summary = {
        "experiment": "mpc-sweep",
        "quick": quick,
        "mpc_solver": solver,
        "adapt": adapt,
        "seeds": list(seeds),
        "references": {**refs, "note": "deterministic and seed-independent: the same for every seed"},
        "policies": policies,
    }
    return SweepOutcome(summary, stores)


# ------------------------------------------------------------------------------------------ the grid test
def grid_experiment(seed: int = 0, quick: bool = False, out: Path | None = None, progress: bool = True,
             store: PairStore | None = None, exploration: str = "guided") -> dict:
    """The paper's exhaustive test: a dense grid of teacher commands inside the learned limits, 0.1 s each, on
    the pairs an MPC run (``seed``, ``exploration``) learned, or on ``store``. The SCM region is where the paper's SC
    map (the ``scm`` mapper without the transfer's choice of map) has a region; every mapper is compared on that
    region, and ``transfer`` is what the station runs: the SC map or linear interpolation per command
    (:class:`transfer.choice.MapChoice`), with its own method counts."""
    if store is None:  # the seed's run alone: the grid needs its pairs, not the references (teacher, baselines)
        store = run_scm(seed, quick, exploration, bar := Progress("mpc") if progress else None)[1]
        if bar:
            bar.done()
    learner = mpc_learner()
    box = store.limits.box
    n = 25 if quick else 60
    gv = np.linspace(box.v[0], box.v[1], n)
    gw = np.linspace(box.w[0], box.w[1], n)
    V, W = np.meshgrid(gv, gw, indexing="ij")
    cmds = np.stack([V.ravel(), W.ravel()], axis=-1)
    x0 = np.array([0.0, 0.0, 0.0])
    target = teacher_step(x0, cmds, DT)
    names = ["scm", "identity", "affine", "barycentric", "transfer"]
    pos_err = {k: np.zeros(len(cmds)) for k in names}
    ang_err = {k: np.zeros(len(cmds)) for k in names}
    method = np.empty(len(cmds), dtype=object)
    transfer_method = np.empty(len(cmds), dtype=object)
    for name in names:
        # the grid maps every command once from one pose and learns nothing: no filling of holes
        opts: dict = {"fill_budget": 0.0} if exploration == "guided" else {}
        if name in ("scm", "transfer"):  # the paper's SC map alone, and the transfer's choice per command
            opts["choice"] = name == "transfer"
        pol = make_policy(store, "scm" if name == "transfer" else name, np.random.default_rng(seed),
                          exploration=exploration, **opts)
        for i, u in enumerate(cmds):
            m = pol.map(u)
            if name == "scm":
                method[i] = m.method
            elif name == "transfer":
                transfer_method[i] = m.method
            x1 = learner.step(x0, m.u_L, DT)
            pos_err[name][i] = np.hypot(*(x1[:2] - target[i, :2]))
            ang_err[name][i] = abs(math.remainder(x1[2] - target[i, 2], 2 * math.pi))
    region = method == "scm"

    def stats(a: NDArray[np.float64], mask: NDArray[np.bool_]) -> dict | None:
        if not mask.any():
            return None
        return {"median": float(np.median(a[mask])), "p95": float(np.percentile(a[mask], 95))}

    per_method = {}
    for meth in sorted(set(method.tolist()) | {"scm", "direct", "perturb"}):
        mask = method == meth
        per_method[meth] = {"count": int(mask.sum()), "scm_pos_err_m": stats(pos_err["scm"], mask),
                            "baseline_pos_err_m": stats(pos_err["identity"], mask)}
    summary = {
        "experiment": "grid",
        "quick": quick,
        "exploration": exploration,
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
        # the transfer's methods on the SCM region: how many of its commands the SC map serves there
        "transfer_methods_region": dict(Counter(transfer_method[region].tolist())) if region.any() else {},
        "baseline_region_median_pos_err_m_all": float(np.median(pos_err["identity"])),
    }
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "grid.npz", commands=cmds, method=method.astype(str),
                            method_transfer=transfer_method.astype(str),
                            **{f"pos_err_{k}": v for k, v in pos_err.items()},
                            **{f"ang_err_{k}": v for k, v in ang_err.items()})
        from sim_learner.figures import grid_figures

        summary["figures"] = grid_figures(out, store, cmds, n, method, pos_err, ang_err)
    return summary


#: the grid figures a seed sweep summarises: SCM / baseline median position error on the SCM region (the paper's
#: reading) and against the baseline over the whole grid, and the region's share of the grid
GRID_FIGURES = ("scm_to_baseline", "scm_to_baseline_all", "scm_region_fraction", "transfer_to_barycentric_median",
                "transfer_to_scm_p95")


def _ratio(g: dict, a: str, b: str, figure: str) -> float | None:
    """Mapper ``a``'s grid ``figure`` over mapper ``b``'s (None without an SCM region)."""
    x, y = g["mappers"][a][figure], g["mappers"][b][figure]
    return None if x is None or not y else x / y


def sweep_grid(seeds: Sequence[int], quick: bool = False, exploration: str = "guided", workers: int = 2,
               progress: bool = True) -> dict:
    """The grid test on the pairs each seed's MPC run learned (the runs in at most two worker processes): per-seed
    figures and their median, spread and worst seed (``figure_stats``)."""
    outcome = sweep_mpc(seeds, quick, [exploration], workers, progress, references=False)
    per_seed = []
    for seed in seeds:
        g = grid_experiment(seed, quick, None, False, outcome.stores[(exploration, seed)], exploration)
        scm = g["scm_region_median_pos_err_m"]
        per_seed.append({
            "seed": seed,
            "scm_to_baseline": None if scm is None else scm / g["baseline_median_pos_err_m"],
            "scm_to_baseline_all": None if scm is None else scm / g["baseline_region_median_pos_err_m_all"],
            "scm_region_fraction": g["scm_region_fraction"],
            "scm_region_median_pos_err_m": scm,
            # the transfer against the better of the two maps in each reading: barycentric's median, SCM's p95
            "transfer_to_barycentric_median": _ratio(g, "transfer", "barycentric", "region_median_pos_err_m"),
            "transfer_to_scm_p95": _ratio(g, "transfer", "scm", "region_p95_pos_err_m"),
            "refined_pairs": len(outcome.stores[(exploration, seed)].refined()),
        })
    return {"experiment": "grid-sweep", "quick": quick, "exploration": exploration, "seeds": list(seeds),
            "stats": {f: figure_stats({p["seed"]: p[f] for p in per_seed}) for f in GRID_FIGURES},
            "per_seed": per_seed}


def _common(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--out", type=Path, default=Path("out"), help="directory for figures and trajectories")
    ap.add_argument("--seed", type=int, default=0, help="the run's seed (default 0)")
    ap.add_argument("--policy", choices=list(EXPLORATIONS), default=None,
                    help="the exploration policy (default: guided; a sweep runs both unless one is named)")
    ap.add_argument("--quick", action="store_true", help="a shortened run (what the tests use)")


def arguments_mpc(ap: argparse.ArgumentParser) -> None:
    _common(ap)
    ap.add_argument("--seeds", default=None, help="a seed sweep, e.g. 0-9 or 0,3,5 (JSON of statistics)")
    ap.add_argument("--workers", type=int, default=2, help="sweep worker processes (at most 2)")
    ap.add_argument("--adapt", action="store_true",
                    help="the store with change detection ([transfer] adapt) on this learner, which does not change")


def arguments_grid(ap: argparse.ArgumentParser) -> None:
    _common(ap)
    ap.add_argument("--seeds", default=None,
                    help="the grid on the pairs of each seed's MPC run, e.g. 10-19 (JSON of statistics)")
    ap.add_argument("--workers", type=int, default=2, help="the MPC runs' worker processes (at most 2)")
    ap.add_argument("--store", type=Path, default=None,
                    help="test the pairs of this pair-store file (e.g. one a sweep wrote) instead of a run's")


def arguments_primitives(ap: argparse.ArgumentParser) -> None:
    _common(ap)


def _emit(summary: dict, t0: float) -> int:
    summary["wall_s"] = time.perf_counter() - t0
    json.dump(summary, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


def run_mpc(args: argparse.Namespace) -> int:
    """The paper's MPC case (Section 5.2): from no pairs at all, the ideal teacher, the SCM learner and two baseline
    learners follow the S-path with the teacher's MPC. --seeds 0-9 runs a seed sweep instead (at most two worker
    processes) and prints, for every claim figure, the median, the spread and the worst seed, per exploration
    policy. Prints one JSON summary; figures and trajectories go to --out."""
    t0 = time.perf_counter()
    if args.seeds is None:
        return _emit(mpc_experiment(args.seed, args.quick, args.out, exploration=args.policy or "guided",
                                    adapt=args.adapt).summary, t0)
    explorations = [args.policy] if args.policy else list(EXPLORATIONS)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        raise UsageError(f"--seeds: {exc}") from None
    outcome = sweep_mpc(seeds, args.quick, explorations, args.workers, adapt=args.adapt)
    summary = outcome.summary
    args.out.mkdir(parents=True, exist_ok=True)
    for (e, seed), store in outcome.stores.items():
        (args.out / f"pairs-{e}-{seed}.bin").write_bytes(store.to_bytes())
    summary["wall_s"] = time.perf_counter() - t0
    (args.out / "mpc_sweep.json").write_text(json.dumps(summary, indent=2) + "\n")
    return _emit(summary, t0)


def run_grid(args: argparse.Namespace) -> int:
    """The paper's exhaustive test: a dense grid of teacher commands inside the learned limits, each applied 0.1 s
    from the same pose to the teacher, the baseline, the SCM learner and each alternative mapper (on the pairs of a
    seed's run, or of --store). Prints one JSON summary; figures go to --out."""
    t0 = time.perf_counter()
    if args.seeds is not None:
        if args.store is not None:
            raise UsageError("--store and --seeds exclude each other")
        try:
            seeds = parse_seeds(args.seeds)
        except ValueError as exc:
            raise UsageError(f"--seeds: {exc}") from None
        return _emit(sweep_grid(seeds, args.quick, args.policy or "guided", args.workers), t0)
    store = PairStore.from_bytes(args.store.read_bytes()) if args.store is not None else None
    return _emit(grid_experiment(args.seed, args.quick, args.out, store=store, exploration=args.policy or "guided"), t0)


def run_primitives(args: argparse.Namespace) -> int:
    """The paper's motion-primitive case (Section 5.1) after a 5 x 5 calibration. Prints one JSON summary; figures
    go to --out."""
    from sim_learner.primitives_sim import run_primitives as primitives_experiment

    t0 = time.perf_counter()
    return _emit(primitives_experiment(args.seed, args.quick, args.out, exploration=args.policy or "guided"), t0)


__all__ = ["MpcOutcome", "SweepOutcome", "grid_experiment", "mpc_experiment", "sweep_grid", "sweep_mpc"]
