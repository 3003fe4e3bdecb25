"""A change spread to the cells not driven since (docs/PAPER.md, "a learner that changes"): :class:`SpreadChange`, the
part of :class:`transfer.store.PairStore` that moves the refined pairs of cells the robot has not driven since its
learner changed by what the cells it did drive since say.

A cell's own pairs find a change only once the robot drives in it again (the change test, or the refined pair
following its recent pairs for a change below ``change_tol``). A change that differs cell by cell (a new floor: the
response curves change shape) is met bend by bend: the first bend after it is driven on cells being re-learned, and
the next one, on other commands, on cells that still hold the old floor. The shared change
(:meth:`transfer.store_adapt.Shifts.share`) moves every cell by one mean change, which is right for a change that is
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
(:meth:`transfer.store_adapt.Shifts.share`: the mean of re-learned cells' changes that agree, right for a change that is
the same everywhere) keeps it where its spread agrees with it within ``AGREE`` of ``change_tol``, and takes the spread
instead where it does not (a new floor's yaw-rate change has the turn's sign: the first bend's mean moved the other
bend's cells the wrong way). A spread within ``move_tol`` of the one the cell has is not applied (the SC maps are not
rebuilt for it). Once the cell has taken k_min raw pairs since its spread was set, its own pairs decide and the spread
is dropped. A spread is neither a re-learning nor saved (``to_bytes`` writes the refined pairs without it).
Nothing happens while no cell is re-learned: where nothing changes the store is the one without it.

*Off by default* (:meth:`ChangeSpread.set`, a store's ``spreading``; ``scmbridge sim drift --spread``): on the new
floor it lowers the deviation after the change but does not bring the recovery within its goal, and it costs a change
that is the same everywhere (the dragging wheel); docs/PAPER.md, "A change spread to the cells not driven since", has
what was measured. A store without it is the store it was.

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


class ChangeSpread:
    """The spread of a change (module docstring) on a :class:`transfer.store.PairStore`'s arrays: the store holds one
    (``spreading``) and calls :meth:`before` and :meth:`after` around each raw pair it takes; the refined pairs' spreads
    are :attr:`shift` (normalised teacher units per cell), which the store adds to and saves without."""

    def __init__(self, store: Any) -> None:
        self.st = store  # the PairStore whose arrays this reads and moves
        gv, gw = store.grid
        self.on = False  # off by default (module docstring); :meth:`set`
        self.shift = np.zeros((gv, gw, 2))  # per cell: the spread its refined pair holds (normalised teacher units)
        self.shift_n = np.zeros((gv, gw), dtype=np.int64)  # raw pairs it took since its spread was set
        self.count = 0  # spreads applied (cells moved)
        self._seen = 0  # ``relearned`` when last looked at
        self._start = -1  # ``added`` when the episode began (-1: none yet)
        self._base = np.zeros((gv, gw, 2))  # the refined pairs then, without provisional shifts nor a small change
        self._base_L = np.zeros((gv, gw, 2))  # their learner parts then
        self._based = np.zeros((gv, gw), dtype=bool)  # a cell's base was taken (it was driven configured)
        self._last = np.full((gv, gw), -(10**9), dtype=np.int64)  # ``added`` at each cell's last raw pair
        self._had = np.zeros((gv, gw), dtype=bool)  # configured then
        self._n = np.zeros((gv, gw), dtype=np.int64)  # raw pairs each took since then
        self._changes = np.zeros((gv, gw), dtype=np.int64)  # each cell's re-learnings then
        self._pre = np.zeros((gv, gw), dtype=bool)  # driven in the PRE_K k_min pairs before it began
        self._rev = -1  # the observed changes' state when the spreads were last computed
        self._live = 0  # cells holding a spread
        self._prov_seen = 0  # ``relearned`` when the spreads last replaced a shared change's shifts

    def set(self, on: bool) -> None:
        """The spread of a change on or off from now on (with change detection, ``adapt``); off clears the spreads
        the refined pairs hold."""
        st = self.st
        self.on = bool(on)
        if not on and self.shift.any():
            for i, j in np.argwhere(self.shift.any(axis=2)):
                st.cells.pub_T[i, j] -= self.shift[i, j]
                st.cells.pub_version[i, j] += 1
            self.shift[:] = 0.0
            self._live = 0
            st._refined_set_changed()
        self._start = -1

    def before(self, cell: tuple[int, int]) -> None:
        """A raw pair is about to go into ``cell``: while no episode is under way, the cell's base is what its refined
        pair says before it (so that a re-learning that begins an episode is measured from before itself)."""
        st = self.st
        if self.on and self._start < 0 and st.cells.pub_version[cell] > 0:
            self._based[cell] = True
            self._base[cell] = st.cells.pub_T[cell] - st.shifts.prov[cell] - self.shift[cell]
            self._base_L[cell] = st.cells.pub_L[cell]

    def _own_T(self) -> NDArray[np.float64]:
        st = self.st
        return st.cells.pub_T - st.shifts.prov - self.shift

    def after(self, cell: tuple[int, int]) -> bool:
        """A raw pair went into ``cell`` (after the store's own update): an episode begun, carried on or ended, the
        spreads computed again where an observed change moved, a cell's own spread dropped once it is driven again.
        Returns whether a refined pair moved."""
        st = self.st
        if not self.on:
            return False
        self._last[cell] = st.added
        if self._start < 0 and st.relearned == self._seen and not self._live:
            return False  # the common case where nothing changed: nothing to do
        moved = False
        if self.shift[cell].any():
            self.shift_n[cell] += 1
            if self.shift_n[cell] >= st.k_min:  # driven again: its own pairs decide
                st.cells.pub_T[cell] -= self.shift[cell]
                self.shift[cell] = 0.0
                self._live = int(np.count_nonzero(self.shift.any(axis=2)))
                st.cells.pub_version[cell] += 1
                st._refined_set_changed()
                moved = True
        if st.relearned != self._seen:
            self._seen = st.relearned
            if self._start < 0:
                self._start = st.added
                self._had = (st.cells.pub_version > 0) & self._based
                self._pre = st.added - self._last <= PRE_K * st.k_min
                self._n[:] = np.where(self._pre, st.k_min, 0)
                self._changes = st.change.changes.copy()
                self._rev = -1
        if self._start < 0:
            return moved
        if st.added - self._start > EPISODE_K * st.k_min:  # over: the cells' own pairs carry on
            self._start = -1
            self._live = int(np.count_nonzero(self.shift.any(axis=2)))  # (a re-learning clears a cell's)
            return moved
        self._n[cell] += 1
        if self._had[cell] and (self._n[cell] >= st.k_min or st.change.changes[cell] > self._changes[cell]):
            moved = self._all() or moved
        if self._live and st.relearned != self._prov_seen:  # a shared change since: it wins where it moved
            self._prov_seen = st.relearned
            both = [(i, j) for i, j in np.argwhere(st.shifts.prov.any(axis=2) & self.shift.any(axis=2))]
            for i, j in both:  # the shift that agrees with the near cells stays; else the spread does
                gap = max(abs(x) for x in (self.shift[i, j] - st.shifts.prov[i, j]).tolist())
                if gap <= AGREE * st.change.change_tol:
                    st.cells.pub_T[i, j] -= self.shift[i, j]
                    self.shift[i, j] = 0.0
                else:
                    st.cells.pub_T[i, j] -= st.shifts.prov[i, j]
                    st.shifts.prov[i, j], st.shifts.prov_n[i, j] = 0.0, 0
                st.cells.pub_version[i, j] += 1
            if len(both):
                self._live = int(np.count_nonzero(self.shift.any(axis=2)))
                st._refined_set_changed()
                moved = True
        return moved

    def _all(self) -> bool:
        """Every configured cell not re-driven: the spread of the observed changes near it (module docstring)."""
        st = self.st
        obs = self._had & ((self._n >= st.k_min) | (st.change.changes > self._changes))
        change = np.array([self._observed((int(i), int(j))) for i, j in np.argwhere(obs)]).reshape(-1, 2)
        # a cell driven just before the episode began may have been driven before the change: it counts only where it
        # shows one, or once it has taken k_min pairs of its own since
        pre = (self._pre & (self._n < 2 * st.k_min) & (st.change.changes == self._changes))[obs]
        keep = ~pre | (np.abs(change).max(axis=1) > PRE_SHOWS * st.change.change_tol)
        obs[obs] = keep
        change = change[keep]
        key = hash((obs.tobytes(), np.round(change / st.move_tol).tobytes()))
        if key == self._rev:
            return False
        self._rev = key
        where = np.argwhere(obs).astype(float)
        if len(where) < MIN_OBSERVED:
            return False
        moved = False
        agree = AGREE * st.change.change_tol
        for i, j in np.argwhere((st.cells.pub_version > 0) & self._had & ~obs):
            d = where - np.array([i, j], dtype=float)
            d2 = (d * d).sum(axis=1)
            near = d2 <= RADIUS * RADIUS
            if near.sum() < MIN_OBSERVED:
                continue
            y = change[near]
            est = np.clip(self._affine(d[near], 1.0 / d2[near], y), y.min(axis=0), y.max(axis=0))
            cell = (int(i), int(j))
            if st.shifts.prov[cell].any():  # a shared change's shift: kept where the near cells agree with it
                if max(abs(x) for x in (est - st.shifts.prov[cell]).tolist()) <= agree:
                    continue
                st.cells.pub_T[cell] -= st.shifts.prov[cell]
                st.shifts.prov[cell], st.shifts.prov_n[cell] = 0.0, 0
            elif max(abs(x) for x in (est - self.shift[cell]).tolist()) <= st.move_tol:
                continue
            st.cells.pub_T[cell] += est - self.shift[cell]
            self.shift[cell] = est
            self.shift_n[cell] = 0
            st.cells.pub_version[cell] += 1
            self.count += 1
            moved = True
        if moved:
            self._live = int(np.count_nonzero(self.shift.any(axis=2)))
            st._refined_set_changed()
        return moved

    def _observed(self, cell: tuple[int, int]) -> list[float]:
        """A re-driven cell's observed change (normalised teacher units): its refined pair's move since the episode
        began (less the move its learner part made, along the cell's slope) and its residual not taken in yet."""
        st = self.st
        sl = st.change._slope_list(cell)
        dT = (self._own_T()[cell] - self._base[cell]).tolist()
        dL = (st.cells.pub_L[cell] - self._base_L[cell]).tolist()
        r = st.change.resid[cell].tolist()
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
