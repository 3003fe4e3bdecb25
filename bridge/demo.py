"""``scmbridge demo``: the SC transfer at work on the paper's nonlinear learner, in-process.

It learns command pairs from the MPC case's learner (Eq. mpc_dynamicmodel_learner, Table 2 ranges) on an
11 x 11 grid of learner commands, then maps a set of teacher commands three ways (SCM, the identity baseline,
the barycentric alternative), drives the learner with each for 0.1 s from the same pose and prints how far each
lands from where the teacher would be. (The hardware-in-the-loop demo over Zenoh replaces this once the station
and the drivers land.)
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scmbridge demo", description=__doc__)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--commands", type=int, default=8, help="teacher commands to show")
    args = ap.parse_args(argv)

    from sim_learner.dynamics import MPC_TEACHER_V, MPC_TEACHER_W, mpc_learner
    from transfer.domain import Bounds
    from transfer.pairs import teacher_equivalent
    from transfer.policy import TransferPolicy
    from transfer.scm import warmup
    from transfer.store import PairStore
    from transfer.teacher.unicycle import step

    t0 = time.perf_counter()
    warmup()
    rng = np.random.default_rng(args.seed)
    learner = mpc_learner()
    LB = Bounds(learner.v_range, learner.w_range)
    TB = Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
    store = PairStore(LB, TB, k_min=5)
    dt = 0.1
    x0 = np.array([0.0, 0.0, 0.0])
    g = (np.arange(11) + 0.5) / 11
    for _ in range(5):  # five noisy visits of every cell: k_min = 5 makes each a refined pair
        for a in g:
            for b in g:
                u = LB.clip(LB.denormalise([a, b] + 0.02 * rng.standard_normal(2)))
                store.add(teacher_equivalent(x0, learner.step(x0, u, dt), dt), u)
    for u in LB.corners():  # the learner's extremes mark its limits on the teacher domain
        store.add(teacher_equivalent(x0, learner.step(x0, u, dt), dt), u)
    box = store.limits.box
    print(f"learned {len(store.refined())} refined pairs from {store.raw_count} raw pairs")
    print(f"learner limits on the teacher domain: v in [{box.v[0]:.3f}, {box.v[1]:.3f}] m/s, "
          f"omega in [{box.w[0]:.3f}, {box.w[1]:.3f}] rad/s (true: v [0.050, 0.300], omega "
          f"[{-math.pi / 16:.3f}, {math.pi / 12:.3f}])")
    policies = {name: TransferPolicy(store, name, seed=args.seed) for name in ("scm", "identity", "barycentric")}
    ids, _, T, _ = store.refined_arrays()
    lo, hi = T.min(axis=0), T.max(axis=0)
    print(f"\n{'teacher (v, w)':>18} | {'SCM learner cmd':>18} {'err mm':>7} | {'baseline err mm':>15} | "
          f"{'barycentric err mm':>18}")
    errs: dict[str, list[float]] = {k: [] for k in policies}
    for _ in range(args.commands):
        uT = TB.denormalise(lo + (hi - lo) * (0.1 + 0.8 * rng.random(2)))
        target = step(x0, uT, dt)
        row = {}
        for name, pol in policies.items():
            m = pol.map(uT)
            reached = learner.step(x0, m.u_L, dt)
            e = float(np.hypot(*(reached[:2] - target[:2]))) * 1e3
            errs[name].append(e)
            row[name] = (m, e)
        m, e = row["scm"]
        print(f"({uT[0]:6.3f}, {uT[1]:+6.3f}) | ({m.u_L[0]:6.3f}, {m.u_L[1]:+6.3f}) {e:7.3f} | "
              f"{row['identity'][1]:15.3f} | {row['barycentric'][1]:18.3f}")
    print("\nmedian position error after 0.1 s (mm): " + ", ".join(
        f"{k} {np.median(v):.3f}" for k, v in errs.items()))
    print(f"done in {time.perf_counter() - t0:.1f} s")
    sys.stdout.flush()
    return 0
