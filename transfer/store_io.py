"""A pair store's saved form, written and read: :func:`to_bytes` and :func:`from_bytes` behind
:meth:`transfer.store.PairStore.to_bytes` / ``from_bytes``. A versioned MessagePack map (its fields typed in
``transfer/store_blob.py``) after a magic and a CRC, so corruption is detected on load; each schema version adds
fields with a default, so a store saved by an older build loads (:data:`READS_VERSIONS`). Each part of the store
gives and takes its own fields: the learned limits through :meth:`transfer.limits.LearnerLimits.saved` and
``restore``.

Pure: bytes in and out, no I/O.
"""

from __future__ import annotations

import zlib
from typing import Any

import msgspec
import numpy as np

from transfer.domain import Bounds
from transfer.store_blob import LimitsBlob, StoreBlob

#: a :class:`transfer.store.PairStore` (not imported here: it imports this module)
PairStore = Any

SCHEMA = "scmbridge.pairstore"
SCHEMA_VERSION = 4
#: the versions this build reads (1: before change detection; its cells start with no recent pairs or slopes; 2:
#: before the per-cell change count, which starts at 1 for a cell with a change time and 0 otherwise; 3: before the
#: yaw-rate curvatures, which start with no boundary pair: a learner that cannot turn in place learns them again)
READS_VERSIONS = (1, 2, 3, 4)
_MAGIC = b"SCMPAIRS"


def to_bytes(store: PairStore) -> bytes:
    """The store's blob: its cells' sums and refined pairs (without a shared change's provisional shift), its limits,
    its change state."""
    c, ch, lim = store.cells, store.change, store.limits
    blob = StoreBlob(
        schema=SCHEMA,
        schema_version=SCHEMA_VERSION,
        learner_bounds=store.learner_bounds.as_list(),
        teacher_bounds=store.teacher_bounds.as_list(),
        grid=list(store.grid),
        k_min=store.k_min,
        move_tol=store.move_tol,
        boundary_tol=store.boundary_tol,
        count=c.count.ravel().tolist(),
        sum_T=c.sum_T.ravel().tolist(),
        sum_L=c.sum_L.ravel().tolist(),
        pub_T=(c.pub_T - store.shifts.prov - store.spreading.shift).ravel().tolist(),
        pub_L=c.pub_L.ravel().tolist(),
        pub_version=c.pub_version.ravel().tolist(),
        revision=store.revision,
        limits=LimitsBlob(**lim.saved()),
        sum_LL=c.sum_LL.ravel().tolist(),
        sum_TL=c.sum_TL.ravel().tolist(),
        adapt=store.adapt, relearned=ch.relearned, added=store.added,
        changed_at=[None if np.isnan(v) else float(v) for v in ch.changed_at.ravel()],
        resid=ch.resid.ravel().tolist(),
        noise2=ch.noise2.tolist(),
        recent_T=c.recent_T.ravel().tolist(),
        recent_L=c.recent_L.ravel().tolist(),
        recent_n=c.recent_n.ravel().tolist(),
        changes=ch.changes.ravel().tolist(),
        cell_noise2=ch.cell_noise2.ravel().tolist(),
        cell_noise_n=ch.cell_noise_n.ravel().tolist(),
    )
    payload = msgspec.msgpack.encode(blob)
    return _MAGIC + zlib.crc32(payload).to_bytes(4, "little") + payload


def _decode(data: bytes) -> StoreBlob:
    """The blob's fields, checked for magic, CRC, schema, version and types; ValueError otherwise."""
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
        return msgspec.convert(raw, StoreBlob)
    except msgspec.ValidationError as exc:
        raise ValueError(f"pair-store blob is malformed: {exc}") from exc


