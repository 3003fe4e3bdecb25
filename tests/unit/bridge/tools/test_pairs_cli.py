"""bridge/tools/pairs_cli.py: the view of what a station learned (:class:`Learned`), built from a ``Pairs`` reply
(:func:`from_message`) or a store (:func:`from_store`, :func:`load_store_file`), its table and JSON, and the
listener that keeps the latest command. The command-line runs (a store file, a real station over Zenoh, the figure,
the triangulation against the mappers') are in tests/integration/test_pairs_cli.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.paths import save_atomic
from bridge.tools.pairs_cli import (
    COMMAND_WAIT_S,
    LatestCommand,
    Learned,
    PairsError,
    _Listener,
    from_message,
    from_store,
    load_store_file,
    table,
)
from bridge.tools.report import _Sample
from transfer.domain import Bounds
from transfer.store import PairStore

TB = Bounds((0.0, 1.0), (-1.0, 1.0))
LB = Bounds((0.0, 0.5), (-0.5, 0.5))


def _rec(i: int, tv: float, tw: float, lv: float, lw: float, count: int = 5) -> M.PairRecord:
    return M.PairRecord(id=i, version=1, count=count, teacher_v=tv, teacher_omega=tw, learner_v=lv, learner_omega=lw)


def _msg(*recs: M.PairRecord, box: list[float] | None = None) -> M.Pairs:
    return M.Pairs(stamp=1.0, robot="r1", pairs=list(recs), limits_box=box,
                   limits_hull=[[0.0, -1.0], [1.0, -1.0], [1.0, 1.0]])


def _view(latest: LatestCommand | None = None, grid: tuple[int, int] = (4, 4)) -> Learned:
    msg = _msg(_rec(5, 0.5, 0.5, 0.25, 0.0), _rec(0, 0.1, -0.5, 0.05, -0.25), _rec(3, 0.9, 0.5, 0.45, 0.25),
               box=[0.0, 1.0, -1.0, 1.0])
    return from_message(msg, TB, LB, grid, "config s.toml", "station for robot 'r1'", latest)


def test_a_reply_is_viewed_in_pair_id_order_with_its_limits() -> None:
    v = _view()
    assert v.ids.tolist() == [0, 3, 5] and v.teacher[0].tolist() == [0.1, -0.5] and v.learner[2].tolist() == [0.25, 0]
    assert v.counts.tolist() == [5, 5, 5] and v.robot == "r1" and v.cells == 16 and v.warnings == []
    assert v.limits_box == TB and v.hull.shape == (3, 2)


def test_a_reply_without_pairs_or_with_an_unusable_box_is_still_a_view() -> None:
    empty = from_message(M.Pairs(stamp=1.0, robot="r1"), TB, LB, (11, 11), "defaults", "s")
    assert empty.ids.shape == (0,) and empty.teacher.shape == (0, 2) and empty.hull.shape == (0, 2)
    assert empty.limits_box is None and empty.triangles() is None and empty.warnings == []
    assert "learned limits (hull, 0 vertices): -" in table(empty) and "(box)" not in table(empty)
    inverted = from_message(_msg(box=[1.0, 0.0, -1.0, 1.0]), TB, LB, (11, 11), "defaults", "s")
    assert inverted.limits_box is None  # an inverted box is no box: not drawn


def test_a_pair_beyond_the_grid_or_outside_the_bounds_is_warned() -> None:
    v = from_message(_msg(_rec(40, 0.5, 0.0, 0.9, 0.0)), TB, LB, (4, 4), "config s.toml", "s")
    assert len(v.warnings) == 2
    assert v.warnings[0].startswith("pair id 40 is beyond the 4 x 4 grid of config s.toml")
    assert "outside the command bounds of config s.toml" in v.warnings[1]


def test_triangles_need_three_pairs_not_on_one_line() -> None:
    assert _view().triangles().tolist() in ([[0, 1, 2]], [[2, 0, 1]], [[1, 2, 0]], [[0, 2, 1]], [[1, 0, 2]],
                                             [[2, 1, 0]])  # one triangle, whatever its orientation
    line = from_message(_msg(_rec(0, 0.1, 0.0, 0, 0), _rec(1, 0.5, 0.0, 0, 0), _rec(2, 0.9, 0.0, 0, 0)), TB, LB,
                        (4, 4), "x", "s")
    assert line.triangles() is None
    two = from_message(_msg(_rec(0, 0.1, 0.0, 0, 0), _rec(1, 0.5, 0.5, 0, 0)), TB, LB, (4, 4), "x", "s")
    assert two.triangles() is None


def test_the_latest_commands_region_is_split_into_pairs_held_and_missing() -> None:
    assert _view().region_points() == ([], [])
    v = _view(LatestCommand(seq=9, method="barycentric", v=0.2, omega=0.1, region=(5, 7, 0)))
    assert v.region_points() == ([5, 0], [7])
    assert v.summary() == "3 refined pairs, 3/16 cells configured; latest command: barycentric, region [5, 7, 0]"
    assert _view(LatestCommand(1, "stop", 0.0, 0.0, ())).summary().endswith("latest command: stop")


def test_the_json_view_is_plain_json_with_the_latest_command() -> None:
    v = _view(LatestCommand(seq=9, method="scm", v=0.2, omega=0.1, region=(0, 3), teacher=(0.4, 0.2)))
    out = json.loads(json.dumps(v.as_json()))
    assert out["pairs"][0] == {"id": 0, "version": 1, "count": 5, "teacher": [0.1, -0.5], "learner": [0.05, -0.25]}
    assert out["latest_command"] == {"seq": 9, "method": "scm", "v": 0.2, "omega": 0.1, "region": [0, 3],
                                     "teacher": [0.4, 0.2]}
    assert out["cells"] == {"configured": 3, "total": 16, "grid": [4, 4]}
    assert out["limits"]["box"] == [0.0, 1.0, -1.0, 1.0] and out["bounds_from"] == "config s.toml"
    assert _view().as_json()["latest_command"] is None


def test_the_table_shows_each_pair_and_the_latest_command_with_what_the_reply_lacks() -> None:
    text = table(_view(LatestCommand(seq=9, method="scm", v=0.2, omega=0.1, region=(0, 9), teacher=(0.4, 0.2))))
    lines = text.splitlines()
    assert lines[0] == "what was learned: station for robot 'r1'"
    assert lines[2] == "    0      5 |     0.1000    -0.5000 |     0.0500    -0.2500"
    assert "refined pairs: 3; configured cells: 3 of 16 (grid 4 x 4)" in text
    assert ("latest command: scm (v 0.200 m/s, omega +0.100 rad/s), region [0, 9], from teacher (0.400, +0.200)"
            in text)
    assert "  region pairs not in the reply: [9]" in lines
    assert f"latest command: none within {COMMAND_WAIT_S:g} s on scm/r1/cmd" in table(_view())


def test_the_table_of_an_empty_store_says_nothing_was_learned() -> None:
    text = table(from_store(PairStore(LB, TB, grid=(3, 3)), "pair store x.bin"))
    assert "  (no refined pair yet)" in text and "configured cells: 0 of 9 (grid 3 x 3); 0 raw pairs, k_min 5" in text
    assert "latest command" not in text  # offline: no robot to listen to
    assert "learned limits on the teacher domain (box)" in text  # a fresh store's limits: its teacher bounds


def test_a_store_round_trips_through_its_file(tmp_path: Path) -> None:
    store = PairStore(LB, TB, grid=(3, 3), k_min=1)
    store.add([0.5, 0.2], [0.25, 0.1])
    f = tmp_path / "pairs.bin"
    save_atomic(f, store.to_bytes())
    view = from_store(load_store_file(f), "pair store pairs.bin")
    assert view.ids.tolist() == [p.id for p in store.refined()] and len(view.ids) == 1
    np.testing.assert_allclose(view.teacher[0], [0.5, 0.2], atol=1e-12)
    np.testing.assert_allclose(view.learner[0], [0.25, 0.1], atol=1e-12)
    assert view.bounds_from == "the store" and view.raw_pairs == 1 and view.grid == (3, 3)


def test_a_store_file_that_cannot_be_read_is_one_line_naming_it(tmp_path: Path) -> None:
    with pytest.raises(PairsError, match=r"missing\.bin: no such pair store file"):
        load_store_file(tmp_path / "missing.bin")
    with pytest.raises(PairsError, match="cannot read"):
        load_store_file(tmp_path)  # a directory
    (tmp_path / "bad.bin").write_bytes(b"garbage")
    with pytest.raises(PairsError) as err:
        load_store_file(tmp_path / "bad.bin")
    assert str(err.value).startswith(f"{tmp_path / 'bad.bin'}: ") and "\n" not in str(err.value)


def test_the_listener_pairs_the_latest_command_with_the_teacher_command_of_its_tick() -> None:
    lis = _Listener()
    assert lis.latest() is None and not lis.got_cmd.is_set()
    lis.on_cmd(_Sample("scm/r1/cmd", b"not a message"))  # a malformed sample is dropped
    assert lis.latest() is None and not lis.got_cmd.is_set()
    lis.on_teacher(_Sample("scm/r1/teacher", M.encode(M.TeacherCommand(stamp=1.0, seq=7, v=0.4, omega=0.2, epoch=3))))
    lis.on_cmd(_Sample("scm/r1/cmd", M.encode(M.Command(stamp=1.0, seq=7, v=0.2, omega=0.1, method="scm",
                                                        region=[1, 2], epoch=3))))
    assert lis.got_cmd.is_set()
    assert lis.latest() == LatestCommand(seq=7, method="scm", v=0.2, omega=0.1, region=(1, 2), teacher=(0.4, 0.2))
    lis.on_cmd(_Sample("scm/r1/cmd", M.encode(M.Command(stamp=1.0, seq=7, v=0.2, omega=0.1, method="scm",
                                                        epoch=4))))  # another station run: not its teacher
    assert lis.latest().teacher is None


def test_the_listener_keeps_only_the_recent_teacher_commands() -> None:
    lis = _Listener()
    for seq in range(100):
        lis.on_teacher(_Sample("k", M.encode(M.TeacherCommand(stamp=1.0, seq=seq, v=0.1, omega=0.0))))
    assert len(lis.teacher) == 64 and (0, 99) in lis.teacher and (0, 0) not in lis.teacher
