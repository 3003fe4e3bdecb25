"""The estop latch on disk (bridge/nodes/latch_store.py), without a driver host: the first start writes the install
marker and a released latch, only a latch signed by this host says released, a failed save is made fail safe
before the host hears of it. A real directory (tmp_path); a full disk is an injected saver (tests/latch.py); no
sleep: each wait is on the writer's own confirmation (LatchStore.defer), bounded."""

from __future__ import annotations

import errno
import os
import threading
from pathlib import Path

from bridge.core import wire as M
from bridge.core.paths import save_atomic
from bridge.nodes.latch_record import record_file
from bridge.nodes.latch_store import Latch, LatchStore, SaveResult, inspect_latch, latch_marker, read_latch
from tests.latch import FullDisk, wait_saved


def _store(path: Path | None, disk=save_atomic) -> tuple[LatchStore, list[SaveResult]]:
    results: list[SaveResult] = []
    store = LatchStore(path, results.append, disk)
    return store, results


def test_the_first_start_writes_the_marker_and_a_released_latch_and_the_next_start_reads_it(tmp_path) -> None:
    path = tmp_path / "state" / "estop-r1.bin"
    store, _ = _store(path)
    assert not store.open().latched and store.fresh_state and store.marker_saved
    assert oct(latch_marker(path).stat().st_mode & 0o777) == "0o600"
    assert inspect_latch(path) == (Latch(latched=False, reason="first start"), "")
    assert store.close(5.0)
    again, _ = _store(path)
    assert not again.open().latched and not again.fresh_state and again.key == store.key
    assert again.close(5.0)


def test_a_latch_submitted_is_saved_signed_and_the_latest_wins(tmp_path) -> None:
    path = tmp_path / "estop-r1.bin"
    store, results = _store(path)
    store.open()
    store.submit(True, "operator", "first")
    store.submit(True, "operator", "second")
    wait_saved(store)
    assert read_latch(path) == Latch(latched=True, source="operator", reason="second")
    assert results and all(r.saved for r in results) and results[-1].latch.reason == "second"
    store.submit(False, "operator", "released")
    wait_saved(store)
    assert inspect_latch(path) == (Latch(latched=False, source="operator", reason="released"), "")
    assert not store.defer(lambda: None)  # nothing waiting: the caller goes on at once
    assert store.close(5.0)


def test_a_save_under_way_is_said_until_it_is_written(tmp_path) -> None:
    """``saving()`` is true from a latch's submission until its save is written: what the estop's latch state waits
    for before it answers. The disk is held by the test's saver until it lets it go."""
    let_go, started = threading.Event(), threading.Event()

    def slow_disk(path: Path, data: bytes) -> None:
        started.set()
        assert let_go.wait(10.0)
        save_atomic(path, data)

    store, _ = _store(tmp_path / "estop-r1.bin", slow_disk)
    let_go.set()  # the start's own saves go through
    store.open()
    wait_saved(store)
    assert not store.saving()
    let_go.clear()
    started.clear()
    store.submit(True, "operator", "held")
    assert started.wait(10.0) and store.saving()  # being written
    let_go.set()
    wait_saved(store)
    assert not store.saving() and read_latch(store.path).reason == "held"
    assert store.close(5.0)
    assert not LatchStore(None, lambda r: None).saving()  # no file, no writer: nothing ever waits


def test_a_latched_save_that_fails_removes_the_old_file_so_a_restart_starts_latched(tmp_path) -> None:
    path = tmp_path / "estop-r1.bin"
    disk = FullDisk()
    store, results = _store(path, disk)
    store.open()
    disk.full.set()
    store.submit(True, "operator", "test")
    wait_saved(store)
    r = results[-1]
    assert not r.saved and not r.relatch and r.error == os.strerror(errno.ENOSPC)
    assert r.text == (f"estop latched but NOT saved to {path}: No space left on device; engage refused until it is "
                      "saved")
    assert not path.exists()  # the released file is gone, before the host heard of it
    latch, problem = inspect_latch(path)
    assert latch.latched and latch.source == "missing latch file" and "missing" in problem
    assert store.close(5.0)


def test_a_release_that_fails_is_to_be_latched_again(tmp_path) -> None:
    path = tmp_path / "estop-r1.bin"
    disk = FullDisk()
    store, results = _store(path, disk)
    store.open()
    store.submit(True, "operator", "test")
    wait_saved(store)
    disk.full.set()
    store.submit(False, "operator", "release")
    wait_saved(store)
    r = results[-1]
    assert not r.saved and r.relatch and "estop release NOT saved to" in r.text
    assert read_latch(path).latched  # the disk still says latched
    assert store.close(5.0)


