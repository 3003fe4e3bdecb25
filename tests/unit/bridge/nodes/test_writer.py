"""Saves off the real-time loop (:mod:`bridge.nodes.writer`): the default save is the atomic, private one; a thread
is started only by the first save; different files are written in the order they were handed; a bug in a save is
reported as a failed save and the thread lives on. Outcomes are collected after :meth:`SaveWriter.close` (which joins
the thread) or awaited on an event: nothing sleeps.

Latest-bytes-win per file and writing after close are tested in tests/unit/bridge/nodes/test_station_saves.py,
a slow disk beside the station's ticks there too."""

from __future__ import annotations

import threading
from pathlib import Path

from bridge.nodes.writer import SaveWriter


def test_the_default_save_writes_each_file_atomically_and_privately(tmp_path) -> None:
    w = SaveWriter()
    a, b = tmp_path / "made" / "a.bin", tmp_path / "b.bin"
    w("store", a, b"A")
    w("control", b, b"B")
    w.close()
    assert a.read_bytes() == b"A" and b.read_bytes() == b"B"
    assert a.stat().st_mode & 0o777 == 0o600 and a.parent.stat().st_mode & 0o777 == 0o700
    assert w.results() == [("store", None), ("control", None)]
    assert w.results() == []  # each outcome comes back once


def test_no_thread_until_the_first_save_and_close_without_one_returns(tmp_path) -> None:
    w = SaveWriter(name="idle-writer")
    assert w.thread is None
    w.close()
    assert w.thread is None and w.results() == []
    w2 = SaveWriter(name="my-writer")
    w2("x", tmp_path / "x", b"1")
    assert w2.thread is not None and w2.thread.name == "my-writer" and w2.thread.daemon
    w2.close()
    assert not w2.thread.is_alive()


def test_files_are_written_in_the_order_they_were_handed(tmp_path) -> None:
    order: list[str] = []
    gate = threading.Event()

    def disk(path: Path, data: bytes) -> None:
        gate.wait(10)
        order.append(path.name)

    w = SaveWriter(disk)
    names = ["c", "a", "d", "b"]
    for n in names:
        w(n, tmp_path / n, n.encode())
    gate.set()
    w.close()
    assert order == names and [what for what, _ in w.results()] == names


def test_a_save_that_raises_a_bug_is_a_failed_save_and_the_thread_goes_on(tmp_path, caplog) -> None:
    done = threading.Event()

    def disk(path: Path, data: bytes) -> None:
        if data == b"bug":
            raise KeyError("no such field")
        path.write_bytes(data)
        done.set()

    w = SaveWriter(disk)
    w("store", tmp_path / "s", b"bug")
    w("control", tmp_path / "c", b"ok")
    assert done.wait(10)  # written after the failed one: the thread lived on
    w.close()
    (what1, err1), (what2, err2) = w.results()
    assert (what1, what2) == ("store", "control") and err2 is None
    assert isinstance(err1, OSError) and str(err1) == "KeyError: 'no such field'"
    assert "saving store to" in caplog.text  # and the traceback is logged, not lost
    assert (tmp_path / "c").read_bytes() == b"ok" and not (tmp_path / "s").exists()


def test_a_failed_write_keeps_its_os_error(tmp_path) -> None:
    w = SaveWriter()
    blocker = tmp_path / "file"
    blocker.write_text("")
    w("store", blocker / "under-a-file.bin", b"x")  # its directory cannot be made
    w.close()
    [(what, err)] = w.results()
    assert what == "store" and isinstance(err, OSError) and err.errno is not None
