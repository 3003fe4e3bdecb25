"""A change spread to the cells not driven since (docs/PAPER.md, "a learner that changes"): :class:`SpreadChange`, the
part of :class:`transfer.store.PairStore` that moves the refined pairs of cells the robot has not driven since its
learner changed by what the cells it did drive since say.

A cell's own pairs find a change only once the robot drives in it again (the change test, or the refined pair
following its recent pairs for a change below ``change_tol``). A change that differs cell by cell (a new floor: the
response curves change shape) is met bend by bend: the first bend after it is driven on cells being re-learned, and
the next one, on other commands, on cells that still hold the old floor. The shared change
(:meth:`transfer.store.PairStore._share`) moves every cell by one mean change, which is right for a change that is
the same everywhere (a dragging wheel's bias) and wrong where it differs, as a new floor's yaw-rate change does,
whose sign follows the turn's.

*An episode* begins when the change test re-learns a cell (``relearned`` grew) and none is under way; it lasts
``EPISODE_K`` k_min raw pairs. Each cell's *base* is its refined pair (without provisional shifts) before its last raw
pair before the episode. A cell is *re-driven* once it has taken k_min raw pairs in the episode, or was re-learned in
it, or was driven in the ``PRE_K`` k_min pairs before it (the change test alarms some seconds after a change) and shows
a change beyond ``PRE_SHOWS`` of ``change_tol``; its *observed change* is its refined pair less its base (less the move
its learner part made, along the cell's slope) plus its residual not taken in yet (``resid``). Every configured cell
not re-driven within ``RADIUS`` cells (grid units) of at least ``MIN_OBSERVED`` re-driven ones takes, per teacher
axis, the value at its own learner command of an affine model of their observed changes (weighted least squares,
weight 1 / d^2 by grid distance d, the slope pulled towards none by ``SLOPE_PRIOR``), kept within the changes they
observed (never beyond what a near cell saw: two cells' noise makes a steep slope). The change is assumed smooth in the
learner's command, as a response curve that changed shape is.

That *spread* moves the cell's refined pair provisionally. A cell holding a shared change's provisional shift
(:meth:`transfer.store.PairStore._share`: the mean of re-learned cells' changes that agree, right for a change that is
the same everywhere) keeps it where its spread agrees with it within ``AGREE`` of ``change_tol``, and takes the spread
instead where it does not (a new floor's yaw-rate change has the turn's sign: the first bend's mean moved the other
bend's cells the wrong way). A spread within ``move_tol`` of the one the cell has is not applied (the SC maps are not
rebuilt for it). Once the cell has taken k_min raw pairs since its spread was set, its own pairs decide and the spread
is dropped. A spread is neither a re-learning nor saved (``to_bytes`` writes the refined pairs without it).
Nothing happens while no cell is re-learned: where nothing changes the store is the one without it.

*Off by default* (:meth:`set_spread`; ``scmbridge sim drift --spread``): on the new floor it lowers the deviation after
the change but does not bring the recovery within its goal, and it costs a change that is the same everywhere (the
dragging wheel); docs/PAPER.md, "A change spread to the cells not driven since", has what was measured. A store
without it is the store it was.

Pure: no I/O, no clock.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: an episode's length in raw pairs, per k_min: a re-learning after this long begins a new one
EPISODE_K = 60
#: grid cells: a cell not re-driven takes a spread only from re-driven cells this near
RADIUS = 2.0
#: raw pairs before an episode, per k_min: a cell driven this recently when it begins counts as re-driven (the change
#: test alarms some seconds after a change; the cells driven meanwhile hold it in their residuals)
PRE_K = 10
#: (such a cell may also have been driven just before the change: it counts only where it shows a change beyond
#: this share of ``change_tol``, more than its noise, or once it has taken k_min raw pairs of its own in the episode)
PRE_SHOWS = 0.5
#: ... and only from this many of them at least (an affine model along a line needs two)
MIN_OBSERVED = 2
#: a shared change's shift stays where the spread agrees with it within this share of ``change_tol`` on each axis (a
#: change that is the same everywhere); where it does not, the near cells' spread replaces it
AGREE = 0.5
#: the ridge on the model's slope (per grid cell), in weight units: with re-driven cells along one row only, the slope
#: across it stays near none
SLOPE_PRIOR = 0.05


class SpreadChange:
    """The spread of a change (module docstring) on :class:`transfer.store.PairStore`'s arrays: a mixin, the store
    holds the state (:meth:`_spread_init`)."""

    grid: tuple[int, int]
    k_min: int
    move_tol: float
    change_tol: float
    relearned: int
    added: int
    pub_T: Any
    pub_L: Any
    pub_version: Any
    prov: Any
    prov_n: Any
    changes: Any
    follow: Any
    resid: Any

    def _slope_list(self, cell: tuple[int, int]) -> list[float]: ...  # pragma: no cover - the store's

    def _refined_set_changed(self) -> None: ...  # pragma: no cover - the store's

    def _spread_init(self) -> None:
        gv, gw = self.grid
        self.spread_on = False  # off by default (module docstring); :meth:`set_spread`
        self.spread = np.zeros((gv, gw, 2))  # per cell: the spread its refined pair holds (normalised teacher units)
        self.spread_n = np.zeros((gv, gw), dtype=np.int64)  # raw pairs it took since its spread was set
        self.spreads = 0  # spreads applied (cells moved)
        self._sp_seen = 0  # ``relearned`` when last looked at
        self._sp_start = -1  # ``added`` when the episode began (-1: none yet)
        self._sp_base = np.zeros((gv, gw, 2))  # the refined pairs then, without provisional shifts nor a small change
        self._sp_base_L = np.zeros((gv, gw, 2))  # their learner parts then
        self._sp_based = np.zeros((gv, gw), dtype=bool)  # a cell's base was taken (it was driven configured)
        self._sp_last = np.full((gv, gw), -(10**9), dtype=np.int64)  # ``added`` at each cell's last raw pair
        self._sp_had = np.zeros((gv, gw), dtype=bool)  # configured then
        self._sp_n = np.zeros((gv, gw), dtype=np.int64)  # raw pairs each took since then
        self._sp_changes = np.zeros((gv, gw), dtype=np.int64)  # each cell's re-learnings then
        self._sp_pre = np.zeros((gv, gw), dtype=bool)  # driven in the PRE_K k_min pairs before it began
        self._sp_rev = -1  # the observed changes' state when the spreads were last computed
        self._sp_live = 0  # cells holding a spread
        self._sp_prov_seen = 0  # ``relearned`` when the spreads last replaced a shared change's shifts

    def set_spread(self, on: bool) -> None:
        """The spread of a change on or off from now on (with change detection, ``adapt``); off clears the spreads
        the refined pairs hold."""
        self.spread_on = bool(on)
        if not on and self.spread.any():
            for i, j in np.argwhere(self.spread.any(axis=2)):
                self.pub_T[i, j] -= self.spread[i, j]
                self.pub_version[i, j] += 1
            self.spread[:] = 0.0
            self._sp_live = 0
            self._refined_set_changed()
        self._sp_start = -1

    def _spread_before(self, cell: tuple[int, int]) -> None:
        """A raw pair is about to go into ``cell``: while no episode is under way, the cell's base is what its refined
        pair says before it (so that a re-learning that begins an episode is measured from before itself)."""
        if self.spread_on and self._sp_start < 0 and self.pub_version[cell] > 0:
            self._sp_based[cell] = True
            self._sp_base[cell] = self.pub_T[cell] - self.prov[cell] - self.spread[cell]
            self._sp_base_L[cell] = self.pub_L[cell]

    def _own_T(self) -> NDArray[np.float64]:
        return self.pub_T - self.prov - self.spread

    def _spread_add(self, cell: tuple[int, int]) -> bool:
        """A raw pair went into ``cell`` (after the store's own update): an episode begun, carried on or ended, the
        spreads computed again where an observed change moved, a cell's own spread dropped once it is driven again.
        Returns whether a refined pair moved."""
        if not self.spread_on:
            return False
        self._sp_last[cell] = self.added
        if self._sp_start < 0 and self.relearned == self._sp_seen and not self._sp_live:
            return False  # the common case where nothing changed: nothing to do
        moved = False
        if self.spread[cell].any():
            self.spread_n[cell] += 1
            if self.spread_n[cell] >= self.k_min:  # driven again: its own pairs decide
                self.pub_T[cell] -= self.spread[cell]
                self.spread[cell] = 0.0
                self._sp_live = int(np.count_nonzero(self.spread.any(axis=2)))
                self.pub_version[cell] += 1
                self._refined_set_changed()
                moved = True
        if self.relearned != self._sp_seen:
            self._sp_seen = self.relearned
            if self._sp_start < 0:
                self._sp_start = self.added
                self._sp_had = (self.pub_version > 0) & self._sp_based
                self._sp_pre = self.added - self._sp_last <= PRE_K * self.k_min
                self._sp_n[:] = np.where(self._sp_pre, self.k_min, 0)
                self._sp_changes = self.changes.copy()
                self._sp_rev = -1
        if self._sp_start < 0:
            return moved
        if self.added - self._sp_start > EPISODE_K * self.k_min:  # over: the cells' own pairs carry on
            self._sp_start = -1
            self._sp_live = int(np.count_nonzero(self.spread.any(axis=2)))  # (a re-learning clears a cell's)
            return moved
        self._sp_n[cell] += 1
        if self._sp_had[cell] and (self._sp_n[cell] >= self.k_min or self.changes[cell] > self._sp_changes[cell]):
            moved = self._spread_all() or moved
        if self._sp_live and self.relearned != self._sp_prov_seen:  # a shared change since: it wins where it moved
            self._sp_prov_seen = self.relearned
            both = [(i, j) for i, j in np.argwhere(self.prov.any(axis=2) & self.spread.any(axis=2))]
            for i, j in both:  # the shift that agrees with the near cells stays; else the spread does
                if max(abs(x) for x in (self.spread[i, j] - self.prov[i, j]).tolist()) <= AGREE * self.change_tol:
                    self.pub_T[i, j] -= self.spread[i, j]
                    self.spread[i, j] = 0.0
                else:
                    self.pub_T[i, j] -= self.prov[i, j]
                    self.prov[i, j], self.prov_n[i, j] = 0.0, 0
                self.pub_version[i, j] += 1
            if len(both):
                self._sp_live = int(np.count_nonzero(self.spread.any(axis=2)))
                self._refined_set_changed()
                moved = True
        return moved

    def _spread_all(self) -> bool:
        """Every configured cell not re-driven: the spread of the observed changes near it (module docstring)."""
        obs = self._sp_had & ((self._sp_n >= self.k_min) | (self.changes > self._sp_changes))
        change = np.array([self._observed((int(i), int(j))) for i, j in np.argwhere(obs)]).reshape(-1, 2)
        # a cell driven just before the episode began may have been driven before the change: it counts only where it
        # shows one, or once it has taken k_min pairs of its own since
        pre = (self._sp_pre & (self._sp_n < 2 * self.k_min) & (self.changes == self._sp_changes))[obs]
        keep = ~pre | (np.abs(change).max(axis=1) > PRE_SHOWS * self.change_tol)
        obs[obs] = keep
        change = change[keep]
        key = hash((obs.tobytes(), np.round(change / self.move_tol).tobytes()))
        if key == self._sp_rev:
            return False
        self._sp_rev = key
        where = np.argwhere(obs).astype(float)
        if len(where) < MIN_OBSERVED:
            return False
        moved = False
        agree = AGREE * self.change_tol
        for i, j in np.argwhere((self.pub_version > 0) & self._sp_had & ~obs):
            d = where - np.array([i, j], dtype=float)
            d2 = (d * d).sum(axis=1)
            near = d2 <= RADIUS * RADIUS
            if near.sum() < MIN_OBSERVED:
                continue
            y = change[near]
            est = np.clip(self._affine(d[near], 1.0 / d2[near], y), y.min(axis=0), y.max(axis=0))
            cell = (int(i), int(j))
            if self.prov[cell].any():  # a shared change's shift: kept where the near cells agree with it
                if max(abs(x) for x in (est - self.prov[cell]).tolist()) <= agree:
                    continue
                self.pub_T[cell] -= self.prov[cell]
                self.prov[cell], self.prov_n[cell] = 0.0, 0
            elif max(abs(x) for x in (est - self.spread[cell]).tolist()) <= self.move_tol:
                continue
            self.pub_T[cell] += est - self.spread[cell]
            self.spread[cell] = est
            self.spread_n[cell] = 0
            self.pub_version[cell] += 1
            self.spreads += 1
            moved = True
        if moved:
            self._sp_live = int(np.count_nonzero(self.spread.any(axis=2)))
            self._refined_set_changed()
        return moved

    def _observed(self, cell: tuple[int, int]) -> list[float]:
        """A re-driven cell's observed change (normalised teacher units): its refined pair's move since the episode
        began (less the move its learner part made, along the cell's slope) and its residual not taken in yet."""
        sl = self._slope_list(cell)
        dT = (self._own_T()[cell] - self._sp_base[cell]).tolist()
        dL = (self.pub_L[cell] - self._sp_base_L[cell]).tolist()
        r = self.resid[cell].tolist()
        return [dT[a] - sl[a] * dL[a] + r[a] for a in (0, 1)]

    @staticmethod
    def _affine(d: NDArray[np.float64], w: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """The intercept (the value at offset 0) of the weighted least-squares affine model ``y ~ a + B d`` with the
        ridge ``SLOPE_PRIOR`` on ``B``; both teacher axes at once."""
        X = np.hstack([np.ones((len(d), 1)), d])
        A = X.T @ (X * w[:, None]) + np.diag([0.0, SLOPE_PRIOR, SLOPE_PRIOR])
        b = X.T @ (y * w[:, None])
        try:
            sol = np.linalg.solve(A, b)
        except np.linalg.LinAlgError:
            return np.zeros(2)
        out = sol[0]
        return out if all(map(math.isfinite, out.tolist())) else np.zeros(2)
