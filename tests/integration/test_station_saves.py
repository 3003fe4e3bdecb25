"""The station's saves never stall its ticks (docs/ARCHITECTURE.md, "Threads and clocks"): with a disk whose every
save takes 0.5 s and the pair store saved every tick, a station on a real Zenoh session still publishes its command
every period and answers mission requests and ``pairs`` queries at once; a save that fails on the writer thread is
reported on the status as before, and retried. Free 127.0.0.1 ports, bounded, the loop always stopped."""

from __future__ import annotations

import errno
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import load_mission, load_station
from bridge.core.paths import save_atomic
from bridge.nodes.station import KernelBuild, Station
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.mission import ask
from tests.collect import Collector

#: what the slow disk costs each save, s
#: the slow disk's stall: long against a loaded machine's scheduling delays (a test worker beside busy loops saw
#: answers take 0.42 s with nothing waiting on a save), so that waiting for a save stands out from them
STALL_S = 1.0
#: what an answer or a gap between commands may take without having waited for a save (STALL_S stands out above it)
PROMPT_S = 0.6


def _station(tmp_path: Path, robot: str, save: Callable[[Path, bytes], None], control: bool) -> Station:
    cfg_file = tmp_path / "station.toml"
    cfg_file.write_text("[station]\npersist_every_s = 0.1\n")  # a save every tick (the fastest allowed)
    st = Station(load_station(str(cfg_file)), robot, 10.0, tmp_path / "pairs.bin", load_mission(None),
                 control_path=tmp_path / "mission.bin" if control else None, save=save)
    st.build = KernelBuild(None)  # no MPC code generation: this station never drives
    return st


@contextmanager
def _serving(st: Station) -> Iterator[tuple[object, Collector]]:
    """``st`` serving on a router session in a thread; yields a client session and its collector."""
    port, stop = free_port(), threading.Event()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as server:
        loop = threading.Thread(target=st.serve, args=(server, stop, 60.0, False), kwargs={"announce": False},
                                name="test-station", daemon=True)
        loop.start()
        try:
            with open_session(make_config(mode="client", connect=[tcp(port)])) as client:
                yield client, Collector(client)
        finally:
            stop.set()
            loop.join(timeout=10)
            assert not loop.is_alive()


@pytest.mark.timeout(90)
def test_a_slow_disk_delays_neither_the_commands_nor_the_answers(tmp_path) -> None:
    """Finding: the station held its one lock over the whole tick, and each ``persist_every_s`` the tick wrote and
    fsynced the store: on a slow disk every command waited for the fsync and every query for the tick."""
    robot = f"slow{os.getpid()}"
    entered: list[float] = []

    def slow_disk(path: Path, data: bytes) -> None:
        entered.append(time.monotonic())
        time.sleep(STALL_S)  # a simulated stall: the disk's itself (fsync injection does the same to a real save)
        save_atomic(path, data)

    st = _station(tmp_path, robot, slow_disk, control=True)
    with _serving(st) as (client, col):
        cmds = col.listen(M.key(robot, "cmd"), M.Command)
        times = col.times[M.key(robot, "cmd")]
        assert col.wait(lambda: len(cmds) >= 3 and len(entered) >= 2, 30), "the station never published"
        t0 = time.monotonic()
        asked: list[tuple[str, float, M.MissionState | None]] = []
        for action in ("status", "start", "status", "pause", "status"):
            t = time.monotonic()
            ans = ask(client, robot, M.MissionRequest(stamp=t, action=action, source="test"), timeout=5.0)
            asked.append((action, time.monotonic() - t, ans))
            time.sleep(0.3)  # pacing: spread over the window, some asked while a save is under way
        t = time.monotonic()
        replies = list(client.get(M.key(robot, "pairs"), timeout=5.0))
        pairs_s = time.monotonic() - t
        # on until the window holds what is judged below (a stalled station takes longer, it does not fail)
        assert col.wait(lambda: sum(x >= t0 for x in times) >= 30 and sum(x >= t0 for x in entered) >= 4, 60)
        with col.lock:
            window = [x for x in times if x >= t0]
        saves = [x for x in entered if x >= t0]
    # commands: one a period (0.1 s), on a machine shared with other work; a tick that waited for a save breaks both
    gaps = np.diff(window)
    assert len(window) >= 30, (len(window), gaps.round(3).tolist())
    assert gaps.max() < PROMPT_S, gaps.round(3).tolist()
    assert len(saves) >= 4 and st.writer.replaced > 0  # the disk was slow all along; the latest save won
    # answers: at once (a save under way is not waited for), and true
    for action, took, ans in asked:
        assert ans is not None and took < PROMPT_S, (action, took)
    assert [a.phase for _, _, a in asked] == ["idle", "running", "running", "paused", "paused"]
    assert all(a.accepted for _, _, a in asked)
    assert len(replies) == 1 and pairs_s < PROMPT_S, pairs_s
    pairs = M.decode(replies[0].ok.payload.to_bytes(), M.Pairs)
    assert pairs.robot == robot
    # the exit's save is synchronous and final: the store and the mission (paused) are on disk
    assert st.persist()
    st.save_control()
    assert (tmp_path / "pairs.bin").exists()
    assert b"paused" in (tmp_path / "mission.bin").read_bytes()


