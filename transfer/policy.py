"""The transfer policy: teacher command -> learner command, and how it was obtained (paper Section 5.2).

``TransferPolicy.map(u_T)`` returns a :class:`Mapped` whose ``method`` is

- ``"scm"`` (or the alternative mapper's name): a mapping region holds u_T;
- ``"direct"``: no region, and the learner cell of u_T (u_T read as a learner command, clipped into the learner's
  box) holds no refined pair yet: apply the teacher command as it is, clipped (explore; the pair it creates fills
  that cell);
- ``"perturb"``: no region, but that cell is already configured: sample a command uniformly inside the nearest
  unconfigured cell around it (ring by ring; ties broken by the policy's random generator) so that pairs are
  learned where they are missing. With every cell configured it falls back to ``"direct"``.

With the ``identity`` mapper (the paper's baseline) every command is ``"direct"``. The result is always finite and
inside the learner's hard bounds; a non-finite u_T is refused with ValueError.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.mappers import IdentityMapper, make_mapper
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
                 *, seed: int | None = None) -> None:
        self.store = store
        self.mapper = make_mapper(mapper, store) if isinstance(mapper, str) else mapper
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
        res = self.mapper.map_normalised(self.store.teacher_bounds.normalise(t))
        if res is not None:
            l_n, region = res
            u = lb.clip(lb.denormalise(l_n))
            if np.all(np.isfinite(u)):
                return Mapped(u, self.mapper.name, region)
        direct = lb.clip(t)
        cell = self.store.cell_of(direct)
        if not self.store.is_configured(cell):
            return Mapped(direct, "direct")
        target = self._nearest_unconfigured(cell)
        if target is None:
            return Mapped(direct, "direct")
        gv, gw = self.store.grid
        n = (np.array(target, dtype=float) + self.rng.random(2)) / np.array([gv, gw], dtype=float)
        return Mapped(lb.clip(lb.denormalise(n)), "perturb")

    def _nearest_unconfigured(self, cell: tuple[int, int]) -> tuple[int, int] | None:
        gv, gw = self.store.grid
        configured = self.store.pub_version > 0
        i0, j0 = cell
        for r in range(1, max(gv, gw)):
            ring = [
                (i, j)
                for i in range(max(0, i0 - r), min(gv, i0 + r + 1))
                for j in range(max(0, j0 - r), min(gw, j0 + r + 1))
                if max(abs(i - i0), abs(j - j0)) == r and not configured[i, j]
            ]
            if ring:
                return ring[int(self.rng.integers(len(ring)))]
        return None
