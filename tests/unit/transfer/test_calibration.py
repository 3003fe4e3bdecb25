"""transfer/calibration.py: the paper's calibration stage (Section 4) as a bounded plan, on a fake clock.

tests/integration/test_calibrate.py drives the plan with a simulated learner end to end; here each rule of the plan
is checked alone with the time and the pose passed in: the grid order and hold, the return toward the start (its
command, its three ways to end), the distance and time bounds, and the refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.calibration import CalibrationPlan
from transfer.domain import Bounds
from transfer.limits import calibration_commands

LB = Bounds((0.05, 0.3), (-0.2, 0.26))
HOME = np.zeros(3)


@pytest.mark.parametrize("kw", [{"hold_s": 0.0}, {"max_distance": -1.0}, {"max_time_s": 0.0}])
def test_non_positive_bounds_are_refused(kw: dict) -> None:
    with pytest.raises(ValueError, match="hold_s, max_distance and max_time_s must be positive"):
        CalibrationPlan(LB, **kw)


def test_a_grid_without_both_extremes_is_refused() -> None:
    with pytest.raises(ValueError, match="n >= 2 on each axis"):
        CalibrationPlan(LB, (1, 5))


def test_it_drives_every_grid_command_in_order_for_hold_s_then_stops() -> None:
    plan = CalibrationPlan(LB, (2, 3), hold_s=0.5)
    grid = calibration_commands(LB, (2, 3))
    assert plan.total == 6 and plan.return_radius == pytest.approx(0.8)
    sent = []
    k = 0
    while True:
        s = plan.step(100.0 + 0.125 * k, HOME)  # any clock (the plan counts from its first step); no return phase
        if s.done:
            break
        assert s.phase == "drive" and s.total == 6
        sent.append((s.index, tuple(s.u_L)))
        k += 1
    indices = [i for i, _ in sent]
    assert indices == sorted(indices) and set(indices) == set(range(6))
    assert all(indices.count(i) == 4 for i in range(6))  # 0.5 s at 0.125 s a tick
    for i, u in sent:
        assert u == tuple(grid[i])
    assert s.reason == "all 6 commands driven" and s.phase == "done" and s.index == 5
    np.testing.assert_array_equal(s.u_L, [0.0, 0.0])


def test_the_distance_bound_ends_the_plan_for_good() -> None:
    plan = CalibrationPlan(LB, hold_s=1.0, max_distance=2.0)
    plan.step(0.0, [1.0, 1.0, 0.0])  # the start is wherever the first step finds the robot
    s = plan.step(0.1, [1.0, 3.5, 0.0])
    assert s.done and s.reason == "stopped at the distance bound (2.50 m > 2.0 m)"
    assert plan.step(0.2, [1.0, 1.0, 0.0]) is s  # back at the start: still done


def test_the_time_bound_ends_the_plan() -> None:
    plan = CalibrationPlan(LB, hold_s=1.0, max_time_s=3.0)
    assert not plan.step(0.0, HOME).done
    assert not plan.step(3.0, HOME).done
    s = plan.step(3.01, HOME)  # the second command (index 1) was being driven
    assert s.done and s.reason == "stopped at the time bound (3 s)" and s.index == 1


def _plan_in_return(x: list[float], **kw) -> CalibrationPlan:
    """A plan whose first command has been held and that now finds the robot at ``x``, outside the return radius."""
    plan = CalibrationPlan(LB, (2, 2), hold_s=1.0, max_distance=2.0, **kw)
    assert plan.step(0.0, HOME).phase == "drive"
    return plan


def test_out_of_the_return_radius_it_steers_back_turning_first_then_driving() -> None:
    plan = _plan_in_return([1.0, 0.0, 0.0])
    s = plan.step(1.0, [1.0, 0.0, 0.0])  # facing away from the start: turn (at the learner's limit), slowly
    assert s.phase == "return" and s.index == 1
    assert s.u_L.tolist() == pytest.approx([0.05, -0.2])
    s = plan.step(1.1, [1.0, 0.0, math.pi])  # facing it: straight on, faster
    assert s.u_L.tolist() == pytest.approx([0.05 + 0.5 * (0.3 - 0.05), 0.0])
    s = plan.step(1.2, [1.0, 0.0, math.pi / 2])  # a quarter turn off: gain 1.5, clipped to the learner's box
    assert s.u_L[1] == pytest.approx(min(1.5 * math.pi / 2, 0.26))
    s = plan.step(1.3, [0.39, 0.0, math.pi])  # within half the radius: the next grid command
    assert s.phase == "drive" and s.index == 1


def test_a_learner_that_cannot_drive_slowly_forward_returns_at_a_quarter_of_its_speed() -> None:
    rev = Bounds((-0.2, 0.4), (-1.0, 1.0))
    plan = CalibrationPlan(rev, (2, 2), hold_s=1.0, max_distance=2.0)
    plan.step(0.0, HOME)
    s = plan.step(1.0, [1.0, 0.0, 0.0])
    assert s.phase == "return" and s.u_L[0] == pytest.approx(0.1)  # min(v_max, 0.25 (v_max - 0))


def test_a_return_ends_when_circling_inside_the_radius_without_getting_closer() -> None:
    plan = _plan_in_return([0.7, 0.0, 0.0], stall_s=2.0, return_radius=0.5)
    assert plan.step(1.0, [0.7, 0.0, 0.0]).phase == "return"
    plan.step(1.125, [0.45, 0.0, math.pi])  # back inside the radius, then circling at 0.45 m
    k, phase = 1, "return"
    while phase == "return":
        k += 1
        t = 1.0 + 0.125 * k
        phase = plan.step(t, [0.45 * math.cos(0.2 * k), 0.45 * math.sin(0.2 * k), 0.2 * k]).phase
        assert t < 5.0
    assert t == 3.25  # the first tick more than stall_s = 2 s after the closest approach (t = 1.125)


def test_a_return_gives_up_after_its_timeout() -> None:
    plan = _plan_in_return([1.0, 0.0, 0.0], return_timeout_s=3.0)
    assert plan.step(1.0, [1.0, 0.0, 0.0]).phase == "return"
    # the robot gets closer and closer but never arrives (still outside the radius): the timeout ends the return
    assert plan.step(3.9, [0.95, 0.0, math.pi]).phase == "return"
    s = plan.step(4.01, [0.9, 0.0, math.pi])
    assert s.phase == "drive" and s.index == 1
