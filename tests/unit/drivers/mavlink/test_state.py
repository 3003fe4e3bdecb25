"""The MAVLink link's pure parts without a vehicle: the pose builder (positions and headings paired at the vehicle's
own time, NED -> ENU) and the judgement of whether the vehicle accepts set-points (one reason per state)."""

from __future__ import annotations

import math

import pytest

from drivers.mavlink.pose import Attitude, PoseBuilder, Position, enu_pose
from drivers.mavlink.state import LinkView, RoverModes, Vehicle, judge

MODES = RoverModes(guided=15, initialising=16, names={4: "HOLD", 15: "GUIDED", 16: "INITIALISING"})
OPEN = LinkView(opened=True, closed=False, connection=True, connected_at=0.0, lost_reason="", url="udpout:x:1")


def test_enu_pose_swaps_the_axes_and_turns_the_heading() -> None:
    # facing east in NED (yaw pi/2), moving east at 1 m/s, turning clockwise at 0.5 rad/s
    p = enu_pose(Position(1000, 7.0, x=2.0, y=3.0, vx=0.0, vy=1.0), Attitude(1000, math.pi / 2, 0.5), None)
    assert (p.stamp, p.x, p.y) == (7.0, 3.0, 2.0)
    assert p.theta == pytest.approx(0.0) and p.v == pytest.approx(1.0) and p.omega == -0.5
    back = enu_pose(Position(1000, 7.0, 0.0, 0.0, vx=0.0, vy=-1.0), Attitude(1000, math.pi / 2, 0.0), None)
    assert back.v == pytest.approx(-1.0)  # reversing is negative: the speed is on the heading


def test_the_heading_is_interpolated_across_a_wrap_or_carried_by_the_yaw_rate() -> None:
    prev, att = Attitude(1000, math.pi - 0.1, 0.0), Attitude(1100, -math.pi + 0.1, 0.0)  # through south
    mid = enu_pose(Position(1050, 0.0, 0, 0, 0, 0), att, prev)
    assert math.remainder(math.pi / 2 - mid.theta - math.pi, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    carried = enu_pose(Position(1080, 0.0, 0, 0, 0, 0), Attitude(1000, 0.0, 1.0), None)
    assert math.pi / 2 - carried.theta == pytest.approx(0.08)
    far = enu_pose(Position(1500, 0.0, 0, 0, 0, 0), Attitude(1000, 0.0, 1.0), None)  # beyond ATTITUDE_MAX_LAG
    assert math.pi / 2 - far.theta == pytest.approx(0.0)


def test_the_builder_waits_for_the_attitude_at_or_after_a_position_and_forgets_on_reset() -> None:
    b = PoseBuilder()
    assert b.position(Position(1000, 1.0, 0, 0, 0, 0)) == []  # no heading yet
    assert b.position(Position(1050, 1.05, 0, 0, 0, 0)) == []  # still none: the first is dropped, not guessed
    (pose,) = b.attitude(Attitude(1060, 0.0, 0.0))
    assert pose.stamp == 1.05 and b.pending is None
    assert b.position(Position(1100, 1.1, 0, 0, 0, 0)) == []  # after the last ATTITUDE: held back
    (carried,) = b.position(Position(1150, 1.15, 0, 0, 0, 0))  # no ATTITUDE came between: the last one carries
    assert carried.stamp == 1.1 and b.pending is not None and b.pending.ms == 1150
    b.reset()
    assert (b.att, b.prev, b.pending) == (None, None, None)


def test_the_judgement_names_one_reason_in_the_order_a_person_acts_on() -> None:
    now = 10.0
    v = Vehicle(custom_mode=15, armed=True, hb_time=9.5, pos_time=9.9)
    assert judge(v, OPEN, now, MODES, 3.0, 1.0).reason == "ok"
    cases = [
        (Vehicle(custom_mode=4, armed=True, hb_time=9.5, pos_time=9.9, guided_seen=True), OPEN, "operator",
         "operator took control: mode HOLD"),
        # a vehicle never in GUIDED since the driver opened (booted in MANUAL): nobody took it from this host
        (Vehicle(custom_mode=4, armed=False, hb_time=9.5, pos_time=9.9), OPEN, "operator",
         "not in GUIDED (the operator's): mode HOLD, disarmed"),
        (Vehicle(custom_mode=4, armed=False, hb_time=9.5, rebooted=True), OPEN, "rebooted",
         "vehicle rebooted: mode HOLD, disarmed"),
        (Vehicle(custom_mode=15, armed=False, hb_time=9.5, pos_time=9.9), OPEN, "disarmed",
         "vehicle disarmed in GUIDED: waiting for the operator to arm it"),
        (Vehicle(custom_mode=15, armed=True, hb_time=9.5, pos_time=8.0), OPEN, "no_telemetry",
         "no LOCAL_POSITION_NED for 2.0 s (EKF origin lost?)"),
        (Vehicle(custom_mode=15, armed=True, hb_time=6.0, pos_time=9.9), OPEN, "link_down", "no heartbeat for 4.0 s"),
        (v, LinkView(True, False, False, 0.0, "EOF", "tcp:h:1"), "link_down",
         "connection lost (EOF), re-opening tcp:h:1; no heartbeat for 0.5 s"),
        (v, LinkView(True, False, True, 9.8, "", "u"), "link_down", "no heartbeat for 0.5 s"),  # heard before reconnect
        (v, LinkView(False, False, True, 0.0, "", "u"), "closed", "not opened"),
        (v, LinkView(True, True, True, 0.0, "", "u"), "closed", "closed"),
    ]
    for vehicle, link, reason, text in cases:
        verdict = judge(vehicle, link, now, MODES, 3.0, 1.0)
        assert (verdict.reason, verdict.text, verdict.ok) == (reason, text, False), verdict
    assert judge(v, LinkView(False, False, True, 0.0, "", "u"), now, MODES, 3.0, 1.0).connected  # heard, not opened
    assert MODES.name(None) == "unknown" and MODES.name(99) == "mode 99"


def test_command_results_and_modes_are_named_from_pymavlinks_tables() -> None:
    from drivers.mavlink import NO_ACK, load_pymavlink, mode_name, result_name

    modes = load_pymavlink().modes
    assert (modes.guided, modes.initialising) == (15, 16) and mode_name(4) == "HOLD" and mode_name(None) == "unknown"
    assert result_name(4) == "MAV_RESULT_FAILED" and result_name(NO_ACK) == "no COMMAND_ACK"
