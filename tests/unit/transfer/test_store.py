"""The pair store's change detection (``PairStore(adapt=True)``; transfer/store.py, "A learner that changes"): noise
alone never re-learns a cell, a changed learner re-learns every cell it is driven in within a few pairs, the learned
limits shrink with it, and the store keeps all of it across a save. Pure: the paper's cubic learner's true response,
with Gaussian noise on the teacher parts where a test says so."""

from __future__ import annotations

import math
import zlib

import msgspec
import numpy as np
import pytest
from numpy.typing import NDArray

from sim_learner.dynamics import mpc_learner
from transfer.domain import Bounds
from transfer.paper import MPC_TEACHER_V, MPC_TEACHER_W
from transfer.store import PairStore

LEARNER = mpc_learner()
LB = Bounds(LEARNER.v_range, LEARNER.w_range)
TB = Bounds(MPC_TEACHER_V, MPC_TEACHER_W)


def _visit(store: PairStore, rng: np.random.Generator, visits: int, noise: float = 0.0, bias=(0.0, 0.0),
           cap_v: float | None = None, cells=None) -> None:
    """``visits`` raw pairs in every cell (or in ``cells``), in random order, at random points of each cell; the
    learner's true response, changed by a yaw-rate ``bias`` (rad/s) or a top-speed ``cap_v`` (m/s), with ``noise``
    (normalised teacher units) on the teacher part."""
    gv, gw = store.grid
    todo = [(i, j) for i in range(gv) for j in range(gw)] if cells is None else list(cells)
    order = [c for c in todo for _ in range(visits)]
    rng.shuffle(order)
    for i, j in order:
        l_n = (np.array([i, j]) + rng.uniform(0.05, 0.95, 2)) / np.array([gv, gw])
        u = LB.denormalise(l_n)
        r = LEARNER.response(u) + np.array(bias)
        if cap_v is not None:
            r[0] = min(r[0], cap_v)
        t = r + noise * TB.span * rng.standard_normal(2)
        store.add(t, u, stamp=float(store.raw_count))


def _relation_error(store: PairStore, cells, shift: float = 0.0) -> NDArray[np.float64]:
    """Per cell, how far its refined pair's teacher yaw rate is from what the learner (its yaw rate moved by
    ``shift``, normalised teacher units) does at the refined pair's learner part."""
    pub_T, pub_L = store.cells.pub_T, store.cells.pub_L
    return np.array([abs(pub_T[c][1] - TB.normalise(LEARNER.response(LB.denormalise(pub_L[c])))[1] - shift)
                     for c in cells])


@pytest.mark.parametrize("noise", [0.0, 0.01, 0.03])
def test_noise_alone_never_relearns_a_cell(noise: float) -> None:
    """3,630 pairs per run (30 in each of the 121 cells): no false alarm, whatever the link's noise (0.03 of the
    teacher's range per pair is 0.017 m/s and 0.047 rad/s, worse than any link measured: docs/RELIABILITY.md)."""
    rng = np.random.default_rng(7)
    store = PairStore(LB, TB, adapt=True)
    _visit(store, rng, 30, noise)
    assert store.relearned == 0
    assert store.raw_count == 121 * 30
    assert np.all(np.isnan(store.change.changed_at))


def test_a_changed_learner_relearns_the_cells_it_drives_in_and_the_paper_store_does_not() -> None:
    """A dragging wheel: every response turns 15 % of the yaw-rate range more to the left from one instant."""
    bias = 0.15 * (LB.w[1] - LB.w[0])
    shift = bias / TB.span[1]  # what the refined pairs' teacher yaw rate must move by (normalised)
    driven = [(10, j) for j in range(2, 9)] + [(6, 5), (3, 5)]
    stores = {}
    for adapt in (True, False):
        rng = np.random.default_rng(3)
        store = PairStore(LB, TB, adapt=adapt)
        _visit(store, rng, 40, noise=0.005)  # a well-learned store: 40 pairs a cell
        before = store.cells.pub_T.copy()
        _visit(store, rng, 10, noise=0.005, bias=(0.0, bias), cells=driven)
        stores[adapt] = (store, before)
    store, before = stores[True]
    assert store.relearned == len(driven)  # each once: a re-learned cell holds only the new relation
    # its refined pair holds the changed relation (it may sit elsewhere in the cell: it follows the recent pairs)
    assert np.all(_relation_error(store, driven, shift) < 0.006), (_relation_error(store, driven, shift), shift)
    assert all(not np.isnan(store.change.changed_at[c]) for c in driven)
    untouched = np.ones(store.grid, dtype=bool)
    for c in driven:
        untouched[c] = False
    assert np.all(np.isnan(store.change.changed_at[untouched]))
    paper, before = stores[False]
    moved_paper = np.array([paper.cells.pub_T[c][1] - before[c][1] for c in driven])
    assert paper.relearned == 0 and np.all(moved_paper < 0.3 * shift)  # 10 new pairs against 40 old ones


