"""A change spread to the cells not driven since (``transfer/store_spread.py``; docs/PAPER.md, "a learner that
changes"): once the change test re-learns a cell, the cells the robot has not driven since take what the re-driven
cells near them observed, provisionally, until their own pairs decide; nothing of it where nothing was re-learned.
Pure: the paper's cubic learner's true response, with a change that differs along the yaw-rate axis as a new floor's
does, and Gaussian noise on the teacher parts."""

from __future__ import annotations

import numpy as np

from sim_learner.dynamics import mpc_learner
from transfer.domain import Bounds
from transfer.paper import MPC_TEACHER_V, MPC_TEACHER_W
from transfer.store import PairStore

LEARNER = mpc_learner()
LB = Bounds(LEARNER.v_range, LEARNER.w_range)
TB = Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
#: the change: the teacher's yaw rate (normalised) moves by this much per yaw-rate column of the grid, from column 5
#: (none there): a response curve that changed shape, beyond change_tol at the grid's right-most columns, and differing
#: there by more than a shared change takes for one (transfer/store.py, "A shared change")
SLOPE = 0.012


def _change(j: float) -> float:
    return SLOPE * (j - 5.0)


def _drive(store: PairStore, rng: np.random.Generator, cells, visits: int, changed: bool,
           noise: float = 0.003) -> None:
    """``visits`` raw pairs in each of ``cells`` (in random order, at random points of each cell): the learner's true
    response, moved by :func:`_change` of the pair's own column where ``changed``."""
    gv, gw = store.grid
    order = [c for c in cells for _ in range(visits)]
    rng.shuffle(order)
    for i, j in order:
        l_n = (np.array([i, j]) + rng.uniform(0.05, 0.95, 2)) / np.array([gv, gw])
        u = LB.denormalise(l_n)
        t_n = TB.normalise(LEARNER.response(u)) + noise * rng.standard_normal(2)
        if changed:
            t_n[1] += _change(l_n[1] * gw - 0.5)
        store.add(TB.denormalise(t_n), u, stamp=float(store.raw_count))


def _learned(seed: int, spread: bool = True) -> tuple[PairStore, np.random.Generator]:
    rng = np.random.default_rng(seed)
    store = PairStore(LB, TB, adapt=True)
    store.spreading.set(spread)
    _drive(store, rng, [(i, j) for i in range(11) for j in range(11)], 30, changed=False)
    return store, rng


def test_a_cell_between_re_driven_ones_takes_its_own_change_before_the_robot_drives_there() -> None:
    """The robot drives two of the top-speed row's right-most columns on the changed learner (the change test
    re-learns both; their changes differ too much for a shared change); the column between them, not driven since,
    moves to its own change before it is driven (the mean of the two is not its change only by chance: the change is
    the same line), and a far cell takes nothing of the spread. Once driven, its own pairs decide: the spread is
    dropped. A save holds the refined pairs without it."""
    for seed in (1, 2, 3):
        store, rng = _learned(seed)
        before = store.cells.pub_T.copy()
        for c in [(10, 0), (10, 2)]:  # one after the other, as a bend is driven
            _drive(store, rng, [c], 12, changed=True)
        assert store.relearned == 2 and store.shifts.shared == 0 and store.spreading.count > 0, (seed, store.relearned)
        mid = (10, 1)
        err = abs(store.cells.pub_T[mid][1] - before[mid][1] - _change(1.0))
        assert err < 2 * store.move_tol < abs(_change(1.0)), (seed, err)  # where it stood: its whole change off
        assert not store.spreading.shift[10, 8].any() and not store.spreading.shift[2, 5].any()  # far: none of it
        saved = PairStore.from_bytes(store.to_bytes())
        own = store.cells.pub_T - store.shifts.prov - store.spreading.shift
        np.testing.assert_allclose(saved.cells.pub_T[mid], own[mid], atol=1e-12)
        _drive(store, rng, [mid], store.k_min, changed=True)
        assert not store.spreading.shift[mid].any(), seed


def test_nothing_is_spread_where_no_cell_is_re_learned() -> None:
    """No change (noise alone) or a change below the tolerance everywhere: no episode, no spread, and the store's
    refined pairs are the ones a store without it would hold (the spread's state is not read)."""
    for changed in (False, True):
        store, rng = _learned(4)
        cells = [(10, j) for j in range(4, 7)]  # the change there is within change_tol
        _drive(store, rng, cells, 20, changed=changed)
        assert store.relearned == 0 and store.spreading.count == 0 and not store.spreading.shift.any(), changed


def test_the_spread_is_off_by_default_and_turning_it_off_takes_the_spreads_back() -> None:
    """A store as the station makes it (``adapt`` alone) spreads nothing: the cell between the two re-driven ones
    stays where it stood. A store that spread and turns it off holds its refined pairs without the spreads."""
    store, rng = _learned(1, spread=False)
    assert not store.spreading.on
    before = store.cells.pub_T.copy()
    for c in [(10, 0), (10, 2)]:
        _drive(store, rng, [c], 12, changed=True)
    assert store.relearned == 2 and store.spreading.count == 0 and not store.spreading.shift.any()
    np.testing.assert_array_equal(store.cells.pub_T[10, 1], before[10, 1])
    store, rng = _learned(1)
    for c in [(10, 0), (10, 2)]:
        _drive(store, rng, [c], 12, changed=True)
    assert store.spreading.shift[10, 1].any()
    own = store.cells.pub_T - store.shifts.prov - store.spreading.shift
    store.spreading.set(False)
    assert not store.spreading.shift.any()
    np.testing.assert_allclose(store.cells.pub_T, own + store.shifts.prov, atol=1e-12)
