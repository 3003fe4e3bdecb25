"""The station's files carry its tag (bridge/nodes/station_tags.py): a mission file changed while the station was
down is refused and said to the person before any resume; a pair store that is not the station's own, or of
another grid or other bounds, is refused with the reason. Real files in tmp_path; the key's record directory is the
test's own (tests/conftest.py)."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from bridge.core import wire as M
from bridge.core.paths import save_atomic
from bridge.nodes import station_tags
from bridge.nodes.mission_control import MissionControl, Saved
from bridge.nodes.station import control_file, restore_control
from bridge.nodes.station_core import load_store
from bridge.nodes.station_tags import FILE_MAGIC, FileTags, untagged
from transfer.domain import Bounds
from transfer.store import PairStore

L, T = Bounds((-0.2, 0.2), (-1.0, 1.0)), Bounds((-0.3, 0.3), (-1.5, 1.5))


@pytest.fixture(autouse=True)
def _no_key_made_before(monkeypatch) -> None:
    """Each test starts as a process that has made no station key (an untagged file is taken only then)."""
    monkeypatch.setattr(station_tags, "_MADE", set())


def _saved(spec_name: str, path: list[list[float]], phase: str = "paused") -> Saved:
    return MissionControl(robot="r1", spec=M.MissionSpec(name=spec_name, path=path), phase=phase).saved()


def test_a_file_is_tagged_and_taken_back_only_unchanged(tmp_path) -> None:
    tags = FileTags()
    f = tmp_path / "x.bin"
    blob = tags.seal("control", f, b"payload")
    assert blob.startswith(FILE_MAGIC) and untagged(blob) == b"payload"
    assert FileTags().open("control", f, blob) == (b"payload", "")
    changed = blob[:-1] + b"X"
    assert FileTags().open("control", f, changed)[0] is None
    assert "does not verify" in FileTags().open("control", f, changed)[1]
    assert FileTags().open("store", f, blob)[0] is None  # a mission file is not a store
    station_tags._MADE.clear()
    assert "no tag" in FileTags().open("control", f, b"payload")[1]  # untagged, the key not made now


def test_a_mission_file_rewritten_while_the_station_was_down_is_refused_and_said(tmp_path) -> None:
    """Finding: with the station down its mission file (unsigned, unlike the latch) was rewritten to a path behind
    the robot; after restart and ``mission resume`` the robot drove x 1.11 -> -0.49 m, and status never said the
    file had changed."""
    path = control_file("r1")
    tags = FileTags()
    save_atomic(path, tags.seal("control", path, M.encode(_saved("lab", [[0.0, 0.0], [2.0, 0.0]]))))
    restored = restore_control("r1", None, None)
    assert restored.phase == "paused" and restored.spec.name == "lab"  # its own file: taken (never running)
    behind = M.encode(_saved("lab", [[1.1, 0.0], [-0.5, 0.0]]))
    save_atomic(path, FILE_MAGIC + path.read_bytes()[len(FILE_MAGIC):len(FILE_MAGIC) + 16] + behind)
    control = restore_control("r1", None, None)
    assert control.phase == "idle" and [list(p) for p in control.spec.path] != [[1.1, 0.0], [-0.5, 0.0]]
    assert "refused" in control.reason and "look at it" in control.reason, control.reason
    assert not path.exists() and list(path.parent.glob(path.name + ".corrupt-*"))  # kept aside for a person


def test_a_store_not_the_stations_own_or_of_another_grid_is_refused_with_the_reason(tmp_path) -> None:
    """Finding: a crafted store (mirrored yaw-rate pairs) cut the obstacle clearance from 0.29 to 0.16 m; a store of
    another grid was used silently."""
    tags = FileTags()
    f = tmp_path / "pairs.bin"
    store = PairStore(L, T, (11, 11), 3)
    save_atomic(f, tags.seal("store", f, store.to_bytes()))
    got, how = load_store(f, L, T, (11, 11), 3, FileTags())
    assert "reloaded" in how
    save_atomic(f, tags.seal("store", f, PairStore(L, T, (7, 7), 3).to_bytes()))
    got, how = load_store(f, L, T, (11, 11), 3, FileTags())
    assert how == "new pair store" and got.grid == (11, 11)
    aside = next(tmp_path.glob("pairs.bin.corrupt-*"))
    aside.unlink()
    save_atomic(f, store.to_bytes())  # crafted, untagged, after the key was made
    station_tags._MADE.clear()
    got, how = load_store(f, L, T, (11, 11), 3, FileTags())
    assert how == "new pair store" and list(tmp_path.glob("pairs.bin.corrupt-*"))


def test_the_reason_a_store_was_refused_is_logged(tmp_path, caplog) -> None:
    tags = FileTags()
    f = tmp_path / "pairs.bin"
    save_atomic(f, tags.seal("store", f, PairStore(L, T, (7, 7), 3).to_bytes()))
    with caplog.at_level("ERROR", logger="scmbridge"):
        load_store(f, L, T, (11, 11), 3, FileTags())
    assert any("grid 7 x 7 is not this configuration's 11 x 11" in r.getMessage() for r in caplog.records)
    assert Path(f).exists() is False


def test_robots_of_one_host_making_their_directorys_key_at_once_all_tag_with_the_key_on_disk(tmp_path) -> None:
    """Two robots of one station host (a loop thread each) once made the key of their shared directory at the same
    moment: each wrote its own random key, the last rename won, and the other robot's files were tagged with a key
    no later start could read (or its loop failed on the rename). Now one makes it and the others read it."""
    gate, out = threading.Barrier(8), [None] * 8

    def seal(i: int) -> None:
        gate.wait()
        try:
            out[i] = FileTags().seal("store", tmp_path / f"pairs-r{i}.bin", b"pairs %d" % i)
        except Exception as exc:  # noqa: BLE001 (the test looks at it)
            out[i] = exc

    threads = [threading.Thread(target=seal, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert all(isinstance(b, bytes) for b in out), out
    reader = FileTags()  # a later start: the key on disk
    assert [reader.open("store", tmp_path / f"pairs-r{i}.bin", b) for i, b in enumerate(out)] == [
        (b"pairs %d" % i, "") for i in range(8)]
    assert {station_tags.key_file(tmp_path / "x")} == station_tags._MADE
