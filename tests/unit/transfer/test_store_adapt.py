"""A pair store's change state and shifts (transfer/store_adapt.py): the change test reads the very arrays the cells
hold (also after a load), a re-learned cell starts its residuals again, and a shared change moves the other configured
cells provisionally while a cell's own pairs revoke a shift that does not fit them."""

from __future__ import annotations

import numpy as np

from tests.stores import LB, TB, filled
from transfer.store import PairStore


def test_the_change_test_reads_the_cells_own_arrays_also_after_a_load() -> None:
    store = filled(300, seed=3, gain=1.2)
    again = PairStore.from_bytes(store.to_bytes())
    for s in (store, again):
        for name in ("count", "sum_T", "sum_L", "sum_LL", "sum_TL", "pub_T", "pub_L", "pub_version"):
            assert getattr(s.change, name) is getattr(s.cells, name), name
        assert s.change.limits is s.limits
    np.testing.assert_array_equal(again.change.noise2, store.change.noise2)


def test_a_restarted_cell_forgets_its_residuals_and_counts_the_change() -> None:
    store = PairStore(LB, TB, adapt=True)
    ch = store.change
    ch.resid[2, 3] = (0.1, -0.1)
    ch.last_resid[2, 3] = (0.05, 0.0)
    ch.cell_noise_n[2, 3] = 7
    ch.restarted((2, 3), 12.5)
    ch.restarted((2, 3), None)
    assert not ch.resid[2, 3].any() and np.all(np.isnan(ch.last_resid[2, 3])) and ch.cell_noise_n[2, 3] == 0
    assert ch.relearned == store.relearned == 2 and ch.changes[2, 3] == 2 and np.isnan(ch.changed_at[2, 3])
    assert [(c.id, c.count) for c in store.changed_cells()] == [(2 * 11 + 3, 2)]


def test_a_shared_change_shifts_the_other_configured_cells_and_their_own_pairs_revoke_it() -> None:
    store = PairStore(LB, TB, adapt=True)
    cells, shifts = store.cells, store.shifts
    cells.pub_version[[0, 1, 5], [0, 1, 5]] = 1  # three configured cells
    change = np.array([0.0, 0.05])
    assert not shifts.share((0, 0), change, added=10)  # one re-learning alone: nothing shared
    before = cells.pub_T.copy()
    assert shifts.share((1, 1), change, added=12)  # a second that agrees, within the window: shared
    assert shifts.shared == 1
    np.testing.assert_allclose(cells.pub_T[5, 5], before[5, 5] + change)  # the cell not re-learned moves
    np.testing.assert_array_equal(cells.pub_T[0, 0], before[0, 0])  # the re-learned ones do not
    assert cells.pub_version[5, 5] == 2 and shifts.prov[5, 5].any()
    # its own pairs say no change (its residuals near zero): after k_min of them the shift is revoked
    revoked = [shifts.check((5, 5)) for _ in range(store.k_min)]
    assert revoked == [False] * (store.k_min - 1) + [True]
    np.testing.assert_allclose(cells.pub_T[5, 5], before[5, 5], atol=1e-15)
    assert not shifts.prov[5, 5].any() and cells.pub_version[5, 5] == 3
    # a change far outside the window is not shared with the earlier ones
    assert not shifts.share((0, 1), change, added=12 + shifts.window + 1)