def test_the_marker_missing_at_start_is_written_by_the_first_save(tmp_path) -> None:
    path = tmp_path / "estop-r1.bin"
    disk = FullDisk()
    store, _ = _store(path, disk)
    store.open()
    latch_marker(path).unlink()
    store.marker_saved = False  # (as when the start could not write it)
    store.submit(True, "operator", "test")
    wait_saved(store)
    assert disk.saves == [record_file(path), latch_marker(path), path] and read_latch(path).latched
    assert store.close(5.0)


def test_a_released_file_not_signed_by_this_host_reads_latched(tmp_path) -> None:
    path = tmp_path / "estop-r1.bin"
    store, _ = _store(path)
    store.open()
    assert store.close(5.0)
    path.write_bytes(M.encode(Latch(latched=False, source="operator")))
    again, _ = _store(path)
    latch = again.open()
    assert latch.latched and latch.source == "unverified latch file"
    assert again.close(5.0)


def test_a_store_in_memory_only_does_nothing_on_disk() -> None:
    store, results = _store(None)
    assert store.open() == Latch(latched=False) and not store.fresh_state
    store.submit(True, "operator", "test")
    assert not store.defer(lambda: None) and store.forget() == "" and store.close(0.1) and results == []


# ------------------------------------------------------------------ the host's own files turned against it
def _latched_then_released_then_latched(path: Path) -> bytes:
    """A host that latched, was released (the released file is copied off) and latched again; the released copy."""
    store, _ = _store(path)
    store.open()
    store.submit(True, "operator", "one")
    wait_saved(store)
    store.submit(False, "operator", "released")
    wait_saved(store)
    released = path.read_bytes()
    store.submit(True, "operator", "parked")
    wait_saved(store)
    assert store.close(5.0)
    return released


def test_latch_and_marker_deleted_together_after_the_host_has_run_start_latched_and_say_so(tmp_path) -> None:
    """Finding: marker and latch deleted together, the host believed it was a first start and drove. Its record,
    outside the state directory, says it has run here."""
    path = tmp_path / "state" / "estop-r1.bin"
    _latched_then_released_then_latched(path)
    path.unlink()
    latch_marker(path).unlink()
    latch, problem = inspect_latch(path)
    assert latch.latched and "missing" in problem and "deleted" in problem, problem
    again, _ = _store(path)
    assert again.open().latched and not again.fresh_state
    assert again.close(5.0)


def test_an_older_released_latch_copied_back_reads_latched(tmp_path) -> None:
    """Finding: an older released latch of this same host, copied back, verified. It names its count; the record
    names the last one saved."""
    path = tmp_path / "estop-r1.bin"
    released = _latched_then_released_then_latched(path)
    path.write_bytes(released)
    latch, problem = inspect_latch(path)
    assert latch.latched and "copied back" in problem, problem


def test_the_key_is_not_beside_the_latch_and_a_replaced_marker_reads_latched(tmp_path) -> None:
    """Finding: a release signed with the key read from the install marker, and a marker replaced by one's own
    key, each drove the robot. The marker holds only a fingerprint; a key put in it is not the record's."""
    import secrets

    from bridge.nodes.latch_store import sign_latch

    path = tmp_path / "estop-r1.bin"
    _latched_then_released_then_latched(path)
    store_key = _store(path)[0]
    marker = latch_marker(path).read_text()
    assert marker.startswith("fingerprint ") and store_key.path is not None
    mine = secrets.token_bytes(32)
    latch_marker(path).write_text(mine.hex() + "\n")  # the marker replaced by one's own key
    path.write_bytes(M.encode(sign_latch(mine, Latch(latched=False, source="operator", count=99))))
    latch, problem = inspect_latch(path)
    assert latch.latched and "another key" in problem, problem


def test_an_older_versions_marker_has_its_key_moved_into_the_record(tmp_path) -> None:
    import secrets

    from bridge.nodes.latch_record import fingerprint, read_record
    from bridge.nodes.latch_store import sign_latch

    path = tmp_path / "estop-r1.bin"
    key = secrets.token_bytes(32)
    save_atomic(latch_marker(path), key.hex().encode() + b"\n")
    save_atomic(path, M.encode(sign_latch(key, Latch(latched=True, source="operator"))))
    store, _ = _store(path)
    assert store.open().latched and store.key == key
    assert read_record(record_file(path)).key == key
    assert latch_marker(path).read_text() == f"fingerprint {fingerprint(key)}\n"
    store.submit(False, "operator", "released")
    wait_saved(store)
    assert store.close(5.0)
    assert inspect_latch(path) == (Latch(latched=False, source="operator", reason="released"), "")
