"""The recording format (:mod:`bridge.tools.mcap_format`): keys of the wire contract and their kinds, the stored JSON
round-trip, the channel specs, renaming robots for a replay, and reading files back (also a torn one) as the
recorder's own sink (:mod:`bridge.tools.mcap_sink`) writes them.

Every topic's viewer schema and :func:`classify`'s outcomes (ok, malformed, noncanonical) are tested in
tests/integration/test_record.py, beside recording, replaying and reporting a run end to end."""

from __future__ import annotations

import json

import pytest

from bridge.core import wire as M
from bridge.tools.mcap_format import (
    ACTUATING,
    MALFORMED,
    SCHEMA_PREFIX,
    TOPIC_KINDS,
    ChannelSpec,
    Entry,
    RawSample,
    classify,
    from_json,
    json_schema,
    kind_of,
    parse_key,
    read_recording,
    rename_robot,
    to_json,
    wire_bytes,
)
from bridge.tools.mcap_sink import McapSink


def test_every_key_of_the_contract_parses_to_its_robot_and_topic() -> None:
    for topic, kind in TOPIC_KINDS.items():
        key = M.status_key("rover1", "driver") if topic == "status" else M.key("rover1", topic)
        assert parse_key(key) == ("rover1", topic) and kind_of(key) is kind
    assert set(ACTUATING) <= set(TOPIC_KINDS) and set(ACTUATING) == {"cmd", "estop"}


@pytest.mark.parametrize(("key", "says"), [
    ("scm/r1", "is not scm/<robot>/<topic>"),
    ("zenoh/r1/cmd", "is not scm/<robot>/<topic>"),
    ("scm/r1/odometry", "unknown topic 'odometry'"),
    ("scm/r*/cmd", "robot name 'r*'"),
    ("scm/r1/status", "status is scm/<robot>/status/<node>"),
    ("scm/r1/status/a/b", "status is scm/<robot>/status/<node>"),
    ("scm/r1/status/n*", "robot name 'n*'"),
    ("scm/r1/cmd/extra", "has chunks after its topic"),
])
def test_a_key_outside_the_contract_is_refused_naming_the_problem(key: str, says: str) -> None:
    with pytest.raises(ValueError, match=says.replace("*", r"\*")):
        parse_key(key)
    with pytest.raises(ValueError):
        kind_of(key)


def test_stored_json_round_trips_and_what_is_not_the_kind_is_a_message_error() -> None:
    msg = M.Status(stamp=1.5, seq=3, node="driver", state="estop", reason="estop", counters={"ticks": 9},
                   host="lab/abcd1234")
    data = to_json(msg)
    assert json.loads(data)["counters"] == {"ticks": 9}  # plain JSON, readable by a viewer
    assert from_json(data, M.Status) == msg
    with pytest.raises(M.MessageError, match="bad Status"):
        from_json(b'{"stamp": 1.0}', M.Status)
    with pytest.raises(M.MessageError, match="bad Command"):
        from_json(b"not json", M.Command)
    with pytest.raises(M.MessageError, match="bad Status"):
        from_json(to_json(msg).replace(b'"estop"', b'"flying"', 1), M.Status)  # validated, not only parsed


def test_a_channel_spec_names_its_schema_by_the_kind_and_holds_its_json_schema() -> None:
    spec = ChannelSpec.for_kind("scm/r1/cmd", M.Command)
    assert (spec.topic, spec.schema_name) == ("scm/r1/cmd", SCHEMA_PREFIX + "Command")
    assert json.loads(spec.schema) == json_schema(M.Command)
    assert ChannelSpec.for_kind("scm/r2/cmd", M.Command).schema is spec.schema  # built once per kind
    raw = json_schema(RawSample)
    assert raw["type"] == "object" and {"key", "size", "payload"} <= set(raw["required"])


def test_rename_robot_renames_only_the_robot_chunk_of_a_named_robot() -> None:
    renames = {"a": "b"}
    assert rename_robot("scm/a/cmd", renames) == "scm/b/cmd"
    assert rename_robot("scm/a/status/driver", renames) == "scm/b/status/driver"
    assert rename_robot("scm/c/cmd", renames) == "scm/c/cmd"
    assert rename_robot("scm/ab/cmd", renames) == "scm/ab/cmd"  # a whole chunk, not a prefix
    assert rename_robot("/scmbridge/malformed", renames) == "/scmbridge/malformed"


