"""A pair store's change state (docs/PAPER.md, "a learner that changes"; ``transfer/store.py``'s module docstring):
:class:`CellChanges`, the part of :class:`transfer.store.PairStore` that tests each configured cell's raw pairs for a
change of the learner (the test itself: :class:`transfer.store_change.ChangeTest`) and keeps what came of it: the
residuals and noise estimates, how often and when each cell was re-learned.

:class:`Shifts` holds what a refined pair carries beyond its cluster's mean with ``adapt``: a shared change's
provisional shift and a small change's following offset.

Pure: no I/O, no clock.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from transfer.limits import LearnerLimits
from transfer.store_cells import CellSums
from transfer.store_change import ChangeTest


class CellChanges(ChangeTest):
    """The change test's state per cell. The test (a mixin) reads the cells' sums and refined pairs by name: they are
    :class:`transfer.store_cells.CellSums`' own arrays (changed in place only), bound here once."""

    def __init__(self, cells: CellSums, limits: LearnerLimits, prior: tuple[float, float], move_tol: float,
                 change_tol: float, change_sigmas: float) -> None:
        gv, gw = cells.grid
        self.grid, self.k_min, self.limits, self._prior = cells.grid, cells.k_min, limits, prior
        self.count, self.pub_version, self.pub_T, self.pub_L = cells.count, cells.pub_version, cells.pub_T, cells.pub_L
        self.sum_T, self.sum_L, self.sum_LL, self.sum_TL = cells.sum_T, cells.sum_L, cells.sum_LL, cells.sum_TL
        self.change_tol = float(change_tol)
        self.change_sigmas = float(change_sigmas)
        self.relearned = 0  # cells re-learned after a change was detected in them
        self.changed_at = np.full((gv, gw), np.nan)  # the stamp of each cell's last re-learning (NaN: never)
        self.changes = np.zeros((gv, gw), dtype=np.int64)  # how often each cell was re-learned
        self.resid = np.zeros((gv, gw, 2))  # per cell: recency-weighted mean of the residuals against its relation
        self.noise2 = np.full(2, float(move_tol) ** 2)  # the residuals' variance per axis when nothing changes
        self.last_resid = np.full((gv, gw, 2), np.nan)  # per cell: its last residual (NaN: none since it changed)
        self.cell_noise2 = np.zeros((gv, gw, 2))  # per cell: its own residuals' variance per axis (same estimator)
        self.cell_noise_n = np.zeros((gv, gw), dtype=np.int64)  # residual differences in it since its last change

    def agreeing(self, cell: tuple[int, int], T: NDArray[np.float64], L: NDArray[np.float64],
                 t_n: NDArray[np.float64], l_n: NDArray[np.float64]) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
        """A changed cell's recent pairs ``T``, ``L``: which agree with the change (their residual nearer the cell's
        mean residual than zero), and the change (the mean residual of those and of the pair at hand ``t_n``,
        ``l_n``; the cell's mean residual where it remembers none)."""
        e = self.resid[cell]
        if not len(T):
            return np.zeros(0, dtype=bool), e
        R = np.array([self._residual(cell, a, b) for a, b in zip(T, L)])
        post = np.linalg.norm(R - e, axis=1) < np.linalg.norm(R, axis=1)
        return post, np.vstack([R[post], self._residual(cell, t_n, l_n)]).mean(axis=0)

    def restarted(self, cell: tuple[int, int], stamp: float | None) -> None:
        """A cell was re-learned (at ``stamp``; None: none given): its residuals and its own noise estimate start
        again."""
        self.resid[cell] = 0.0
        self.last_resid[cell] = np.nan
        self.cell_noise_n[cell] = 0
        self.relearned += 1
        self.changes[cell] += 1
        self.changed_at[cell] = np.nan if stamp is None else float(stamp)


