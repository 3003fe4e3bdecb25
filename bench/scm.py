"""``scmbridge bench scm``: build and evaluation cost of the SC rectangle map, one JSON object on stdout."""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.common import emit, summary_us


def _random_quad(rng: np.random.Generator) -> list[complex]:
    """A command-domain quadrilateral like those the mapping regions produce (v ~ [0, 0.6], omega ~ [-0.8, 0.8])."""
    while True:
        v0, v1 = sorted(rng.uniform(0.0, 0.6, 2))
        w0, w1 = sorted(rng.uniform(-0.8, 0.8, 2))
        if v1 - v0 < 0.1 or w1 - w0 < 0.2:
            continue
        j = 0.15 * rng.uniform(-1, 1, (4, 2)) * np.array([v1 - v0, w1 - w0])
        quad = [complex(v0, w0), complex(v1, w0), complex(v1, w1), complex(v0, w1)]
        quad = [q + complex(*d) for q, d in zip(quad, j)]
        from transfer.scm import is_simple_ccw

        if is_simple_ccw(quad):
            return quad


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--n", type=int, default=200, help="repetitions per measurement")
    ap.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    rng = np.random.default_rng(args.seed)

    t0 = time.perf_counter()
    from transfer.scm import QuadTransfer, RectangleMap, warmup

    warmup()
    warmup_s = time.perf_counter() - t0

    build, to1, to1k, from1, from1k, tbuild, tpoint, first = [], [], [], [], [], [], [], []
    err = 0.0
    for i in range(args.n):
        quad = _random_quad(rng)
        t = time.perf_counter()
        f = RectangleMap(quad)
        build.append(time.perf_counter() - t)
        p1 = np.array([complex(rng.uniform(0.05, 0.95), rng.uniform(0.05, 0.95))])
        w1 = f.from_unit_square(p1)
        t = time.perf_counter()
        f.to_unit_square(w1)  # the first inverse also builds the start table
        first.append(time.perf_counter() - t)
        t = time.perf_counter()
        s1 = f.to_unit_square(w1)
        to1.append(time.perf_counter() - t)
        t = time.perf_counter()
        f.from_unit_square(s1)
        from1.append(time.perf_counter() - t)
        if i % 10 == 0:
            pk = rng.uniform(0.0, 1.0, 1000) + 1j * rng.uniform(0.0, 1.0, 1000)
            t = time.perf_counter()
            wk = f.from_unit_square(pk)
            from1k.append(time.perf_counter() - t)
            t = time.perf_counter()
            sk = f.to_unit_square(wk)
            to1k.append(time.perf_counter() - t)
            err = max(err, float(np.max(np.abs(f.from_unit_square(sk) - wk))))
        learner = _random_quad(rng)
        t = time.perf_counter()
        qt = QuadTransfer(quad, learner)
        tbuild.append(time.perf_counter() - t)
        qt(w1)  # first point (builds the teacher's start table)
        t = time.perf_counter()
        qt(w1)
        tpoint.append(time.perf_counter() - t)

    build_plus_point = np.asarray(tbuild) + np.asarray(first)
    emit(
        {
            "build_us": summary_us(build),
            "to_unit_square_1_us": summary_us(to1),
            "to_unit_square_1000_us": summary_us(to1k),
            "from_unit_square_1_us": summary_us(from1),
            "from_unit_square_1000_us": summary_us(from1k),
            "first_inverse_us": summary_us(first),
            "transfer_build_us": summary_us(tbuild),
            "transfer_point_us": summary_us(tpoint),
            "transfer_build_plus_first_point_us": summary_us(build_plus_point),
            "roundtrip_max_err": err,
            "warmup_s": warmup_s,
            "n": args.n,
            "targets": {"build_us": 2000, "point_us": 50, "build_plus_point_us": 5000, "roundtrip_max_err": 1e-10},
        }
    )
    return 0
