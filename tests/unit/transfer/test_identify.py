"""transfer/identify.py: the learner's range measured by bounded probes, on simulated vehicles driven at the
station's 10 Hz: one that lags its speed command and turns in place, one (car-like) whose turn rate is its speed
times a curvature, and one far faster than the teacher for what it accepts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.domain import Bounds
from transfer.identify import IdentifyPlan

TEACHER_TOP = (0.6, math.pi / 4)


def drive(plan: IdentifyPlan, gain_v: float, gain_w: float, lag_s: float, max_curvature: float | None = None,
          dt: float = 0.1, limit_s: float = 60.0, creep_cmd: float = 0.0) -> list[float]:
    """Run ``plan`` against a vehicle reaching ``gain_v`` of its speed command through a first-order lag and
    ``gain_w`` of its turn command (a car-like one at most ``max_curvature`` times its speed; one whose throttle
    creeps no slower than a forward command of ``creep_cmd``); returns the distances from the start."""
    x = np.zeros(3)
    v = w = 0.0
    dists = []
    t = 0.0
    while plan.finished is None and t < limit_s:
        step = plan.step(t, x)
        a = 1.0 - math.exp(-dt / lag_s)
        v_cmd = float(step.u_L[0])
        v += a * (gain_v * (max(v_cmd, creep_cmd) if v_cmd > 0 else v_cmd) - v)
        w_cmd = gain_w * float(step.u_L[1])
        if max_curvature is not None:
            w_cmd = float(np.clip(w_cmd, -max_curvature * abs(v), max_curvature * abs(v)))
        w += a * (w_cmd - w)
        x = x + dt * np.array([v * math.cos(x[2]), v * math.sin(x[2]), w])
        dists.append(float(np.hypot(*x[:2])))
        t += dt
    return dists


def test_a_weak_vehicle_that_turns_in_place_keeps_the_range_it_needs_to_reach_the_teachers_top() -> None:
    plan = IdentifyPlan(Bounds((0.05, 3.0), (-2.0, 2.0)), TEACHER_TOP)
    dists = drive(plan, gain_v=0.5, gain_w=0.5, lag_s=0.3)
    got = plan.result()
    assert plan.finished is not None and max(dists) <= 2 * plan.max_distance + 0.1
    assert got.turns_in_place
    assert got.v_max == pytest.approx(1.2, rel=0.1)  # 0.6 commanded reached 0.3: twice the command for the top
    assert got.w_range[1] == pytest.approx(2 * math.pi / 4, rel=0.15) and got.w_range[0] == pytest.approx(
        -2 * math.pi / 4, rel=0.15)
    assert 0.2 < got.settle_s < 0.6 and got.settle_top_s < 1.2  # a 0.3 s lag


def test_a_vehicle_faster_than_the_teacher_for_what_it_accepts_is_bounded_where_it_reaches_the_teachers_top() -> None:
    plan = IdentifyPlan(Bounds((0.05, 5.0), (-2.0, 2.0)), TEACHER_TOP)
    drive(plan, gain_v=1.0, gain_w=1.0, lag_s=0.2)
    got = plan.result()
    assert got.v_max == pytest.approx(0.6, rel=0.05)  # it follows its commands: the teacher's top, not 5 m/s
    assert got.w_range[1] == pytest.approx(math.pi / 4, rel=0.1)


def test_a_vehicle_that_overshoots_its_commands_is_bounded_below_the_probe_inside_the_teachers_range() -> None:
    plan = IdentifyPlan(Bounds((0.05, 3.0), (-2.0, 2.0)), TEACHER_TOP)
    drive(plan, gain_v=1.6, gain_w=1.4, lag_s=0.3)
    got = plan.result()
    assert got.v_max == pytest.approx(0.6 / 1.6, rel=0.1)  # 0.6 commanded drove 0.96 m/s: beyond the teacher's top
    assert got.w_range[1] == pytest.approx(math.pi / 4 / 1.4, rel=0.15)


def test_a_car_like_vehicle_needs_speed_to_turn_and_keeps_its_accepted_turn_command() -> None:
    plan = IdentifyPlan(Bounds((0.05, 5.0), (-0.52, 0.52)), TEACHER_TOP)
    dists = drive(plan, gain_v=0.6, gain_w=0.6, lag_s=0.8, max_curvature=1.1)
    got = plan.result()
    assert not got.turns_in_place and got.w_range == (-0.52, 0.52)
    assert got.v_max == pytest.approx(1.0, rel=0.1)
    assert 0.5 < got.settle_s < 1.6 and got.settle_top_s > 1.5  # the slow body (its turn follows its speed)
    assert max(dists) <= 2 * plan.max_distance + 0.1


def test_a_car_whose_creep_is_as_fast_as_its_turn_probes_still_needs_speed() -> None:
    """Its turn rates at a crawl and at ``v_low`` are alike (its throttle creeps at ``v_low``, as a stalled probe or
    a dead band can make them), but it turns no more sharply at a crawl: a car, not a vehicle that turns in place
    (the turn rates alone read it as one, and the station would ask it to turn on the spot)."""
    plan = IdentifyPlan(Bounds((0.05, 5.0), (-0.52, 0.52)), TEACHER_TOP)
    drive(plan, gain_v=0.6, gain_w=0.6, lag_s=0.8, max_curvature=1.1, creep_cmd=plan.v_low)
    got = plan.result()
    creep, turn = got.reached["creep+"], got.reached["turn+"]
    assert creep[1] >= 0.9 * turn[1] > 0.05, got.reached  # as fast a turn at its crawl as at v_low ...
    assert not got.turns_in_place and got.w_range == (-0.52, 0.52)  # ... and still a car
    reach = got.reach()
    assert reach is not None and 0.85 * 1.1 < reach.left <= 1.1  # its lag: the turn still settling at the end


def test_a_vehicle_that_turns_in_place_is_read_so_however_its_creep_turns_against_its_turn_probes() -> None:
    """Turning in place, its creep probes' turn rate over their speed is many times its turn probes'."""
    plan = IdentifyPlan(Bounds((0.05, 3.0), (-2.0, 2.0)), TEACHER_TOP)
    drive(plan, gain_v=1.0, gain_w=0.7, lag_s=0.3)
    got = plan.result()
    (vc, wc), (vt, wt) = got.reached["creep+"], got.reached["turn+"]
    assert wc / vc >= 2.5 * wt / vt, got.reached
    assert got.turns_in_place and got.reach() is None


def test_the_probes_stop_at_the_distance_bound_and_a_vehicle_that_never_moves_keeps_what_it_accepts() -> None:
    plan = IdentifyPlan(Bounds((0.05, 3.0), (-1.0, 1.0)), TEACHER_TOP, max_distance=0.5)
    dists = drive(plan, gain_v=1.0, gain_w=1.0, lag_s=0.2)
    assert max(dists) <= 2 * 0.5 + 0.1  # each probe within 0.5 m of its start, the whole within 1 m
    assert len(plan.samples["straight"]) < 15  # the straight ended at its bound (0.5 m at 0.6 m/s), not its time
    still = IdentifyPlan(Bounds((0.05, 3.0), (-1.0, 1.0)), TEACHER_TOP)
    drive(still, gain_v=0.0, gain_w=0.0, lag_s=0.2)
    got = still.result()
    assert got.v_max == 3.0 and got.w_range == (-1.0, 1.0) and "did not move" in got.why
    with pytest.raises(ValueError):
        IdentifyPlan(Bounds((0.05, 3.0), (-1.0, 1.0)), TEACHER_TOP, hold_s=0.5)
