"""A station's saves (bridge.nodes.station_saves): when the pair store is saved, what a failure leaves for the
status, and the writer's outcomes coming back; real files in a temporary directory, times passed in, no Zenoh."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bridge.core import wire as M
from bridge.nodes.mission_control import Fitness, MissionControl, Saved
from bridge.nodes.station_saves import StationSaves, snapshot
from bridge.nodes.station_status import StationCounters
from bridge.nodes.station_tags import read_store
from bridge.nodes.writer import SaveWriter
from sim_learner.dynamics import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W
from transfer.domain import Bounds
from transfer.store import PairStore

SPEC = M.MissionSpec(name="line", path=[[0.0, 0.0], [2.0, 0.0]])


def _saves(tmp_path: Path, store_path: Path | None = None, control_path: Path | None = None,
           every: float = 1.0, phase: float = 0.0) -> StationSaves:
    store = PairStore(Bounds(MPC_LEARNER_V, MPC_LEARNER_W), Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=1)
    return StationSaves(store, store_path or tmp_path / "pairs.bin", MissionControl("r1", SPEC), control_path,
                        StationCounters(), every, phase)


def test_the_store_is_saved_at_the_first_periodic_tick_and_then_each_period(tmp_path) -> None:
    s = _saves(tmp_path, every=1.0)
    handed: list[tuple[str, Path, float]] = []
    s.writer = lambda what, path, data: handed.append((what, path, len(data())))  # the adapter's writer's signature
    for now in (10.0, 10.5, 10.99, 11.0, 11.5, 12.0):
        s.periodic(now)
    assert [w for w, _, _ in handed] == ["store"] * 3 and {p for _, p, _ in handed} == {tmp_path / "pairs.bin"}
    assert s.next_at == 13.0


def test_a_robots_phase_delays_its_second_save_only_so_that_a_fleet_started_together_spreads_its_saves(
        tmp_path) -> None:
    saved: dict[float, list[float]] = {}
    for phase in (0.0, 0.25, 0.75):
        s = _saves(tmp_path, every=4.0, phase=phase)
        handed: list[str] = []
        s.writer = lambda what, path, data, _h=handed: _h.append(what)
        for k in range(0, 141):
            now = 10.0 + 0.1 * k
            n = len(handed)
            s.periodic(now)
            if len(handed) > n:
                saved.setdefault(phase, []).append(now)
    starts = {p: [round(t, 1) for t in ts] for p, ts in saved.items()}
    assert starts == {0.0: [10.0, 14.0, 18.0, 22.0], 0.25: [10.0, 15.0, 19.0, 23.0], 0.75: [10.0, 17.0, 21.0]}


def test_without_a_writer_a_save_is_made_at_once_and_a_mission_without_a_path_is_not_kept(tmp_path) -> None:
    s = _saves(tmp_path)
    s.save("store")
    assert (tmp_path / "pairs.bin").exists() and s.error == ""
    s.save("control")  # no control path: nothing, and no error
    handed: list[str] = []
    s.writer = lambda what, path, data: handed.append(what)
    s.save("control")
    assert handed == [] and s.error == "" and s.counters.persist_failures == 0


def test_a_failed_store_save_is_counted_reported_and_cleared_by_the_next_that_succeeds(tmp_path) -> None:
    (tmp_path / "not-a-dir").write_text("")
    s = _saves(tmp_path, store_path=tmp_path / "not-a-dir" / "pairs.bin")
    assert s.persist() is False
    assert s.error.startswith("pair store not saved: ") and s.counters.persist_failures == 1
    assert s.saved("store", None) is True and s.error == ""  # the writer's next save succeeded


def test_a_failed_mission_save_is_retried_at_the_next_tick(tmp_path) -> None:
    (tmp_path / "not-a-dir").write_text("")
    s = _saves(tmp_path, control_path=tmp_path / "not-a-dir" / "mission.bin")
    s.control.saved()  # as after a save: nothing changed since
    assert not s.control.changed
    s.save_control()
    assert s.error.startswith("mission state not saved: ") and s.counters.persist_failures == 1
    assert s.control.changed  # the next tick asks again
    assert s.saved("control", OSError(28, "No space left on device")) is False
    assert s.error == "mission state not saved: No space left on device" and s.counters.persist_failures == 2


def test_the_writer_writes_the_ticks_snapshots_and_its_outcomes_come_back(tmp_path) -> None:
    s = _saves(tmp_path, control_path=tmp_path / "mission.bin")
    writer = SaveWriter(name="test-saves")
    s.writer = writer
    s.control.request(M.MissionRequest(stamp=0.0, action="abort", source="test"), Fitness(), 0.0)
    s.save("store")
    s.save("control")
    writer.close()  # writes what waits: no waiting on a clock
    outcomes = writer.results()
    assert sorted(w for w, _ in outcomes) == ["control", "store"] and all(e is None for _, e in outcomes)
    assert all(s.saved(w, e) for w, e in outcomes)
    assert M.decode((tmp_path / "mission.bin").read_bytes(), Saved).phase == "aborted"
    assert read_store(tmp_path / "pairs.bin").raw_count == 0


def test_the_tick_hands_over_a_snapshot_encoded_later_that_the_stores_later_changes_leave_alone(tmp_path) -> None:
    """The save is sealed off the tick: the tick hands the writer a function, not bytes; called later (on the
    writer's thread) it gives the store as it was when the tick asked, tagged, however the store changed since."""
    from bridge.nodes.station_tags import FileTags, untagged

    s = _saves(tmp_path, control_path=tmp_path / "mission.bin")
    s.tags = FileTags()
    rng = np.random.default_rng(3)
    for _ in range(40):
        s.store.add(rng.uniform(-0.3, 0.3, 2), rng.uniform(-0.3, 0.3, 2))
    before = s.store.to_bytes()
    handed: list = []
    s.writer = lambda what, path, data: handed.append((what, data))
    s.save("store")
    s.save("control")
    (what, data), (what_c, data_c) = handed
    assert what == "store" and what_c == "control" and callable(data) and callable(data_c)
    for _ in range(40):  # the tick goes on: pairs, limits, change tests
        s.store.add(rng.uniform(-0.3, 0.3, 2), rng.uniform(-0.3, 0.3, 2))
    s.control.request(M.MissionRequest(stamp=0.0, action="abort", source="test"), Fitness(), 0.0)
    assert s.store.to_bytes() != before
    blob = data()
    assert untagged(blob) == before and s.tags.open("store", s.store_path, blob) == (before, "")
    assert M.decode(untagged(data_c()), Saved).phase == "idle"  # the mission as it was handed over


def test_a_snapshot_owns_its_arrays_down_to_the_limits_and_encodes_as_the_store_did() -> None:
    store = PairStore(Bounds(MPC_LEARNER_V, MPC_LEARNER_W), Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=1)
    store.add(np.array([0.1, 0.1]), np.array([0.1, 0.1]))
    snap = snapshot(store)
    assert snap.to_bytes() == store.to_bytes()
    assert snap.cells.count is not store.cells.count and snap.limits is not store.limits
    assert snap.limits.lo is not store.limits.lo
    store.limits.hull_sum += 1.0
    store.cells.count += 1
    assert snap.to_bytes() != store.to_bytes() and PairStore.from_bytes(snap.to_bytes()).raw_count == 1


def test_a_files_key_is_made_on_the_loops_thread_at_its_first_save_not_by_the_writer(tmp_path) -> None:
    """The stations of one process share a directory, so a key: made by the loop's thread at the first save (as
    the stations take turns there), never by several writer threads at once, one replacing another's."""
    from bridge.nodes.station_tags import FileTags, key_file

    s = _saves(tmp_path / "state", control_path=tmp_path / "state" / "mission.bin")
    s.tags = FileTags()
    handed: list = []
    s.writer = lambda what, path, data: handed.append(data)  # nothing encoded, sealed or written yet
    assert not key_file(s.store_path).exists()
    s.save("store")
    assert key_file(s.store_path).exists() and handed
    other = _saves(tmp_path / "state")  # a second station of the process, same directory: reads that key
    other.tags = FileTags()
    other.writer = lambda what, path, data: handed.append(data)
    other.save("store")
    key = key_file(s.store_path).read_bytes()
    blobs = [d() for d in handed]
    assert key_file(s.store_path).read_bytes() == key
    assert all(FileTags().open("store", s.store_path, b)[1] == "" for b in blobs)
