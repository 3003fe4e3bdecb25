"""The pair store's saved form (:meth:`transfer.store.PairStore.to_bytes`): one MessagePack map per store, its fields
typed here so a blob that is not one is refused on load. Each schema version adds fields with a default, so a blob of
an older version loads (``transfer.store.READS_VERSIONS``)."""

from __future__ import annotations

import msgspec


class LimitsBlob(msgspec.Struct, forbid_unknown_fields=True):
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
    # schema 4: the yaw-rate sides' curvatures (transfer.limits, a learner that cannot turn in place)
    turn_vw: list[float] | None = None
    turn_vv: list[float] | None = None
    turn_n: list[int] | None = None
    turn_prop: list[float | None] | None = None  # null: none extrapolated


class StoreBlob(msgspec.Struct, forbid_unknown_fields=True):
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
    limits: LimitsBlob
    # schema 2: change detection (module docstring); absent in version 1
    sum_LL: list[float] | None = None
    sum_TL: list[float] | None = None
    adapt: bool = False
    relearned: int = 0
    added: int | None = None
    changed_at: list[float | None] | None = None
    resid: list[float] | None = None
    noise2: list[float] | None = None
    recent_T: list[float] | None = None
    recent_L: list[float] | None = None
    recent_n: list[int] | None = None
    # schema 3: how often each cell was re-learned, each cell's own noise estimate; absent in versions 1 and 2
    changes: list[int] | None = None
    cell_noise2: list[float] | None = None
    cell_noise_n: list[int] | None = None
