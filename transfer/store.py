"""The pair store: raw command pairs clustered on the learner grid, refined pairs, learner limits, persistence.

Refinement (paper Section 5.2): the learner domain, normalised to [0, 1]^2 by the learner's bounds, is cut into a
grid (11 x 11 by default); each raw pair falls into the cell of its learner part; a cell's *refined pair* is the
mean of its cluster once it holds ``k_min`` members. Memory is fixed by the grid (running sums and counts, never
lists), however long the robot runs.

Every refined pair has a stable id (its cell index) and a version. The published position of a refined pair only
moves (and its version only changes) when the running mean has drifted by more than ``move_tol`` from it
(normalised units; 0.5 % of the range by default, about the noise of one raw pair): cached SC maps stay valid while
a cell merely collects more of the same, and are rebuilt when the pair really moves. ``revision`` counts changes of
the refined set as a whole.

*A learner that changes* (``adapt=True``; off by default, as in the paper; what it costs where nothing changes and gains
where something does: docs/PAPER.md, "a learner that changes"). The paper's store never forgets: after a thousand pairs
in a cell, a change of the learner needs about a thousand more to move its mean halfway. With ``adapt``, each configured
cell tests every new raw pair against what its pairs so far say for that learner command (their mean moved along the
cell's own least-squares slope, each axis alone, pulled towards its neighbours' slope): the recency-weighted mean of
these residuals (weight 1/k_min) beyond ``change_tol`` (normalised teacher units) or ``change_sigmas`` standard
deviations of its noise (estimated from the differences of consecutive residuals, which a change does not move: the
store's over all cells, and each cell's own, the larger of the two once the cell has k_min of its own) means the learner
changed there. The cell then forgets its pairs from before the change (its cluster becomes its remembered recent pairs
that agree with the change), its refined pair moves by the change's mean residual at once (so the map is right before
the cell holds k_min again), the learned limits forget the cell's boundary pairs (a limit shrinks as well as grows; with
``adapt`` a limit is the recency-weighted mean of about ``LIMIT_MEMORY_K`` k_min boundary pairs and tests them for a
change itself, ``transfer/limits.py``: it follows a learner that lost reach by its boundary pairs alone, before any cell
is re-learned), the revision changes (the SC maps of that region are rebuilt), and ``relearned``, ``changes`` (per cell)
and ``changed_at`` (the stamp given to :meth:`PairStore.add`) say so. A cell is tested only once it has its own noise
estimate (k_min residual differences; for a re-learned cell, since its change), or, never re-learned, holds ``YOUNG_K``
k_min pairs: the residuals of a cell with few pairs carry its slope's error, a bias their differences hide.

*A shared change.* A cell is re-learned only once the robot drives in it again, so a change that moves every cell
alike (a dragging wheel: a yaw-rate bias whatever the command) would be met cell by cell, each bend of the path
driven on a stale map until its cells are re-learned. When a second cell re-learns within ``SHARED_WINDOW_K`` k_min
raw pairs of another and their changes agree (within ``SHARED_AGREE`` of ``change_tol`` on each axis), every other
configured cell that has not changed meanwhile moves its refined pair by the two changes' mean, provisionally
(``prov``; ``shared`` counts these events). Its own pairs then decide: a cell whose learner did change as the others
did alarms the change test and is re-learned from its own pairs; one whose learner did not (the change was not
shared) has its shift revoked after k_min pairs whose residuals lie nearer no change than the shift. A provisional
shift is neither a re-learning (``relearned``, ``changed_at`` are untouched) nor saved (``to_bytes`` writes the
refined pairs without it).

Assumed: the learner's response to a command is a function of the command, the same wherever the robot is and
whatever it did before, changing seldom (a step or a ramp, then steady for at least tens of pairs per cell). Where it
breaks: a response that depends on the learner's history (an acceleration limit that binds: ``sim drift --scenario
payload``) makes a cell's pairs scatter; the cell's own noise estimate then raises its threshold, so the store
re-learns such a cell once or twice rather than over and over, and finds in it only changes larger than that scatter.
A change smaller than ``change_tol`` is never found by the test; the refined pairs follow it (below). docs/PAPER.md
("Beyond the paper") has the measured figures.

*A small change* (a new floor: 0.3-1.3 % of the teacher's range on the cells a mission drives, below ``change_tol``,
which cannot go lower without re-learning the cells' own shape). With ``adapt`` each cell keeps a recency-weighted mean
of its raw pairs (weight 1 / m; m is k_min, or as many pairs as keep its noise within ``move_tol`` / ``TRACK_SIGMAS``),
and once it holds k_min pairs (no provisional shift pending) its refined pair follows it: where the relation the cell's
pairs give (their mean moved along the cell's slope, and by the offset so far) is more than ``move_tol`` off at that
recent mean, the offset takes that in, and the refined pair is the mean of the cell's pairs (as in the paper) moved by
the offset on the teacher axes. Its learner part is never moved by it: one that moved to the recent pairs' mean sat
where the robot drove last and bunched the map's triangles, which cost the paper's case its deviation with nothing
changed (docs/PAPER.md). The change test, its sums and the limits ignore the offset; a re-learning clears it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer import store_io
from transfer.domain import Bounds, clamp
from transfer.limits import LearnerLimits, grid_cell
from transfer.store_adapt import CellChanges, Shifts
from transfer.store_cells import CellSums
from transfer.store_io import READS_VERSIONS, SCHEMA, SCHEMA_VERSION
from transfer.store_spread import ChangeSpread

__all__ = ["READS_VERSIONS", "SCHEMA", "SCHEMA_VERSION", "AddResult", "CellChange", "PairStore", "RefinedPair"]
#: a cell's learner has changed when the recency-weighted mean of its residuals is beyond this (normalised teacher
#: units; 2 % of the teacher's range: 0.011 m/s and 0.031 rad/s for the paper's MPC teacher), or beyond
#: ``CHANGE_SIGMAS`` standard deviations of that mean's noise, whichever is larger
CHANGE_TOL = 0.02
CHANGE_SIGMAS = 5.0
#: raw pairs a cell remembers (to re-learn from after a change), per k_min
RECENT_PER_K = 2
#: with change detection a learned limit is the recency-weighted mean of about this many boundary pairs (per k_min) of
#: its side (:class:`transfer.limits.LearnerLimits` ``memory``); without it, of every one, as in the paper
LIMIT_MEMORY_K = 4
#: a small change: a cell's recent mean (its refined pair with ``adapt``) weighs as many pairs as keep its noise within
#: ``move_tol`` over this
TRACK_SIGMAS = 3.0
#: a shared change: two cells re-learned within this many raw pairs (per k_min) of each other whose changes agree
SHARED_WINDOW_K = 40
#: ... within this share of ``change_tol`` on each axis
SHARED_AGREE = 0.5


@dataclass(frozen=True)
class RefinedPair:
    """A refined command pair ``<u_T, u_L>`` (teacher and learner units), its cell id, version and cluster size."""

    id: int
    version: int
    count: int
    u_T: NDArray[np.float64]
    u_L: NDArray[np.float64]


@dataclass(frozen=True)
class AddResult:
    """What one raw pair did: its cell, whether a refined pair appeared or moved, whether the limits moved."""

    cell: tuple[int, int]
    refined_changed: bool
    limits_changed: bool


@dataclass(frozen=True)
class CellChange:
    """A cell whose learner changed: its id (the refined pair's), how often it was re-learned, and the stamp of the
    last time (what the caller gave :meth:`PairStore.add`: the station gives wall-clock seconds; None: no stamp)."""

    id: int
    count: int
    at: float | None


class PairStore:
    """Clusters raw pairs into refined pairs and keeps the learner's limits on the teacher domain up to date. Its parts,
    one job each: :attr:`cells` (the pairs and their grid, ``transfer/store_cells.py``), :attr:`limits` (the learned
    limits, ``transfer/limits.py``), :attr:`change` (the change test's state) and :attr:`shifts` (what a refined pair
    carries beyond its cluster's mean), both ``transfer/store_adapt.py``; the store itself keeps the refined set's
    revision and its cached arrays."""

    def __init__(
        self,
        learner_bounds: Bounds,
        teacher_bounds: Bounds,
        grid: tuple[int, int] = (11, 11),
        k_min: int = 5,
        *,
        move_tol: float = 5e-3,
        boundary_tol: float = 1e-6,
        adapt: bool = False,
        change_tol: float = CHANGE_TOL,
        change_sigmas: float = CHANGE_SIGMAS,
    ) -> None:
        gv, gw = (int(grid[0]), int(grid[1]))
        if gv < 2 or gw < 2:
            raise ValueError(f"grid must be at least 2 x 2, got {grid}")
        if k_min < 1:
            raise ValueError(f"k_min must be >= 1, got {k_min}")
        self.learner_bounds = learner_bounds
        self.teacher_bounds = teacher_bounds
        self.grid = (gv, gw)
        self.k_min = int(k_min)
        self.move_tol = float(move_tol)
        self.boundary_tol = float(boundary_tol)
        self.cells = CellSums(self.grid, self.k_min, RECENT_PER_K * self.k_min)
        self.revision = 0  # changes of the refined set as a whole
        self.limits = LearnerLimits(teacher_bounds, learner_bounds, self.grid, boundary_tol)
        self.limits.refined_points = lambda: self.refined_arrays()[2]
        self._arrays: tuple | None = None
        prior = tuple(float(x) for x in learner_bounds.span / teacher_bounds.span)  # the identity response's slope
        self.change = CellChanges(self.cells, self.limits, prior, self.move_tol, change_tol, change_sigmas)
        self.shifts = Shifts(self.cells, self.change, self.move_tol, SHARED_WINDOW_K * self.k_min, SHARED_AGREE,
                             TRACK_SIGMAS)
        self.spreading = ChangeSpread(self)  # a change spread to the cells not driven since (off by default)
        self.added = 0  # raw pairs taken
        self.set_adapt(adapt)

    # ------------------------------------------------------------------------------------------ clustering
    def cell_of(self, u_L: ArrayLike) -> tuple[int, int]:
        """Grid cell of a learner command (clipped into the learner's box first)."""
        return grid_cell(clamp(self.learner_bounds.normalise(u_L), 0.0, 1.0), self.grid)

    def add(self, u_T_bar: ArrayLike, u_L: ArrayLike, stamp: float | None = None,
            prev_u_L: ArrayLike | None = None) -> AddResult:
        """Add one raw pair (teacher equivalent, learner command actually applied); ``prev_u_L``: the learner command
        applied just before it, where the caller knows it (with ``adapt``, a boundary pair taken before the learner
        settled at that extreme does not move a learned edge: ``transfer/limits_watch.py``, "A settled edge")."""
        t = np.asarray(u_T_bar, dtype=float).reshape(2)
        lcmd = np.asarray(u_L, dtype=float).reshape(2)
        if not all(map(math.isfinite, (*t.tolist(), *lcmd.tolist()))):
            raise ValueError(f"command pair must be finite, got u_T={t}, u_L={lcmd}")
        t_n = self.teacher_bounds.normalise(t)
        l_n = clamp(self.learner_bounds.normalise(lcmd), 0.0, 1.0)
        cell = grid_cell(l_n, self.grid)
        cells, shifts = self.cells, self.shifts
        self.added += 1
        refined_changed = False
        if self.adapt:
            self.spreading.before(cell)
            if cells.pub_version[cell] > 0 and self.change._changed(cell, t_n, l_n):
                self._relearn(cell, t_n, l_n, stamp)
                refined_changed = True
            elif shifts.prov[cell].any() and shifts.check(cell):
                self._refined_set_changed()
                refined_changed = True
            cells.remember(cell, t_n, l_n)
        n = cells.take(cell, t_n, l_n)
        if self.adapt:  # the cell's relation follows its recent pairs (a small change: module docstring)
            shifts.track(cell, t_n, l_n)
        if n >= self.k_min:
            mT, mL = cells.mean(cell)
            mT = mT + shifts.prov[cell] + shifts.follow[cell] + self.spreading.shift[cell]  # provisional, small change
            moved = max(abs(d) for d in (*(mT - cells.pub_T[cell]).tolist(), *(mL - cells.pub_L[cell]).tolist()))
            if cells.pub_version[cell] == 0 or moved > self.move_tol:
                cells.pub_T[cell], cells.pub_L[cell] = mT, mL
                cells.pub_version[cell] += 1
                self._refined_set_changed()
                refined_changed = True
        if self.adapt:
            refined_changed = self.spreading.after(cell) or refined_changed
        prev = None if prev_u_L is None else clamp(
            self.learner_bounds.normalise(np.asarray(prev_u_L, dtype=float).reshape(2)), 0.0, 1.0)
        limits_changed = self.limits.update(t_n, l_n, cell, prev)
        return AddResult(cell, refined_changed, limits_changed)

    def _relearn(self, cell: tuple[int, int], t_n: NDArray[np.float64], l_n: NDArray[np.float64],
                 stamp: float | None) -> None:
        """Forget what a changed cell learned before the change: its cluster becomes its recent pairs that agree with
        the change, the raw pair at hand joins it as usual; until it holds k_min again its refined pair is the old one
        moved by the change's mean residual, so the map is right at once. The learned limits forget the cell's
        boundary pairs likewise; a change that other cells share moves them too (module docstring)."""
        cells, shifts = self.cells, self.shifts
        T, L = cells.recent(cell)
        post, shift = self.change.agreeing(cell, T, L, t_n, l_n)
        cells.restart(cell, T[post], L[post])
        self.limits.forget(cell, T[~post], L[~post], T[post], L[post])
        spread = self.spreading.shift[cell]
        cells.pub_T[cell] = cells.pub_T[cell] - shifts.prov[cell] - shifts.follow[cell] - spread + shift
        shifts.cleared(cell)
        self.spreading.shift[cell] = 0.0
        cells.pub_version[cell] += 1
        self._refined_set_changed()
        if shifts.share(cell, shift, self.added):
            self._refined_set_changed()
        self.change.restarted(cell, stamp)

    def _refined_set_changed(self) -> None:
        """A refined pair appeared or moved: the set's revision changes (the SC maps of its regions are rebuilt), the
        cached arrays and the hull are computed again when next asked."""
        self.revision += 1
        self._arrays = None
        self.limits.refined_changed()

    def changed_cells(self) -> list[CellChange]:
        """The cells re-learned since the store began (this run or an earlier one it was loaded from), the most
        recently changed last (cells without a stamp first)."""
        changes = self.change.changes.ravel()
        at = self.change.changed_at.ravel()
        out = [CellChange(int(i), int(changes[i]), None if np.isnan(at[i]) else float(at[i]))
               for i in np.flatnonzero(changes > 0)]
        return sorted(out, key=lambda c: (c.at is not None, c.at or 0.0, c.id))

    def cluster_mean(self, cell: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The mean of a cell's raw pairs so far, (teacher part, learner part) normalised, even before it holds k_min
        of them (then it is not a refined pair yet); the cell must hold at least one."""
        return self.cells.mean(cell)

    def is_configured(self, cell: tuple[int, int]) -> bool:
        """A cell is configured when it holds a refined pair (k_min members)."""
        return bool(self.cells.pub_version[cell] > 0)

    def n_configured(self) -> int:
        """How many cells are configured (the refined pairs' cached ids: asked every tick)."""
        return int(self.refined_arrays()[0].size)

    def configured(self) -> NDArray[np.bool_]:
        """Which cells are configured, as a (n_v, n_omega) mask (a copy: the caller cannot change the store)."""
        return self.cells.pub_version > 0

    def refined_arrays(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """(ids, versions, teacher parts normalised, learner parts normalised) of all refined pairs (cached)."""
        if self._arrays is None:
            c = self.cells
            ids = np.flatnonzero((c.pub_version > 0).ravel())
            self._arrays = (ids, c.pub_version.ravel()[ids], c.pub_T.reshape(-1, 2)[ids], c.pub_L.reshape(-1, 2)[ids])
        return self._arrays

    def refined(self) -> list[RefinedPair]:
        """All refined pairs in teacher and learner units."""
        ids, vers, T, L = self.refined_arrays()
        cnt = self.cells.count.ravel()
        tT = self.teacher_bounds.denormalise(T)
        tL = self.learner_bounds.denormalise(L)
        return [RefinedPair(int(i), int(v), int(cnt[i]), tT[k], tL[k]) for k, (i, v) in enumerate(zip(ids, vers))]

    @property
    def raw_count(self) -> int:
        """Raw pairs the store has taken (a re-learned cell forgets its pairs, not this count)."""
        return self.added

    @property
    def relearned(self) -> int:
        """Cells re-learned after a change was detected in them (:attr:`change`)."""
        return self.change.relearned

    def slows_for_bends(self) -> bool:
        """Whether the teacher's MPC should slow for the bends its learned yaw-rate bound cannot turn at the top speed
        (:meth:`transfer.store_change.ChangeTest.slows_for_bends`)."""
        return self.change.slows_for_bends()

    def set_adapt(self, on: bool) -> None:
        """Change detection on or off from now on (a station's configuration), the limits' memory and test with it."""
        self.adapt, self.limits.memory = bool(on), (LIMIT_MEMORY_K * self.k_min if on else 0)
        self.limits.set_change_test(max(self.k_min, 2) if on else 0, self.change.change_tol, self.change.change_sigmas)

    # ----------------------------------------------------------------------------------------- persistence
    def to_bytes(self) -> bytes:
        """Versioned MessagePack blob with a CRC, so corruption is detected on load (``transfer/store_io.py``)."""
        return store_io.to_bytes(self)

    @classmethod
    def from_bytes(cls, data: bytes) -> PairStore:
        """Load a blob written by :meth:`to_bytes`; ValueError for anything corrupted or incompatible."""
        return store_io.from_bytes(data, cls)
