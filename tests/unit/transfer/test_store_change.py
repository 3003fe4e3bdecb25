"""The change test (transfer/store_change.py) in scalar arithmetic gives the array form's results bit for bit: the
residuals, the noise estimates and every decision, on a stream of noisy pairs with a change in it."""

from __future__ import annotations

import numpy as np

from transfer.domain import Bounds
from transfer.limits import grid_cell
from transfer.store import PairStore
from transfer.store_adapt import CellChanges
from transfer.store_change import CELL_NOISE_PER_K, NOISE_WEIGHT, YOUNG_K


def _array_form(store: CellChanges, cell, t_n, l_n) -> bool:
    """The change test as it was written on numpy arrays (the reference)."""
    n = store.count[cell]
    slope = np.array(store._slope_list(cell))
    if n == 0:
        r = t_n - store.pub_T[cell] - (l_n - store.pub_L[cell]) * slope
    else:
        r = t_n - (store.sum_T[cell] + (n * l_n - store.sum_L[cell]) * slope) / n
    e = store.resid[cell] = store.resid[cell] + (r - store.resid[cell]) / store.k_min
    tested = (store.cell_noise_n[cell] >= store.k_min
              or (store.changes[cell] == 0 and store.count[cell] >= YOUNG_K * store.k_min))
    noise2 = (np.maximum(store.noise2, store.cell_noise2[cell]) if store.cell_noise_n[cell] >= store.k_min
              else store.noise2)
    a = 1.0 / store.k_min
    threshold = np.maximum(store.change_sigmas * np.sqrt(noise2 * a / (2.0 - a)), store.change_tol)
    if tested and np.any(np.abs(e) > threshold):
        return True
    last = store.last_resid[cell]
    if not np.any(np.isnan(last)):
        d2 = 0.5 * (r - last) ** 2
        store.noise2 += NOISE_WEIGHT * (d2 - store.noise2)
        m = store.cell_noise_n[cell] = store.cell_noise_n[cell] + 1
        store.cell_noise2[cell] += (d2 - store.cell_noise2[cell]) / min(m, CELL_NOISE_PER_K * store.k_min)
    store.last_resid[cell] = r
    return False


def test_the_scalar_change_test_is_the_array_form_bit_for_bit() -> None:
    rng = np.random.default_rng(7)
    stores = [PairStore(Bounds((0.0, 0.3), (-0.5, 0.5)), Bounds((0.0, 0.6), (-1.0, 1.0)), adapt=True)
              for _ in range(2)]
    n = 4000
    L = np.column_stack([rng.uniform(0.0, 0.3, n), rng.uniform(-0.5, 0.5, n)])
    gain = np.where(np.arange(n)[:, None] < n // 2, [1.6, 1.8], [1.2, 1.8])  # the learner changes half-way
    T = L * gain + rng.normal(0.0, 0.004, (n, 2))
    decisions = [0, 0]
    for t, l in zip(T, L):
        got = []
        for k, store in enumerate(stores):
            t_n = store.teacher_bounds.normalise(t)
            l_n = np.clip(store.learner_bounds.normalise(l), 0.0, 1.0)
            cell = grid_cell(l_n, store.grid)
            if store.cells.pub_version[cell] > 0:
                ch = store.change
                got.append(ch._changed(cell, t_n, l_n) if k == 0 else _array_form(ch, cell, t_n, l_n))
            store.add(t, l)
        assert got[:1] == got[1:]
        decisions[0] += sum(got[:1])
    a, b = stores
    assert decisions[0] > 0  # the change is seen, so both branches ran
    for name in ("resid", "last_resid", "noise2", "cell_noise2", "cell_noise_n", "count", "pub_T", "pub_L"):
        assert np.array_equal(getattr(a.change, name), getattr(b.change, name), equal_nan=True), name
