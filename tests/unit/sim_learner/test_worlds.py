"""sim_learner/worlds.py: the paper's two worlds, read from the mission files shipped with scmbridge."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_learner.worlds import World, mpc_world, primitives_world
from transfer.mission import Mission


def test_the_mpc_world_is_the_shipped_s_path() -> None:
    w = mpc_world()
    assert World is Mission and isinstance(w, Mission) and w.name == "paper-s-path"
    xs = w.path.points[:, 0]
    assert xs.min() == pytest.approx(0.0) and xs.max() == pytest.approx(8.0)  # an 8 m S
    assert len(w.obstacles) >= 3 and w.goal_tolerance > 0
    assert w.start is not None
    assert w.path.distance(w.start[:2]) == pytest.approx(0.3)  # the start 0.3 m beside the path
    assert w.start[2] == pytest.approx(-math.pi / 4)
    assert not w.collides(w.start[:2]) and not any(w.collides(p) for p in w.path.points)


def test_scale_shrinks_the_mpc_world_and_one_is_the_file_itself() -> None:
    w, half = mpc_world(), mpc_world(0.5)
    np.testing.assert_allclose(half.path.points, 0.5 * w.path.points)
    np.testing.assert_allclose(half.obstacles, 0.5 * w.obstacles)
    assert half.goal_tolerance == w.goal_tolerance
    assert mpc_world(1.0).path.length == w.path.length


def test_the_primitives_world_is_the_same_s_four_times_larger_with_its_own_obstacles() -> None:
    w, p = mpc_world(), primitives_world()
    assert p.name == "paper-primitives-s-path"
    np.testing.assert_allclose(p.path.points, 4 * w.path.points)
    assert p.path.length == pytest.approx(4 * w.path.length)
    assert not np.allclose(p.obstacles, 4 * w.obstacles)  # its own obstacles, not the scaled ones
    assert not any(p.collides(q) for q in p.path.points)
