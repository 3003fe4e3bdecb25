"""The software learner's dynamics (paper Eq. mpc_dynamicmodel_learner) and the shared simulated body."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_learner.dynamics import (
    MPC_LEARNER_V,
    MPC_LEARNER_W,
    experiment_learner,
    model_by_name,
    mpc_learner,
    scaled_learner,
)
from sim_learner.vehicle import SimVehicle
from transfer.teacher.unicycle import rollout, step, wrap_angle


def test_mpc_learner_response_matches_the_paper_formula() -> None:
    m = mpc_learner()
    v0, v1 = MPC_LEARNER_V
    w0, w1 = MPC_LEARNER_W
    u = np.array([0.2, 0.1])
    nv, nw = (u[0] - v0) / (v1 - v0), (u[1] - w0) / (w1 - w0)
    want = np.array([nv**3 * (v1 - v0) + v0, (4 * (nw - 0.5) ** 3 + 0.5) * (w1 - w0) + w0])
    np.testing.assert_allclose(m.response(u), want, rtol=0, atol=1e-15)
    # The extremes are fixed points of the distortion; commands beyond the range are clamped.
    np.testing.assert_allclose(m.response([v1, w1]), [v1, w1], atol=1e-15)
    np.testing.assert_allclose(m.response([5.0, -5.0]), [v1, w0], atol=1e-15)


def test_experiment_learner_is_monotone_and_stays_in_range() -> None:
    m = experiment_learner()
    w = np.linspace(*m.w_range, 201)
    out = m.response(np.stack([np.full_like(w, 0.1), w], axis=-1))[:, 1]
    assert np.all(np.diff(out) >= -1e-12)
    assert out.min() >= m.w_range[0] - 1e-12 and out.max() <= m.w_range[1] + 1e-12


def test_scaled_learner_scales_each_axis() -> None:
    m = scaled_learner(1.5, 2.0)
    np.testing.assert_allclose(m.response([0.5, 0.1]), [0.75, 0.2])
    assert model_by_name("scaled").gain_v == pytest.approx(1.2)
    with pytest.raises(ValueError, match="unknown learner model"):
        model_by_name("jet")


def test_learner_step_equals_unicycle_with_the_response() -> None:
    m = mpc_learner()
    s = np.array([1.0, -2.0, 0.3])
    u = np.array([0.25, -0.1])
    np.testing.assert_allclose(m.step(s, u, 0.1), step(s, m.response(u), 0.1))
    with pytest.raises(ValueError, match="random generator"):
        m.step(s, u, 0.1, pos_noise=0.1)


def test_unicycle_helpers() -> None:
    assert wrap_angle(3 * math.pi) == pytest.approx(-math.pi)
    traj = rollout([0.0, 0.0, 0.0], [1.0, 0.0], 0.1, 10)
    assert traj.shape == (11, 3)
    np.testing.assert_allclose(traj[-1], [1.0, 0.0, 0.0], atol=1e-12)


def test_sim_vehicle_integrates_holds_and_stops() -> None:
    veh = SimVehicle(mpc_learner(), (0.0, 0.0, math.pi / 2), now=0.0)
    veh.command(0.3, 0.0, now=0.0)
    s = veh.advance(2.0)
    resp = mpc_learner().response([0.3, 0.0])
    # Constant (v, w): exact arc end point, the Euler sub-steps of 10 ms stay within a millimetre.
    th = math.pi / 2 + resp[1] * 2.0
    x_arc = resp[0] / resp[1] * (math.sin(th) - 1.0)
    y_arc = -resp[0] / resp[1] * (math.cos(th) - 0.0)
    assert s.x == pytest.approx(x_arc, abs=1e-3) and s.y == pytest.approx(y_arc, abs=1e-3)
    veh.stop(2.0)
    before = (s.x, s.y)
    s = veh.advance(5.0)
    assert (s.x, s.y) == before and s.v == 0.0
    with pytest.raises(ValueError, match="non-finite"):
        veh.command(math.nan, 0.0, now=5.0)


def test_the_miswired_robot_turns_the_other_way_at_the_speed_it_was_asked() -> None:
    m = model_by_name("miswired")
    assert m.response(np.array([0.3, 0.5])) == pytest.approx([0.3, -0.5])
    assert m.response(np.array([0.2, -1.0])) == pytest.approx([0.2, 1.0])
