"""Authenticated datagrams (bridge.core.auth) and ``scmbridge keys``: a datagram verifies only with its key and
unaltered; key files are made 0600, never silently replaced, and refused with one line when unsafe or malformed."""

from __future__ import annotations

import os

import pytest

from bridge.core import auth
from bridge.tools.cli import main


def test_a_sealed_datagram_opens_only_with_its_key_and_unaltered() -> None:
    key, other = os.urandom(32), os.urandom(32)
    d = auth.seal(key, b"payload with epoch and seq")
    assert auth.open_sealed(key, d) == b"payload with epoch and seq"
    assert auth.open_sealed(other, d) is None
    for i in range(len(d)):  # any one flipped bit anywhere is refused
        bad = bytearray(d)
        bad[i] ^= 0x01
        assert auth.open_sealed(key, bytes(bad)) is None
    assert auth.open_sealed(key, b"payload with epoch and seq") is None  # unauthenticated
    assert auth.open_sealed(key, d[: auth.OVERHEAD - 1]) is None


def test_keys_command_makes_a_private_key_and_never_replaces_one_silently(tmp_path, capsys) -> None:
    assert main(["keys", "udp", "--robot", "rover1"]) == 0
    path = auth.key_path("rover1", "udp")
    assert capsys.readouterr().out.strip() == str(path)
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    key = auth.load_key(path)
    assert len(key) == auth.KEY_BYTES
    assert main(["keys", "udp", "--robot", "rover1"]) == 2  # exists: one line, exit 2
    assert "--force" in capsys.readouterr().err
    assert auth.load_key(path) == key
    assert main(["keys", "udp", "--robot", "rover1", "--force"]) == 0 and auth.load_key(path) != key


def test_unsafe_or_malformed_key_files_are_refused_in_one_line(tmp_path) -> None:
    f = tmp_path / "k.key"
    with pytest.raises(auth.KeyFileError, match="not found"):
        auth.load_key(f)
    f.write_text(os.urandom(32).hex())
    f.chmod(0o644)
    with pytest.raises(auth.KeyFileError, match="readable by others"):
        auth.load_key(f)
    f.chmod(0o600)
    assert len(auth.load_key(f)) == 32
    f.write_text("not hex")
    with pytest.raises(auth.KeyFileError, match="32 bytes as hex"):
        auth.load_key(f)


def test_state_files_are_private_whatever_the_umask(tmp_path) -> None:
    """``save_atomic`` (keys, the estop latch, the pair store): the file 0600, the directories it makes 0700."""
    from bridge.core.paths import save_atomic

    old = os.umask(0)
    try:
        target = tmp_path / "made" / "here" / "state.bin"
        save_atomic(target, b"one")
        save_atomic(target, b"two")  # replaced: still private
    finally:
        os.umask(old)
    assert target.read_bytes() == b"two"
    assert oct(target.stat().st_mode & 0o777) == "0o600"
    assert {oct(d.stat().st_mode & 0o777) for d in (target.parent, target.parent.parent)} == {"0o700"}


def test_a_key_created_once_is_read_back_by_the_next_maker_and_never_replaced(tmp_path) -> None:
    f = tmp_path / "keys" / "station-x.key"
    key, made = auth.create_key(f)
    assert made and len(key) == auth.KEY_BYTES and auth.load_key(f, "station") == key
    assert auth.create_key(f) == (key, False)
    assert f.stat().st_mode & 0o777 == 0o600
    f.chmod(0o644)  # a key others may read is refused, not taken
    with pytest.raises(auth.KeyFileError, match="readable by others"):
        auth.create_key(f)
