"""transfer/mission.py: a mission as the method sees it, and its one goal rule and one collision rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.mission import EXPLORE_CLEARANCE, GOAL_MIN_PROGRESS, Mission
from transfer.teacher.path import Polyline

STRAIGHT = Polyline(np.array([[0.0, 0.0], [10.0, 0.0]]))


def _mission(**kw) -> Mission:
    args = {"name": "m", "path": STRAIGHT, "obstacles": np.array([[5.0, 2.0, 1.0]]), "goal_tolerance": 0.5}
    args.update(kw)
    return Mission(**args)


@pytest.mark.parametrize(
    "kw,match",
    [
        ({"obstacles": np.array([[1.0, 1.0, 0.0]])}, "obstacles must be finite rows"),
        ({"obstacles": np.array([[1.0, np.nan, 1.0]])}, "obstacles must be finite rows"),
        ({"goal_tolerance": 0.0}, "goal tolerance must be a positive number, got 0.0"),
        ({"goal_tolerance": math.nan}, "goal tolerance must be a positive number"),
        ({"start": [0.0, math.inf, 0.0]}, "the start pose must be finite"),
    ],
)
def test_a_malformed_mission_is_refused_by_name(kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _mission(**kw)


def test_obstacles_and_start_are_normalised_to_arrays() -> None:
    m = _mission(obstacles=[1.0, 2.0, 0.5, 3.0, 4.0, 0.25], start=[[1, 2, 3]])
    assert m.obstacles.shape == (2, 3) and m.obstacles.dtype == np.float64
    assert m.start is not None and m.start.tolist() == [1.0, 2.0, 3.0]
    assert _mission(obstacles=np.zeros((0, 3))).obstacles.shape == (0, 3)
    np.testing.assert_array_equal(m.goal, [10.0, 0.0])


def test_progress_is_the_covered_fraction_of_the_path() -> None:
    m = _mission()
    assert m.progress([0.0, 3.0]) == 0.0
    assert m.progress([2.5, -1.0]) == pytest.approx(0.25)
    assert m.progress([12.0, 0.0]) == 1.0


def test_the_goal_needs_both_progress_and_the_tolerance() -> None:
    m = _mission()
    assert m.reached([9.8, 0.1, 0.0])
    assert not m.reached([10.0, 3.0, 0.0])  # past the end's arc length, but 3 m beside the goal
    assert not m.reached([9.0, 0.0])  # on the path, 1 m short: outside the tolerance
    # a loop whose end is its start: at the start the vehicle is within the tolerance but has covered nothing
    loop = Mission("loop", Polyline(np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0], [0.0, 0.3]])),
                   np.zeros((0, 3)), 0.5)
    assert not loop.reached([0.0, 0.0, 0.0])
    assert loop.reached([0.0, 0.4, 0.0])
    # reached_at judges the arc length it is given: just under GOAL_MIN_PROGRESS is not enough
    assert not m.reached_at(GOAL_MIN_PROGRESS * 10.0 - 1e-9, [10.0, 0.0])
    assert m.reached_at(GOAL_MIN_PROGRESS * 10.0, [10.0, 0.0])


def test_collisions_and_clearances() -> None:
    m = _mission()
    assert m.collides([5.0, 1.5]) and not m.collides([5.0, 0.5])
    assert m.collides([5.0, 0.5], radius=0.6)  # a disc of 0.6 m touches it
    np.testing.assert_allclose(m.clearance([5.0, 0.0]), [1.0])
    np.testing.assert_allclose(m.clearance([5.0, 2.0]), [-1.0])  # negative inside
    assert m.min_clearance([5.0, -1.0]) == pytest.approx(2.0)
    free = _mission(obstacles=np.zeros((0, 3)))
    assert not free.collides([0.0, 0.0], radius=100.0) and free.min_clearance([0.0, 0.0]) == math.inf


def test_exploration_is_allowed_only_away_from_every_obstacle() -> None:
    m = _mission()
    at_edge = [5.0, 1.0 - EXPLORE_CLEARANCE]
    assert m.may_explore(at_edge) and not m.may_explore([5.0, 1.0 - EXPLORE_CLEARANCE + 1e-6])
    assert not m.may_explore([5.0, 0.0], clearance=1.5) and m.may_explore([5.0, 0.0], clearance=1.0)
    assert _mission(obstacles=np.zeros((0, 3))).may_explore([5.0, 2.0])


def test_scaled_scales_positions_and_radii_and_keeps_tolerance_and_heading() -> None:
    m = _mission(start=[1.0, 2.0, 0.7], frame="lab")
    s = m.scaled(0.5)
    assert s.name == "m" and s.frame == "lab" and s.goal_tolerance == 0.5
    np.testing.assert_allclose(s.path.points, STRAIGHT.points * 0.5)
    np.testing.assert_allclose(s.obstacles, [[2.5, 1.0, 0.5]])
    assert s.start is not None and s.start.tolist() == [0.5, 1.0, 0.7]
    assert m.scaled(2.0, name="big").name == "big" and _mission().scaled(3.0).start is None
    assert m.obstacles.tolist() == [[5.0, 2.0, 1.0]]  # the original is untouched
