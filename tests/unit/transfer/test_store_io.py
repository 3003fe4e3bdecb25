"""A pair store's saved form written and read (transfer/store_io.py): a store comes back as it was, a blob that is
not one is refused, and a blob whose limits are wrong is refused by the limits themselves, which then keep what they
held (the store does not set their internals)."""

from __future__ import annotations

import zlib

import msgspec
import numpy as np
import pytest

from tests.stores import LB, TB, filled
from transfer.limits import LearnerLimits
from transfer.store import PairStore
from transfer.store_io import from_bytes, to_bytes


def _filled() -> PairStore:
    return filled(400, seed=5, gain=1.3)


def test_a_store_comes_back_as_it_was() -> None:
    store = _filled()
    again = from_bytes(to_bytes(store), PairStore)
    assert to_bytes(again) == to_bytes(store)
    assert again.limits.saved() == store.limits.saved() and again.limits.box == store.limits.box
    assert ([(p.id, p.version, p.count) for p in again.refined()]
            == [(p.id, p.version, p.count) for p in store.refined()])


def test_a_blob_that_is_not_one_is_refused() -> None:
    blob = to_bytes(_filled())
    with pytest.raises(ValueError, match="bad magic"):
        from_bytes(b"NOTPAIRS" + blob[8:], PairStore)
    with pytest.raises(ValueError, match="CRC"):
        from_bytes(blob[:-1] + bytes([blob[-1] ^ 1]), PairStore)


def test_wrong_limits_are_refused_by_the_limits_which_keep_what_they_held() -> None:
    store = _filled()
    lim = store.limits
    held = lim.saved()
    for bad in ({"lo": [0.0]}, {"hull_cnt": [0, 1]}, {"bsum_hi": [np.nan, 0.0]}, {"turn_vv": None}):
        s = dict(held, **bad)
        with pytest.raises(ValueError):
            lim.restore(s)
        assert lim.saved() == held
    fresh = LearnerLimits(TB, LB, store.grid, store.boundary_tol)
    fresh.restore(held)
    assert fresh.saved() == held and fresh.box == lim.box
    # through a blob too
    raw = msgspec.msgpack.decode(to_bytes(store)[12:])
    raw["limits"]["hi"] = [1.0]
    payload = msgspec.msgpack.encode(raw)
    with pytest.raises(ValueError, match="limits field hi"):
        from_bytes(b"SCMPAIRS" + zlib.crc32(payload).to_bytes(4, "little") + payload, PairStore)
