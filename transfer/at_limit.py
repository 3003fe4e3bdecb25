"""A teacher command at a driven learned limit, mapped (paper Section 5.2; docs/PAPER.md, "Along a driven limit" and
"The calibrated start").

A bounded controller's commands sit exactly at the learned limits (the MPC saturates there), where the mission's own
refined pairs are nearly collinear (the boundary row of cells' means): the 2-D regions there are slivers whose maps are
ill-conditioned. :class:`LimitMap` maps such a command one-dimensionally, along the limit's row of pairs (``row``),
or, after the paper's calibrated start, by the mapping region just inside the limit (``region``, :data:`AT_LIMIT`),
with the learner's extreme on the limit's axis either way. Used by :mod:`transfer.policy`; pure, as all of transfer/.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from transfer.store import PairStore

#: normalised teacher distance to a learned limit within which a command is mapped along it (a hundredth of a cell
#: of the 11 x 11 grid: an interior-point MPC stops about 1e-4 short of its bounds)
ALONG_LIMIT_TOL = 1e-3
#: how a command at a driven limit is mapped: ``row``, interpolated along the limit's row of pairs (a mission's own
#: pairs there are nearly collinear: slivers); ``region``, the mapper's region just inside the limit (a quarter of a
#: cell), the learner's extreme on the limit's axis: the paper's calibrated start, whose pairs at the learner's
#: extremes form well-shaped quadrilaterals (docs/PAPER.md, "The calibrated start"); the row where it has none
AT_LIMIT = ("row", "region")

#: a normalised teacher command -> (normalised learner command, method, region) or None (no region there)
RegionMap = Callable[[NDArray[np.float64]], tuple | None]


class LimitMap:
    """How a policy maps a command at a driven learned limit: ``map(t_n)`` (:meth:`map`). ``region_map`` is the
    policy's mapper (or its choice of map) at a normalised teacher point, ``beyond`` its whole unperturbed chain
    (region, fallback, estimate) for a command beyond the row's pairs."""

    def __init__(self, store: PairStore, at_limit: str, region_map: RegionMap,
                 beyond: Callable[[NDArray[np.float64]], tuple]) -> None:
        if at_limit not in AT_LIMIT:
            raise ValueError(f"unknown at_limit {at_limit!r}; known: {', '.join(AT_LIMIT)}")
        self.store, self.at_limit, self.region_map, self.beyond = store, at_limit, region_map, beyond
        self._rows_of: tuple | None = None  # the refined arrays the cached rows of _limit_row belong to
        self._rows: dict[tuple[int, int], tuple[list[int], list[float], list[float]]] = {}

    def map(self, t_n: NDArray[np.float64], linear: bool = False) -> tuple | None:
        """A command saturated at a learned limit whose boundary has been driven (a bounded controller's commands
        sit exactly there): the learner's extreme on that axis, and on the other the linear interpolation between
        the two neighbouring refined pairs of the boundary row of cells on that side. Those pairs are (nearly)
        collinear in the teacher domain, so the 2-D regions along the limit are slivers whose maps are
        ill-conditioned; along the row the map is one-dimensional (with ``at_limit = "region"``, the mapper's region
        just inside the limit first: :meth:`_inside_limit`). None when ``t_n`` is not at such a limit, or lies
        beyond the row's pairs (with ``adapt``: the extreme, the other axis mapped, and that map's gap, explored as
        without: the limit keeps its boundary pairs coming). A learner that cannot turn in place has its curvature at
        ``t_n``'s speed as its yaw-rate limit (``turn_edges_at``): commands there go to the full lock."""
        arrays = self.store.refined_arrays()
        if arrays[0].size < 2:
            return None
        sides = self._driven_limits(t_n)
        if not (sides[0] or sides[1]):
            return None
        if self.at_limit == "region" and not linear:
            inside = self._inside_limit(t_n, [at[0] if at else None for at in sides])
            if inside is not None:
                return inside
        for (a, b), at in zip(((0, 1), (1, 0)), sides):
            for extreme, _, row in at:
                ids, xs, ls = self._limit_row(arrays, a, row)
                if len(xs) < 2:
                    continue
                x = float(t_n[b])
                if not xs[0] <= x <= xs[-1]:
                    if not self.store.adapt:
                        continue
                    got = self.beyond(t_n)
                    return np.where(np.arange(2) == a, extreme, got[0]), got[1], got[2], *got[3:]  # explored as ever
                k = min(max(bisect_right(xs, x), 1), len(xs) - 1)  # = np.searchsorted(xs, x, side="right")
                span = xs[k] - xs[k - 1]
                w = (x - xs[k - 1]) / span if span > 0 else 0.5
                l_n = np.empty(2)
                l_n[a], l_n[b] = extreme, ls[k - 1] + w * (ls[k] - ls[k - 1])
                return l_n, "barycentric", (ids[k - 1], ids[k])
        return None

    def _driven_limits(self, t_n: NDArray[np.float64]) -> list[list[tuple[float, float, int]]]:
        """Per axis, the driven learned limits ``t_n`` sits at (within ``ALONG_LIMIT_TOL``), the top's first, each as
        ``(extreme, limit, row)``: ``extreme`` 1.0 at the top, 0.0 at the bottom, ``limit`` the normalised teacher
        limit, ``row`` the boundary row of cells on that side; empty where it is at no driven limit (both only where
        the limits are closer than twice the tolerance). A command at a corner of the learned limits (a bounded MPC
        turning in place at the slowest speed, or turning hardest at the top speed) is at a limit of each axis."""
        lim, grid = self.store.limits, self.store.grid
        sides: list[list[tuple[float, float, int]]] = [[], []]
        # Python floats and ints: the same comparisons as on the numpy scalars, without their cost per command
        t, lims_lo, lims_hi = t_n.tolist(), lim.lo.tolist(), lim.hi.tolist()
        bcnt_lo, bcnt_hi = lim.bcnt_lo.tolist(), lim.bcnt_hi.tolist()
        for a in (0, 1):
            lo, hi = (lims_lo[a], lims_hi[a]) if a == 0 or not lim.needs_speed else lim.turn_edges_at(t[0])
            if bcnt_hi[a] > 0 and t[a] >= hi - ALONG_LIMIT_TOL:
                sides[a].append((1.0, float(hi), grid[a] - 1))
            if bcnt_lo[a] > 0 and t[a] <= lo + ALONG_LIMIT_TOL:
                sides[a].append((0.0, float(lo), 0))
        return sides

    def _inside_limit(self, t_n: NDArray[np.float64], sides: list[tuple[float, float, int] | None]) -> tuple | None:
        """``at_limit = "region"``: the mapper's answer (with ``choice``, the chosen map's) a quarter of a cell inside
        every driven limit ``t_n`` sits at (``sides``: per axis the first of :meth:`_driven_limits`, or None), with
        the learner's extreme on each such axis (as along the row), or None where the mapper has no region there (the
        row decides). At a corner both axes move inside: the learned limits are the envelope of the boundary
        responses, and the refined pairs at the learner's corners (cell means) sit a little inside it, so the corner
        itself lies just outside their region."""
        t_in = np.array(t_n, dtype=float)
        for a, side in enumerate(sides):
            if side is not None:
                extreme, limit, _ = side
                inset = 0.25 / self.store.grid[a]
                t_in[a] = min(t_in[a], limit) - inset if extreme else max(t_in[a], limit) + inset
        got = self.region_map(t_in)
        if got is None or not np.all(np.isfinite(got[0])):  # no mapping region there (the fallback's slivers)
            return None
        l_n = np.array(got[0], dtype=float)
        for a, side in enumerate(sides):
            if side is not None:
                l_n[a] = side[0]
        return l_n, got[1], got[2]

    def _limit_row(self, arrays: tuple, a: int, row: int) -> tuple[list[int], list[float], list[float]]:
        """The refined pairs of the cells on ``row`` of axis ``a`` (of ``arrays``, the store's
        :meth:`~transfer.store.PairStore.refined_arrays`) sorted along the other axis: their ids, their teacher parts
        and their learner parts on it, as Python lists; computed once per set of refined pairs (every command at a
        limit reads them, and a search of a sorted list costs less than numpy's on a small array)."""
        if self._rows_of is not arrays:
            self._rows_of, self._rows = arrays, {}
        got = self._rows.get((a, row))
        if got is None:
            ids, _, T, L = arrays
            b = 1 - a
            on_row = np.flatnonzero(np.unravel_index(ids, self.store.grid)[a] == row)  # the pairs on that row
            on_row = on_row[np.argsort(T[on_row, b], kind="stable")]
            got = self._rows[(a, row)] = (ids[on_row].tolist(), T[on_row, b].tolist(), L[on_row, b].tolist())
        return got
