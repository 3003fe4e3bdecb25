"""The learner's limits on the teacher's command domain (paper Section 4.2, Eq. learn_capability).

The teacher's controller and planner must only ask for what the learner can do. The learner's limits are known
in the *learner's* command units (its hard bounds), but what matters is where they land on the *teacher's*
domain: the teacher equivalents of the learner's extreme commands. Two ways to learn them, both here:

- **Calibration**: drive the learner's extreme commands first (:func:`calibration_commands`); every pair whose
  learner part lies on the learner's boundary marks the bound directly.
- **Online adaptation**: start from the teacher's full range; a pair whose learner part is a new outlier (beyond
  every learner part seen so far on that axis and side) updates the bound on that side: on the learner's
  boundary it *is* the bound (averaged over all boundary pairs of that side, to tame noise; with a ``memory`` of M
  pairs, the store's change detection, over the last M or so: a running mean whose count stops at M is a
  recency-weighted one, so a limit follows a learner that lost or gained reach by its boundary pairs alone, where the
  paper's mean of every pair ever taken needs as many again to move halfway); inside, the bound is
  the proportional extrapolation of the paper's Eq. learn_capability, ``u_T,norm|max = u_T,norm / u_L,norm``
  (and its mirror ``1 - (1 - u_T,norm) / (1 - u_L,norm)`` for the lower side), until a boundary pair arrives.
  A bound is set only by pairs at its own edge: a pair whose teacher part is at (or beyond) the teacher's opposite
  edge extrapolates nothing on this side. The mirror assumes that the learner's top command gives the teacher's top;
  a pair that already gives the teacher's top part-way up the learner's range (a learner wider than the teacher:
  the stock SITL rover's 120 deg/s under the teacher's 45) refutes it, and the extrapolation would put the lower
  bound at the teacher's top (found on SITL, docs/BENCHMARKS.md: omega in [0.785, 0.785], the teacher turning one
  way only); likewise a pair at the teacher's bottom and the upper bound. A pair just inside that edge still
  extrapolates a narrow range (the paper's rule), which the probe of the never-driven limit then measures
  (:mod:`transfer.policy`).

**A learner that cannot turn in place** (an Ackermann rover, ``needs_speed``): its yaw-rate limit on each side is not a
number but a curvature, ``omega <= kappa * v`` (at standstill it cannot turn at all; at the top speed its turn
rate is the box's). Each side's ``kappa`` is the least-squares slope through the standstill point of that side's
boundary pairs, in teacher units: ``kappa = sum(v omega) / sum(v^2)`` over the pairs whose learner part lies on the
learner's yaw-rate edge (the full lock), weighted by ``v^2`` so the fast pairs, whose speed is measured best, count
most (with the same ``memory`` as the box). The box's yaw-rate edge is then ``kappa`` times the box's top speed,
and :attr:`LearnerLimits.curvature` gives the MPC the two slopes as linear constraints (``transfer.teacher.mpc``).
Why: on a car-like rover the mean of its boundary pairs, taken at whatever speed each came, allows its top turn rate
at its slowest speed, where it turns a fraction of it, and a turn probe sent at the slowest speed learns that it
cannot turn at all (docs/BENCHMARKS.md, "The transfer on SITL").

**An edge that moved** (:meth:`LearnerLimits.set_change_test`: the store's change detection switches it on with its own
``change_tol``; off, the paper's). A learned edge's boundary pairs may come sparsely, from cells the robot seldom drives
again (on the SITL rover, a turn-rate cap lowered mid-run: a side's seven boundary pairs in a whole run, three of them
from before the change), so neither the memory above nor a cell's own change test finds the change: the edge stays the
mean of old and new. Each side of each axis therefore tests its boundary pairs as a cell tests its pairs
(``transfer/store.py``, "A learner that changes"): a pair's residual is its teacher part less the edge it was taken at
(with ``needs_speed``, a yaw-rate side's curvature at the pair's speed); the recency-weighted mean of the residuals
(weight 1/k) beyond the tolerance and beyond ``sigmas`` standard deviations of its noise and of the edge's own error
(the mean of its n pairs: 1/n of their variance), with the last two pairs each beyond the tolerance on the change's side
(one outlier is not a change), means the edge moved. The noise is estimated from the median size of the differences of a
side's consecutive residuals, both taken against the edge the later pair is tested at (both sides of an axis pooled; a
change moves one difference per side, which would raise a mean square above the change), and the test waits for k of
them. On an alarm the side keeps only its last 2 k boundary pairs that agree with the change (their residual nearer the
mean than zero), and so do its curvature and the hull points of its cells; ``relearned`` counts it. Not persisted:
after a load the test learns its noise again. Its false alarms on unchanged runs and on noisy pairs are in
docs/PAPER.md, "An edge that moved".

All arithmetic is on normalised coordinates: the teacher side by the teacher's bounds, the learner side by the
learner's. Exposed as the axis-aligned ``box`` (what bounds the MPC inputs and filters primitives) and the convex
``hull`` of the boundary pairs' teacher parts and the refined pairs' (the paper's dashed envelope: every command the
learner has been seen to follow is inside it; of the boundary pairs alone, a run that met only the learner's top
speed would have a sliver of a hull that left out most of its refined pairs).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.domain import Bounds
from transfer.hull import convex_hull
from transfer.limits_watch import TURN_LOST, EdgeWatch, unsettled

_MIN_PROPORTIONAL = 0.2  # below this normalised learner level a proportional extrapolation is too noisy to use


def calibration_commands(learner_bounds: Bounds, n: int | tuple[int, int] = 5) -> NDArray[np.float64]:
    """An n x n (or n_v x n_omega) grid of learner commands spanning the learner's box, extremes included
    (calibration stage)."""
    nv, nw = (n, n) if isinstance(n, int) else (int(n[0]), int(n[1]))
    if nv < 2 or nw < 2:
        raise ValueError("a calibration grid needs n >= 2 on each axis to reach both extremes")
    V, W = np.meshgrid(np.linspace(0.0, 1.0, nv), np.linspace(0.0, 1.0, nw), indexing="ij")
    return learner_bounds.denormalise(np.stack([V.ravel(), W.ravel()], axis=-1))


def _recency(n: int, memory: int) -> tuple[float, int]:
    """A running mean's count stopped at ``memory`` (0: never): the factor to scale its sum by before the next term
    and the count it then has, so the mean weighs about the last ``memory`` terms (recency-weighted)."""
    return ((memory - 1) / n, memory - 1) if memory and n >= memory else (1.0, n)


def grid_cell(l_n: ArrayLike, grid: tuple[int, int]) -> tuple[int, int]:
    """The cell of the ``grid`` (n_v, n_omega) a normalised learner part in [0, 1]^2 falls in (paper Section 5.2's
    clustering; the last cell holds the upper edge)."""
    gv, gw = grid
    return (min(int(l_n[0] * gv), gv - 1), min(int(l_n[1] * gw), gw - 1))


def _keep_apart(lo: list[float], hi: list[float], a: int) -> None:
    """Axis ``a``'s normalised edges (in place) a millionth apart at least: a collapsed box stays a box."""
    if hi[a] - lo[a] < 1e-6:
        mid = 0.5 * (hi[a] + lo[a])
        lo[a], hi[a] = mid - 5e-7, mid + 5e-7


