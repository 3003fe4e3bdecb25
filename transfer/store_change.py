"""The change test of a pair store's cells (docs/PAPER.md, "a learner that changes"): :class:`ChangeTest`, the part of
:class:`transfer.store.PairStore` that says whether a configured cell's learner has changed, from each raw pair's
residual against the relation the cell's pairs so far describe.

Each raw pair's teacher part is compared with what the cell's pairs say for its learner part (their mean moved along
the cell's slope, :meth:`ChangeTest._slope`); the recency-weighted mean of those residuals beyond
:meth:`ChangeTest._threshold` means a change. The noise the threshold is made of is learned from the residuals
themselves. The arithmetic is scalar, axis by axis, in the order the array form has: numpy's per-call overhead on
two-element vectors was most of the cost of every pair added, on the station's tick.

Pure: no I/O, no clock.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: the weight of one residual in the store's noise estimate
NOISE_WEIGHT = 0.01
#: a cell's own noise estimate is the mean of its last this many residual differences, per k_min
CELL_NOISE_PER_K = 4
#: a cell with fewer pairs than this (per k_min) and no noise estimate of its own is not tested yet
YOUNG_K = 4


class ChangeTest:
    """The change test on :class:`transfer.store.PairStore`'s per-cell arrays (its sums, refined pairs, residual and
    noise estimates): a mixin, the store holds the state."""

    count: Any
    grid: tuple[int, int]
    k_min: int
    _prior: Any
    pub_version: Any
    pub_T: Any
    pub_L: Any
    sum_T: Any
    sum_L: Any
    sum_LL: Any
    sum_TL: Any
    resid: Any
    last_resid: Any
    noise2: Any
    cell_noise2: Any
    cell_noise_n: Any
    changes: Any
    change_sigmas: float
    change_tol: float
    relearned: int
    limits: Any

    def slows_for_bends(self) -> bool:
        """Whether the teacher's MPC should slow for the bends its learned yaw-rate bound cannot turn at the top speed
        (``curve_margin``; docs/PAPER.md, "a learner that changes"): once the learner has changed (a cell or a learned
        edge re-learned: the map and the limits are being learned again, and a bend driven fast on them is driven
        wide) or a yaw-rate edge lost reach (:meth:`transfer.limits.LearnerLimits.turn_lost`). Never where nothing
        changed: the paper's MPC, as its experiment has it."""
        return self.relearned > 0 or self.limits.relearned > 0 or self.limits.turn_lost()

    def _slope(self, cell: tuple[int, int]) -> NDArray[np.float64]:
        """dT/dL per axis (normalised) of the learner's response in a cell: the least-squares slope of the cell's own
        raw pairs, each axis alone, pulled towards the slope between its refined neighbours on that axis (or the
        identity response's, where it has none) as if ``k_min`` more pairs had spread a quarter cell around its mean:
        a cell whose pairs all lie at one command knows no slope of its own."""
        return np.array(self._slope_list(cell))

    def _slope_list(self, cell: tuple[int, int]) -> list[float]:
        """:meth:`_slope` as a list of two floats (what the per-pair tests read)."""
        n = int(self.count[cell])
        grid = self.grid
        prior = list(self._prior)  # a learner that does what it is told
        i, j = cell
        pv, pT, pL = self.pub_version, self.pub_T, self.pub_L
        # scalar arithmetic (two axes: numpy's per-call overhead was most of the cost), in the arrays' order
        for a, lo, hi in ((0, (i - 1, j), (i + 1, j)), (1, (i, j - 1), (i, j + 1))):
            if lo[a] >= 0 and hi[a] < grid[a] and pv[lo] > 0 and pv[hi] > 0:
                dL = float(pL[hi + (a,)] - pL[lo + (a,)])
                if abs(dL) > 0.5 / grid[a]:
                    prior[a] = float(pT[hi + (a,)] - pT[lo + (a,)]) / dL
        if n == 0:
            return prior
        sT, sL, sLL, sTL = (x[cell].tolist() for x in (self.sum_T, self.sum_L, self.sum_LL, self.sum_TL))
        out = [0.0, 0.0]
        for a in (0, 1):
            mL = sL[a] / n
            sxx = sLL[a] - n * mL * mL
            sxy = sTL[a] - n * mL * (sT[a] / n)
            q = 0.25 / float(grid[a])
            lam = self.k_min * (q * q)
            out[a] = (sxy + lam * prior[a]) / (max(sxx, 0.0) + lam)
        return out

    def _residual(self, cell: tuple[int, int], t_n: NDArray[np.float64], l_n: NDArray[np.float64]) -> NDArray:
        """How far a raw pair's teacher part is from what the cell's pairs so far say for its learner part (their
        mean moved along the cell's slope): what a change of the learner moves (normalised teacher units)."""
        n = self.count[cell]
        if n == 0:  # re-learned, no pair since: its refined pair is the reference
            return t_n - self.pub_T[cell] - (l_n - self.pub_L[cell]) * self._slope(cell)
        return t_n - (self.sum_T[cell] + (n * l_n - self.sum_L[cell]) * self._slope(cell)) / n

    def _noise2(self, cell: tuple[int, int] | None = None) -> NDArray[np.float64]:
        """The residuals' variance per axis when nothing changes: the store's, or the cell's own where it has one
        and it is larger."""
        if cell is not None and self.cell_noise_n[cell] >= self.k_min:
            return np.maximum(self.noise2, self.cell_noise2[cell])
        return self.noise2

    def _threshold(self, cell: tuple[int, int] | None = None) -> NDArray[np.float64]:
        """A cell's mean residual beyond which its learner has changed, per axis: ``change_sigmas`` standard
        deviations of that mean when nothing changes (:meth:`_noise2`), and never below ``change_tol``."""
        a = 1.0 / self.k_min
        return np.maximum(self.change_sigmas * np.sqrt(self._noise2(cell) * a / (2.0 - a)), self.change_tol)

    def _changed(self, cell: tuple[int, int], t_n: NDArray[np.float64], l_n: NDArray[np.float64]) -> bool:
        """The change test of a configured cell (module docstring): the recency-weighted mean of its residuals (weight
        1/k_min) beyond :meth:`_threshold` on either axis. A cell is tested only once it has its own noise estimate
        (k_min residual differences; for a re-learned cell, since its change) or, never re-learned, holds ``YOUNG_K``
        k_min pairs: a few pairs' mean and slope are not yet a relation to test against (the unchanged runs' false
        alarms were all in such cells), and a learner whose response depends on its history (an acceleration limit
        that binds) shows in a cell's own estimate how far its pairs scatter. A pair that does not alarm updates the
        noise estimates."""
        # scalar arithmetic on the two axes, in the order the array form has (numpy's per-call overhead on 2-vectors
        # was most of the cost of every pair added); the results are the array form's, bit for bit
        k = self.k_min
        c = int(self.count[cell])
        if c == 0:
            r = self._residual(cell, t_n, l_n).tolist()
        else:
            t, l = t_n.tolist(), l_n.tolist()
            sT, sL, sl = self.sum_T[cell].tolist(), self.sum_L[cell].tolist(), self._slope_list(cell)
            r = [t[a] - (sT[a] + (c * l[a] - sL[a]) * sl[a]) / c for a in (0, 1)]
        old = self.resid[cell].tolist()
        e = [old[a] + (r[a] - old[a]) / k for a in (0, 1)]
        self.resid[cell] = e
        cn = int(self.cell_noise_n[cell])
        tested = cn >= k or (self.changes[cell] == 0 and c >= YOUNG_K * k)
        if tested:
            n2 = self.noise2.tolist()
            if cn >= k:
                own = self.cell_noise2[cell].tolist()
                n2 = [max(n2[a], own[a]) for a in (0, 1)]
            w = 1.0 / k
            if any(abs(e[a]) > max(self.change_sigmas * math.sqrt(n2[a] * w / (2.0 - w)), self.change_tol)
                   for a in (0, 1)):
                return True
        # the noise is learned from the difference of a cell's consecutive residuals (half its square): a change moves
        # both alike, so a learner that changed everywhere does not pass for a noisy one and hide its own change
        last = self.last_resid[cell].tolist()
        if not (math.isnan(last[0]) or math.isnan(last[1])):
            d2 = [0.5 * ((r[a] - last[a]) * (r[a] - last[a])) for a in (0, 1)]
            g = self.noise2
            g[0], g[1] = (g[0] + NOISE_WEIGHT * (d2[0] - g[0]), g[1] + NOISE_WEIGHT * (d2[1] - g[1]))
            cn = self.cell_noise_n[cell] = cn + 1
            m = min(cn, CELL_NOISE_PER_K * k)
            own = self.cell_noise2[cell].tolist()
            self.cell_noise2[cell] = [own[a] + (d2[a] - own[a]) / m for a in (0, 1)]
        self.last_resid[cell] = r
        return False
