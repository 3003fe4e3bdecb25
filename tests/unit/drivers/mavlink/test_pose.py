"""drivers/mavlink/pose.py: its API that tests/unit/drivers/mavlink/test_state.py (axes, interpolation, the builder's
waiting and reset) does not reach: :func:`telemetry_valid` on pymavlink's own messages, :func:`ground_speed`, the
heading range, and the builder paths where the ATTITUDE comes first or late."""

from __future__ import annotations

import math

import pytest

from drivers.mavlink.dialect import load_pymavlink
from drivers.mavlink.pose import (
    ATTITUDE_MAX_LAG,
    POSITION_MAX,
    SPEED_MAX,
    YAW_MAX,
    YAW_RATE_MAX,
    Attitude,
    PoseBuilder,
    Position,
    enu_pose,
    ground_speed,
    telemetry_valid,
)

MAV = load_pymavlink().mav


def _lpn(x=0.0, y=0.0, vx=0.0, vy=0.0):
    return MAV.MAVLink_local_position_ned_message(1000, x, y, 0.0, vx, vy, 0.0)


def _att(yaw=0.0, yawspeed=0.0):
    return MAV.MAVLink_attitude_message(1000, 0.0, 0.0, yaw, 0.0, 0.0, yawspeed)


def test_telemetry_within_the_bounds_is_valid_up_to_the_bound_itself() -> None:
    assert telemetry_valid(_lpn(1.0, -2.0, 0.5, -0.5))
    assert telemetry_valid(_lpn(POSITION_MAX, -POSITION_MAX, SPEED_MAX, -SPEED_MAX))
    assert telemetry_valid(_att(YAW_MAX, -YAW_RATE_MAX))


@pytest.mark.parametrize("msg", [
    _lpn(x=math.nan), _lpn(y=math.inf), _lpn(x=2 * POSITION_MAX), _lpn(vx=SPEED_MAX + 1), _lpn(vy=-math.inf),
    _att(yaw=math.nan), _att(yaw=-YAW_MAX - 0.01), _att(yawspeed=YAW_RATE_MAX * 2), _att(yawspeed=math.inf),
])
def test_telemetry_a_vehicle_cannot_send_is_invalid(msg) -> None:
    assert not telemetry_valid(msg)


def test_other_message_types_are_not_judged() -> None:
    hb = MAV.MAVLink_heartbeat_message(MAV.MAV_TYPE_GROUND_ROVER, 3, 0, 4, 4, 3)
    assert telemetry_valid(hb)


def test_ground_speed_is_the_horizontal_speed_or_none() -> None:
    assert ground_speed(None) is None
    assert ground_speed(Position(0, 0.0, 0.0, 0.0, vx=3.0, vy=-4.0)) == pytest.approx(5.0)


@pytest.mark.parametrize("yaw", [-math.pi, -math.pi / 2, 0.0, math.pi / 2, math.pi - 1e-9, 3.0, -3.0])
def test_theta_is_kept_in_minus_half_pi_to_three_halves_pi(yaw: float) -> None:
    p = enu_pose(Position(1000, 0.0, 0, 0, 0, 0), Attitude(1000, yaw, 0.0), None)
    assert -math.pi / 2 - 1e-12 <= p.theta <= 3 * math.pi / 2 + 1e-12
    assert math.remainder(p.theta - (math.pi / 2 - yaw), 2 * math.pi) == pytest.approx(0.0, abs=1e-12)


def test_the_heading_is_exactly_the_previous_one_at_its_own_time() -> None:
    prev, att = Attitude(1000, 0.3, 0.0), Attitude(1100, 0.5, 0.0)
    at_prev = enu_pose(Position(1000, 0.0, 0, 0, 0, 0), att, prev)
    assert math.pi / 2 - at_prev.theta == pytest.approx(0.3)


def test_a_yaw_rate_carries_the_heading_backwards_too_within_the_lag() -> None:
    lag_ms = 1000 * ATTITUDE_MAX_LAG
    p = enu_pose(Position(int(2000 - lag_ms), 0.0, 0, 0, 0, 0), Attitude(2000, 0.0, 1.0), None)
    assert math.pi / 2 - p.theta == pytest.approx(-ATTITUDE_MAX_LAG)


def test_an_attitude_at_or_after_a_position_completes_it_at_once() -> None:
    b = PoseBuilder()
    assert b.attitude(Attitude(1000, 0.0, 0.0)) == []  # nothing waiting
    (same_time,) = b.position(Position(1000, 1.0, 1.0, 2.0, 0, 0))
    assert (same_time.stamp, same_time.x, same_time.y) == (1.0, 2.0, 1.0) and b.pending is None


def test_an_older_attitude_does_not_complete_a_waiting_position() -> None:
    b = PoseBuilder()
    assert b.position(Position(1000, 1.0, 0, 0, 0, 0)) == []
    assert b.attitude(Attitude(990, 0.0, 0.0)) == []  # before the position: it keeps waiting
    assert b.pending is not None
    (pose,) = b.attitude(Attitude(1010, 0.2, 0.0))
    # interpolated between the two ATTITUDEs around it
    assert math.pi / 2 - pose.theta == pytest.approx(0.1) and b.pending is None
    assert (b.prev.ms, b.att.ms) == (990, 1010)


def test_after_a_reset_no_old_heading_reaches_a_new_position() -> None:
    b = PoseBuilder()
    b.attitude(Attitude(5000, 1.0, 0.0))
    b.reset()
    assert b.position(Position(100, 1.0, 0, 0, 0, 0)) == []  # the rebooted vehicle's times start again