@pytest.mark.timeout(90)
def test_a_save_that_fails_off_the_tick_is_reported_on_the_status_and_retried(tmp_path) -> None:
    """The writer thread's failure reaches the status as the tick's own failure did: not ok, the reason in the
    text, ``persist_failures`` counted; the next save that succeeds clears it."""
    robot = f"full{os.getpid()}"
    disk_full = threading.Event()
    disk_full.set()

    def disk(path: Path, data: bytes) -> None:
        if disk_full.is_set():
            raise OSError(errno.ENOSPC, "No space left on device")
        save_atomic(path, data)

    st = _station(tmp_path, robot, disk, control=False)
    with _serving(st) as (_, col):
        status = col.listen(M.status_key(robot, "station"), M.Status)
        assert col.wait(lambda: any("pair store not saved: No space left on device" in s.text for s in status), 30)
        with col.lock:
            bad = next(s for s in status if "pair store not saved" in s.text)
        assert not bad.ok and bad.counters["persist_failures"] >= 1
        disk_full.clear()
        n = len(col.snapshot(M.status_key(robot, "station")))
        assert col.wait(lambda: any("not saved" not in s.text for s in status[n:]), 10)
    assert (tmp_path / "pairs.bin").exists() and st.persist()


@pytest.mark.timeout(30)
def test_the_writer_keeps_the_latest_bytes_of_each_file_and_close_writes_what_waits(tmp_path) -> None:
    """Latest wins per file (a save waiting for the disk is replaced by a newer one of the same file, never one
    being written); every outcome comes back once; close writes what waits; after it a save is made at once."""
    from bridge.nodes.writer import SaveWriter

    entered, release = threading.Event(), threading.Event()

    def disk(path: Path, data: bytes) -> None:
        if data == b"a1":
            entered.set()
            assert release.wait(10)
        if data == b"bad":
            raise OSError(errno.EIO, "Input/output error")
        save_atomic(path, data)

    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    w = SaveWriter(disk)
    w("store", a, b"a1")
    assert entered.wait(10)  # a1 is being written (the disk stalls)
    w("store", a, b"a2")
    w("control", b, b"bad")
    w("store", a, b"a3")  # replaces a2, which waited
    assert w.replaced == 1 and w.results() == []
    release.set()
    w.close()
    got = w.results()
    assert [what for what, _ in got] == ["store", "control", "store"]
    assert got[0][1] is None and got[2][1] is None and got[1][1].errno == errno.EIO
    assert a.read_bytes() == b"a3" and not b.exists()
    w("control", b, b"b1")  # closed: written at once, in this thread
    assert b.read_bytes() == b"b1" and w.results() == [("control", None)]
