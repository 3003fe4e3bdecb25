"""The guided policy's search for a hole of the map, as a state machine of short steps (pure: no I/O, no clock).

A hole search (:class:`transfer.policy.GuidedPolicy`, "Filling the map's holes") maps a few dozen slowed teacher
commands on the linear map and then checks its best ``FILL_CHECKS`` candidates on the SC map itself, each of which
may build a quadrilateral's SC map: done at once it costs several commands' worth of CPU in one command, the tail
of a station's tick. :func:`hole_search` is the same search cut into steps: a generator that yields after each
stage (the ranking of the slowed speeds and of their yaw rates, ``RANK_ROWS`` commands a step, then each SC map
built and each map of each check), so that its
caller runs one step per command and uses the result on a later one (:meth:`transfer.policy.GuidedPolicy._fill`;
a station runs the step after the command, :meth:`transfer.policy.GuidedPolicy.search_step`), or all of it at once
(:func:`run_search`). The commands in between are served as if no search were running; the
result names a cell, which the caller checks is still a hole when it is used.

The search works on the teacher command it began with and on the store as each step finds it: a step never holds
a stale piece of the store across a yield except the candidates' ranking, which the checks re-read against the
store (a candidate whose cell was learned meanwhile is skipped).
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from transfer.store import PairStore

#: how many of a hole search's best candidates (ranked on the linear map) are mapped with the mapper itself, the
#: best of them on it taken (each costs up to two maps)
FILL_CHECKS = 3

#: slowed commands a step of the ranking maps on the linear map (each outside the learned region costs an estimate)
RANK_ROWS = 8
#: what a finished search gives: the hole's cell and the burst's first learner command, or None (no hole)
Hole = tuple[tuple[int, int], NDArray[np.float64]] | None
#: a running search: yields between its steps, returns the :data:`Hole`
Search = Generator[None, None, Hole]


class Searcher(Protocol):
    """What a search reads and sets of its policy (:class:`transfer.policy.GuidedPolicy`)."""

    store: PairStore
    mapper: Any
    _speeds: NDArray[np.float64]
    _served: int
    _search_after: int

    def _unperturbed(self, t: NDArray[np.float64], t_n: NDArray[np.float64]) -> tuple: ...

    def _unperturbed_many(self, ts: NDArray[np.float64], *, linear: bool = False) -> tuple: ...

    def _at_speed(self, t: NDArray[np.float64], v_n: float, s: float) -> NDArray[np.float64] | None: ...

    def _at_learner_speed(self, u: NDArray[np.float64], v_n: float) -> NDArray[np.float64]: ...


def hole_search(policy: Searcher, t: NDArray[np.float64]) -> Search:
    """Where a new burst goes (:class:`transfer.policy.GuidedPolicy`, "Filling the map's holes"): along the teacher's
    command ``t`` slowed by s (1 down to ``fill_depth``, no slower than the learned speed limit), the learner command
    for speed ``s * v_T`` at curvature ``omega_T / v_T``; among those in unconfigured cells, a cell an earlier burst
    began first, else the one whose teacher command ``s * u_T`` is farthest from every refined pair (normalised
    teacher units: the map's biggest hole on the teacher's way). Returns (cell, learner command), or None.

    The candidates are ranked on the linear map of the same triangles (every slowed speed, and the yaw rate where
    that speed's row of cells has a hole: no SC map is built for a guess); the best ``FILL_CHECKS`` of them are then
    mapped with the mapper itself, and the best of those in an unconfigured cell on it is taken (ranked again with
    that cell). One that found nothing makes the next wait as many commands as it tried speeds and yaw rates
    (the policy's ``_search_after``). Yields after each stage and each SC map (module docstring)."""
    t = np.array(t, dtype=float)
    store = policy.store
    tb, lb = store.teacher_bounds, store.learner_bounds
    gv = store.grid[0]
    speeds = policy._speeds
    slowed = t * speeds[:, None]
    below = np.flatnonzero(tb.normalise(slowed)[:, 0] < store.limits.lo[0])  # no slower than the speed limit
    n = int(below[0]) if below.size else len(slowed)
    # ranked on the linear map (every slowed command at once, no SC map built), then the yaw rate at the
    # teacher's speed where that speed's row of cells has a hole
    v_n = np.empty(n)
    for a in range(0, n, RANK_ROWS):
        if a:
            yield
        rows_l = policy._unperturbed_many(slowed[a:min(a + RANK_ROWS, n)], linear=True)[0]
        v_n[a:a + RANK_ROWS] = lb.normalise(rows_l)[:, 0]
    rows = np.minimum((v_n * gv).astype(int), gv - 1)
    open_ = [i for i in range(n) if not store.cells.pub_version[rows[i]].all()]
    cost = n + len(open_)
    ranked: list[tuple[tuple[bool, float], int]] = []
    if open_:
        s = speeds[open_]
        yaw = np.stack([np.full(len(open_), t[0]), t[1] * s], axis=1)
        u_w, methods = np.empty((len(open_), 2)), []
        for a in range(0, len(open_), RANK_ROWS):
            yield
            u_w[a:a + RANK_ROWS], got = policy._unperturbed_many(yaw[a:a + RANK_ROWS], linear=True)
            methods += got
        _, _, T, _ = store.refined_arrays()
        for j, i in enumerate(open_):
            if methods[j] == "direct":  # no learned region for that yaw rate (as _at_speed)
                continue
            cell = store.cell_of(policy._at_learner_speed(u_w[j], v_n[i]))
            if store.is_configured(cell):
                continue
            ts_n = tb.normalise(slowed[i])
            ranked.append(((bool(store.cells.count[cell] > 0),
                            float(np.min(np.hypot(*(T - ts_n).T))) if len(T) else 0.0), i))
    ranked.sort(key=lambda e: e[0], reverse=True)  # stable: of equal keys the fastest first
    best: tuple[tuple[bool, float], tuple[int, int], NDArray[np.float64]] | None = None
    for key, i in sorted(ranked[:FILL_CHECKS], key=lambda e: e[1]):  # the best few, on the map itself
        yield
        yield from _prepared(policy, tb.normalise(slowed[i]))
        v = float(lb.normalise(policy._unperturbed(slowed[i], tb.normalise(slowed[i]))[0])[0])
        yield
        yield from _prepared(policy, tb.normalise(np.array([t[0], t[1] * speeds[i]])))
        u = policy._at_speed(t, v, float(speeds[i]))
        if u is None or store.is_configured(cell := store.cell_of(u)):
            continue
        key = (bool(store.cells.count[cell] > 0), key[1])
        if best is None or key > best[0]:
            best = (key, cell, u)
    if best is None:
        policy._search_after = policy._served + cost
        return None
    return best[1], best[2]


def _prepared(policy: Searcher, t_n: NDArray[np.float64]) -> Generator[None, None, None]:
    """A step of its own for building the SC map the next map of ``t_n`` (normalised teacher units) needs, when it
    is not built yet (:meth:`transfer.mappers.ScmMapper.prepare`): the build and the map are then two steps."""
    prepare = getattr(policy.mapper, "prepare", None)
    if prepare is not None and prepare(t_n):
        yield


def run_search(search: Search) -> Hole:
    """A search run to its end at once: its :data:`Hole`."""
    while True:
        try:
            next(search)
        except StopIteration as done:
            return done.value


__all__ = ["FILL_CHECKS", "RANK_ROWS", "Searcher", "Hole", "Search", "hole_search", "run_search"]