class _EdgeTest:
    """The change test of the learned edges (module docstring, "An edge that moved"): per axis side (index ``[axis]
    [side]``, side 0 the lower) the recency-weighted mean (weight 1/k) of its boundary pairs' residuals against the
    edge they were taken at, the axis's noise (from the differences of a side's consecutive residuals against one
    edge, which a lasting change moves once; both sides pooled) and the side's last ``2 k`` boundary pairs (normalised
    teacher and learner parts: what the edge re-learns from). Python lists: a pair at an edge is one tick's few
    scalars, and numpy's per-element overhead was most of their cost."""

    def __init__(self, k: int, tol: float, sigmas: float) -> None:
        self.k, self.tol, self.sigmas = int(k), float(tol), float(sigmas)
        self.resid = [[0.0, 0.0], [0.0, 0.0]]
        self.last = [[math.nan, math.nan], [math.nan, math.nan]]
        #: per axis: the last 4 k residual differences' sizes, oldest first (the test waits for k of them)
        self.diffs: list[list[float]] = [[], []]
        self.ring: list[list[list[tuple[float, ...]]]] = [[[], []], [[], []]]  # per side: its last 2 k pairs

    def noise2(self, a: int) -> float:
        """Axis ``a``'s residual variance when nothing changes, from the median size of its last 4 k residual
        differences (a difference of two residuals of spread s spreads s sqrt(2), and half of its sizes lie within
        0.674 of that): the differences across a change (one per side that changed) would raise a mean square above
        the change it is to find, and do not move the median."""
        d = self.diffs[a]
        return (statistics.median(d) / (0.6745 * math.sqrt(2.0))) ** 2 if d else 0.0

    def alarm(self, a: int, side: int, r: float, count: int, prev: float) -> bool:
        """One boundary pair's residual ``r`` on side ``side`` of axis ``a``, whose edge is the mean of ``count``
        boundary pairs: whether the edge moved (the residuals' mean beyond ``tol`` and ``sigmas`` standard deviations
        of its noise and of the edge's own, this pair's residual and the last one each beyond ``tol`` on its side, once
        the axis has ``k`` differences). A pair that does not alarm teaches the noise: its difference from ``prev``,
        the side's previous boundary pair's residual against the same edge as ``r`` (NaN: none), from a side's second
        pair on and after an alarm too (the kept pairs are the new edge's). Against the edge each was taken at, the
        differences after a change shrank with the edge as it took the new pairs in, each one a part of the change,
        and raised the noise's median above the next side's change; and a side's first two pairs gave none, so a run
        with few pairs at its locks waited past its change (both traced on SITL)."""
        res = self.resid[a]
        e = res[side] = res[side] + (r - res[side]) / self.k
        w = 1.0 / self.k
        last = self.last[a][side]
        if (len(self.diffs[a]) >= self.k and abs(e) > self.tol
                and not math.isnan(last) and r * e > 0.0 and last * e > 0.0 and min(abs(r), abs(last)) > self.tol
                and abs(e) > self.sigmas * math.sqrt(self.noise2(a) * (w / (2 - w) + 1.0 / count))):
            return True
        if not math.isnan(prev):
            d = self.diffs[a]
            d.append(abs(r - prev))
            if len(d) > 4 * self.k:
                del d[0]
        self.last[a][side] = r
        return False

    def remember(self, a: int, side: int, tn: list[float], ln: list[float]) -> None:
        """A boundary pair of that side (normalised teacher and learner parts) into its ring."""
        ring = self.ring[a][side]
        ring.append((*tn, *ln))
        if len(ring) > 2 * self.k:
            del ring[0]

    def recent(self, a: int, side: int) -> NDArray[np.float64]:
        """The side's last boundary pairs, oldest first, as rows (t_v, t_w, l_v, l_w) (normalised)."""
        return np.array(self.ring[a][side], dtype=float).reshape(-1, 4)

    def restart(self, a: int, side: int) -> None:
        """The side's edge was learned again: its residuals start again (its noise stays: the learner's)."""
        self.resid[a][side] = 0.0
        self.last[a][side] = math.nan


