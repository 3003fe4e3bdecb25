"""sim_learner/sitl_response.py: measuring a rover's open-loop response to GUIDED set-points.

Against SITL itself it runs in tests/integration/test_demo_sitl.py (needs the SITL binary). Here: the ratios and
the table, and :func:`hold`'s measurement through a real ground-station link (:class:`sim_learner.sitl.Pilot`) to
the emulated rover, whose learner responds exactly as commanded, so the measurement must read back the command:
the forward speed projected on the heading and the turn rate counter-clockwise."""

from __future__ import annotations

import math
import time

import pytest

from sim_learner.dynamics import LearnerModel
from sim_learner.mavlink_rover import MAV, MavlinkRover
from sim_learner.sitl import Pilot
from sim_learner.sitl_response import Point, forward_speed, hold, table
from sim_learner.vehicle import SimVehicle


def test_ratios_are_achieved_over_commanded_and_nan_for_a_zero_command() -> None:
    p = Point(0.4, -0.2, 0.3, -0.1)
    assert p.v_ratio == pytest.approx(0.75) and p.w_ratio == pytest.approx(0.5)
    z = Point(0.0, 0.0, 0.01, 0.0)
    assert math.isnan(z.v_ratio) and math.isnan(z.w_ratio)


def test_the_table_is_markdown_with_one_row_per_point() -> None:
    t = table([Point(0.4, -0.2, 0.3, -0.1), Point(0.1, 0.0, 0.05, 0.002)])
    lines = t.splitlines()
    assert lines[0].startswith("| v cmd m/s | omega cmd rad/s |") and lines[1] == "|---|---|---|---|---|---|"
    assert lines[2] == "| 0.40 | -0.200 | 0.300 | -0.100 | 0.75 | 0.50 |"
    assert lines[3] == "| 0.10 | +0.000 | 0.050 | +0.002 | 0.50 | nan |"
    assert table([]).count("\n") == 1


def test_hold_reads_back_what_an_exactly_responding_rover_did() -> None:
    exact = LearnerModel((-2.0, 2.0), (-4.0, 4.0), name="exact")
    vehicle = SimVehicle(exact, (0.0, 0.0, 0.7), now=time.monotonic())
    with MavlinkRover(vehicle, init_s=0.05, ekf_position_s=0.1) as rover:
        pilot = Pilot(f"udpout:127.0.0.1:{rover.port}")
        try:
            for msg_id in (MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, MAV.MAVLINK_MSG_ID_ATTITUDE):
                pilot.interval(msg_id, 20.0)
                time.sleep(0.025)  # the two streams half a period apart, as a busy machine (and SITL) may have them
            assert pilot.wait(lambda s: s.position is not None, 5.0)  # the EKF has its origin: GUIDED can arm
            pilot.set_mode("GUIDED")
            pilot.arm(True)
            p = hold(pilot, 0.3, 0.2, 1.0, 0.5)
            assert (p.v_cmd, p.w_cmd) == (0.3, 0.2)
            assert p.v == pytest.approx(0.3, abs=1e-6) and p.w == pytest.approx(0.2, abs=1e-6)
            assert vehicle.cmd == pytest.approx((0.3, 0.2))  # ENU counter-clockwise, sent clockwise on the wire
        finally:
            pilot.close()


def test_the_forward_speed_takes_the_heading_at_the_velocitys_instant() -> None:
    class Msg:
        def __init__(self, **kw: float) -> None:
            self.__dict__.update(kw)

    yaw_then, rate = 0.5, -0.2  # NED: clockwise positive, so this rover turns counter-clockwise
    yaw_at_velocity = yaw_then + rate * 0.040
    pos = Msg(time_boot_ms=1040, vx=0.3 * math.cos(yaw_at_velocity), vy=0.3 * math.sin(yaw_at_velocity))
    att = Msg(time_boot_ms=1000, yaw=yaw_then, yawspeed=rate)
    assert forward_speed(pos, att) == pytest.approx(0.3, abs=1e-12)
    wrapped = Msg(time_boot_ms=(2**32 - 40) & 0xFFFFFFFF, yaw=yaw_then, yawspeed=rate)  # the clock wrapped between
    assert forward_speed(Msg(time_boot_ms=0, vx=pos.vx, vy=pos.vy), wrapped) == pytest.approx(0.3, abs=1e-12)
    backwards = Msg(time_boot_ms=1040, vx=-pos.vx, vy=-pos.vy)
    assert forward_speed(backwards, att) == pytest.approx(-0.3, abs=1e-12)
