"""The pairs and their grid: :class:`CellSums`, the part of :class:`transfer.store.PairStore` that holds what each cell
of the learner grid took (paper Section 5.2, refinement): its running sums and count, its refined pair as published,
and a ring of its last raw pairs (for re-learning after a change, docs/PAPER.md "a learner that changes").

Memory is fixed by the grid (running sums and counts, a ring of fixed length per cell, never lists), however long the
robot runs. All parts normalised (the learner's and the teacher's bounds map to [0, 1]^2).

The arrays are made once and changed in place only (a load copies into them): the store's change test reads the same
arrays by name (:class:`transfer.store_adapt.CellChanges`).

Pure: no I/O, no clock.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class CellSums:
    """Per cell of a ``grid``: the raw pairs' count and sums (teacher part, learner part, and per axis the learner
    part squared and times the teacher part: the cell's slope), the published refined pair and its version (0: none
    yet), and the ring of its last ``recent`` raw pairs."""

    def __init__(self, grid: tuple[int, int], k_min: int, recent: int) -> None:
        gv, gw = grid
        self.grid = (int(gv), int(gw))
        self.k_min = int(k_min)
        self.count = np.zeros((gv, gw), dtype=np.int64)
        self.sum_T = np.zeros((gv, gw, 2))  # normalised teacher parts
        self.sum_L = np.zeros((gv, gw, 2))  # normalised learner parts
        self.sum_LL = np.zeros((gv, gw, 2))  # per axis: learner parts squared, and times the teacher parts (slopes)
        self.sum_TL = np.zeros((gv, gw, 2))
        self.pub_T = np.zeros((gv, gw, 2))
        self.pub_L = np.zeros((gv, gw, 2))
        self.pub_version = np.zeros((gv, gw), dtype=np.int64)  # 0: no refined pair yet
        self.recent_T = np.zeros((gv, gw, recent, 2))  # per cell: its last raw pairs (a ring), normalised
        self.recent_L = np.zeros((gv, gw, recent, 2))
        self.recent_n = np.zeros((gv, gw), dtype=np.int64)  # raw pairs ever put in the ring (the next slot: mod r)

    def take(self, cell: tuple[int, int], t_n: NDArray[np.float64], l_n: NDArray[np.float64]) -> int:
        """A raw pair into its cell's sums; returns the cell's count."""
        n = self.count[cell] = self.count[cell] + 1
        self.sum_T[cell] += t_n
        self.sum_L[cell] += l_n
        self.sum_LL[cell] += l_n * l_n
        self.sum_TL[cell] += t_n * l_n
        return int(n)

    def remember(self, cell: tuple[int, int], t_n: NDArray[np.float64], l_n: NDArray[np.float64]) -> None:
        """A raw pair into its cell's ring (the oldest one drops out)."""
        k = self.recent_n[cell] % self.recent_T.shape[2]
        self.recent_T[cell][k], self.recent_L[cell][k] = t_n, l_n
        self.recent_n[cell] += 1

    def recent(self, cell: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The cell's last raw pairs, oldest first (teacher parts, learner parts)."""
        r = self.recent_T.shape[2]
        n = int(self.recent_n[cell])
        idx = np.arange(max(0, n - r), n) % r
        return self.recent_T[cell][idx], self.recent_L[cell][idx]

    def mean(self, cell: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The mean of a cell's raw pairs so far (teacher part, learner part); the cell must hold at least one."""
        n = self.count[cell]
        if n == 0:
            raise ValueError(f"cell {cell} holds no raw pair")
        return self.sum_T[cell] / n, self.sum_L[cell] / n

    def restart(self, cell: tuple[int, int], T: NDArray[np.float64], L: NDArray[np.float64]) -> None:
        """A re-learned cell: its cluster and its ring become the pairs ``T``, ``L`` (those that agree with the
        change), everything it took before forgotten."""
        some = len(T) > 0
        self.count[cell] = len(T)
        self.sum_T[cell] = T.sum(axis=0) if some else 0.0
        self.sum_L[cell] = L.sum(axis=0) if some else 0.0
        self.sum_LL[cell] = (L ** 2).sum(axis=0) if some else 0.0
        self.sum_TL[cell] = (T * L).sum(axis=0) if some else 0.0
        self.recent_n[cell] = 0
        for a, b in zip(T, L):
            self.remember(cell, a, b)
