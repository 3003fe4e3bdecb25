"""Pair stores the unit tests fill: the same learner and teacher boxes, and a store filled with a learner whose
teacher-equivalent response is a fixed gain of its command (each test picks the pairs, the seed and the gain)."""

from __future__ import annotations

import numpy as np

from transfer.domain import Bounds
from transfer.store import PairStore

LB = Bounds((0.05, 0.3), (-0.2, 0.26))
TB = Bounds((0.05, 0.6), (-0.8, 0.8))


def filled(pairs: int, seed: int, gain: float) -> PairStore:
    """A store with change detection, given ``pairs`` raw pairs ``(gain * u, u)`` at uniform learner commands."""
    store = PairStore(LB, TB, adapt=True)
    rng = np.random.default_rng(seed)
    for _ in range(pairs):
        u = LB.denormalise(rng.uniform(0, 1, 2))
        store.add(u * gain, u)
    return store
