"""The fleet demo's one line for the whole fleet (bridge/tools/demo_fleet.py): each robot's progress and deviation
while few, the spread of them beyond six, and the robots not reporting yet. The whole demo runs in
tests/integration/test_fleet.py."""

from __future__ import annotations

import threading

from bridge.core import wire as M
from bridge.core.config import load_mission
from bridge.tools.demo_fleet import _fleet_line


class _Mon:
    """What the line reads of a robot's monitor: its lock, the station's status, the latest pose."""

    def __init__(self, station: M.Status | None, pose: tuple | None) -> None:
        self.lock = threading.Lock()
        self.status = {} if station is None else {"station": station}
        self.states = [] if pose is None else [pose]


def _station(goal: bool, missed: int, pairs: int) -> M.Status:
    return M.Status(stamp=1.0, seq=1, node="station",
                    counters={"goal_reached": int(goal), "missed_deadlines": missed, "refined_pairs": pairs})


def test_a_few_robots_each_get_their_progress_and_one_not_reporting_says_so() -> None:
    world = load_mission()
    start, end = world.path.points[0], world.path.points[-1]
    mons = {"a": _Mon(_station(False, 1, 10), (0.0, float(start[0]), float(start[1]))),
            "b": _Mon(_station(True, 2, 20), (0.0, float(end[0]), float(end[1]))),
            "c": _Mon(None, None)}
    line = _fleet_line(mons, world, 12.34)
    assert line.startswith("t= 12.3s at goal 1/3 pairs=30 missed=3 | ")
    assert "a   0%" in line and "b 100%" in line and "c --" in line


def test_beyond_six_robots_the_line_gives_the_spread_of_their_progress() -> None:
    world = load_mission()
    p = world.path.points[len(world.path.points) // 2]
    mons = {f"r{i}": _Mon(_station(False, 0, 1), (0.0, float(p[0]), float(p[1]))) for i in range(7)}
    mons["late"] = _Mon(None, None)
    line = _fleet_line(mons, world, 1.0)
    assert "progress min" in line and "(7/8 reporting)" in line
    assert _fleet_line({f"r{i}": _Mon(None, None) for i in range(8)}, world, 1.0).endswith(
        "waiting for stations and drivers...")
