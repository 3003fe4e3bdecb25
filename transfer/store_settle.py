"""A settled pair for a cell (docs/PAPER.md, "a learner that changes": "A settled pair"): :class:`SettledPairs`, the
part of :class:`transfer.store.PairStore` that says whether a raw pair shows what the learner does at its command once
it has settled there, or a moment of its way towards it.

The method assumes the learner's response is a function of the command (``transfer/store.py``'s module docstring). A
learner whose response depends on its history (an acceleration limit that binds: ``sim drift --scenario payload``)
gives, the tick a command is sent far from the one before, a pair short of its response there, and the next ones catch
up with the command unchanged; such pairs scatter a cell's cluster, move its refined pair off the learner's steady
response and alarm the change test (the payload re-learned 10 to 15 cells a run). With change detection, where the
caller gives the command before a pair (:meth:`transfer.store.PairStore.add`'s ``prev_u_L``, which must be the learner
part of the raw pair added just before), a pair counts for its cell only when its response moved from the previous
pair's as the cell's relation says it moves with the command: on each axis, the change of the teacher part less the
cell's slope times the change of the learner part within the change test's tolerance (``change_tol``). A learner that
does what it is told passes every pair (a cubic's curvature over one tick's command step is far inside it); one that
lags fails the pairs of its lag. A pair that fails is not taken into its cell, its change test nor its recent pairs;
the learned limits take it as before (they have their own settled rule, ``transfer/limits_watch.py``). Like the limits'
rule, it is the pair conditioned on the previous command, as the issue of a history-dependent response has it.

Without ``prev_u_L`` (the station's pairs, each from a command held until it settled; ``sim mpc``) nothing changes.

Pure: no I/O, no clock; Python floats (one pair a tick).
"""

from __future__ import annotations

from collections.abc import Callable

#: a command held: within this share of a grid cell of the one before, on an axis (the learner catching up with it)
HOLD_CELLS = 0.5


class SettledPairs:
    """The last raw pair a store took and the settled rule (module docstring). ``slope(cell)`` is the cell's dT/dL per
    axis (normalised), :meth:`transfer.store_change.ChangeTest._slope_list`."""

    def __init__(self, slope: Callable[[tuple[int, int]], list[float]], grid: tuple[int, int]) -> None:
        self.slope = slope
        self.hold = (HOLD_CELLS / grid[0], HOLD_CELLS / grid[1])  # normalised learner units
        self.on = False  # with change detection only (the store's ``adapt``)
        self.last: tuple[list[float], list[float]] | None = None  # the last raw pair (teacher, learner), normalised
        self.unsettled = 0  # pairs not taken into a cell for it

    def settled(self, cell: tuple[int, int], t_n: list[float], l_n: list[float], prev_l: list[float] | None,
                tol: float) -> bool:
        """Whether the raw pair ``(t_n, l_n)`` in ``cell`` counts for it (module docstring); ``prev_l``: the learner
        part of the pair before it, as the caller gives it (None: the caller does not know; it counts). Remembers the
        pair for the next call."""
        last, self.last = self.last, (t_n, l_n)
        if not self.on or prev_l is None or last is None:
            return True
        lt, ll = last
        if any(abs(ll[a] - prev_l[a]) > 1e-9 for a in (0, 1)):
            return True  # the pair before was not the one the caller names: nothing to compare with
        sl = self.slope(cell)
        ok = all(abs(l_n[a] - ll[a]) > self.hold[a] or abs((t_n[a] - lt[a]) - sl[a] * (l_n[a] - ll[a])) <= tol
                 for a in (0, 1))
        if not ok:
            self.unsettled += 1
        return ok
