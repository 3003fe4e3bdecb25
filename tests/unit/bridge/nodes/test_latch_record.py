"""The latch's record outside the state directory (bridge/nodes/latch_record.py): where it lives, one per state
directory, what it and the marker hold, and what is refused when reading them. Real files in tmp_path."""

from __future__ import annotations

import os

import pytest

from bridge.nodes.latch_record import (
    Record,
    fingerprint,
    marker_text,
    read_marker_text,
    read_record,
    record_dir,
    record_file,
)


def test_the_record_lives_outside_the_state_directory_one_per_state_directory(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("SCMBRIDGE_RECORD_DIR", str(tmp_path / "rec"))
    assert record_dir() == tmp_path / "rec"
    a, b = record_file(tmp_path / "one" / "estop-r1.bin"), record_file(tmp_path / "two" / "estop-r1.bin")
    assert a.parent == b.parent == tmp_path / "rec" and a != b and a.name.startswith("estop-r1-")
    monkeypatch.delenv("SCMBRIDGE_RECORD_DIR")
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/scmbridge:/var/lib/scmbridge-record")
    assert str(record_dir()) == "/var/lib/scmbridge-record"  # systemd's second StateDirectory=


def test_the_record_round_trips_and_a_bad_one_is_refused(tmp_path) -> None:
    f = tmp_path / "r.record"
    assert read_record(f) is None
    rec = Record(os.urandom(32), 7)
    f.write_bytes(rec.encode())
    f.chmod(0o600)
    assert read_record(f) == rec
    f.chmod(0o644)
    with pytest.raises(ValueError, match="readable by others"):
        read_record(f)
    f.chmod(0o600)
    f.write_text("scmbridge estop record 1\nabcd\n3\n")
    with pytest.raises(ValueError, match="not an estop record"):
        read_record(f)


def test_the_marker_holds_a_fingerprint_and_an_older_markers_key_is_read_as_such(tmp_path) -> None:
    key = os.urandom(32)
    m = tmp_path / "estop-r1.installed"
    m.write_bytes(marker_text(key))
    m.chmod(0o600)
    assert read_marker_text(m) == (fingerprint(key), None) and key.hex() not in m.read_text()
    m.write_text(key.hex() + "\n")  # an older version's marker: the key itself
    assert read_marker_text(m) == (fingerprint(key), key)
    m.write_text("garbage\n")
    with pytest.raises(ValueError, match="not an install marker"):
        read_marker_text(m)
