"""``scmbridge bench transfer``: per-command cost of the transfer policy with a full 11 x 11 set of refined pairs.

``map_hit_us``: commands whose mapping region is already built (cached QuadTransfer); ``map_rebuild_us``: commands
right after the region's pairs moved (the QuadTransfer is rebuilt); ``ingest_us``: adding one raw pair;
``map_stream_us``: the station's stream, one pair ingested and one command mapped; ``map_holes_us``: a store with holes
off the teacher's way, where the guided policy's hole search runs and finds nothing (the targets and the figures:
docs/BENCHMARKS.md, "The transfer step"). ``--adapt``: the same with the store's change detection and its refined
pairs following their recent pairs (``PairStore(adapt=True)``, the station's ``[transfer] adapt``). The stream comes
after the rebuilds, which moved the pairs of the cells they timed by 1 % of the range: a store with change detection
finds those cells changed and re-learns them from the stream's pairs, so its stream is the cost after a change.
``--choice``: the policy with the transfer's choice of map (the station's ``[transfer] map_choice``; docs/PAPER.md,
"The transfer's choice of map").
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.common import emit, summary_us

DT = 0.1


def _filled_store(rng: np.random.Generator, holes: frozenset[tuple[int, int]] = frozenset(), adapt: bool = False):
    """Five noisy visits of every cell of the paper's cubic learner (but ``holes``, left unvisited): a full 11 x 11
    set of refined pairs; returns the store, the learner model and the per-pair ingest times."""
    from sim_learner.dynamics import mpc_learner
    from transfer.domain import Bounds
    from transfer.pairs import teacher_equivalent
    from transfer.paper import MPC_TEACHER_V, MPC_TEACHER_W
    from transfer.store import PairStore

    model = mpc_learner()  # the paper's nonlinear learner, so regions are genuinely curved
    LB = Bounds(model.v_range, model.w_range)
    store = PairStore(LB, Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=5, adapt=adapt)
    x0 = np.zeros(3)
    ingest = []
    g = (np.arange(11) + 0.5) / 11
    for _ in range(5):
        for i, a in enumerate(g):
            for j, b in enumerate(g):
                if (i, j) in holes:
                    continue
                u = LB.clip(LB.denormalise([a, b]) + 0.01 * rng.standard_normal(2) * LB.span)
                ut = teacher_equivalent(x0, model.step(x0, u, DT), DT)
                t = time.perf_counter()
                store.add(ut, u)
                ingest.append(time.perf_counter() - t)
    return store, model, ingest


def _time_hits(policy, command, n: int) -> tuple[list[float], dict[str, int]]:
    """Warm every region once, then time the commands whose region was already built."""
    for _ in range(3 * n // 4):
        policy.map(command())
    hits, methods = [], {}
    for _ in range(n):
        u = command()
        builds = policy.mapper.builds
        t = time.perf_counter()
        m = policy.map(u)
        dtm = time.perf_counter() - t
        methods[m.method] = methods.get(m.method, 0) + 1
        if policy.mapper.builds == builds:
            hits.append(dtm)
    return hits, methods


def _time_rebuilds(policy, store, command, n: int) -> list[float]:
    """Time a command right after one pair of its region moved (its QuadTransfer must be rebuilt)."""
    TB, LB = store.teacher_bounds, store.learner_bounds
    out = []
    for _ in range(max(50, n // 10)):
        u = command()
        m = policy.map(u)
        if not m.region:
            continue
        cell = divmod(m.region[0], 11)
        tN = store.cells.pub_T[cell] + 0.01
        for _k in range(store.k_min * 2):
            store.add(TB.denormalise(tN), LB.denormalise(store.cells.pub_L[cell]))
        t = time.perf_counter()
        policy.map(u)
        out.append(time.perf_counter() - t)
    return out


def _time_stream(policy, store, model, command, rng, n: int) -> list[float]:
    """The station's real stream: one raw pair ingested and one command mapped per tick, rebuilds included."""
    from transfer.pairs import teacher_equivalent

    LB, x0, out = store.learner_bounds, np.zeros(3), []
    for _ in range(n):
        u = LB.clip(LB.denormalise(rng.random(2)))
        store.add(teacher_equivalent(x0, model.step(x0, u, DT), DT), u)
        c = command()
        t = time.perf_counter()
        policy.map(c)
        out.append(time.perf_counter() - t)
    return out


def _time_holes(rng: np.random.Generator, n: int, adapt: bool, choice: bool = False) -> list[float]:
    """A learned store with holes the teacher's commands do not lead to (the slowest speeds' hardest turns): the
    guided policy's fill budget is saved up and its hole search finds nothing, a station's steady state. Every
    command timed, searches included (their cost is amortised: the mean says it)."""
    from transfer.policy import make_policy

    store, _, _ = _filled_store(rng, frozenset((i, j) for i in range(3) for j in (0, 10)), adapt)
    policy = make_policy(store, "scm", rng=rng, choice=choice)
    _, _, T, _ = store.refined_arrays()
    lo, hi = np.quantile(T, 0.3, axis=0), T.max(axis=0)  # the faster commands, away from the holes
    out = []
    for _ in range(n):
        c = store.teacher_bounds.denormalise(lo + (hi - lo) * rng.random(2))
        t = time.perf_counter()
        policy.map(c)
        out.append(time.perf_counter() - t)
    return out


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--n", type=int, default=2000, help="commands per measurement")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--adapt", action="store_true",
                    help="the store with change detection ([transfer] adapt; docs/PAPER.md, 'a learner that changes')")
    ap.add_argument("--choice", action="store_true",
                    help="the transfer's choice of map ([transfer] map_choice; docs/PAPER.md, 'The transfer's choice "
                         "of map')")


def run(args: argparse.Namespace) -> int:

    from transfer.policy import make_policy
    from transfer.scm import warmup

    warmup()
    rng = np.random.default_rng(args.seed)
    store, model, ingest = _filled_store(rng, adapt=args.adapt)
    policy = make_policy(store, "scm", rng=rng, choice=args.choice)
    ids, _, T, _ = store.refined_arrays()
    lo, hi = T.min(axis=0), T.max(axis=0)

    def command() -> np.ndarray:
        return store.teacher_bounds.denormalise(lo + (hi - lo) * (0.1 + 0.8 * rng.random(2)))

    hits, methods = _time_hits(policy, command, args.n)
    rebuilds = _time_rebuilds(policy, store, command, args.n)
    mixed = _time_stream(policy, store, model, command, rng, args.n)
    holed = _time_holes(rng, args.n, args.adapt, args.choice)
    emit(
        {
            "map_hit_us": summary_us(hits, pcts=(99,)),
            "map_rebuild_us": summary_us(rebuilds, pcts=(99,)),
            "ingest_us": summary_us(ingest, pcts=(99,)),
            "map_stream_us": summary_us(mixed, pcts=(99,)),
            "map_holes_us": {**summary_us(holed, pcts=(99,)), "mean": float(np.mean(holed) * 1e6)},
            "refined_pairs": int(ids.size),
            "adapt": bool(args.adapt),
            "choice": bool(args.choice),
            "methods": methods,
            "targets": {"map_hit_median_us": 200, "map_p99_incl_rebuild_us": 5000},
        }
    )
    return 0
