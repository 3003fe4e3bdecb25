"""``scmbridge mission place`` (bridge/tools/mission_place.py): the rigid move of a mission onto a pose, the frame it
names, and a robot that moves refused; against a driver host on ArduPilot's SITL:
tests/integration/test_sitl_radio.py."""

from __future__ import annotations

import math
import subprocess
import sys

import msgspec
import pytest

from bridge.core import wire as M
from bridge.core.config import load_mission_spec
from bridge.core.errors import UsageError
from bridge.tools.mission_place import mission_toml, place, still_pose


def _spec() -> M.MissionSpec:
    return M.MissionSpec(name="m", path=[[0.0, 0.0], [2.0, 0.0], [2.0, 1.0]], obstacles=[[1.0, 0.5, 0.2]],
                         start=[0.0, 0.0, 0.0])


def test_the_mission_moves_rigidly_onto_the_pose() -> None:
    placed = place(_spec(), (10.0, 5.0, math.pi / 2), "ekf-origin")
    assert placed.frame == "ekf-origin" and placed.name == "m@placed"
    assert placed.start == pytest.approx([10.0, 5.0, math.pi / 2])
    assert placed.path == [pytest.approx(p) for p in ([10.0, 5.0], [10.0, 7.0], [9.0, 7.0])]
    assert placed.obstacles[0] == pytest.approx([9.5, 6.0, 0.2])  # radius kept
    seg = [math.dist(a, b) for a, b in zip(placed.path, placed.path[1:])]
    assert seg == pytest.approx([2.0, 1.0])


def test_without_a_start_its_first_point_facing_along_the_path_lands_on_the_pose() -> None:
    spec = msgspec.structs.replace(_spec(), start=None, path=[[1.0, 1.0], [1.0, 3.0]])
    placed = place(spec, (0.0, 0.0, 0.0), "odometry")
    assert placed.path == [pytest.approx([0.0, 0.0]), pytest.approx([2.0, 0.0])]


def test_the_placed_mission_reads_back_as_a_mission_file(tmp_path) -> None:
    placed = place(load_mission_spec(), (3.0, -4.0, 1.0), "ekf-origin")
    path = tmp_path / "placed.toml"
    path.write_text(mission_toml(placed))
    again = load_mission_spec(str(path))
    assert again.frame == "ekf-origin" and again.start == pytest.approx(placed.start, abs=1e-6)
    assert len(again.path) == len(placed.path) and again.path[-1] == pytest.approx(placed.path[-1], abs=1e-6)


def _state(x: float, y: float, th: float, v: float | None = 0.0) -> M.LearnerState:
    return M.LearnerState(stamp=0.0, seq=0, x=x, y=y, theta=th, v=v, source="mavlink")


def test_a_robot_standing_still_gives_its_last_pose_and_one_moving_is_refused() -> None:
    assert still_pose([_state(1.0, 2.0, 0.5), _state(1.01, 2.0, 0.51)]) == (1.01, 2.0, 0.51)
    with pytest.raises(UsageError, match="moving"):
        still_pose([_state(1.0, 2.0, 0.5), _state(1.2, 2.0, 0.5)])
    with pytest.raises(UsageError, match="moving"):
        still_pose([_state(1.0, 2.0, 0.5, v=0.3)])


def test_place_at_a_named_pose_prints_the_mission_and_where(tmp_path) -> None:
    r = subprocess.run([sys.executable, "-m", "bridge", "mission", "place", "paper-s-path", "--robot", "r1", "--at",
                        "1,2,90", "--out", str(tmp_path / "p.toml")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "placed 'paper-s-path' at x 1.000 m, y 2.000 m, heading 90.0 deg in frame 'world'" in r.stdout
    assert load_mission_spec(str(tmp_path / "p.toml")).start == pytest.approx([1.0, 2.0, math.pi / 2])
    bad = subprocess.run([sys.executable, "-m", "bridge", "mission", "place", "paper-s-path", "--robot", "r1",
                          "--at", "1,nan,0"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "not a pose" in bad.stderr
