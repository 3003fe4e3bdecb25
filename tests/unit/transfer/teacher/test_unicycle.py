"""transfer/teacher/unicycle.py: the teacher's Euler unicycle (paper Eq. motion_primitives_dynamicmodel), the one
step every model of the project takes, and the angle wrap."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.teacher.unicycle import euler, rollout, step, wrap_angle


def test_wrap_angle_lands_in_minus_pi_to_pi_for_floats_and_arrays_alike() -> None:
    a = np.linspace(-20.0, 20.0, 401)
    w = wrap_angle(a)
    assert isinstance(w, np.ndarray) and np.all(w >= -math.pi) and np.all(w < math.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    for x in (-7.0, -math.pi, 0.0, 3.0, math.pi, 12.5):
        got = wrap_angle(x)
        assert type(got) is float and got == pytest.approx(float(wrap_angle(np.array(x))), abs=1e-15)
    assert wrap_angle(math.pi) == -math.pi  # the half-open interval: +pi is -pi
    assert type(wrap_angle(np.float64(1.0))) is float and type(wrap_angle(2)) is float  # 0-d comes back a float


def test_one_euler_step_moves_along_the_initial_heading() -> None:
    x, y, th = euler(1.0, 2.0, math.pi / 2, 0.5, 0.3, 0.2)
    assert (x, y, th) == pytest.approx((1.0, 2.1, math.pi / 2 + 0.06), abs=1e-15)
    # any arithmetic: the same step with math's cos and sin on plain floats
    assert euler(0.0, 0.0, 0.4, 1.0, 0.0, 1.0, cos=math.cos, sin=math.sin) == pytest.approx(
        (math.cos(0.4), math.sin(0.4), 0.4))


def test_step_broadcasts_poses_against_commands() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, math.pi]])
    out = step(poses, [1.0, 0.5], 0.1)  # one command for every pose
    np.testing.assert_allclose(out, [[0.1, 0.0, 0.05], [0.9, 1.0, math.pi + 0.05]], atol=1e-15)
    cmds = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    out = step(np.zeros(3), cmds, 0.5)  # one pose, three commands
    np.testing.assert_allclose(out, [[0.5, 0.0, 0.0], [0.0, 0.0, 0.5], [-0.5, 0.0, 0.0]], atol=1e-15)


def test_rollout_holds_the_command_and_starts_with_the_state() -> None:
    r = rollout([0.0, 0.0, 0.0], [1.0, 0.0], 0.1, 10)
    assert r.shape == (11, 3)
    np.testing.assert_allclose(r[:, 0], np.arange(11) * 0.1, atol=1e-12)
    assert np.all(r[:, 1:] == 0.0)
    turn = rollout([0.0, 0.0, 0.0], [0.0, 1.0], 0.1, 5)  # turning in place: only the heading moves
    np.testing.assert_allclose(turn[:, 2], np.arange(6) * 0.1, atol=1e-12)
    assert np.all(turn[:, :2] == 0.0)
    assert rollout([1.0, 2.0, 3.0], [1.0, 1.0], 0.1, 0).tolist() == [[1.0, 2.0, 3.0]]
    batch = rollout(np.zeros((4, 3)), [1.0, 0.0], 0.1, 3)
    assert batch.shape == (4, 4, 3)
    # each step of the rollout is step() of the previous pose
    np.testing.assert_allclose(r[1:], step(r[:-1], [1.0, 0.0], 0.1), atol=1e-15)