def from_bytes(data: bytes, cls: Any) -> PairStore:
    """A store of class ``cls`` from a blob written by :func:`to_bytes` (this build's or an older one's); ValueError for
    anything corrupted or incompatible."""
    b = _decode(data)
    gv, gw = b.grid
    n = gv * gw
    sizes = {"count": (b.count, n), "sum_T": (b.sum_T, 2 * n), "sum_L": (b.sum_L, 2 * n), "pub_T": (b.pub_T, 2 * n),
             "pub_L": (b.pub_L, 2 * n), "pub_version": (b.pub_version, n)}
    for name, (arr, want) in sizes.items():
        if len(arr) != want:
            raise ValueError(f"pair-store field {name} has {len(arr)} values, expected {want}")
    store = cls(Bounds.from_list(b.learner_bounds), Bounds.from_list(b.teacher_bounds), (gv, gw), b.k_min,
                move_tol=b.move_tol, boundary_tol=b.boundary_tol, adapt=b.adapt)
    c, ch = store.cells, store.change
    r = c.recent_T.shape[2]
    optional = {"sum_LL": 2 * n, "sum_TL": 2 * n, "changed_at": n, "resid": 2 * n, "noise2": 2,
                "recent_T": 2 * n * r, "recent_L": 2 * n * r, "recent_n": n, "changes": n,
                "cell_noise2": 2 * n, "cell_noise_n": n}
    for name, want in optional.items():
        arr = getattr(b, name)
        if arr is not None and len(arr) != want:
            raise ValueError(f"pair-store field {name} has {len(arr)} values, expected {want}")
    store.limits.restore(msgspec.structs.asdict(b.limits))
    # the parts' arrays are changed in place: the change test reads the cells' by name (transfer/store_adapt.py)
    c.count[...] = np.array(b.count, dtype=np.int64).reshape(gv, gw)
    c.sum_T[...] = np.array(b.sum_T, dtype=float).reshape(gv, gw, 2)
    c.sum_L[...] = np.array(b.sum_L, dtype=float).reshape(gv, gw, 2)
    c.pub_T[...] = np.array(b.pub_T, dtype=float).reshape(gv, gw, 2)
    c.pub_L[...] = np.array(b.pub_L, dtype=float).reshape(gv, gw, 2)
    c.pub_version[...] = np.array(b.pub_version, dtype=np.int64).reshape(gv, gw)
    store._arrays = None  # the refined pairs' cache (set in place above: whatever was asked before is stale)
    store.revision = b.revision
    ch.relearned = b.relearned
    store.added = int(c.count.sum()) if b.added is None else b.added
    if b.sum_LL is not None and b.sum_TL is not None:
        c.sum_LL[...] = np.array(b.sum_LL, dtype=float).reshape(gv, gw, 2)
        c.sum_TL[...] = np.array(b.sum_TL, dtype=float).reshape(gv, gw, 2)
    else:  # version 1: the cells' slopes start from their means (as if their pairs had all been at them)
        mL = c.sum_L / np.maximum(c.count, 1)[..., None]
        c.sum_LL[...] = c.count[..., None] * mL * mL
        c.sum_TL[...] = c.count[..., None] * mL * c.sum_T / np.maximum(c.count, 1)[..., None]
    if b.changed_at is not None:
        ch.changed_at[...] = np.array([np.nan if v is None else v for v in b.changed_at], dtype=float).reshape(gv, gw)
    if b.changes is not None:
        ch.changes[...] = np.array(b.changes, dtype=np.int64).reshape(gv, gw)
    else:  # versions 1 and 2: a cell with a change time changed once at least
        ch.changes[...] = (~np.isnan(ch.changed_at)).astype(np.int64)
    if b.cell_noise2 is not None and b.cell_noise_n is not None:  # versions 1 and 2: no cell has its own yet
        ch.cell_noise2[...] = np.array(b.cell_noise2, dtype=float).reshape(gv, gw, 2)
        ch.cell_noise_n[...] = np.array(b.cell_noise_n, dtype=np.int64).reshape(gv, gw)
    if b.resid is not None:
        ch.resid[...] = np.array(b.resid, dtype=float).reshape(gv, gw, 2)
    if b.noise2 is not None:
        ch.noise2[...] = np.array(b.noise2, dtype=float)
    if b.recent_T is not None and b.recent_L is not None and b.recent_n is not None:
        c.recent_T[...] = np.array(b.recent_T, dtype=float).reshape(gv, gw, r, 2)
        c.recent_L[...] = np.array(b.recent_L, dtype=float).reshape(gv, gw, r, 2)
        c.recent_n[...] = np.array(b.recent_n, dtype=np.int64).reshape(gv, gw)
    arrays = [c.sum_T, c.sum_L, c.pub_T, c.pub_L, c.sum_LL, c.sum_TL, ch.resid, ch.noise2, c.recent_T, c.recent_L,
              ch.cell_noise2]
    if (not all(np.all(np.isfinite(a)) for a in arrays) or np.any(c.count < 0) or np.any(c.recent_n < 0)
            or np.any(ch.changes < 0) or np.any(ch.noise2 < 0) or np.any(ch.cell_noise2 < 0)
            or np.any(ch.cell_noise_n < 0)):
        raise ValueError("pair-store blob holds non-finite or negative values")
    return store
