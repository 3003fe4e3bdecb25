"""Where a node keeps its files and how it writes them (:mod:`bridge.core.paths`): the state and cache directories'
order of precedence, a write that fails leaving the old file and no temporary one, and quarantine.

That ``save_atomic`` makes the file 0600 and the directories it creates 0700 whatever the umask is tested in
tests/unit/bridge/core/test_auth.py; the stores and the latch that use it in their own tests."""

from __future__ import annotations

import errno
import os
import re
import threading
import time
from pathlib import Path

import pytest

from bridge.core.paths import cache_dir, quarantine, save_atomic, save_new, state_dir, temporary_name

VARS = ("SCMBRIDGE_STATE_DIR", "STATE_DIRECTORY", "XDG_STATE_HOME", "SCMBRIDGE_CACHE_DIR", "CACHE_DIRECTORY",
        "XDG_CACHE_HOME")


@pytest.fixture
def env(monkeypatch, tmp_path):
    """No directory variable set (the suite sets SCMBRIDGE_STATE_DIR for every test), HOME in tmp_path."""
    for var in VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    return monkeypatch


def test_state_dir_prefers_scmbridges_variable_then_systemds_then_xdg_then_home(env, tmp_path) -> None:
    assert state_dir() == tmp_path / "home" / ".local" / "state" / "scmbridge"
    env.setenv("XDG_STATE_HOME", "/x/state")
    assert state_dir() == Path("/x/state/scmbridge")
    env.setenv("STATE_DIRECTORY", "/var/lib/scmbridge-station:/var/lib/other")  # systemd: this unit's first
    assert state_dir() == Path("/var/lib/scmbridge-station")
    env.setenv("SCMBRIDGE_STATE_DIR", "/mine")
    assert state_dir() == Path("/mine")
    env.setenv("SCMBRIDGE_STATE_DIR", "")  # empty: as if unset
    assert state_dir() == Path("/var/lib/scmbridge-station")


def test_cache_dir_prefers_scmbridges_variable_then_systemds_then_xdg_then_home(env, tmp_path) -> None:
    assert cache_dir() == tmp_path / "home" / ".cache" / "scmbridge"
    env.setenv("XDG_CACHE_HOME", "")
    assert cache_dir() == tmp_path / "home" / ".cache" / "scmbridge"
    env.setenv("XDG_CACHE_HOME", "/x/cache")
    assert cache_dir() == Path("/x/cache/scmbridge")
    env.setenv("CACHE_DIRECTORY", "/var/cache/a:/var/cache/b")
    assert cache_dir() == Path("/var/cache/a")
    env.setenv("SCMBRIDGE_CACHE_DIR", "/c")
    assert cache_dir() == Path("/c")
    assert state_dir() != cache_dir()  # the two never share a variable


def test_neither_directory_is_ever_the_working_directory(env, tmp_path) -> None:
    (tmp_path / "home").mkdir()
    env.chdir(tmp_path / "home")  # started in its home directory: still not the working directory itself
    for d in (state_dir(), cache_dir()):
        assert d.is_absolute() and d != Path.cwd() and d.name == "scmbridge"


def test_a_save_replaces_the_content_and_leaves_no_temporary_file(tmp_path) -> None:
    f = tmp_path / "latch.bin"
    save_atomic(f, b"old")
    save_atomic(f, b"new")
    assert f.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latch.bin"]


def test_a_failed_save_leaves_the_old_content_and_removes_its_temporary_file(tmp_path) -> None:
    """The rename fails (here: a directory stands where the file goes): the error is raised, nothing is torn."""
    target = tmp_path / "store.bin"
    target.mkdir()
    (target / "keep").write_bytes(b"old")
    with pytest.raises(OSError):
        save_atomic(target, b"new")
    assert (target / "keep").read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["store.bin"]  # the .store.bin.<pid>.<thread>.tmp is gone


def test_a_stale_temporary_file_of_a_crash_is_overwritten_private(tmp_path) -> None:
    f = tmp_path / "key.bin"
    stale = temporary_name(f)  # a crash's, of a process and thread with this one's numbers
    stale.write_bytes(b"half a key from a crash")
    stale.chmod(0o644)
    save_atomic(f, b"k")
    assert f.read_bytes() == b"k" and not stale.exists()
    assert f.stat().st_mode & 0o777 == 0o600


def _together(n: int, fn) -> list:
    """``fn(i)`` on ``n`` threads released at once; their results (an exception is a result)."""
    gate, out = threading.Barrier(n), [None] * n

    def run(i: int) -> None:
        gate.wait()
        try:
            out[i] = fn(i)
        except Exception as exc:  # noqa: BLE001 (the test looks at it)
            out[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    return out


def test_threads_saving_one_file_at_once_each_save_it_whole(tmp_path) -> None:
    """Two robots of one station host once made their shared key at the same moment: their temporary files had one
    name, so one thread's rename took the other's file away (FileNotFoundError) or its content mixed with the
    other's."""
    f = tmp_path / "station.key"
    values = [bytes([65 + i]) * 4096 for i in range(8)]

    def save(i: int) -> None:
        for _ in range(40):
            save_atomic(f, values[i])

    assert _together(8, save) == [None] * 8
    assert f.read_bytes() in values
    assert sorted(p.name for p in tmp_path.iterdir()) == ["station.key"]


def test_a_new_file_is_written_once_and_never_replaced(tmp_path) -> None:
    f = tmp_path / "station.key"
    assert save_new(f, b"first") and not save_new(f, b"second")
    assert f.read_bytes() == b"first" and f.stat().st_mode & 0o777 == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["station.key"]


def test_of_threads_creating_one_file_at_once_exactly_one_writes_it(tmp_path) -> None:
    f = tmp_path / "d" / "station.key"
    made = _together(8, lambda i: save_new(f, bytes([65 + i]) * 64))
    assert sorted(made) == [False] * 7 + [True]
    assert f.read_bytes() == bytes([65 + made.index(True)]) * 64
    assert sorted(p.name for p in f.parent.iterdir()) == ["station.key"]


def test_a_directory_that_exists_is_left_as_its_owner_set_it(tmp_path) -> None:
    d = tmp_path / "shared"
    d.mkdir()
    d.chmod(0o750)
    save_atomic(d / "f", b"x")
    assert d.stat().st_mode & 0o777 == 0o750


def test_quarantine_moves_the_file_aside_with_the_time_and_keeps_its_bytes(tmp_path) -> None:
    f = tmp_path / "pairs-r1.bin"
    f.write_bytes(b"\x00garbage")
    before = int(time.time())
    aside = quarantine(f)
    after = int(time.time())
    assert not f.exists() and aside.parent == tmp_path and aside.read_bytes() == b"\x00garbage"
    m = re.fullmatch(r"pairs-r1\.bin\.corrupt-(\d+)", aside.name)
    assert m and before <= int(m.group(1)) <= after
    with pytest.raises(FileNotFoundError):
        quarantine(tmp_path / "absent.bin")


def test_without_hard_links_a_new_file_is_still_written_once(tmp_path, monkeypatch) -> None:
    """A filesystem without hard links (FAT, some network filesystems): the file is created exclusively instead."""
    def no_links(src, dst) -> None:
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "link", no_links)
    f = tmp_path / "station.key"
    assert save_new(f, b"first") and not save_new(f, b"second")
    assert f.read_bytes() == b"first" and f.stat().st_mode & 0o777 == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["station.key"]
