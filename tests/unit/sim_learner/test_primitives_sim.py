"""sim_learner/primitives_sim.py: the paper's motion-primitive case (Section 5.1), its calibration and closed loop.

The whole case (``run_primitives``: the SCM learner reaches the goal, the baseline deviates 3x more) is tested in
tests/unit/sim_learner/test_experiments.py. Here its two parts alone, on small inputs: :func:`calibrate` measures the
learner's limits on the teacher domain and :func:`follow` closes the loop (replans, the goal rule, collisions, the
event trigger), with the measurement noise drawn from the generator it is given."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_learner.dynamics import LearnerModel, scaled_learner
from sim_learner.primitives_sim import VEHICLE_RADIUS, calibrate, follow
from sim_learner.runs import DT
from transfer.domain import Bounds
from transfer.mission import Mission
from transfer.paper import PRIM_TEACHER_V, PRIM_TEACHER_W
from transfer.store import PairStore
from transfer.teacher.path import Polyline
from transfer.teacher.primitives import PrimitiveLibrary, PrimitivePlanner

TB = Bounds(PRIM_TEACHER_V, PRIM_TEACHER_W)
TEACHER_LIKE = LearnerModel(PRIM_TEACHER_V, PRIM_TEACHER_W, name="teacher-like")  # responds as commanded


def test_calibration_drives_the_grid_and_measures_the_scaled_learners_limits() -> None:
    learner = scaled_learner(1.2, 1.6)
    LB = Bounds(learner.v_range, learner.w_range)
    store = PairStore(LB, TB, grid=(11, 11), k_min=1)
    calibrate(learner, store, 1.0)
    assert store.raw_count == 25 * 10  # 25 commands, one pair per control interval of one second
    assert store.n_configured() == 25  # the 5 x 5 grid's cells
    box = store.limits.box
    assert box.v == pytest.approx((0.0, 1.2), abs=1e-9)
    assert box.w == pytest.approx((-1.6 * math.pi / 8, 1.6 * math.pi / 8), abs=1e-9)


def _straight(length: float, obstacles: np.ndarray | None = None) -> Mission:
    return Mission("straight", Polyline(np.array([[0.0, 0.0], [length, 0.0]])),
                   np.zeros((0, 3)) if obstacles is None else obstacles, 0.5, np.zeros(3))


def _planner() -> PrimitivePlanner:
    return PrimitivePlanner(PrimitiveLibrary(TB, 5, duration=1.0, dt=DT), horizon=1)


def test_follow_reaches_the_goal_of_a_straight_path_and_reports_the_run() -> None:
    planner = _planner()
    world = _straight(12.0)
    r = follow("scm", world, TEACHER_LIKE, planner, np.ones(len(planner.lib), dtype=bool), lambda u, x: u,
               np.random.default_rng(0), 30.0, None)
    assert r["reached"] and not r["collided"]
    assert r["time_s"] == pytest.approx(len(r["commands"]) * DT)
    assert r["poses"].shape == (len(r["commands"]) + 1, 3) and r["replans"] == len(r["plans"]) >= 4
    assert world.reached(r["poses"][-1]) and not world.reached(r["poses"][-2])  # it stops at the goal
    assert r["max_dev_m"] < 0.5 and r["mean_dev_m"] <= r["max_dev_m"]


def test_follow_stops_at_its_time_bound_and_counts_collisions_and_event_replans() -> None:
    planner = _planner()
    # an obstacle on the path, and a learner that drives at half the speed it is told and turns the wrong way
    world = _straight(12.0, np.array([[3.0, 0.0, 0.5]]))
    bad = LearnerModel(PRIM_TEACHER_V, PRIM_TEACHER_W, gain_v=0.5, gain_w=-1.0, name="bad")
    r = follow("baseline", world, bad, planner, np.ones(len(planner.lib), dtype=bool), lambda u, x: u,
               np.random.default_rng(1), 5.0, None)
    assert not r["reached"] and r["time_s"] is None
    assert len(r["commands"]) == round(5.0 / DT)  # the time bound, in control ticks
    assert 1 <= r["event_replans"] <= r["replans"]  # it leaves each plan: every replan is event-triggered
    assert r["collided"] == any(world.collides(p[:2], VEHICLE_RADIUS) for p in r["poses"][1:])


def test_follow_plans_from_the_measured_pose_with_the_generator_it_is_given() -> None:
    planner = _planner()
    world = _straight(6.0)
    allowed = np.ones(len(planner.lib), dtype=bool)
    runs = [follow("scm", world, TEACHER_LIKE, planner, allowed, lambda u, x: u, np.random.default_rng(3), 10.0,
                   None) for _ in range(2)]
    np.testing.assert_array_equal(runs[0]["poses"], runs[1]["poses"])  # same seed, same run
    seen = []
    follow("scm", world, TEACHER_LIKE, planner, allowed, lambda u, x: (seen.append(x.copy()), u)[1],
           np.random.default_rng(5), 3.0, None)
    assert seen and not np.array_equal(seen[0], world.start)  # the first plan is from a noisy measurement
    assert np.hypot(*(seen[0][:2] - world.start[:2])) < 0.3
