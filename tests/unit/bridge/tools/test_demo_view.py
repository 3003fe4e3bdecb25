"""bridge/tools/demo_view.py: the method of the command driving at each pose, and the trajectory figure coloured
by method."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bridge.core.config import load_mission
from bridge.tools.demo_view import METHOD_COLORS, methods_along, trajectory_figure


def test_each_pose_takes_the_method_of_the_command_driving_when_it_was_measured() -> None:
    cmds = {1: "scm", 2: "barycentric", 3: "perturb"}
    applied = [(1.0, "cmd", 1), (2.0, "clamped", 2), (3.0, "stop", None), (4.0, "cmd", 3), (5.0, "cmd", 9)]
    states = [(0.5, 0, 0, 0), (1.0, 0, 0, 0), (1.5, 0, 0, 0), (2.5, 0, 0, 0), (3.5, 0, 0, 0), (4.5, 0, 0, 0),
              (5.5, 0, 0, 0)]
    # before any command, after a stop echo, and for a command this process never saw: stop
    assert methods_along(states, applied, cmds) == ["stop", "scm", "scm", "barycentric", "stop", "perturb", "stop"]


def test_the_trajectory_is_drawn_in_each_methods_colour(tmp_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    world = load_mission(None)
    t = np.linspace(0.0, 1.0, 60)
    traj = np.column_stack([world.path.points[0, 0] + 3 * t, world.path.points[0, 1] + 0 * t, 0 * t])
    methods = ["scm"] * 30 + ["barycentric"] * 20 + ["direct"] * 10
    path = trajectory_figure(tmp_path, world, traj, methods, "CAN")
    assert path.stat().st_size > 10_000
    assert {"scm", "barycentric", "direct", "perturb", "stop"} <= set(METHOD_COLORS)