def test_a_change_below_the_tolerance_is_followed_by_the_refined_pairs_without_a_relearning() -> None:
    """A yaw-rate bias of 1 % of the teacher's range (half ``change_tol``: the change test does not see it, as a new
    floor's on the cells a mission drives): after 8 pairs in each driven cell its refined pair is within
    ``move_tol`` (and the pairs' noise) of the changed learner, where the paper's store's is off by the whole change.
    (The top row's cells weigh about 10 pairs in their recent mean: their steep speed response is noise to their
    linear slope.)"""
    shift = 0.01
    driven = [(10, j) for j in range(2, 9)] + [(6, 5), (3, 5)]
    err = {}
    for adapt in (True, False):
        rng = np.random.default_rng(3)
        store = PairStore(LB, TB, adapt=adapt)
        _visit(store, rng, 40, noise=0.002)
        assert np.all(_relation_error(store, driven) < 0.006)
        _visit(store, rng, 8, noise=0.002, bias=(0.0, shift * TB.span[1]), cells=driven)
        assert store.relearned == 0
        err[adapt] = _relation_error(store, driven, shift)
    assert np.all(err[True] < 0.006), err
    assert np.all(err[False] > 0.008), err


@pytest.mark.parametrize("noise", [0.0, 0.01, 0.03])
def test_with_no_change_the_refined_pairs_that_follow_the_recent_pairs_are_as_near_the_learner_as_the_papers(
        noise: float) -> None:
    """With ``adapt`` a refined pair follows its cell's recent pairs, whose mean weighs as many pairs as keep its
    noise within ``move_tol`` / ``TRACK_SIGMAS``: on a noisy link it is no further from the learner than the mean of
    every pair (the paper's store), and moves no more often."""
    err, revision = {}, {}
    for adapt in (True, False):
        store = PairStore(LB, TB, adapt=adapt)
        _visit(store, np.random.default_rng(5), 60, noise=noise)
        cells = list(zip(*np.nonzero(store.cells.pub_version > 0)))
        assert len(cells) == 121
        err[adapt], revision[adapt] = _relation_error(store, cells), store.revision
    assert np.median(err[True]) <= 1.25 * np.median(err[False]) + 0.0005, err
    assert np.max(err[True]) <= 1.25 * np.max(err[False]) + 0.001, err
    assert revision[True] <= revision[False]


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_a_refined_pair_that_follows_its_recent_pairs_keeps_the_learner_part_of_every_pair(noise: float) -> None:
    """With ``adapt`` a cell's relation follows its recent pairs on the teacher axes only: its refined pair's learner
    part stays the mean of every pair of the cell (within ``move_tol``), as in the paper, wherever the robot drove
    last (a refined pair that moved to the recent pairs' learner part bunched the map's triangles: docs/PAPER.md,
    "a learner that changes"); a change below the tolerance still moves its teacher part (the test above)."""
    store = PairStore(LB, TB, adapt=True)
    rng = np.random.default_rng(11)
    _visit(store, rng, 30, noise=noise)
    corner = [(i, j) for i in range(11) for j in range(11)]
    for c in corner:  # the last pairs of each cell all in one corner of it
        for _ in range(10):
            u = LB.denormalise((np.array(c) + rng.uniform(0.05, 0.2, 2)) / 11)
            store.add(LEARNER.response(u) + noise * TB.span * rng.standard_normal(2), u)
    mean_L = store.cells.sum_L / store.cells.count[..., None]
    assert np.max(np.abs(store.cells.pub_L - mean_L)) <= store.move_tol


