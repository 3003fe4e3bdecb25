"""sim_learner/vehicle.py: the simulated learner body every link emulator drives, on a clock passed in.

Integration along an arc, holding and the refusal of a non-finite command are tested in
tests/unit/sim_learner/test_dynamics.py; here the rest of its contract: a zero command holds the wheels (no creep),
rolling bypasses the learner's response, time never runs backwards, the signed distance, sub-steps, and the
position noise that touches only the reported pose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_learner.dynamics import LearnerModel, mpc_learner
from sim_learner.vehicle import BodyState, SimVehicle


def test_position_noise_needs_an_explicit_generator() -> None:
    with pytest.raises(ValueError, match="position noise needs an explicit random generator"):
        SimVehicle(mpc_learner(), pos_noise=0.01)


def test_the_start_state_and_a_command_taken_at_its_time() -> None:
    veh = SimVehicle(mpc_learner(), (1, 2, 0.5), now=10.0)
    assert veh.state == BodyState(1.0, 2.0, 0.5) and veh.t == 10.0 and veh.theta0 == 0.5
    assert veh.cmd == (0.0, 0.0) and not veh.moving
    veh.command(0.2, 0.1, now=11.0)  # one second held still under the old (zero) command, then the new one
    assert (veh.state.x, veh.state.y) == (1.0, 2.0) and veh.moving and veh.cmd == (0.2, 0.1)


def test_an_exact_zero_command_holds_the_wheels_though_the_learner_would_creep() -> None:
    model = mpc_learner()
    assert model.response(np.zeros(2))[0] > 0  # the paper's learner maps (0, 0) to a crawl at v_min
    veh = SimVehicle(model, now=0.0)
    veh.command(0.2, 0.0, now=0.0)
    veh.command(0.0, 0.0, now=1.0)
    x1 = veh.state.x
    s = veh.advance(5.0)
    assert s.x == x1 and s.v == 0.0 and s.omega == 0.0 and not veh.moving


def test_roll_moves_the_body_at_the_speed_given_not_through_the_response() -> None:
    veh = SimVehicle(mpc_learner(), now=0.0)
    veh.roll(0.5, 0.0, now=0.0)  # beyond the learner's range: a coast is not a command
    s = veh.advance(2.0)
    assert s.x == pytest.approx(1.0) and s.v == 0.5 and veh.rolling
    veh.command(0.2, 0.0, now=2.0)  # a command ends the roll
    assert not veh.rolling and veh.advance(3.0).v == pytest.approx(float(mpc_learner().response([0.2, 0.0])[0]))


def test_time_never_runs_backwards_and_the_distance_is_signed() -> None:
    reverse = LearnerModel((-0.5, 0.5), (-1.0, 1.0), name="reverse")
    veh = SimVehicle(reverse, now=0.0)
    veh.command(-0.4, 0.0, now=0.0)
    veh.advance(1.0)
    before = (veh.state.x, veh.t)
    assert veh.advance(0.5) is veh.state and (veh.state.x, veh.t) == before  # an earlier time: no-op
    assert veh.state.x < 0 and veh.distance == pytest.approx(veh.state.x)


def test_long_intervals_are_integrated_in_sub_steps_of_max_dt() -> None:
    model = mpc_learner()
    v, w = (float(a) for a in model.response([0.3, 0.2]))
    coarse = SimVehicle(model, now=0.0, max_dt=10.0)
    fine = SimVehicle(model, now=0.0, max_dt=0.001)
    for veh in (coarse, fine):
        veh.command(0.3, 0.2, now=0.0)
        veh.advance(4.0)
    # one Euler step of 4 s goes straight on; 4000 steps follow the arc of radius v / w
    assert coarse.state.y == 0.0 and coarse.state.x == pytest.approx(4 * v)
    assert fine.state.x == pytest.approx(v / w * math.sin(4 * w), abs=1e-3)
    assert fine.state.y == pytest.approx(v / w * (1 - math.cos(4 * w)), abs=1e-3)


def test_noise_is_a_measurement_error_only() -> None:
    veh = SimVehicle(mpc_learner(), now=0.0, pos_noise=0.05, rng=np.random.default_rng(3))
    twin = SimVehicle(mpc_learner(), now=0.0)  # the same vehicle without noise
    for v in (veh, twin):
        v.command(0.2, 0.0, now=0.0)
    reads = np.array([veh.measured_pose(1.0) for _ in range(400)])
    twin.advance(1.0)
    assert veh.state == twin.state  # the integrated state is undisturbed
    assert reads[:, 0].std() == pytest.approx(0.05, rel=0.15) and reads[:, 0].mean() == pytest.approx(veh.state.x,
                                                                                                     abs=0.01)
    assert np.all(reads[:, 2] == veh.state.theta)  # the heading is not noised
    quiet = SimVehicle(mpc_learner(), (1.0, 2.0, 0.3), now=0.0)
    assert quiet.measured_pose(0.0) == (1.0, 2.0, 0.3)
