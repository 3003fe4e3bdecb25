"""The pair store's saved form (transfer/store_blob.py): a blob written today fills every field of its schema, an older
version's blob (fewer fields) is read with their defaults, and a field the schema does not know is refused."""

from __future__ import annotations

import msgspec
import pytest

from tests.stores import LB, TB, filled
from transfer.store import SCHEMA_VERSION, PairStore
from transfer.store_blob import StoreBlob


def _payload(store: PairStore) -> dict:
    return msgspec.msgpack.decode(store.to_bytes()[12:])


def test_a_blob_written_now_fills_every_field_of_its_schema() -> None:
    raw = _payload(filled(200, seed=1, gain=1.1))
    blob = msgspec.convert(raw, StoreBlob)
    assert blob.schema_version == SCHEMA_VERSION
    assert set(raw) == set(StoreBlob.__struct_fields__)  # nothing left to a default
    assert blob.limits.turn_n is not None and blob.changes is not None and blob.added == 200


def test_an_older_blob_reads_with_the_defaults_and_an_unknown_field_is_refused() -> None:
    raw = _payload(PairStore(LB, TB))
    for name in ("sum_LL", "sum_TL", "adapt", "relearned", "added", "changed_at", "resid", "noise2", "recent_T",
                 "recent_L", "recent_n", "changes", "cell_noise2", "cell_noise_n"):
        raw.pop(name)  # a version-1 blob had none of these
    for name in ("turn_vw", "turn_vv", "turn_n", "turn_prop"):
        raw["limits"].pop(name)
    old = msgspec.convert(raw, StoreBlob)
    assert old.sum_LL is None and old.adapt is False and old.limits.turn_n is None
    raw["limits"]["mystery"] = 1
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert(raw, StoreBlob)
