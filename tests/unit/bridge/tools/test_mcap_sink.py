"""bridge/tools/mcap_sink.py: the MCAP file(s) ``scmbridge record`` writes, written here in a temporary directory and
read back with :func:`bridge.tools.mcap_format.read_recording`: file names, start and end metadata, chunks closed by
size and by time, rotation keeping the newest files, oversize messages. The size limit's bound over many channel
mixes is in tests/integration/test_record.py (test_size_limit_is_never_exceeded)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bridge.core import wire as M
from bridge.tools.mcap_format import META_END, META_START, SCHEMA_PREFIX, ChannelSpec, classify, read_recording
from bridge.tools.mcap_sink import McapSink


def _state(i: int, pad: int = 0) -> tuple[ChannelSpec, bytes]:
    msg = M.LearnerState(stamp=float(i), seq=i, x=0.1 * i, y=0.0, theta=0.0, source="x" * pad)
    spec, data, outcome = classify("scm/r1/state", M.encode(msg))[0]
    assert outcome == "ok"
    return spec, data


def test_max_bytes_and_rotation_exclude_each_other(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="exclude each other"):
        McapSink(tmp_path / "a.mcap", max_bytes=10_000, rotate_bytes=10_000)


def test_file_names_are_numbered_only_when_rotating(tmp_path: Path) -> None:
    assert McapSink(tmp_path / "run.mcap").path_for(3) == tmp_path / "run.mcap"
    rot = McapSink(tmp_path / "run.mcap", rotate_bytes=10_000)
    assert rot.path_for(1) == tmp_path / "run-0001.mcap" and rot.path_for(12) == tmp_path / "run-0012.mcap"
    assert McapSink(tmp_path / "run", rotate_bytes=10_000).path_for(2) == tmp_path / "run-0002.mcap"


def test_an_empty_recording_is_still_a_valid_file_that_says_why(tmp_path: Path) -> None:
    sink = McapSink(tmp_path / "sub" / "empty.mcap", meta={"pattern": "scm/**"})
    sink.close("signal")
    entries, rec = read_recording([tmp_path / "sub" / "empty.mcap"])
    assert entries == [] and rec.truncated == [] and sink.kept() == [tmp_path / "sub" / "empty.mcap"]
    meta = dict(rec.metadata)
    assert meta[META_START] == {"pattern": "scm/**", "file_index": "1"}
    assert meta[META_END] == {"reason": "signal", "file_messages": "0"}


def test_messages_read_back_in_order_with_their_times_schema_and_end_counts(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    sink = McapSink(out, chunk_bytes=512)
    for i in range(50):
        assert sink.write(*_state(i), log_time_ns=10_000 + i) == "ok"
    sink.counts["messages"] = 50
    sink.counts["dropped"] = 2
    sink.close("duration")
    entries, rec = read_recording([out])
    assert [e.message().seq for e in entries] == list(range(50))
    assert [e.log_time for e in entries] == [10_000 + i for i in range(50)]
    assert {e.topic for e in entries} == {"scm/r1/state"} and {e.schema for e in entries} == {
        SCHEMA_PREFIX + "LearnerState"}
    assert dict(rec.metadata)[META_END] == {"reason": "duration", "dropped": "2", "messages": "50",
                                            "file_messages": "50"}


def test_a_chunk_is_closed_by_size_and_by_time_only_when_it_is_old_enough(tmp_path: Path) -> None:
    sink = McapSink(tmp_path / "a.mcap", chunk_bytes=1 << 20, flush_s=1.0)
    sink.write(*_state(0), log_time_ns=1)
    assert sink.pending > 0 and sink.pending_channels
    sink.tick(sink.last_flush + 0.5)  # not a second old: stays open
    assert sink.pending_channels
    sink.tick(sink.last_flush + 1.0)
    assert sink.pending == 0 and not sink.pending_channels
    sink.tick(sink.last_flush + 5.0)  # nothing pending: nothing to close
    small = McapSink(tmp_path / "b.mcap", chunk_bytes=1)  # every message closes its chunk
    small.write(*_state(0), log_time_ns=1)
    assert small.pending == 0
    sink.close("x")
    small.close("x")


def test_a_chunk_closed_is_on_disk_before_the_file_is(tmp_path: Path) -> None:
    out = tmp_path / "killed.mcap"
    sink = McapSink(out, chunk_bytes=256)
    for i in range(30):
        sink.write(*_state(i), log_time_ns=i)
    entries, rec = read_recording([out])  # read while still open: a kill -9 now leaves this
    assert 0 < len(entries) <= 30 and [e.message().seq for e in entries] == list(range(len(entries)))
    assert rec.truncated
    sink.close("x")


def test_a_size_limit_refuses_the_message_that_would_pass_it_and_keeps_the_file_whole(tmp_path: Path) -> None:
    out = tmp_path / "cap.mcap"
    sink = McapSink(out, max_bytes=6000, chunk_bytes=1024)
    written = 0
    while sink.write(*_state(written, pad=20), log_time_ns=written) == "ok":
        written += 1
    assert written > 0
    sink.close("size limit")
    entries, rec = read_recording([out])
    assert out.stat().st_size <= 6000 and len(entries) == written and not rec.truncated


def test_rotation_keeps_the_newest_files_each_complete_and_within_its_size(tmp_path: Path) -> None:
    sink = McapSink(tmp_path / "rot.mcap", rotate_bytes=6000, keep=2, chunk_bytes=512)
    n = 200
    for i in range(n):
        assert sink.write(*_state(i, pad=10), log_time_ns=i) == "ok"
    sink.close("signal")
    kept = sink.kept()
    assert len(sink.files) > 2 and len(kept) == 2 and kept == sink.files[-2:]
    assert not any(p.exists() for p in sink.files[:-2])
    seqs = []
    for p in kept:
        entries, rec = read_recording([p])
        assert p.stat().st_size <= 6000 and not rec.truncated
        seqs += [e.message().seq for e in entries]
        index = int(p.stem.rsplit("-", 1)[1])
        assert dict(rec.metadata)[META_START]["file_index"] == str(index)
    assert seqs == list(range(n - len(seqs), n))  # the newest messages, in order, none lost between the two files
    ends = [dict(read_recording([p])[1].metadata)[META_END]["reason"] for p in kept]
    assert ends == ["rotated", "signal"]


def test_a_message_too_big_for_any_rotated_file_is_dropped_and_counted(tmp_path: Path) -> None:
    sink = McapSink(tmp_path / "big.mcap", rotate_bytes=5000, keep=5)
    assert sink.write(*_state(0), log_time_ns=0) == "ok"
    spec, data = _state(1)
    huge = data + b" " * 6000  # the sink stores bytes as given: a message of 6 kB
    assert sink.write(spec, huge, log_time_ns=1) == "oversize"
    assert sink.write(spec, huge, log_time_ns=2) == "oversize"  # into the fresh, empty file: still not
    assert sink.counts["oversize"] == 2
    assert sink.write(*_state(3), log_time_ns=3) == "ok"
    sink.close("signal")
    seqs = [e.message().seq for p in sink.kept() for e in read_recording([p])[0]]
    assert seqs == [0, 3]