class Shifts:
    """What a refined pair carries beyond its cluster's mean with ``adapt`` (``transfer/store.py``'s module docstring,
    "a shared change" and "a small change"): per cell the provisional shift of a shared change and the raw pairs it
    took since, the changes of the last re-learnings, the recency-weighted mean of the cell's raw pairs and the
    offset its refined pair follows (teacher parts). Not persisted: a saved store holds its refined pairs without a
    provisional shift, and with the offset they followed."""

    def __init__(self, cells: CellSums, change: CellChanges, move_tol: float, window: int, agree: float,
                 track_sigmas: float) -> None:
        gv, gw = cells.grid
        self.cells, self.change, self.move_tol = cells, change, float(move_tol)
        self.window, self.agree, self.track_sigmas = int(window), float(agree), float(track_sigmas)
        self.seen: list[tuple[tuple[int, int], NDArray[np.float64], int]] = []  # (cell, change, raw pairs then)
        self.prov = np.zeros((gv, gw, 2))
        self.prov_n = np.zeros((gv, gw), dtype=np.int64)
        self.shared = 0  # shared changes applied
        self.track_T, self.track_L, self.follow = np.zeros((gv, gw, 2)), np.zeros((gv, gw, 2)), np.zeros((gv, gw, 2))
        self.track_n = np.zeros((gv, gw), dtype=np.int64)

    def cleared(self, cell: tuple[int, int]) -> None:
        """A re-learned cell drops its provisional shift and its following offset."""
        self.prov[cell] = 0.0
        self.track_n[cell], self.follow[cell] = 0, 0.0

    def share(self, cell: tuple[int, int], change: NDArray[np.float64], added: int) -> bool:
        """A shared change (``transfer/store.py``): when another cell re-learned within ``window`` raw pairs with a
        change that agrees with this one (within ``agree`` of ``change_tol`` on each axis), every other configured
        cell that has not changed in that window moves its refined pair by the agreeing changes' mean, for now: its
        own pairs then confirm it (the change test re-learns the cell) or revoke it (:meth:`check`). Returns whether
        a refined pair moved."""
        tol = self.agree * self.change.change_tol
        self.seen = [c for c in self.seen if added - c[2] <= self.window and c[0] != cell]
        agree = [c[1] for c in self.seen if np.all(np.abs(c[1] - change) <= tol)]
        self.seen.append((cell, np.array(change, dtype=float), added))
        if not agree:
            return False
        recent = {c[0] for c in self.seen}
        s = np.mean([change, *agree], axis=0)
        moved = False
        pub_T, pub_version = self.cells.pub_T, self.cells.pub_version
        for c in zip(*np.nonzero(pub_version > 0)):
            c = (int(c[0]), int(c[1]))
            if c in recent or np.all(np.abs(self.prov[c] - s) <= tol):
                continue
            pub_T[c] += s - self.prov[c]
            self.prov[c] = s
            self.prov_n[c] = 0
            pub_version[c] += 1
            moved = True
        if moved:
            self.shared += 1
        return moved

    def check(self, cell: tuple[int, int]) -> bool:
        """A provisionally shifted cell took a raw pair that did not alarm its change test: after k_min such pairs,
        if the recency-weighted mean of its residuals lies nearer no change than the shift, its learner did not
        change as the others did and the shift is revoked (its refined pair is its cluster's mean again). Returns
        whether the refined pair moved."""
        self.prov_n[cell] += 1
        if self.prov_n[cell] < self.cells.k_min:
            return False
        e, p = self.change.resid[cell], self.prov[cell]
        if np.linalg.norm(e - p) <= np.linalg.norm(e):
            return False
        self.cells.pub_T[cell] -= p
        self.prov[cell] = 0.0
        self.cells.pub_version[cell] += 1
        return True

    def track(self, cell: tuple[int, int], t_n: NDArray[np.float64], l_n: NDArray[np.float64]) -> None:
        """A small change: the raw pair (already in the cell's sums) into the cell's recent mean; the offset of the
        cell's relation there, beyond ``move_tol``, into the offset its refined pair follows. Scalar arithmetic."""
        cells, k_min = self.cells, self.cells.k_min
        n = self.track_n[cell] = self.track_n[cell] + 1
        q = self.track_sigmas / self.move_tol  # noise within move_tol / q: a mean of m pairs has 1 / (2 m - 1)
        w = 1.0 / min(n, max(k_min, 0.5 + 0.5 * max(self.change._noise2(cell).tolist()) * (q * q)))
        tT, tL = self.track_T[cell], self.track_L[cell]
        eT, eL = tT.tolist(), tL.tolist()
        t, l = t_n.tolist(), l_n.tolist()
        for a in (0, 1):
            eT[a] = eT[a] + w * (t[a] - eT[a])
            eL[a] = eL[a] + w * (l[a] - eL[a])
        tT[:], tL[:] = eT, eL
        c = int(cells.count[cell])
        if not (n >= k_min and c >= k_min and cells.pub_version[cell] > 0 and not self.prov[cell].any()):
            return
        sT, sL, f = cells.sum_T[cell].tolist(), cells.sum_L[cell].tolist(), self.follow[cell].tolist()
        sl = self.change._slope_list(cell)
        d = [eT[a] - f[a] - (sT[a] + (c * eL[a] - sL[a]) * sl[a]) / c for a in (0, 1)]
        if max(abs(d[0]), abs(d[1])) > self.move_tol:
            self.follow[cell] += d
