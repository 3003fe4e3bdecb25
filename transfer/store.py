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
import zlib
from dataclasses import dataclass

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.domain import Bounds
from transfer.limits import LearnerLimits, grid_cell
from transfer.store_blob import LimitsBlob, StoreBlob
from transfer.store_change import ChangeTest
from transfer.store_spread import ChangeSpread

SCHEMA = "scmbridge.pairstore"
SCHEMA_VERSION = 4
#: the versions this build reads (1: before change detection; its cells start with no recent pairs or slopes; 2:
#: before the per-cell change count, which starts at 1 for a cell with a change time and 0 otherwise; 3: before the
#: yaw-rate curvatures, which start with no boundary pair: a learner that cannot turn in place learns them again)
READS_VERSIONS = (1, 2, 3, 4)
_MAGIC = b"SCMPAIRS"
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


class PairStore(ChangeTest):
    """Clusters raw pairs into refined pairs and keeps the learner's limits on the teacher domain up to date."""

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
        self._prior = tuple(float(x) for x in learner_bounds.span / teacher_bounds.span)  # _slope's identity slope
        self.move_tol = float(move_tol)
        self.boundary_tol = float(boundary_tol)
        self.count = np.zeros((gv, gw), dtype=np.int64)
        self.sum_T = np.zeros((gv, gw, 2))  # normalised teacher parts
        self.sum_L = np.zeros((gv, gw, 2))  # normalised learner parts
        self.sum_LL = np.zeros((gv, gw, 2))  # per axis: learner parts squared, and times the teacher parts (slopes)
        self.sum_TL = np.zeros((gv, gw, 2))
        self.pub_T = np.zeros((gv, gw, 2))
        self.pub_L = np.zeros((gv, gw, 2))
        self.pub_version = np.zeros((gv, gw), dtype=np.int64)  # 0: no refined pair yet
        self.revision = 0
        self.limits = LearnerLimits(teacher_bounds, learner_bounds, self.grid, boundary_tol)
        self.limits.refined_points = lambda: self.refined_arrays()[2]
        self._arrays: tuple | None = None
        # change detection (module docstring, "A learner that changes")
        self.change_tol = float(change_tol)
        self.change_sigmas = float(change_sigmas)
        self.set_adapt(adapt)
        self.relearned = 0  # cells re-learned after a change was detected in them
        self.added = 0  # raw pairs taken
        self.changed_at = np.full((gv, gw), np.nan)  # the stamp of each cell's last re-learning (NaN: never)
        self.changes = np.zeros((gv, gw), dtype=np.int64)  # how often each cell was re-learned
        self.resid = np.zeros((gv, gw, 2))  # per cell: recency-weighted mean of the residuals against its relation
        self.noise2 = np.full(2, self.move_tol ** 2)  # the residuals' variance per axis when nothing changes
        self.last_resid = np.full((gv, gw, 2), np.nan)  # per cell: its last residual (NaN: none since it changed)
        self.cell_noise2 = np.zeros((gv, gw, 2))  # per cell: its own residuals' variance per axis (same estimator)
        self.cell_noise_n = np.zeros((gv, gw), dtype=np.int64)  # residual differences in it since its last change
        r = RECENT_PER_K * self.k_min
        self.recent_T = np.zeros((gv, gw, r, 2))  # per cell: its last raw pairs (a ring), normalised
        self.recent_L = np.zeros((gv, gw, r, 2))
        self.recent_n = np.zeros((gv, gw), dtype=np.int64)  # raw pairs ever put in the ring (the next slot: mod r)
        # a shared change (module docstring): the changes of the last re-learnings (cell, change, ``added`` then), and
        # per cell the provisional shift of its refined pair (normalised teacher units; 0: none) and the raw pairs
        # it took since. Not persisted: a saved store holds its refined pairs without their provisional shifts.
        self._changes_seen: list[tuple[tuple[int, int], NDArray[np.float64], int]] = []
        self.prov = np.zeros((gv, gw, 2))
        self.prov_n = np.zeros((gv, gw), dtype=np.int64)
        self.shared = 0  # shared changes applied
        # a small change (module docstring): per cell the recency-weighted mean of its raw pairs (normalised) and how
        # many it took since the store began or the cell re-learned, and the offset its refined pair follows (teacher
        # parts). Not persisted: after a load it starts again (the saved refined pairs hold the offset).
        self.track_T, self.track_L, self.follow = np.zeros((gv, gw, 2)), np.zeros((gv, gw, 2)), np.zeros((gv, gw, 2))
        self.track_n = np.zeros((gv, gw), dtype=np.int64)
        self.spreading = ChangeSpread(self)  # a change spread to the cells not driven since (off by default)

    # ------------------------------------------------------------------------------------------ clustering
    def cell_of(self, u_L: ArrayLike) -> tuple[int, int]:
        """Grid cell of a learner command (clipped into the learner's box first)."""
        n = np.clip(self.learner_bounds.normalise(u_L), 0.0, 1.0)
        return self._cell_n(n)

    def _cell_n(self, n: NDArray[np.float64]) -> tuple[int, int]:
        return grid_cell(n, self.grid)

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
        l_n = np.clip(self.learner_bounds.normalise(lcmd), 0.0, 1.0)
        cell = self._cell_n(l_n)
        self.added += 1
        refined_changed = False
        if self.adapt:
            self.spreading.before(cell)
            if self.pub_version[cell] > 0 and self._changed(cell, t_n, l_n):
                self._relearn(cell, t_n, l_n, stamp)
                refined_changed = True
            elif self.prov[cell].any():
                refined_changed = self._check_provision(cell)
            self._remember(cell, t_n, l_n)
        self.count[cell] += 1
        self.sum_T[cell] += t_n
        self.sum_L[cell] += l_n
        self.sum_LL[cell] += l_n * l_n
        self.sum_TL[cell] += t_n * l_n
        if self.adapt:  # the cell's relation follows its recent pairs (a small change: module docstring)
            self._track(cell, t_n, l_n)
        if self.count[cell] >= self.k_min:
            mT, mL = self.cluster_mean(cell)
            mT = mT + self.prov[cell] + self.follow[cell] + self.spreading.shift[cell]  # provisional, small change
            moved = max(abs(d) for d in (*(mT - self.pub_T[cell]).tolist(), *(mL - self.pub_L[cell]).tolist()))
            if self.pub_version[cell] == 0 or moved > self.move_tol:
                self.pub_T[cell], self.pub_L[cell] = mT, mL
                self.pub_version[cell] += 1
                self._refined_set_changed()
                refined_changed = True
        if self.adapt:
            refined_changed = self.spreading.after(cell) or refined_changed
        prev = None if prev_u_L is None else np.clip(
            self.learner_bounds.normalise(np.asarray(prev_u_L, dtype=float).reshape(2)), 0.0, 1.0)
        limits_changed = self.limits.update(t_n, l_n, cell, prev)
        return AddResult(cell, refined_changed, limits_changed)

    def _remember(self, cell: tuple[int, int], t_n: NDArray[np.float64], l_n: NDArray[np.float64]) -> None:
        k = self.recent_n[cell] % self.recent_T.shape[2]
        self.recent_T[cell][k], self.recent_L[cell][k] = t_n, l_n
        self.recent_n[cell] += 1

    def _track(self, cell: tuple[int, int], t_n: NDArray[np.float64], l_n: NDArray[np.float64]) -> None:
        """A small change (module docstring): the raw pair into the cell's recent mean; the offset of the cell's
        relation there, beyond ``move_tol``, into the offset its refined pair follows. Scalar arithmetic."""
        n = self.track_n[cell] = self.track_n[cell] + 1
        q = TRACK_SIGMAS / self.move_tol  # its noise within move_tol / q: a mean of m pairs has 1 / (2 m - 1) of theirs
        w = 1.0 / min(n, max(self.k_min, 0.5 + 0.5 * max(self._noise2(cell).tolist()) * (q * q)))
        tT, tL = self.track_T[cell], self.track_L[cell]
        eT, eL = tT.tolist(), tL.tolist()
        t, l = t_n.tolist(), l_n.tolist()
        for a in (0, 1):
            eT[a] = eT[a] + w * (t[a] - eT[a])
            eL[a] = eL[a] + w * (l[a] - eL[a])
        tT[:], tL[:] = eT, eL
        c = int(self.count[cell])
        if not (n >= self.k_min and c >= self.k_min and self.pub_version[cell] > 0 and not self.prov[cell].any()):
            return
        sT, sL, f = self.sum_T[cell].tolist(), self.sum_L[cell].tolist(), self.follow[cell].tolist()
        sl = self._slope_list(cell)
        d = [eT[a] - f[a] - (sT[a] + (c * eL[a] - sL[a]) * sl[a]) / c for a in (0, 1)]
        if max(abs(d[0]), abs(d[1])) > self.move_tol:
            self.follow[cell] += d

    def _recent(self, cell: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The cell's last raw pairs, oldest first (teacher parts, learner parts)."""
        r = self.recent_T.shape[2]
        n = int(self.recent_n[cell])
        idx = np.arange(max(0, n - r), n) % r
        return self.recent_T[cell][idx], self.recent_L[cell][idx]

    def _relearn(self, cell: tuple[int, int], t_n: NDArray[np.float64], l_n: NDArray[np.float64],
                 stamp: float | None) -> None:
        """Forget what a changed cell learned before the change: its cluster becomes its recent pairs that agree with
        the change (their residual nearer the cell's mean residual than zero), the raw pair at hand joins it as
        usual; until it holds k_min again its refined pair is the old one moved by the change's mean residual, so
        the map is right at once. The learned limits forget the cell's boundary pairs likewise."""
        e = self.resid[cell]
        T, L = self._recent(cell)
        post = np.zeros(len(T), dtype=bool)
        if len(T):
            R = np.array([self._residual(cell, a, b) for a, b in zip(T, L)])
            post = np.linalg.norm(R - e, axis=1) < np.linalg.norm(R, axis=1)
        shift = np.vstack([R[post], self._residual(cell, t_n, l_n)]).mean(axis=0) if len(T) else e
        self.count[cell] = int(post.sum())
        self.sum_T[cell] = T[post].sum(axis=0) if post.any() else 0.0
        self.sum_L[cell] = L[post].sum(axis=0) if post.any() else 0.0
        self.sum_LL[cell] = (L[post] ** 2).sum(axis=0) if post.any() else 0.0
        self.sum_TL[cell] = (T[post] * L[post]).sum(axis=0) if post.any() else 0.0
        self.limits.forget(cell, T[~post], L[~post], T[post], L[post])
        self.recent_n[cell] = 0
        for a, b in zip(T[post], L[post]):
            self._remember(cell, a, b)
        self.pub_T[cell] = self.pub_T[cell] - self.prov[cell] - self.follow[cell] - self.spreading.shift[cell] + shift
        self.prov[cell], self.spreading.shift[cell] = 0.0, 0.0
        self.pub_version[cell] += 1
        self._refined_set_changed()
        self._share(cell, shift)
        self.resid[cell] = 0.0
        self.last_resid[cell] = np.nan
        self.cell_noise_n[cell] = 0
        self.track_n[cell], self.follow[cell] = 0, 0.0
        self.relearned += 1
        self.changes[cell] += 1
        self.changed_at[cell] = np.nan if stamp is None else float(stamp)

    def _refined_set_changed(self) -> None:
        """A refined pair appeared or moved: the set's revision changes (the SC maps of its regions are rebuilt), the
        cached arrays and the hull are computed again when next asked."""
        self.revision += 1
        self._arrays = None
        self.limits.refined_changed()

    def _share(self, cell: tuple[int, int], change: NDArray[np.float64]) -> None:
        """A shared change (module docstring): when another cell re-learned within ``SHARED_WINDOW_K`` k_min raw pairs
        with a change that agrees with this one (within ``SHARED_AGREE`` of ``change_tol`` on each axis), every other
        configured cell that has not changed in that window moves its refined pair by the agreeing changes' mean, for
        now: its own pairs then confirm it (the change test re-learns the cell) or revoke it
        (:meth:`_check_provision`)."""
        window = SHARED_WINDOW_K * self.k_min
        self._changes_seen = [c for c in self._changes_seen if self.added - c[2] <= window and c[0] != cell]
        agree = [c[1] for c in self._changes_seen
                 if np.all(np.abs(c[1] - change) <= SHARED_AGREE * self.change_tol)]
        self._changes_seen.append((cell, np.array(change, dtype=float), self.added))
        if not agree:
            return
        recent = {c[0] for c in self._changes_seen}
        s = np.mean([change, *agree], axis=0)
        moved = False
        for c in zip(*np.nonzero(self.pub_version > 0)):
            c = (int(c[0]), int(c[1]))
            if c in recent or np.all(np.abs(self.prov[c] - s) <= SHARED_AGREE * self.change_tol):
                continue
            self.pub_T[c] += s - self.prov[c]
            self.prov[c] = s
            self.prov_n[c] = 0
            self.pub_version[c] += 1
            moved = True
        if moved:
            self.shared += 1
            self._refined_set_changed()

    def _check_provision(self, cell: tuple[int, int]) -> bool:
        """A provisionally shifted cell took a raw pair that did not alarm its change test: after k_min such pairs,
        if the recency-weighted mean of its residuals lies nearer no change than the shift, its learner did not
        change as the others did and the shift is revoked (its refined pair is its cluster's mean again). Returns
        whether the refined pair moved."""
        self.prov_n[cell] += 1
        if self.prov_n[cell] < self.k_min:
            return False
        e, p = self.resid[cell], self.prov[cell]
        if np.linalg.norm(e - p) <= np.linalg.norm(e):
            return False
        self.pub_T[cell] -= p
        self.prov[cell] = 0.0
        self.pub_version[cell] += 1
        self._refined_set_changed()
        return True

    def changed_cells(self) -> list[CellChange]:
        """The cells re-learned since the store began (this run or an earlier one it was loaded from), the most
        recently changed last (cells without a stamp first)."""
        ids = np.flatnonzero(self.changes.ravel() > 0)
        at = self.changed_at.ravel()
        out = [CellChange(int(i), int(self.changes.ravel()[i]), None if np.isnan(at[i]) else float(at[i]))
               for i in ids]
        return sorted(out, key=lambda c: (c.at is not None, c.at or 0.0, c.id))

    def cluster_mean(self, cell: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The mean of a cell's raw pairs so far, (teacher part, learner part) normalised, even before it holds k_min
        of them (then it is not a refined pair yet); the cell must hold at least one."""
        n = self.count[cell]
        if n == 0:
            raise ValueError(f"cell {cell} holds no raw pair")
        return self.sum_T[cell] / n, self.sum_L[cell] / n

    def is_configured(self, cell: tuple[int, int]) -> bool:
        """A cell is configured when it holds a refined pair (k_min members)."""
        return bool(self.pub_version[cell] > 0)

    def n_configured(self) -> int:
        """How many cells are configured."""
        return int(np.count_nonzero(self.pub_version))

    def configured(self) -> NDArray[np.bool_]:
        """Which cells are configured, as a (n_v, n_omega) mask (a copy: the caller cannot change the store)."""
        return self.pub_version > 0

    def refined_arrays(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """(ids, versions, teacher parts normalised, learner parts normalised) of all refined pairs (cached)."""
        if self._arrays is None:
            mask = self.pub_version > 0
            ids = np.flatnonzero(mask.ravel())
            self._arrays = (
                ids,
                self.pub_version.ravel()[ids],
                self.pub_T.reshape(-1, 2)[ids],
                self.pub_L.reshape(-1, 2)[ids],
            )
        return self._arrays

    def refined(self) -> list[RefinedPair]:
        """All refined pairs in teacher and learner units."""
        ids, vers, T, L = self.refined_arrays()
        cnt = self.count.ravel()
        tT = self.teacher_bounds.denormalise(T)
        tL = self.learner_bounds.denormalise(L)
        return [RefinedPair(int(i), int(v), int(cnt[i]), tT[k], tL[k]) for k, (i, v) in enumerate(zip(ids, vers))]

    @property
    def raw_count(self) -> int:
        """Raw pairs the store has taken (a re-learned cell forgets its pairs, not this count)."""
        return self.added

    def set_adapt(self, on: bool) -> None:
        """Change detection on or off from now on (a station's configuration), the limits' memory and test with it."""
        self.adapt, self.limits.memory = bool(on), (LIMIT_MEMORY_K * self.k_min if on else 0)
        self.limits.set_change_test(max(self.k_min, 2) if on else 0, self.change_tol, self.change_sigmas)

    # ----------------------------------------------------------------------------------------- persistence
    def to_bytes(self) -> bytes:
        """Versioned MessagePack blob with a CRC, so corruption is detected on load."""
        lim = self.limits
        blob = StoreBlob(
            schema=SCHEMA,
            schema_version=SCHEMA_VERSION,
            learner_bounds=self.learner_bounds.as_list(),
            teacher_bounds=self.teacher_bounds.as_list(),
            grid=list(self.grid),
            k_min=self.k_min,
            move_tol=self.move_tol,
            boundary_tol=self.boundary_tol,
            count=self.count.ravel().tolist(),
            sum_T=self.sum_T.ravel().tolist(),
            sum_L=self.sum_L.ravel().tolist(),
            pub_T=(self.pub_T - self.prov - self.spreading.shift).ravel().tolist(),
            pub_L=self.pub_L.ravel().tolist(),
            pub_version=self.pub_version.ravel().tolist(),
            revision=self.revision,
            limits=LimitsBlob(
                lo=lim.lo.tolist(), hi=lim.hi.tolist(), ext_lo=lim.ext_lo.tolist(), ext_hi=lim.ext_hi.tolist(),
                bsum_lo=lim.bsum_lo.tolist(), bsum_hi=lim.bsum_hi.tolist(), bcnt_lo=lim.bcnt_lo.tolist(),
                bcnt_hi=lim.bcnt_hi.tolist(), hull_sum=lim.hull_sum.ravel().tolist(),
                hull_cnt=lim.hull_cnt.ravel().tolist(), version=lim.version, **lim.turn_state(),
            ),
            sum_LL=self.sum_LL.ravel().tolist(),
            sum_TL=self.sum_TL.ravel().tolist(),
            adapt=self.adapt, relearned=self.relearned, added=self.added,
            changed_at=[None if np.isnan(v) else float(v) for v in self.changed_at.ravel()],
            resid=self.resid.ravel().tolist(),
            noise2=self.noise2.tolist(),
            recent_T=self.recent_T.ravel().tolist(),
            recent_L=self.recent_L.ravel().tolist(),
            recent_n=self.recent_n.ravel().tolist(),
            changes=self.changes.ravel().tolist(),
            cell_noise2=self.cell_noise2.ravel().tolist(),
            cell_noise_n=self.cell_noise_n.ravel().tolist(),
        )
        payload = msgspec.msgpack.encode(blob)
        return _MAGIC + zlib.crc32(payload).to_bytes(4, "little") + payload

    @classmethod
    def from_bytes(cls, data: bytes) -> PairStore:
        """Load a blob written by :meth:`to_bytes`; ValueError for anything corrupted or incompatible."""
        data = bytes(data)
        if len(data) < 12 or not data.startswith(_MAGIC):
            raise ValueError("not a pair-store blob (bad magic)")
        payload = data[12:]
        if zlib.crc32(payload).to_bytes(4, "little") != data[8:12]:
            raise ValueError("pair-store blob is corrupted (CRC mismatch)")
        try:
            raw = msgspec.msgpack.decode(payload)
        except msgspec.DecodeError as exc:
            raise ValueError(f"pair-store blob does not decode: {exc}") from exc
        if not isinstance(raw, dict) or raw.get("schema") != SCHEMA:
            raise ValueError("pair-store blob has the wrong schema")
        if raw.get("schema_version") not in READS_VERSIONS:
            raise ValueError(f"pair-store schema version {raw.get('schema_version')} is not supported "
                             f"(this build reads versions {', '.join(map(str, READS_VERSIONS))})")
        try:
            b = msgspec.convert(raw, StoreBlob)
        except msgspec.ValidationError as exc:
            raise ValueError(f"pair-store blob is malformed: {exc}") from exc
        gv, gw = b.grid
        n = gv * gw
        sizes = {
            "count": (b.count, n), "sum_T": (b.sum_T, 2 * n), "sum_L": (b.sum_L, 2 * n), "pub_T": (b.pub_T, 2 * n),
            "pub_L": (b.pub_L, 2 * n), "pub_version": (b.pub_version, n), "hull_sum": (b.limits.hull_sum, 2 * n),
            "hull_cnt": (b.limits.hull_cnt, n),
        }
        for name, (arr, want) in sizes.items():
            if len(arr) != want:
                raise ValueError(f"pair-store field {name} has {len(arr)} values, expected {want}")
        for name in ("lo", "hi", "ext_lo", "ext_hi", "bsum_lo", "bsum_hi", "bcnt_lo", "bcnt_hi"):
            if len(getattr(b.limits, name)) != 2:
                raise ValueError(f"pair-store limits field {name} must have 2 values")
        store = cls(Bounds.from_list(b.learner_bounds), Bounds.from_list(b.teacher_bounds), (gv, gw), b.k_min,
                    move_tol=b.move_tol, boundary_tol=b.boundary_tol, adapt=b.adapt)
        r = store.recent_T.shape[2]
        optional = {"sum_LL": 2 * n, "sum_TL": 2 * n, "changed_at": n, "resid": 2 * n, "noise2": 2,
                    "recent_T": 2 * n * r, "recent_L": 2 * n * r, "recent_n": n, "changes": n,
                    "cell_noise2": 2 * n, "cell_noise_n": n}
        for name, want in optional.items():
            arr = getattr(b, name)
            if arr is not None and len(arr) != want:
                raise ValueError(f"pair-store field {name} has {len(arr)} values, expected {want}")
        store.count = np.array(b.count, dtype=np.int64).reshape(gv, gw)
        store.sum_T = np.array(b.sum_T, dtype=float).reshape(gv, gw, 2)
        store.sum_L = np.array(b.sum_L, dtype=float).reshape(gv, gw, 2)
        store.pub_T = np.array(b.pub_T, dtype=float).reshape(gv, gw, 2)
        store.pub_L = np.array(b.pub_L, dtype=float).reshape(gv, gw, 2)
        store.pub_version = np.array(b.pub_version, dtype=np.int64).reshape(gv, gw)
        store.revision = b.revision
        lim = store.limits
        lim.lo, lim.hi = np.array(b.limits.lo, float), np.array(b.limits.hi, float)
        lim.ext_lo, lim.ext_hi = np.array(b.limits.ext_lo, float), np.array(b.limits.ext_hi, float)
        lim.bsum_lo, lim.bsum_hi = np.array(b.limits.bsum_lo, float), np.array(b.limits.bsum_hi, float)
        lim.bcnt_lo = np.array(b.limits.bcnt_lo, dtype=np.int64)
        lim.bcnt_hi = np.array(b.limits.bcnt_hi, dtype=np.int64)
        lim.hull_sum = np.array(b.limits.hull_sum, float).reshape(gv, gw, 2)
        lim.hull_cnt = np.array(b.limits.hull_cnt, dtype=np.int64).reshape(gv, gw)
        lim.version = b.limits.version
        if b.limits.turn_vw is not None:  # schema 4 (else none learned yet)
            lim.set_turn_state(b.limits.turn_vw, b.limits.turn_vv, b.limits.turn_n, b.limits.turn_prop)
        store.relearned = b.relearned
        store.added = int(store.count.sum()) if b.added is None else b.added
        if b.sum_LL is not None and b.sum_TL is not None:
            store.sum_LL = np.array(b.sum_LL, dtype=float).reshape(gv, gw, 2)
            store.sum_TL = np.array(b.sum_TL, dtype=float).reshape(gv, gw, 2)
        else:  # version 1: the cells' slopes start from their means (as if their pairs had all been at them)
            mL = store.sum_L / np.maximum(store.count, 1)[..., None]
            store.sum_LL = store.count[..., None] * mL * mL
            store.sum_TL = store.count[..., None] * mL * store.sum_T / np.maximum(store.count, 1)[..., None]
        if b.changed_at is not None:
            store.changed_at = np.array([np.nan if v is None else v for v in b.changed_at], dtype=float).reshape(gv, gw)
        if b.changes is not None:
            store.changes = np.array(b.changes, dtype=np.int64).reshape(gv, gw)
        else:  # versions 1 and 2: a cell with a change time changed once at least
            store.changes = (~np.isnan(store.changed_at)).astype(np.int64)
        if b.cell_noise2 is not None and b.cell_noise_n is not None:  # versions 1 and 2: no cell has its own yet
            store.cell_noise2 = np.array(b.cell_noise2, dtype=float).reshape(gv, gw, 2)
            store.cell_noise_n = np.array(b.cell_noise_n, dtype=np.int64).reshape(gv, gw)
        if b.resid is not None:
            store.resid = np.array(b.resid, dtype=float).reshape(gv, gw, 2)
        if b.noise2 is not None:
            store.noise2 = np.array(b.noise2, dtype=float)
        if b.recent_T is not None and b.recent_L is not None and b.recent_n is not None:
            store.recent_T = np.array(b.recent_T, dtype=float).reshape(gv, gw, r, 2)
            store.recent_L = np.array(b.recent_L, dtype=float).reshape(gv, gw, r, 2)
            store.recent_n = np.array(b.recent_n, dtype=np.int64).reshape(gv, gw)
        arrays = [store.sum_T, store.sum_L, store.pub_T, store.pub_L, lim.lo, lim.hi, lim.bsum_lo, lim.bsum_hi,
                  lim.hull_sum, store.sum_LL, store.sum_TL, store.resid, store.noise2, store.recent_T, store.recent_L,
                  store.cell_noise2]
        if (not all(np.all(np.isfinite(a)) for a in arrays) or np.any(store.count < 0) or np.any(store.recent_n < 0)
                or np.any(store.changes < 0) or np.any(store.noise2 < 0) or np.any(store.cell_noise2 < 0)
                or np.any(store.cell_noise_n < 0)):
            raise ValueError("pair-store blob holds non-finite or negative values")
        return store
