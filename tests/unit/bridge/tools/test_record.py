"""bridge/tools/record.py: ``scmbridge record``'s pure parts: sizes on the command line (:func:`parse_bytes`), the
receive clock of ``log_time`` (:class:`Clock`), the start metadata and the refusals before anything is opened
(``_check``). The recorder against a real router (every sample in order, a killed recorder, size limits,
rotation) is in tests/integration/test_record.py; the file it writes in tests/unit/bridge/tools/test_mcap_sink.py."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from bridge.core.errors import UsageError
from bridge.tools import record
from bridge.tools.mcap_format import NONCANONICAL
from bridge.tools.record import Clock, parse_bytes


@pytest.mark.parametrize(("text", "n"), [
    ("65536", 65536), ("64k", 64 << 10), ("64K", 64 << 10), ("10M", 10 << 20), ("1G", 1 << 30), ("64KiB", 64 << 10),
    ("10MB", 10 << 20), ("512b", 512), (" 2 m ", 2 << 20),
])
def test_sizes_are_read_in_powers_of_1024(text: str, n: int) -> None:
    assert parse_bytes(text) == n


@pytest.mark.parametrize(("text", "says"), [
    ("0", "must be > 0"), ("0k", "must be > 0"), ("1.5M", "is not a size"), ("-1", "is not a size"),
    ("10T", "is not a size"), ("", "is not a size"), ("k", "is not a size"),
])
def test_what_is_not_a_positive_size_is_refused_for_argparse(text: str, says: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=says):
        parse_bytes(text)


def test_log_time_is_the_start_wall_clock_plus_the_monotonic_time_since() -> None:
    c = Clock()
    assert c.log_time(c.mono0) == c.wall0
    assert c.log_time(c.mono0 + 1_500_000_000) == c.wall0 + 1_500_000_000
    assert c.log_time(c.mono0 - 7) == c.wall0 - 7  # a sample stamped just before: still ordered


def test_the_start_metadata_says_what_was_recorded_and_how_times_read() -> None:
    c = Clock()
    meta = record._start_meta("scm/r1/**", c)
    assert meta["pattern"] == "scm/r1/**" and meta["started_unix_ns"] == str(c.wall0)
    assert meta["monotonic_at_start_ns"] == str(c.mono0) and meta["host"] and meta["scmbridge"]
    assert NONCANONICAL in meta["message_encoding"] and "receipt" in meta["log_time"]
    assert all(isinstance(v, str) for v in meta.values())  # MCAP metadata is strings only


def _args(out: Path, **kw) -> argparse.Namespace:
    base = {"out": str(out), "keep": 10, "rotate_bytes": None, "force": False}
    return argparse.Namespace(**{**base, **kw})


def test_keep_must_be_positive_and_goes_with_rotation(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="--keep must be >= 1"):
        record._check(_args(tmp_path / "a.mcap", keep=0, rotate_bytes=1000))
    with pytest.raises(UsageError, match="--keep goes with --rotate-bytes"):
        record._check(_args(tmp_path / "a.mcap", keep=3))
    record._check(_args(tmp_path / "a.mcap", keep=3, rotate_bytes=1000))  # fine


def test_an_existing_recording_is_not_overwritten_without_force(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    record._check(_args(out))
    out.write_bytes(b"x")
    with pytest.raises(UsageError, match=r"run\.mcap exists \(--force overwrites\)"):
        record._check(_args(out))
    record._check(_args(out, force=True))


def test_with_rotation_the_numbered_files_are_what_must_not_exist(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    out.write_bytes(b"x")  # the plain name is not what a rotating recorder writes
    record._check(_args(out, rotate_bytes=1000))
    (tmp_path / "run-0002.mcap").write_bytes(b"x")
    with pytest.raises(UsageError, match=r"run-0002\.mcap exists"):
        record._check(_args(out, rotate_bytes=1000))
    (tmp_path / "plain-0001.mcap").write_bytes(b"x")
    with pytest.raises(UsageError, match=r"plain-0001\.mcap exists"):  # an OUT without a suffix gets .mcap
        record._check(_args(tmp_path / "plain", rotate_bytes=1000))