class LearnerLimits:
    """Per-axis lower/upper bounds on the normalised teacher domain plus the boundary points for the hull."""

    def __init__(self, teacher_bounds: Bounds, learner_bounds: Bounds, grid: tuple[int, int], boundary_tol: float,
                 memory: int = 0, needs_speed: bool = False):
        if memory < 0 or memory == 1:
            raise ValueError(f"limits memory must be 0 (never forget) or at least 2 pairs, got {memory}")
        self.memory = int(memory)  # boundary pairs a bound's mean weighs (module docstring); 0: every pair alike
        #: the learner cannot turn in place: its yaw-rate edges are curvatures (module docstring); the sums below are
        #: kept either way, so a store can be read with either setting
        self.needs_speed = bool(needs_speed)
        self.teacher_bounds = teacher_bounds
        self.learner_bounds = learner_bounds
        self.grid = grid
        self.boundary_tol = float(boundary_tol)
        self.lo = np.zeros(2)  # normalised teacher-domain bounds
        self.hi = np.ones(2)
        self.ext_lo = np.full(2, np.inf)  # most extreme normalised learner parts seen
        self.ext_hi = np.full(2, -np.inf)
        self.bsum_lo = np.zeros(2)  # running sums of boundary pairs' teacher parts per axis side
        self.bsum_hi = np.zeros(2)
        self.bcnt_lo = np.zeros(2, dtype=np.int64)
        self.bcnt_hi = np.zeros(2, dtype=np.int64)
        # per yaw-rate side (0: lower, 1: upper): sums of v*omega and v^2 of its boundary pairs (teacher units)
        self.turn_vw = np.zeros(2)
        self.turn_vv = np.zeros(2)
        self.turn_n = np.zeros(2, dtype=np.int64)
        self.turn_prop = np.full(2, np.nan)  # each side's curvature extrapolated from its outliers (NaN: none yet)
        gv, gw = grid
        self.hull_sum = np.zeros((gv, gw, 2))  # boundary cells: running mean of teacher parts on the boundary
        self.hull_cnt = np.zeros((gv, gw), dtype=np.int64)
        self.version = 0
        self.relearned = 0  # edges learned again by their change test (``set_change_test``)
        self._test: _EdgeTest | None = None
        #: after a change, the sides whose edge is unknown; the widest edges held (``transfer/limits_watch.py``)
        self.watch = EdgeWatch()
        self._prev_t: list[float] | None = None  # the last pair's teacher part, when its caller gave the one before
        self._box_cache: Bounds | None = None
        self._hull_cache: NDArray[np.float64] | None = None
        #: the refined pairs' normalised teacher parts (the store gives them; it drops the hull's cache when they
        #: change): the hull encloses them too
        self.refined_points: Callable[[], NDArray[np.float64]] | None = None

    def set_change_test(self, k: int, tol: float = 0.0, sigmas: float = 5.0) -> None:
        """The edges' change test on (``k`` >= 2: its residuals' weight is 1/k; ``tol``: the least change it finds,
        normalised teacher units; ``sigmas``: in standard deviations of its noise) or off (``k`` 0, the paper's)."""
        self._test = _EdgeTest(k, tol, sigmas) if k >= 2 else None

    def refined_changed(self) -> None:
        """The store's refined pairs changed: the hull is computed again when next asked."""
        self._hull_cache = None

    # ------------------------------------------------------------------------------------------- updating
    def update(self, t_n: NDArray[np.float64], l_n: NDArray[np.float64], cell: tuple[int, int],
               prev_l_n: NDArray[np.float64] | None = None) -> bool:
        """Take one pair (normalised teacher part, normalised learner part); return True if the limits moved.
        ``prev_l_n``: the learner command before it (normalised; None: unknown); with the change test on, a boundary
        pair counts only once the learner settled at that extreme (``transfer/limits_watch.py``, "A settled edge").

        Scalar arithmetic on Python floats (one pair a tick, two axes: numpy's per-element overhead was most of the
        cost); the same operations in the same order as on the arrays, so the same results."""
        tol = self.boundary_tol
        on_boundary = False
        lo, hi = self.lo.tolist(), self.hi.tolist()
        old = (lo[:], hi[:])
        ext_lo, ext_hi = self.ext_lo.tolist(), self.ext_hi.tolist()
        old_ext = (ext_lo[:], ext_hi[:])
        bcnt_lo, bcnt_hi = self.bcnt_lo.tolist(), self.bcnt_hi.tolist()
        bsum_lo, bsum_hi = self.bsum_lo.tolist(), self.bsum_hi.tolist()
        tn, ln = np.asarray(t_n, dtype=float).tolist(), np.asarray(l_n, dtype=float).tolist()
        mem, test = self.memory, self._test
        prev = None if prev_l_n is None or test is None else np.asarray(prev_l_n, dtype=float).tolist()
        prev_t, self._prev_t = self._prev_t, (tn if prev is not None else None)
        if prev_t is None:
            prev_t = [math.nan, math.nan]
        for a in range(2):
            t, l = tn[a], ln[a]
            if prev is not None and test is not None and unsettled(t, l, prev_t[a], prev[a], tol, test.tol):
                ext_hi[a], ext_lo[a] = max(ext_hi[a], l), min(ext_lo[a], l)
                continue
            if l >= 1.0 - tol:
                on_boundary = True
                if test is not None:
                    moved = self._edge_pair(test, a, 1, bsum_hi[a] / max(bcnt_hi[a], 1), tn, ln, bcnt_hi[a])
                    if moved is not None:
                        bsum_hi[a], bcnt_hi[a] = moved
                    self.watch.known(a, 1, 1)
                keep, bcnt_hi[a] = _recency(bcnt_hi[a], mem)
                bsum_hi[a] *= keep
                bsum_hi[a] += t
                bcnt_hi[a] += 1
                hi[a] = bsum_hi[a] / bcnt_hi[a]
            elif l > ext_hi[a] and bcnt_hi[a] == 0 and l >= _MIN_PROPORTIONAL and t > tol:
                hi[a] = t / l  # Eq. learn_capability
            if l <= tol:
                on_boundary = True
                if test is not None:
                    moved = self._edge_pair(test, a, 0, bsum_lo[a] / max(bcnt_lo[a], 1), tn, ln, bcnt_lo[a])
                    if moved is not None:
                        bsum_lo[a], bcnt_lo[a] = moved
                    self.watch.known(a, 0, 1)
                keep, bcnt_lo[a] = _recency(bcnt_lo[a], mem)
                bsum_lo[a] *= keep
                bsum_lo[a] += t
                bcnt_lo[a] += 1
                lo[a] = bsum_lo[a] / bcnt_lo[a]
            elif l < ext_lo[a] and bcnt_lo[a] == 0 and 1.0 - l >= _MIN_PROPORTIONAL and t < 1.0 - tol:
                lo[a] = 1.0 - (1.0 - t) / (1.0 - l)  # its mirror for the lower side
            ext_hi[a] = max(ext_hi[a], l)
            ext_lo[a] = min(ext_lo[a], l)
            # the teacher's own range is the outer limit; keep lo < hi
            lo[a] = min(max(lo[a], 0.0), 1.0)
            hi[a] = min(max(hi[a], 0.0), 1.0)
            _keep_apart(lo, hi, a)
        if prev is not None and test is not None and unsettled(tn[1], ln[1], prev_t[1], prev[1], tol, test.tol):
            pass  # an unsettled pair at a learned yaw-rate edge: no sample of its curvature either
        elif ln[1] >= 1.0 - tol or ln[1] <= tol:  # on the learner's yaw-rate edge: a sample of that side's curvature
            self._turn_sample(1 if ln[1] >= 1.0 - tol else 0, tn[0], tn[1])
        else:  # a new outlier inside it: Eq. learn_capability's (the first pair is a new outlier on both sides;
            # _turn_extrapolate keeps it only for the side its turn is on)
            if ln[1] > old_ext[1][1]:
                self._turn_extrapolate(1, tn, ln)
            if ln[1] < old_ext[0][1]:
                self._turn_extrapolate(0, tn, ln)
        if self.needs_speed:
            self._turn_edges(lo, hi)
        changed = old != (lo, hi)
        if changed:  # written back only when they moved (most pairs move nothing)
            self.lo[:], self.hi[:] = lo, hi
        if old_ext != (ext_lo, ext_hi):
            self.ext_lo[:], self.ext_hi[:] = ext_lo, ext_hi
        if on_boundary:
            self.bsum_lo[:], self.bsum_hi[:] = bsum_lo, bsum_hi
            self.bcnt_lo[:], self.bcnt_hi[:] = bcnt_lo, bcnt_hi
            self.watch.widen(lo, hi, bcnt_lo, bcnt_hi)
            self.hull_sum[cell] += t_n
            self.hull_cnt[cell] += 1
            self._hull_cache = None
        if changed or on_boundary:
            self.version += 1
            self._box_cache = None
        return changed

    def _edge_pair(self, test: _EdgeTest, a: int, side: int, edge: float, tn: list[float], ln: list[float],
                   count: int) -> tuple[float, int] | None:
        """A boundary pair of side ``side`` of axis ``a`` (module docstring, "An edge that moved"), before it joins the
        side's sums (``count`` pairs, their mean ``edge``, not clipped to the teacher's range): its residual against
        the edge it was taken at (:meth:`_edge_at`) into the side's change test. On an alarm the side forgets its
        boundary pairs but its recent ones that agree with the change (their residual nearer the test's mean than
        zero), and so do its curvature and its cells' hull points; returns the side's new (sum, count), else None. An
        edge with no boundary pair yet (extrapolated) is not tested."""
        at_speed = a == 1 and self.needs_speed
        r = tn[a] - (self._edge_at(a, side, edge, tn[0]) if at_speed else edge)
        ring = test.ring[a][side]  # its last pair: the previous residual, against the same edge
        prev = math.nan if not ring else ring[-1][a] - (self._edge_at(a, side, edge, ring[-1][0]) if at_speed else edge)
        alarm = count > 0 and not math.isnan(r) and test.alarm(a, side, r, count, prev)
        out = None
        if alarm:
            e = test.resid[a][side]
            rows = test.recent(a, side)
            res = rows[:, a] - np.array([self._edge_at(a, side, edge, v) for v in rows[:, 0].tolist()])
            keep = np.abs(res - e) < np.abs(res)
            kept = rows[keep]
            out = (float(kept[:, a].sum()), len(kept))
            if a == 1:
                self.turn_vw[side] = self.turn_vv[side] = 0.0
                self.turn_n[side] = 0
                self.turn_prop[side] = np.nan
                for tv, tw in kept[:, :2].tolist():
                    self._turn_sample(side, tv, tw)
            row = self.grid[a] - 1 if side else 0  # the side's cells: their hull points are the kept pairs in them
            cells = [grid_cell(x, self.grid) for x in kept[:, 2:].tolist()]
            for c in zip(*np.nonzero(self.hull_cnt > 0)):
                c = (int(c[0]), int(c[1]))
                if c[a] == row:
                    mine = [k for k, ck in enumerate(cells) if ck == c]
                    self.hull_sum[c] = kept[mine, :2].sum(axis=0) if mine else 0.0
                    self.hull_cnt[c] = len(mine)
            self._hull_cache = None
            test.restart(a, side)
            self.relearned += 1
            # an edge moved: every other learned side is unknown until it shows its edge again (transfer/
            # limits_watch.py); this one was learned again from its pairs since the change
            self.watch.changed([[int(self.bcnt_lo[b]) or (b == a and side == 0),
                                 int(self.bcnt_hi[b]) or (b == a and side == 1)] for b in (0, 1)])
            self.watch.known(a, side, len(kept))
        test.remember(a, side, tn, ln)
        return out

    def _edge_at(self, a: int, side: int, edge: float, v_n: float) -> float:
        """The edge a boundary pair at normalised teacher speed ``v_n`` is tested against: ``edge``, or with
        ``needs_speed`` a yaw-rate side's curvature times that speed (NaN while the side has no full-lock pair)."""
        if a == 1 and self.needs_speed:
            got = self._turn_edge(side, max(self._teacher(0, v_n), 0.0))
            return math.nan if got is None or self.turn_n[side] == 0 else got
        return edge

    def set_needs_speed(self, on: bool) -> None:
        """Read the limits as those of a learner that cannot turn in place (``on``), or one that can: the box's
        yaw-rate edges follow at once (from the curvatures, or back to the mean of the boundary pairs)."""
        on = bool(on)
        if on == self.needs_speed:
            return
        self.needs_speed = on
        lo, hi = self.lo.tolist(), self.hi.tolist()
        if on:
            self._turn_edges(lo, hi)
        else:
            if self.bcnt_hi[1]:
                hi[1] = float(self.bsum_hi[1] / self.bcnt_hi[1])
            if self.bcnt_lo[1]:
                lo[1] = float(self.bsum_lo[1] / self.bcnt_lo[1])
        self.lo[:], self.hi[:] = lo, hi
        self.version += 1
        self._box_cache = None
        self._hull_cache = None

    def saved(self) -> dict[str, Any]:
        """The limits as a saved store holds them (the fields of ``transfer/store_blob.py``'s ``LimitsBlob``; a side's
        ``turn_prop`` None: none extrapolated on it)."""
        return {"lo": self.lo.tolist(), "hi": self.hi.tolist(), "ext_lo": self.ext_lo.tolist(),
                "ext_hi": self.ext_hi.tolist(), "bsum_lo": self.bsum_lo.tolist(), "bsum_hi": self.bsum_hi.tolist(),
                "bcnt_lo": self.bcnt_lo.tolist(), "bcnt_hi": self.bcnt_hi.tolist(),
                "hull_sum": self.hull_sum.ravel().tolist(), "hull_cnt": self.hull_cnt.ravel().tolist(),
                "version": self.version, "turn_vw": self.turn_vw.tolist(), "turn_vv": self.turn_vv.tolist(),
                "turn_n": self.turn_n.tolist(),
                "turn_prop": [None if math.isnan(k) else float(k) for k in self.turn_prop]}

    def restore(self, s: dict[str, Any]) -> None:
        """Load what :meth:`saved` gave (or an older store's, without the curvatures: none learned yet); ValueError
        for anything a saved store cannot hold, and then nothing is changed."""
        gv, gw = self.grid
        for name in ("lo", "hi", "ext_lo", "ext_hi", "bsum_lo", "bsum_hi", "bcnt_lo", "bcnt_hi"):
            if len(s[name]) != 2:
                raise ValueError(f"pair-store limits field {name} must have 2 values")
        for name, want in (("hull_sum", 2 * gv * gw), ("hull_cnt", gv * gw)):
            if len(s[name]) != want:
                raise ValueError(f"pair-store field {name} has {len(s[name])} values, expected {want}")
        f = {k: np.array(s[k], dtype=float) for k in ("lo", "hi", "ext_lo", "ext_hi", "bsum_lo", "bsum_hi")}
        hull_sum = np.array(s["hull_sum"], dtype=float).reshape(gv, gw, 2)
        if not all(np.all(np.isfinite(f[k])) for k in ("lo", "hi", "bsum_lo", "bsum_hi")) or not np.all(
                np.isfinite(hull_sum)):
            raise ValueError("pair-store blob holds non-finite or negative values (the limits)")
        if s.get("turn_vw") is not None:  # (else none learned yet)
            self.set_turn_state(s["turn_vw"], s.get("turn_vv"), s.get("turn_n"), s.get("turn_prop"))
        self.lo, self.hi, self.ext_lo, self.ext_hi = f["lo"], f["hi"], f["ext_lo"], f["ext_hi"]
        self.bsum_lo, self.bsum_hi = f["bsum_lo"], f["bsum_hi"]
        self.bcnt_lo, self.bcnt_hi = np.array(s["bcnt_lo"], dtype=np.int64), np.array(s["bcnt_hi"], dtype=np.int64)
        self.hull_sum, self.hull_cnt = hull_sum, np.array(s["hull_cnt"], dtype=np.int64).reshape(gv, gw)
        self.version = int(s["version"])
        self._box_cache = self._hull_cache = None

    def set_turn_state(self, vw: list, vv: list | None, n: list | None, prop: list | None) -> None:
        """Load what :meth:`turn_state` gave; ValueError for anything a saved store cannot hold."""
        if vv is None or n is None or prop is None or not len(vw) == len(vv) == len(n) == len(prop) == 2:
            raise ValueError("pair-store limits fields turn_vw, turn_vv, turn_n, turn_prop need 2 values each")
        a_vw, a_vv, a_n = np.array(vw, dtype=float), np.array(vv, dtype=float), np.array(n, dtype=np.int64)
        a_prop = np.array([np.nan if k is None else k for k in prop], dtype=float)
        if (not np.all(np.isfinite(a_vw)) or not np.all(np.isfinite(a_vv)) or np.any(np.isinf(a_prop))
                or np.any(a_vv < 0) or np.any(a_n < 0)):
            raise ValueError("pair-store blob holds non-finite or negative values (the limits' curvatures)")
        self.turn_vw, self.turn_vv, self.turn_n, self.turn_prop = a_vw, a_vv, a_n, a_prop

    def _turn_sample(self, side: int, tv_n: float, tw_n: float) -> None:
        """One boundary pair of yaw-rate side ``side`` (0: lower, 1: upper), its normalised teacher part: into the
        side's curvature sums (teacher units, recency-weighted with the box's ``memory``); a pair at standstill or
        backwards says nothing of a curvature."""
        v = self._teacher(0, tv_n)
        if v <= 0.0:
            return
        w = self._teacher(1, tw_n)
        keep, n = _recency(int(self.turn_n[side]), self.memory)
        self.turn_vw[side] *= keep
        self.turn_vv[side] *= keep
        self.turn_vw[side] += v * w
        self.turn_vv[side] += v * v
        self.turn_n[side] = n + 1

    def _turn_extrapolate(self, side: int, tn: list[float], ln: list[float]) -> None:
        """A new outlier of yaw-rate side ``side`` inside the learner's edge (normalised parts ``tn``, ``ln``): while
        the side has no full-lock pair, its curvature is the pair's own (omega / v) over the share of the side's
        full lock it was commanded, the paper's proportional extrapolation (Eq. learn_capability) read as a
        curvature; too slow a pair, or too small a share, says too little."""
        if self.turn_n[side]:
            return
        lb = self.learner_bounds
        v, w = self._teacher(0, tn[0]), self._teacher(1, tn[1])
        w_l = lb.w[0] + ln[1] * (lb.w[1] - lb.w[0])
        lock = lb.w[1] if side else lb.w[0]
        share = w_l / lock if lock else 0.0
        if share < _MIN_PROPORTIONAL or tn[0] < _MIN_PROPORTIONAL or v <= 0.0 or (w > 0.0) != bool(side) or w == 0.0:
            return
        self.turn_prop[side] = (w / v) / share

    def _kappa(self, side: int) -> float:
        """Side ``side``'s learned curvature (rad/m; the lower side's <= 0 <= the upper's): from its full-lock
        pairs, else extrapolated from its outliers (:meth:`_turn_extrapolate`), else +-inf. A vehicle can always
        drive straight, so a slope past zero (a pair read part-way into a turn the other way) is taken as zero."""
        if self.turn_n[side] == 0 or self.turn_vv[side] <= 0.0:
            prop = float(self.turn_prop[side])
            if math.isnan(prop):
                return math.inf if side else -math.inf
            return max(prop, 0.0) if side else min(prop, 0.0)
        k = float(self.turn_vw[side] / self.turn_vv[side])
        return max(k, 0.0) if side else min(k, 0.0)

    def _turn_edges(self, lo: list[float], hi: list[float]) -> None:
        """``needs_speed``: the box's yaw-rate edges (normalised, in place) are each side's curvature times the box's
        top speed, on the sides that have one (learned or extrapolated)."""
        v_top = max(self._teacher(0, hi[0]), 0.0)
        for side, edges in ((0, lo), (1, hi)):
            wn = self._turn_edge(side, v_top)
            if wn is not None:
                edges[1] = min(max(wn, 0.0), 1.0)
        _keep_apart(lo, hi, 1)

    def _teacher(self, a: int, x_n: float) -> float:
        """Normalised teacher coordinate ``x_n`` of axis ``a`` (0: v, 1: omega) in teacher units (one scalar: what
        ``Bounds.denormalise`` does to arrays)."""
        lo, hi = self.teacher_bounds.v if a == 0 else self.teacher_bounds.w
        return lo + x_n * (hi - lo)

    def _turn_edge(self, side: int, v: float) -> float | None:
        """Side ``side``'s yaw-rate edge at speed ``v`` (teacher units), its curvature times ``v``, normalised and not
        clipped; None while the side has no curvature."""
        k = self._kappa(side)
        if math.isinf(k):
            return None
        tb = self.teacher_bounds
        return (k * v - tb.w[0]) / (tb.w[1] - tb.w[0])

    def forget(self, cell: tuple[int, int], old_T: NDArray[np.float64], old_L: NDArray[np.float64],
               new_T: NDArray[np.float64], new_L: NDArray[np.float64]) -> None:
        """A cell's learner changed (:meth:`transfer.store.PairStore.add`): the side of every axis where its pairs
        before the change (``old_*``, normalised) lay on the learner's boundary forgets every boundary pair it had
        and keeps only the cell's pairs since the change (``new_*``) that lie there, so a limit shrinks as well as
        grows; the cell's hull point likewise."""
        tol = self.boundary_tol
        edge = self.hull_cnt[cell] > 0  # the cell has given boundary pairs (its row or column is at an edge)
        for a in range(2):
            if np.any(old_L[:, a] >= 1.0 - tol) or (edge and cell[a] == self.grid[a] - 1):
                if self._test is not None:
                    self._test.restart(a, 1)
                on = new_L[:, a] >= 1.0 - tol
                self.bsum_hi[a], self.bcnt_hi[a] = float(new_T[on, a].sum()), int(on.sum())
                if on.any():
                    self.hi[a] = self.bsum_hi[a] / self.bcnt_hi[a]
            if np.any(old_L[:, a] <= tol) or (edge and cell[a] == 0):
                if self._test is not None:
                    self._test.restart(a, 0)
                on = new_L[:, a] <= tol
                self.bsum_lo[a], self.bcnt_lo[a] = float(new_T[on, a].sum()), int(on.sum())
                if on.any():
                    self.lo[a] = self.bsum_lo[a] / self.bcnt_lo[a]
        for side, was, on in ((1, np.any(old_L[:, 1] >= 1.0 - tol) or (edge and cell[1] == self.grid[1] - 1),
                               new_L[:, 1] >= 1.0 - tol),
                              (0, np.any(old_L[:, 1] <= tol) or (edge and cell[1] == 0), new_L[:, 1] <= tol)):
            if was:  # the yaw-rate side's curvature likewise
                self.turn_vw[side] = self.turn_vv[side] = 0.0
                self.turn_n[side] = 0
                self.turn_prop[side] = np.nan
                for tv, tw in new_T[on].tolist():
                    self._turn_sample(side, tv, tw)
        if self.needs_speed:
            lo, hi = self.lo.tolist(), self.hi.tolist()
            self._turn_edges(lo, hi)
            self.lo[:], self.hi[:] = lo, hi
        on = np.any((new_L >= 1.0 - tol) | (new_L <= tol), axis=1) if len(new_L) else np.zeros(0, dtype=bool)
        self.hull_sum[cell] = new_T[on].sum(axis=0) if on.any() else 0.0
        self.hull_cnt[cell] = int(on.sum())
        self.version += 1
        self._box_cache = None
        self._hull_cache = None

    # -------------------------------------------------------------------------------------------- queries
    def turn_lost(self, tol: float = TURN_LOST) -> bool:
        """Whether a yaw-rate edge has come inside the widest it held by more than ``tol`` (normalised teacher units):
        the learner lost reach, and the teacher's MPC slows for bends (``transfer/limits_watch.py``)."""
        return self.watch.turn_lost(float(self.lo[1]), float(self.hi[1]), tol)

    def reprobe(self, t_n: ArrayLike) -> list[tuple[int, int]]:
        """The sides (axis, side; side 0 the lower) whose edge is unknown after a change and which teacher command
        ``t_n`` (normalised) leans towards: probe them (``transfer/limits_watch.py``). Empty without the change
        test (the paper's limits)."""
        if self._test is None:
            return []
        tn = np.asarray(t_n, dtype=float).tolist()
        return self.watch.reprobe(tn, self.lo.tolist(), self.hi.tolist())

    @property
    def box(self) -> Bounds:
        """The axis-aligned teacher-domain box the teacher's controller and planner are bounded by."""
        if self._box_cache is None:
            tb = self.teacher_bounds
            lo = tb.denormalise(self.lo)
            hi = tb.denormalise(self.hi)
            self._box_cache = Bounds((float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])))
        return self._box_cache

    @property
    def curvature(self) -> tuple[float, float] | None:
        """``needs_speed``: the learned curvatures (rad/m) of the lower and the upper yaw-rate side, ``(k_lo, k_hi)``
        with ``k_lo * v <= omega <= k_hi * v`` (teacher units; +-inf for a side with neither a full-lock pair nor an
        extrapolation yet); None for a learner that turns in place."""
        return self.learned_curvature() if self.needs_speed else None

    def turn_edges_at(self, v_n: float) -> tuple[float, float]:
        """The normalised yaw-rate edges ``(lo, hi)`` at normalised teacher speed ``v_n``: with ``needs_speed`` each
        learned side's curvature times that speed (the line the MPC's inputs may reach), else the box's."""
        lo, hi = float(self.lo[1]), float(self.hi[1])
        if not self.needs_speed:
            return lo, hi
        v = max(self._teacher(0, v_n), 0.0)
        e_lo, e_hi = self._turn_edge(0, v), self._turn_edge(1, v)
        return (lo if e_lo is None else max(lo, e_lo)), (hi if e_hi is None else min(hi, e_hi))

    def learned_curvature(self) -> tuple[float, float]:
        """The two sides' curvatures, from their full-lock pairs or extrapolated (rad/m; +-inf: none yet), whatever
        ``needs_speed`` says (for a learner that turns in place they bound nothing: ``pairs show`` prints them)."""
        return self._kappa(0), self._kappa(1)

    def known_curvature(self) -> tuple[float | None, float | None]:
        """:meth:`learned_curvature` with None for a side not learned yet (its +-inf), as reports and messages
        carry it (JSON has no infinity)."""
        k_lo, k_hi = self.learned_curvature()
        return (None if math.isinf(k_lo) else k_lo), (None if math.isinf(k_hi) else k_hi)

    @property
    def hull(self) -> NDArray[np.float64]:
        """Convex hull (counter-clockwise (K, 2) vertices, teacher units) of the boundary pairs' teacher parts and
        the refined pairs'; the box's corners while fewer than three non-collinear such points are known."""
        if self._hull_cache is None:
            mask = self.hull_cnt > 0
            pts = self.hull_sum[mask] / self.hull_cnt[mask][:, None]
            if self.refined_points is not None:
                pts = np.vstack([pts, np.asarray(self.refined_points(), dtype=float).reshape(-1, 2)])
            hull_n = convex_hull(pts)
            self._hull_cache = (
                self.box.corners() if hull_n is None else self.teacher_bounds.denormalise(hull_n)
            )
        return self._hull_cache

    def contains(self, u_T: ArrayLike, *, use_hull: bool = False, tol: float = 1e-9) -> bool | NDArray[np.bool_]:
        """Is the teacher command inside the learned limits (the box, or the hull)?"""
        u = np.asarray(u_T, dtype=float)
        if not use_hull:
            return self.box.contains(u, tol)
        h = self.hull
        edges = np.roll(h, -1, axis=0) - h
        rel = u[..., None, :] - h
        cross = edges[:, 0] * rel[..., 1] - edges[:, 1] * rel[..., 0]
        scale = tol * float(np.max(self.teacher_bounds.span))
        inside = np.all(cross >= -scale * np.linalg.norm(edges, axis=1), axis=-1)
        return bool(inside) if np.ndim(inside) == 0 else inside
