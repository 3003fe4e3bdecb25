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
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.domain import Bounds
from transfer.limits import LearnerLimits

SCHEMA = "scmbridge.pairstore"
SCHEMA_VERSION = 1
_MAGIC = b"SCMPAIRS"


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


class _LimitsBlob(msgspec.Struct, forbid_unknown_fields=True):
    lo: list[float]
    hi: list[float]
    ext_lo: list[float]
    ext_hi: list[float]
    bsum_lo: list[float]
    bsum_hi: list[float]
    bcnt_lo: list[int]
    bcnt_hi: list[int]
    hull_sum: list[float]
    hull_cnt: list[int]
    version: int


class _StoreBlob(msgspec.Struct, forbid_unknown_fields=True):
    schema: str
    schema_version: int
    learner_bounds: list[float]
    teacher_bounds: list[float]
    grid: list[int]
    k_min: int
    move_tol: float
    boundary_tol: float
    count: list[int]
    sum_T: list[float]
    sum_L: list[float]
    pub_T: list[float]
    pub_L: list[float]
    pub_version: list[int]
    revision: int
    limits: _LimitsBlob


class PairStore:
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
        self.count = np.zeros((gv, gw), dtype=np.int64)
        self.sum_T = np.zeros((gv, gw, 2))  # normalised teacher parts
        self.sum_L = np.zeros((gv, gw, 2))  # normalised learner parts
        self.pub_T = np.zeros((gv, gw, 2))
        self.pub_L = np.zeros((gv, gw, 2))
        self.pub_version = np.zeros((gv, gw), dtype=np.int64)  # 0: no refined pair yet
        self.revision = 0
        self.limits = LearnerLimits(teacher_bounds, learner_bounds, self.grid, boundary_tol)
        self._arrays: tuple | None = None

    # ------------------------------------------------------------------------------------------ clustering
    def cell_of(self, u_L: ArrayLike) -> tuple[int, int]:
        """Grid cell of a learner command (clipped into the learner's box first)."""
        n = np.clip(self.learner_bounds.normalise(u_L), 0.0, 1.0)
        return self._cell_n(n)

    def _cell_n(self, n: NDArray[np.float64]) -> tuple[int, int]:
        gv, gw = self.grid
        return (min(int(n[0] * gv), gv - 1), min(int(n[1] * gw), gw - 1))

    def add(self, u_T_bar: ArrayLike, u_L: ArrayLike) -> AddResult:
        """Add one raw pair (teacher equivalent, learner command actually applied)."""
        t = np.asarray(u_T_bar, dtype=float).reshape(2)
        lcmd = np.asarray(u_L, dtype=float).reshape(2)
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(lcmd))):
            raise ValueError(f"command pair must be finite, got u_T={t}, u_L={lcmd}")
        t_n = self.teacher_bounds.normalise(t)
        l_n = np.clip(self.learner_bounds.normalise(lcmd), 0.0, 1.0)
        cell = self._cell_n(l_n)
        self.count[cell] += 1
        self.sum_T[cell] += t_n
        self.sum_L[cell] += l_n
        refined_changed = False
        if self.count[cell] >= self.k_min:
            mT, mL = self.cluster_mean(cell)
            moved = max(np.max(np.abs(mT - self.pub_T[cell])), np.max(np.abs(mL - self.pub_L[cell])))
            if self.pub_version[cell] == 0 or moved > self.move_tol:
                self.pub_T[cell], self.pub_L[cell] = mT, mL
                self.pub_version[cell] += 1
                self.revision += 1
                self._arrays = None
                refined_changed = True
        limits_changed = self.limits.update(t_n, l_n, cell)
        return AddResult(cell, refined_changed, limits_changed)

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
        return int(self.count.sum())

    # ----------------------------------------------------------------------------------------- persistence
    def to_bytes(self) -> bytes:
        """Versioned MessagePack blob with a CRC, so corruption is detected on load."""
        lim = self.limits
        blob = _StoreBlob(
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
            pub_T=self.pub_T.ravel().tolist(),
            pub_L=self.pub_L.ravel().tolist(),
            pub_version=self.pub_version.ravel().tolist(),
            revision=self.revision,
            limits=_LimitsBlob(
                lo=lim.lo.tolist(), hi=lim.hi.tolist(), ext_lo=lim.ext_lo.tolist(), ext_hi=lim.ext_hi.tolist(),
                bsum_lo=lim.bsum_lo.tolist(), bsum_hi=lim.bsum_hi.tolist(), bcnt_lo=lim.bcnt_lo.tolist(),
                bcnt_hi=lim.bcnt_hi.tolist(), hull_sum=lim.hull_sum.ravel().tolist(),
                hull_cnt=lim.hull_cnt.ravel().tolist(), version=lim.version,
            ),
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
        if raw.get("schema_version") != SCHEMA_VERSION:
            raise ValueError(f"pair-store schema version {raw.get('schema_version')} is not supported "
                             f"(this build reads version {SCHEMA_VERSION})")
        try:
            b = msgspec.convert(raw, _StoreBlob)
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
                    move_tol=b.move_tol, boundary_tol=b.boundary_tol)
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
        arrays = [store.sum_T, store.sum_L, store.pub_T, store.pub_L, lim.lo, lim.hi, lim.bsum_lo, lim.bsum_hi,
                  lim.hull_sum]
        if not all(np.all(np.isfinite(a)) for a in arrays) or np.any(store.count < 0):
            raise ValueError("pair-store blob holds non-finite or negative values")
        return store
