"""``scmbridge bench transfer``: per-command cost of the transfer policy with a full 11 x 11 set of refined pairs.

``map_hit_us``: commands whose mapping region is already built (cached QuadTransfer); ``map_rebuild_us``: commands
right after the region's pairs moved (the QuadTransfer is rebuilt); ``ingest_us``: adding one raw pair.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from bridge.bench.common import emit, summary_us


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scmbridge bench transfer", description=__doc__)
    ap.add_argument("--n", type=int, default=2000, help="commands per measurement")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    from sim_learner.dynamics import mpc_learner
    from transfer.domain import Bounds
    from transfer.pairs import teacher_equivalent
    from transfer.policy import TransferPolicy
    from transfer.scm import warmup
    from transfer.store import PairStore

    warmup()
    rng = np.random.default_rng(args.seed)
    model = mpc_learner()  # the paper's nonlinear learner, so regions are genuinely curved
    LB = Bounds(model.v_range, model.w_range)
    TB = Bounds((0.05, 0.6), (-math.pi / 4, math.pi / 4))
    store = PairStore(LB, TB, k_min=5)
    dt = 0.1
    x0 = np.zeros(3)


    ingest = []
    g = (np.arange(11) + 0.5) / 11
    for _ in range(5):
        for a in g:
            for b in g:
                u = LB.denormalise([a, b]) + 0.01 * rng.standard_normal(2) * LB.span
                u = LB.clip(u)
                ut = teacher_equivalent(x0, model.step(x0, u, dt), dt)
                t = time.perf_counter()
                store.add(ut, u)
                ingest.append(time.perf_counter() - t)
    policy = TransferPolicy(store, "scm", rng=rng)
    ids, _, T, _ = store.refined_arrays()
    lo, hi = T.min(axis=0), T.max(axis=0)

    def command() -> np.ndarray:
        return TB.denormalise(lo + (hi - lo) * (0.1 + 0.8 * rng.random(2)))

    # warm every region once, then time cache hits
    for _ in range(3 * args.n // 4):
        policy.map(command())
    hits, methods = [], {}
    for _ in range(args.n):
        u = command()
        builds = policy.mapper.builds
        t = time.perf_counter()
        m = policy.map(u)
        dtm = time.perf_counter() - t
        methods[m.method] = methods.get(m.method, 0) + 1
        if policy.mapper.builds == builds:
            hits.append(dtm)
    rebuilds = []
    for _ in range(max(50, args.n // 10)):
        u = command()
        m = policy.map(u)
        if not m.region:
            continue
        # move one pair of the region, so its QuadTransfer must be rebuilt on the next command
        cell = divmod(m.region[0], 11)
        tN = store.pub_T[cell] + 0.01
        for _k in range(store.k_min * 2):
            store.add(TB.denormalise(tN), LB.denormalise(store.pub_L[cell]))
        t = time.perf_counter()
        policy.map(u)
        rebuilds.append(time.perf_counter() - t)
    # the station's real stream: one raw pair ingested and one command mapped per tick, rebuilds included
    mixed = []
    for _ in range(args.n):
        u = LB.clip(LB.denormalise(rng.random(2)))
        store.add(teacher_equivalent(x0, model.step(x0, u, dt), dt), u)
        c = command()
        t = time.perf_counter()
        policy.map(c)
        mixed.append(time.perf_counter() - t)
    emit(
        {
            "map_hit_us": summary_us(hits, pcts=(99,)),
            "map_rebuild_us": summary_us(rebuilds, pcts=(99,)),
            "ingest_us": summary_us(ingest, pcts=(99,)),
            "map_stream_us": summary_us(mixed, pcts=(99,)),
            "refined_pairs": int(ids.size),
            "methods": methods,
            "targets": {"map_hit_median_us": 200, "map_p99_incl_rebuild_us": 5000},
        }
    )
    return 0