def test_a_change_two_cells_share_moves_the_cells_not_yet_driven_until_their_own_pairs_decide() -> None:
    """A dragging wheel seen in two cells: every other configured cell's refined pair moves by their change at once
    (for now), before the robot drives there. A cell driven after it with the wheel still dragging confirms it (the
    change test re-learns it); a cell whose learner did not change (here: driven with the wheel mended) takes its
    cluster's mean back after k_min pairs. A save holds the refined pairs without the provisional shifts."""
    bias = 0.15 * (LB.w[1] - LB.w[0])
    shift = bias / TB.span[1]
    rng = np.random.default_rng(3)
    store = PairStore(LB, TB, adapt=True)
    _visit(store, rng, 40, noise=0.005)
    before = store.cells.pub_T.copy()
    first = [(10, 1), (10, 0)]
    for c in first:
        _visit(store, rng, 10, noise=0.005, bias=(0.0, bias), cells=[c])
    assert store.relearned == 2 and store.shifts.shared == 1
    others = [(i, j) for i in range(11) for j in range(11) if (i, j) not in first]
    moved = np.array([store.cells.pub_T[c][1] - before[c][1] for c in others])
    assert np.all(np.abs(moved - shift) < 0.006), moved
    assert np.all(np.isnan([store.change.changed_at[c] for c in others]))  # provisional: not a re-learning
    saved = PairStore.from_bytes(store.to_bytes())
    np.testing.assert_allclose(saved.cells.pub_T[5, 5], before[5, 5], atol=1e-12)
    # the wheel still drags where the robot drives next: the cell re-learns from its own pairs, near the shift
    _visit(store, rng, 10, noise=0.005, bias=(0.0, bias), cells=[(6, 5)])
    assert store.change.changes[6, 5] == 1 and abs(store.cells.pub_T[6, 5][1] - before[6, 5][1] - shift) < 0.006
    # mended: a cell driven without the bias revokes the shift (its mean again) and is not re-learned
    _visit(store, rng, 10, noise=0.005, cells=[(3, 5)])
    assert store.change.changes[3, 5] == 0 and not store.shifts.prov[3, 5].any()
    assert abs(store.cells.pub_T[3, 5][1] - before[3, 5][1]) < 0.006


def test_a_sagging_battery_shrinks_the_learned_top_speed() -> None:
    rng = np.random.default_rng(5)
    store = PairStore(LB, TB, adapt=True)
    top = [(10, j) for j in range(11)]
    for _ in range(20):  # the top speed itself, where the learned limit is measured
        for j in range(11):
            u = LB.denormalise(np.array([1.0, (j + 0.5) / 11]))
            store.add(LEARNER.response(u), u)
    _visit(store, rng, 20)
    v_hi = store.limits.box.v[1]
    assert v_hi == pytest.approx(LB.v[1], abs=1e-9)
    cap = 0.7 * LB.v[1]
    for _ in range(10):
        for j in range(11):
            u = LB.denormalise(np.array([1.0, (j + 0.5) / 11]))
            r = LEARNER.response(u)
            store.add(np.array([min(r[0], cap), r[1]]), u)
    assert store.relearned >= 1
    assert store.limits.box.v[1] == pytest.approx(cap, abs=1e-6)  # the limit shrank to what the learner now does
    assert all(store.cells.pub_T[c][0] < (cap - TB.v[0]) / TB.span[0] + 1e-6
               for c in top if store.change.changed_at[c] >= 0)


def test_the_change_detection_survives_a_save_and_a_version_1_store_loads() -> None:
    rng = np.random.default_rng(9)
    store = PairStore(LB, TB, adapt=True)
    _visit(store, rng, 12, noise=0.01)
    _visit(store, rng, 8, bias=(0.0, 0.07), cells=[(10, 5)])
    again = PairStore.from_bytes(store.to_bytes())
    assert again.adapt and again.relearned == store.relearned == 1 and again.raw_count == store.raw_count
    for name in ("sum_LL", "sum_TL", "recent_T", "recent_L", "recent_n", "pub_T", "count"):
        np.testing.assert_array_equal(getattr(again.cells, name), getattr(store.cells, name), err_msg=name)
    for name in ("resid", "noise2"):
        np.testing.assert_array_equal(getattr(again.change, name), getattr(store.change, name), err_msg=name)
    np.testing.assert_array_equal(np.isnan(again.change.changed_at), np.isnan(store.change.changed_at))
    # a store written before change detection (schema 1): loads, with the same refined pairs and no history
    raw = msgspec.msgpack.decode(store.to_bytes()[12:])
    for k in ("sum_LL", "sum_TL", "adapt", "relearned", "added", "changed_at", "resid", "noise2", "recent_T",
              "recent_L", "recent_n"):
        raw.pop(k)
    raw["schema_version"] = 1
    payload = msgspec.msgpack.encode(raw)
    old = PairStore.from_bytes(b"SCMPAIRS" + zlib.crc32(payload).to_bytes(4, "little") + payload)
    np.testing.assert_array_equal(old.cells.pub_T, store.cells.pub_T)
    assert not old.adapt and old.raw_count == int(store.cells.count.sum()) and old.relearned == 0


