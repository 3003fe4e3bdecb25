"""The transfer policy: teacher command -> learner command, and how it was obtained (paper Section 5.2).

``TransferPolicy.map(u_T)`` returns a :class:`Mapped` whose ``method`` is

- ``"scm"`` (or the alternative mapper's name): a mapping region holds u_T; or u_T lies inside the learned
  limits but just outside the triangulated region (within ``saturate``, normalised units, default 0.1 ~ one grid
  cell), as a saturated controller's commands at the edge of the limits do: then the nearest point of the
  learned region is mapped (otherwise such commands would be perturbed forever, since the refined pairs of the
  outermost cells are cell means and lie inside the limits);
- ``"direct"``: no region, and the learner cell of u_T (u_T read as a learner command, clipped into the learner's
  box) holds no refined pair yet: apply the teacher command as it is, clipped (explore; the pair it creates fills
  that cell);
- ``"perturb"`` (exploration): u_T sits at a learned limit whose learner boundary has never been driven: the
  learner's extreme command on that axis is sent once so the limit is measured, not extrapolated; or
  no region, but the cell of u_T is already configured: sample a command uniformly inside the nearest
  unconfigured cell around it (ring by ring; in the ring, the cell nearest to where the least-squares affine
  fit of the refined pairs puts u_T; ties broken by the policy's random generator) so that pairs are
  learned where they are missing. With every cell configured it falls back to ``"direct"``.

With the ``identity`` mapper (the paper's baseline) every command is ``"direct"``. The result is always finite and
inside the learner's hard bounds; a non-finite u_T is refused with ValueError.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.mappers import AffineMapper, IdentityMapper, make_mapper
from transfer.store import PairStore


@dataclass(frozen=True)
class Mapped:
    """A learner command (learner units), the method that produced it and the refined-pair ids of its region."""

    u_L: NDArray[np.float64]
    method: str
    region: tuple[int, ...] = ()


class TransferPolicy:
    """Maps teacher commands to learner commands with a mapper over a :class:`PairStore` (see module docstring)."""

    def __init__(self, store: PairStore, mapper: str | object = "scm", rng: np.random.Generator | None = None,
                 *, seed: int | None = None, saturate: float = 0.1, probe_tol: float = 1e-6) -> None:
        self.store = store
        self.saturate = float(saturate)
        self.probe_tol = float(probe_tol)
        self.mapper = make_mapper(mapper, store) if isinstance(mapper, str) else mapper
        self._affine = None if isinstance(self.mapper, IdentityMapper) else AffineMapper(store)
        if rng is None:
            rng = np.random.default_rng(seed)
        self.rng = rng

    def map(self, u_T: ArrayLike) -> Mapped:
        t = np.asarray(u_T, dtype=float).reshape(2)
        if not np.all(np.isfinite(t)):
            raise ValueError(f"teacher command must be finite, got {t}")
        lb = self.store.learner_bounds
        if isinstance(self.mapper, IdentityMapper):
            return Mapped(lb.clip(t), "direct")
        t_n = self.store.teacher_bounds.normalise(t)
        probe = self._probe_limits(t, t_n)
        if probe is not None:
            return Mapped(probe, "perturb")
        res = self.mapper.map_normalised(t_n)
        if res is None and self.saturate > 0 and self.store.limits.contains(t):
            # inside the learned limits but just outside the learned region: a command at the edge of what the
            # learner can do (a saturated controller) maps through the nearest learned command, not by exploring
            near = self.mapper.nearest_on_hull(t_n)
            if near is not None and near[1] <= self.saturate:
                res = self.mapper.map_normalised(near[0])
        if res is not None:
            l_n, region = res
            u = lb.clip(lb.denormalise(l_n))
            if np.all(np.isfinite(u)):
                return Mapped(u, self.mapper.name, region)
        direct = lb.clip(t)
        cell = self.store.cell_of(direct)
        if not self.store.is_configured(cell):
            return Mapped(direct, "direct")
        target = self._nearest_unconfigured(cell, self._predict(t_n, direct))
        if target is None:
            return Mapped(direct, "direct")
        gv, gw = self.store.grid
        n = (np.array(target, dtype=float) + self.rng.random(2)) / np.array([gv, gw], dtype=float)
        return Mapped(lb.clip(lb.denormalise(n)), "perturb")

    def _probe_limits(self, t: NDArray[np.float64], t_n: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """A teacher command saturated at a learned limit whose learner boundary has never been seen: send the
        learner's extreme command on that axis once, so the boundary pair fixes the limit (paper: a new outlier on
        the boundary moves the bound). Without it a proportional estimate from an interior outlier, which
        underestimates a convex learner response (the paper's h_v = v^3), would bound the teacher for good."""
        lim = self.store.limits
        lb = self.store.learner_bounds
        u = lb.clip(t)
        probed = False
        for a in range(2):
            if lim.bcnt_hi[a] == 0 and t_n[a] >= lim.hi[a] - self.probe_tol:
                u[a] = lb.hi[a]
                probed = True
            elif lim.bcnt_lo[a] == 0 and t_n[a] <= lim.lo[a] + self.probe_tol:
                u[a] = lb.lo[a]
                probed = True
        return u if probed else None

    def _predict(self, t_n: NDArray[np.float64], direct: NDArray[np.float64]) -> NDArray[np.float64]:
        """Where the learner command for t_n probably is (normalised): the least-squares affine map of the refined
        pairs, or the teacher command itself while there are too few pairs for one."""
        guess = self._affine.extrapolate(t_n) if self._affine is not None else None
        if guess is None:
            return self.store.learner_bounds.normalise(direct)
        return np.clip(guess, 0.0, 1.0)

    def _nearest_unconfigured(self, cell: tuple[int, int], towards: NDArray[np.float64]) -> tuple[int, int] | None:
        """The unconfigured cell of the nearest ring around ``cell`` closest to ``towards`` (normalised learner
        point; ties broken by the random generator): exploring where the command probably maps, not anywhere."""
        gv, gw = self.store.grid
        configured = self.store.pub_version > 0
        i0, j0 = cell
        goal = np.asarray(towards) * np.array([gv, gw], dtype=float)
        for r in range(1, max(gv, gw)):
            ring = [
                (i, j)
                for i in range(max(0, i0 - r), min(gv, i0 + r + 1))
                for j in range(max(0, j0 - r), min(gw, j0 + r + 1))
                if max(abs(i - i0), abs(j - j0)) == r and not configured[i, j]
            ]
            if ring:
                d = np.array([np.hypot(i + 0.5 - goal[0], j + 0.5 - goal[1]) for i, j in ring])
                best = np.flatnonzero(d <= d.min() + 1e-9)
                return ring[int(best[self.rng.integers(best.size)])]
        return None
