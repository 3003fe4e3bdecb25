"""Motion-primitive library, DTW scoring, filtering by learner limits, replanning threshold."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.domain import Bounds
from transfer.teacher.path import Polyline
from transfer.teacher.primitives import PrimitiveLibrary, PrimitivePlanner, dtw, replan_threshold
from transfer.teacher.unicycle import rollout

TB = Bounds((0.0, 3.0), (-math.pi / 3, math.pi / 3))


def test_library_trajectories_are_the_teacher_rollouts() -> None:
    lib = PrimitiveLibrary(TB, 11, 1.0, 0.1)
    assert len(lib) == 121
    rel = lib.relative_trajectories()
    for i in (0, 60, 120):
        np.testing.assert_allclose(rel[i], rollout([0, 0, 0], lib.commands[i], 0.1, 10), atol=1e-12)


def test_dtw_is_zero_for_identical_sequences_and_grows_with_offset() -> None:
    a = np.stack([np.linspace(0, 1, 10), np.zeros(10)], axis=-1)
    d = dtw(np.stack([a, a + [0, 0.1], a + [0, 0.5]]), a)
    assert d[0] == pytest.approx(0.0) and 0 < d[1] < d[2]


def test_planner_picks_the_primitive_that_follows_a_straight_path() -> None:
    lib = PrimitiveLibrary(TB, 11, 1.0, 0.1)
    path = Polyline(np.stack([np.linspace(0, 20, 100), np.zeros(100)], axis=-1))
    plan = PrimitivePlanner(lib, horizon=2).plan(np.zeros(3), path, np.ones(len(lib), dtype=bool))
    assert plan.commands[0, 1] == pytest.approx(0.0, abs=1e-12) and plan.commands[0, 0] > 2.0
    # restricted to slow primitives, it still goes straight, as fast as allowed
    slow = lib.commands[:, 0] <= 1.2 + 1e-9
    plan = PrimitivePlanner(lib, horizon=2).plan(np.zeros(3), path, slow)
    assert plan.commands[0, 0] == pytest.approx(1.2) and abs(plan.commands[0, 1]) < 1e-12
    with pytest.raises(ValueError, match="no primitive"):
        PrimitivePlanner(lib).plan(np.zeros(3), path, np.zeros(len(lib), dtype=bool))


def test_replanning_threshold_depends_on_obstacles_in_view() -> None:
    obstacles = np.array([[3.0, 0.0, 1.0]])
    assert replan_threshold(np.zeros(3), obstacles, eta=0.25, eps_max=0.8) == pytest.approx(0.5)
    behind = np.array([0.0, 0.0, math.pi])
    assert replan_threshold(behind, obstacles, eta=0.25, eps_max=0.8) == pytest.approx(0.8)
    assert replan_threshold(np.zeros(3), np.zeros((0, 3)), eps_max=0.7) == pytest.approx(0.7)