def test_each_cells_change_count_and_time_survive_a_save_and_a_version_2_store_loads_with_them() -> None:
    """Schema 3 keeps how often each cell was re-learned beside when (``pairs show`` names them); a store written by
    schema 2 (a change time per cell, no count) loads with a count of 1 where it has a time."""
    rng = np.random.default_rng(9)
    store = PairStore(LB, TB, adapt=True)
    _visit(store, rng, 12, noise=0.01)
    _visit(store, rng, 8, bias=(0.0, 0.07), cells=[(10, 5)])
    _visit(store, rng, 8, bias=(0.0, 0.0), cells=[(10, 5)])  # and back: the cell changed twice
    assert store.change.changes[10, 5] == 2 and store.change.changes.sum() == 2 == store.relearned
    (c,) = store.changed_cells()
    assert (c.id, c.count, c.at) == (115, 2, store.change.changed_at[10, 5])
    again = PairStore.from_bytes(store.to_bytes())
    np.testing.assert_array_equal(again.change.changes, store.change.changes)
    assert again.changed_cells() == store.changed_cells()
    raw = msgspec.msgpack.decode(store.to_bytes()[12:])
    raw.pop("changes")
    raw["schema_version"] = 2
    payload = msgspec.msgpack.encode(raw)
    old = PairStore.from_bytes(b"SCMPAIRS" + zlib.crc32(payload).to_bytes(4, "little") + payload)
    assert old.changed_cells() == [type(c)(115, 1, c.at)] and old.relearned == 2


def test_a_cell_whose_pairs_scatter_is_not_relearned_over_and_over_and_still_sees_a_real_change() -> None:
    """A learner whose response depends on its history (an acceleration limit that binds, as ``sim drift
    --scenario payload``): in one cell its pairs scatter +-0.04 of the teacher's range about the relation, far more
    than elsewhere. The store re-learns that cell at most once or twice (then it has its own noise estimate and tests
    against it) instead of over and over, and a real change there (0.15 of the range) is still found."""
    rng = np.random.default_rng(11)
    store = PairStore(LB, TB, adapt=True)
    _visit(store, rng, 20, noise=0.005)
    cell = (10, 5)

    def scattered(n: int, shift: float = 0.0) -> None:
        for _ in range(n):
            l_n = (np.array(cell) + rng.uniform(0.05, 0.95, 2)) / 11
            u = LB.denormalise(l_n)
            lag = rng.choice((-1.0, 1.0)) * 0.04 * rng.uniform(0.5, 1.0, 2)
            store.add(LEARNER.response(u) + (lag + np.array([0.0, shift])) * TB.span, u)

    scattered(300)
    assert store.change.changes[cell] <= 2, store.change.changes[cell]
    assert store.relearned == store.change.changes[cell]  # no other cell
    before = store.change.changes[cell]
    scattered(20, shift=0.15)
    assert store.change.changes[cell] == before + 1


def test_the_learned_curvatures_survive_a_save_and_a_version_3_store_loads_without_them() -> None:
    """Schema 4 keeps the yaw-rate sides' curvature sums (a learner that cannot turn in place); a store written by
    schema 3 loads with none (its curvatures are learned again from its first full-lock pairs); a negative count is
    refused."""
    store = PairStore(LB, TB, k_min=1)
    for v in (0.05, 0.1, 0.2):
        store.add([2 * v, 0.6 * 2 * v], [v, LB.w[1]])
    k = store.limits.learned_curvature()
    assert k[1] == pytest.approx(0.6) and math.isinf(k[0])
    again = PairStore.from_bytes(store.to_bytes())
    assert again.limits.learned_curvature() == k
    np.testing.assert_array_equal(again.limits.turn_n, store.limits.turn_n)
    raw = msgspec.msgpack.decode(store.to_bytes()[12:])
    for name in ("turn_vw", "turn_vv", "turn_n"):
        raw["limits"].pop(name)
    raw["schema_version"] = 3
    payload = msgspec.msgpack.encode(raw)
    old = PairStore.from_bytes(b"SCMPAIRS" + zlib.crc32(payload).to_bytes(4, "little") + payload)
    assert all(math.isinf(x) for x in old.limits.learned_curvature())
    raw = msgspec.msgpack.decode(store.to_bytes()[12:])
    raw["limits"]["turn_n"] = [0, -1]
    payload = msgspec.msgpack.encode(raw)
    with pytest.raises(ValueError, match="non-finite or negative"):
        PairStore.from_bytes(b"SCMPAIRS" + zlib.crc32(payload).to_bytes(4, "little") + payload)


def test_change_detection_is_switched_with_the_limits_memory_whatever_the_store_was_saved_with() -> None:
    """A station's configuration decides, not the file (``set_adapt``): a store saved without change detection
    reloaded with it keeps a learned limit as a recency-weighted mean, and the other way round the paper's mean."""
    saved = PairStore.from_bytes(PairStore(LB, TB).to_bytes())
    assert not saved.adapt and saved.limits.memory == 0
    saved.set_adapt(True)
    assert saved.adapt and saved.limits.memory == PairStore(LB, TB, adapt=True).limits.memory == 4 * saved.k_min
    saved.set_adapt(False)
    assert not saved.adapt and saved.limits.memory == 0
