"""The pairs and their grid (transfer/store_cells.py): a cell's sums give its mean and slope sums, its ring holds its
last raw pairs oldest first, and a re-learned cell keeps exactly the pairs it is given."""

from __future__ import annotations

import numpy as np
import pytest

from transfer.store_cells import CellSums


def test_a_cell_sums_its_pairs_and_its_ring_holds_the_last_ones_oldest_first() -> None:
    cells = CellSums((3, 4), k_min=2, recent=3)
    pairs = [(np.array([0.1 * k, 0.2]), np.array([0.05 * k, 0.3])) for k in range(1, 6)]
    for k, (t, l) in enumerate(pairs):
        assert cells.take((1, 2), t, l) == k + 1
        cells.remember((1, 2), t, l)
    T = np.array([p[0] for p in pairs])
    L = np.array([p[1] for p in pairs])
    mT, mL = cells.mean((1, 2))
    np.testing.assert_allclose(mT, T.mean(axis=0))
    np.testing.assert_allclose(mL, L.mean(axis=0))
    np.testing.assert_allclose(cells.sum_LL[1, 2], (L * L).sum(axis=0))
    np.testing.assert_allclose(cells.sum_TL[1, 2], (T * L).sum(axis=0))
    rT, rL = cells.recent((1, 2))
    np.testing.assert_array_equal(rT, T[-3:])
    np.testing.assert_array_equal(rL, L[-3:])
    assert cells.count.sum() == 5  # no other cell touched
    with pytest.raises(ValueError):
        cells.mean((0, 0))


def test_a_restarted_cell_holds_only_the_pairs_it_keeps_and_its_arrays_stay_the_same_objects() -> None:
    cells = CellSums((2, 2), k_min=1, recent=4)
    arrays = [cells.count, cells.sum_T, cells.sum_L, cells.sum_LL, cells.sum_TL, cells.recent_T, cells.recent_n]
    for k in range(4):
        t, l = np.array([0.1 * k, 0.0]), np.array([0.2, 0.1 * k])
        cells.take((0, 1), t, l)
        cells.remember((0, 1), t, l)
    T, L = cells.recent((0, 1))
    cells.restart((0, 1), T[2:], L[2:])
    assert cells.count[0, 1] == 2
    np.testing.assert_allclose(cells.sum_T[0, 1], T[2:].sum(axis=0))
    np.testing.assert_allclose(cells.sum_LL[0, 1], (L[2:] ** 2).sum(axis=0))
    rT, _ = cells.recent((0, 1))
    np.testing.assert_array_equal(rT, T[2:])
    cells.restart((0, 1), T[:0], L[:0])
    assert cells.count[0, 1] == 0 and not cells.sum_T[0, 1].any() and len(cells.recent((0, 1))[0]) == 0
    # the change test reads these arrays by name: they are changed in place, never replaced
    assert all(a is b for a, b in zip(arrays, [cells.count, cells.sum_T, cells.sum_L, cells.sum_LL, cells.sum_TL,
                                                cells.recent_T, cells.recent_n]))