def test_wire_bytes_rename_the_key_and_the_robot_field_of_limits_and_pairs() -> None:
    lim = M.Limits(stamp=1.0, robot="a", version=2, box=[0.0, 1.0, -1.0, 1.0])
    key, data = wire_bytes(Entry("scm/a/limits", SCHEMA_PREFIX + "Limits", 5, to_json(lim)), {"a": "b"})
    assert key == "scm/b/limits" and M.decode(data, M.Limits).robot == "b"
    pairs = M.Pairs(stamp=1.0, robot="a")
    assert M.decode(wire_bytes(Entry("scm/a/pairs", "", 5, to_json(pairs)), {"a": "b"})[1], M.Pairs).robot == "b"
    cmd = M.Command(stamp=1.0, seq=1, v=0.1, omega=0.0, method="scm")
    key, data = wire_bytes(Entry("scm/a/cmd", "", 5, to_json(cmd)), {})
    assert key == "scm/a/cmd" and data == M.encode(cmd)  # no rename: the wire's own bytes


def test_an_entry_tells_wire_messages_from_the_recorders_own_channels() -> None:
    raw = RawSample(key="scm/r/cmd", error="bad", size=2, payload=b"\xc1\x00")
    e = Entry(MALFORMED, SCHEMA_PREFIX + "RawSample", 1, to_json(raw))
    assert not e.is_wire and e.message() == raw
    w = Entry("scm/r/estop", SCHEMA_PREFIX + "Estop", 1, to_json(M.Estop(stamp=1.0, source="op")))
    assert w.is_wire and w.message() == M.Estop(stamp=1.0, source="op")


def _write(path, samples: list[tuple[str, bytes]]) -> None:
    sink = McapSink(path, chunk_bytes=256)
    for i, (key, payload) in enumerate(samples):
        for spec, data, _ in classify(key, payload):
            sink.write(spec, data, log_time_ns=1000 + i)
    sink.close("test done")


def test_files_are_read_back_in_order_with_their_schemas_and_metadata(tmp_path) -> None:
    msgs = [M.Command(stamp=float(i), seq=i, v=0.01 * i, omega=0.0, method="scm") for i in range(40)]
    samples = [("scm/r1/cmd", M.encode(m)) for m in msgs] + [("scm/r1/cmd", b"\xc1")]
    _write(tmp_path / "a.mcap", samples[:20])
    _write(tmp_path / "b.mcap", samples[20:])
    entries, rec = read_recording([tmp_path / "a.mcap", str(tmp_path / "b.mcap")])
    assert [e.message() for e in entries[:40]] == msgs and [e.log_time for e in entries[:3]] == [1000, 1001, 1002]
    assert {e.schema for e in entries[:40]} == {SCHEMA_PREFIX + "Command"}
    assert entries[40].topic == MALFORMED and entries[40].message().payload == b"\xc1"
    assert rec.entries == 41 and rec.truncated == [] and rec.files == [tmp_path / "a.mcap", tmp_path / "b.mcap"]
    assert rec.metadata  # the sink's start/end records


def test_a_torn_file_is_read_up_to_its_last_complete_chunk_and_says_so(tmp_path) -> None:
    msgs = [M.LearnerState(stamp=float(i), seq=i, x=0.1 * i, y=0.0, theta=0.0, source="x" * 40) for i in range(200)]
    f = tmp_path / "torn.mcap"
    _write(f, [("scm/r1/state", M.encode(m)) for m in msgs])
    whole = f.read_bytes()
    f.write_bytes(whole[: len(whole) * 2 // 3])  # the recorder was killed mid-file
    entries, rec = read_recording([f])
    assert 0 < len(entries) < len(msgs)
    assert [e.message() for e in entries] == msgs[: len(entries)]  # what was read is exactly the start
    assert len(rec.truncated) == 1 and rec.truncated[0].startswith(f"{f}: ")
