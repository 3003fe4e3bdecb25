"""sim_learner/mavlink_rover.py: the emulated ArduPilot Rover's rules, fed MAVLink messages on a fake clock.

Over a real link it is tested in tests/integration/test_mavlink_link.py (ACKs to the sender, refusals with their
texts, set-points ignored outside GUIDED or without an origin, non-finite parameters and set-points, RC switches),
tests/integration/test_mavlink_signing.py (signing) and against the firmware in tests/integration/test_sitl.py. Here
no socket and no thread: the rover's own handlers are given parsed messages and times, and what it would send is
read back from its encoder. What that adds: the boot (a GUIDED set during boot is lost), the mode and arming rules
the link tests do not reach, GUID_TIMEOUT and braking at ATC_DECEL_MAX, coasting when disarmed, message intervals,
parameters, the GCS failsafe, the HEARTBEAT's flags, MAVLink routing, and ArduPilot's NaN arithmetic helpers."""

from __future__ import annotations

import math
from typing import Any

import pytest

from sim_learner import mavlink_rover as R
from sim_learner.dynamics import LearnerModel
from sim_learner.vehicle import SimVehicle

MAV = R.MAV
LINEAR = LearnerModel((-2.0, 2.0), (-4.0, 4.0), name="linear")
GCS = MAV.MAVLink(None, srcSystem=255, srcComponent=190)
CUSTOM = MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


class Rig:
    """A rover on a fake clock (its boot at t = 0) whose output is parsed back as a ground station would."""

    def __init__(self, **kw: Any) -> None:
        self.vehicle = SimVehicle(LINEAR, now=0.0)
        self.rover = R.MavlinkRover(self.vehicle, init_s=0.3, ekf_position_s=1.0, **kw)
        self.rover.t0 = 0.0
        self.out: list[bytes] = []
        self.rover._transmit = self.out.append  # what it sends, instead of a socket
        self._reader = MAV.MAVLink(None)

    def sent(self, kind: str) -> list[Any]:
        msgs = [m for b in self.out for m in (self._reader.parse_buffer(b) or [])]
        self.out.clear()
        return [m for m in msgs if m.get_type() == kind]

    def give(self, msg: Any, now: float, src: MAV.MAVLink = GCS) -> None:
        for m in self.rover._parser.parse_buffer(msg.pack(src)) or []:
            self.rover._handle(m, now)

    def command(self, command: int, *p: float, now: float, target: int = 1) -> int:
        args = [*p, *([0.0] * (7 - len(p)))]
        self.give(MAV.MAVLink_command_long_message(target, 1, command, 0, *args), now)
        return self.rover.commands[-1]["result"] if self.rover.commands else -1

    def set_mode(self, mode: int, now: float) -> int:
        return self.command(MAV.MAV_CMD_DO_SET_MODE, CUSTOM, mode, now=now)

    def arm(self, on: bool, now: float) -> int:
        return self.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if on else 0.0, now=now)

    def setpoint(self, vx: float, yaw_rate: float, now: float, *, mask: int = R.VELOCITY_YAWRATE_MASK,
                 frame: int = MAV.MAV_FRAME_BODY_NED, vy: float = 0.0) -> None:
        self.give(MAV.MAVLink_set_position_target_local_ned_message(0, 1, 1, frame, mask, 0, 0, 0, vx, vy, 0, 0, 0, 0,
                                                                    0, yaw_rate), now)

    def driving(self, now: float = 2.0) -> Rig:
        """Booted, with a position, in GUIDED and armed."""
        self.rover._update(now)
        assert self.set_mode(R.GUIDED, now) == MAV.MAV_RESULT_ACCEPTED and self.arm(True, now) == 0
        return self


def test_an_unknown_transport_is_refused() -> None:
    with pytest.raises(ValueError, match="transport 'serial': udp or tcp"):
        R.MavlinkRover(SimVehicle(LINEAR, now=0.0), transport="serial")


def test_a_mode_set_during_boot_is_acknowledged_and_lost() -> None:
    rig = Rig()
    assert rig.rover.mode_name == "INITIALISING"
    assert rig.arm(True, 0.1) == MAV.MAV_RESULT_FAILED and rig.rover.statustexts[-1] == "PreArm: Mode not armable"
    assert rig.set_mode(R.GUIDED, 0.1) == MAV.MAV_RESULT_ACCEPTED and rig.rover.mode_name == "GUIDED"
    rig.rover._update(0.29)
    assert rig.rover.mode_name == "GUIDED"
    rig.rover._update(0.3)  # INITIAL_MODE, whatever was set meanwhile
    assert rig.rover.mode_name == "MANUAL"


def test_mode_changes_follow_rovers_rules() -> None:
    rig = Rig()
    rig.rover._update(0.5)
    assert rig.command(MAV.MAV_CMD_DO_SET_MODE, 0, R.HOLD, now=0.5) == MAV.MAV_RESULT_DENIED  # no custom-mode flag
    assert rig.set_mode(77, 0.5) == MAV.MAV_RESULT_FAILED and rig.rover.statustexts[-1] == "No such mode 77"
    assert rig.set_mode(2, 0.5) == MAV.MAV_RESULT_FAILED  # LEARNING is gone from Rover 4
    assert rig.arm(True, 0.5) == MAV.MAV_RESULT_ACCEPTED  # MANUAL needs no position
    assert rig.set_mode(R.GUIDED, 0.6) == MAV.MAV_RESULT_FAILED  # armed, and no position yet
    assert rig.rover.statustexts[-1] == "Flight mode change failed" and rig.rover.mode_name == "MANUAL"
    assert rig.set_mode(R.GUIDED, 1.0) == MAV.MAV_RESULT_ACCEPTED  # the EKF has its position now
    hb = rig.sent("HEARTBEAT")  # a mode change sends a HEARTBEAT at once
    assert hb and hb[-1].custom_mode == R.GUIDED


def test_arming_checks_and_their_texts() -> None:
    rig = Rig()
    rig.rover._update(0.5)
    rig.rover.safety_switch = True
    assert rig.arm(True, 0.5) == MAV.MAV_RESULT_FAILED and rig.rover.statustexts[-1] == "PreArm: Hardware safety switch"
    rig.rover.safety_switch = False
    assert rig.arm(False, 0.5) == MAV.MAV_RESULT_ACCEPTED  # already disarmed: accepted, nothing said
    assert rig.rover.statustexts[-1] == "PreArm: Hardware safety switch"
    assert rig.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 0.5, now=0.5) == MAV.MAV_RESULT_UNSUPPORTED
    assert rig.arm(True, 0.5) == MAV.MAV_RESULT_ACCEPTED and rig.rover.statustexts[-1] == "Throttle armed"
    acks = rig.sent("COMMAND_ACK")
    assert len(acks) == 4 and (acks[-1].target_system, acks[-1].target_component) == (255, 190)


def test_commands_for_another_system_are_not_this_vehicles() -> None:
    rig = Rig()
    rig.rover._update(0.5)
    rig.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, now=0.5, target=7)
    assert rig.rover.commands == [] and not rig.rover.armed and rig.sent("COMMAND_ACK") == []
    assert rig.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, now=0.5, target=0) == 0  # broadcast: for everyone
    assert rig.command(MAV.MAV_CMD_NAV_LOITER_UNLIM, now=0.5) == MAV.MAV_RESULT_UNSUPPORTED


def test_velocity_and_yaw_rate_set_points_are_capped_and_reverse_keeps_its_sign() -> None:
    rig = Rig(wp_speed=0.5, str_rat_max=1.0).driving()
    rig.setpoint(0.3, 0.2, 2.0)  # NED yaw rate clockwise: ENU omega -0.2
    assert rig.vehicle.cmd == pytest.approx((0.3, -0.2))
    rig.setpoint(0.6, 0.0, 2.1, vy=0.8)  # |(vx, vy)| = 1.0, capped at WP_SPEED
    assert rig.vehicle.cmd == pytest.approx((0.5, 0.0))
    rig.setpoint(-0.3, -3.0, 2.2)  # backwards; the turn capped at ATC_STR_RAT_MAX
    assert rig.vehicle.cmd == pytest.approx((-0.3, 1.0))
    for mask, frame, reason in ((R.VELOCITY_YAWRATE_MASK, MAV.MAV_FRAME_GLOBAL, "frame"),
                                (0x0FF8, MAV.MAV_FRAME_BODY_NED, "unsupported type_mask"),  # a position target
                                (0x0DFF, MAV.MAV_FRAME_BODY_NED, "unsupported type_mask")):  # nothing used
        rig.setpoint(0.3, 0.0, 2.3, mask=mask, frame=frame)
        assert rig.rover.ignored_setpoints[reason] >= 1
    assert rig.vehicle.cmd == pytest.approx((-0.3, 1.0)) and len(rig.rover.setpoints) == 3


def test_the_guided_timeout_stops_the_rover_braking_at_decel_max() -> None:
    rig = Rig(decel_max=2.0, guid_timeout=3.0).driving()
    rig.setpoint(1.0, 0.0, 2.0)
    rig.rover._update(5.0)  # exactly the timeout: not yet
    assert rig.rover.target is not None
    rig.rover._update(5.01)
    assert rig.rover.target is None and rig.rover.statustexts[-1] == "target not received last 3secs, stopping"
    rig.rover._update(5.21)  # braking: 2 m/s^2 for 0.2 s
    assert rig.vehicle.rolling and rig.vehicle.cmd == pytest.approx((0.6, 0.0), abs=1e-9)
    rig.rover._update(5.6)
    assert not rig.vehicle.moving and rig.rover.slowing_at is None


def test_a_disarmed_rover_coasts_and_each_disarm_is_recorded_with_its_speed() -> None:
    rig = Rig(coast_decel=0.5).driving()
    rig.setpoint(1.0, 0.0, 2.0)
    assert rig.arm(False, 2.5) == MAV.MAV_RESULT_ACCEPTED
    assert rig.rover.disarms == [(2.5, 1.0)] and rig.rover.statustexts[-1] == "Throttle disarmed"
    rig.rover._update(3.5)
    assert rig.vehicle.rolling and rig.vehicle.cmd[0] == pytest.approx(0.5, abs=1e-9)  # coasting at 0.5 m/s^2
    rig.setpoint(1.0, 0.0, 3.6)  # disarmed: the target is taken, the motors stay off
    assert rig.rover.target == (1.0, -0.0) and rig.vehicle.rolling


def test_message_intervals() -> None:
    rig = Rig()
    lpn, att = MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, MAV.MAVLINK_MSG_ID_ATTITUDE
    interval = MAV.MAV_CMD_SET_MESSAGE_INTERVAL
    assert rig.command(interval, lpn, 2e5, now=1.0) == 0 and rig.rover.intervals[lpn] == pytest.approx(0.2)
    assert rig.command(interval, att, -1, now=1.0) == 0 and rig.rover.intervals[att] == math.inf  # stopped
    assert rig.command(interval, att, 0, now=1.0) == 0 and rig.rover.intervals[att] == 1.0  # its default
    rig.command(interval, lpn, 10.0, now=1.0)
    assert rig.rover.intervals[lpn] == pytest.approx(1e-3)  # at most 1 kHz
    rig.command(interval, lpn, 1e9, now=1.0)
    assert rig.rover.intervals[lpn] == pytest.approx(60.0)
    assert rig.command(interval, MAV.MAVLINK_MSG_ID_VFR_HUD, 1e5, now=1.0) == 0  # known, not streamed here
    assert MAV.MAVLINK_MSG_ID_VFR_HUD not in rig.rover.intervals
    assert rig.command(interval, 9999, 1e5, now=1.0) == MAV.MAV_RESULT_FAILED


def test_parameters_are_answered_by_name_index_and_list_and_an_unknown_name_gets_nothing() -> None:
    rig = Rig(wp_speed=0.8, str_rat_max=1.0, params={"FS_GCS_ENABLE": 1.0})
    rig.give(MAV.MAVLink_param_request_read_message(1, 1, b"WP_SPEED", -1), 1.0)
    (pv,) = rig.sent("PARAM_VALUE")
    assert pv.param_id == "WP_SPEED" and pv.param_value == pytest.approx(0.8)
    assert pv.param_type == MAV.MAV_PARAM_TYPE_REAL32 and pv.param_count == len(rig.rover.params)
    rig.give(MAV.MAVLink_param_request_read_message(1, 1, b"", pv.param_index), 1.0)
    assert rig.sent("PARAM_VALUE")[0].param_id == "WP_SPEED"
    rig.give(MAV.MAVLink_param_request_read_message(1, 1, b"NO_SUCH", -1), 1.0)
    rig.give(MAV.MAVLink_param_request_read_message(1, 1, b"", 999), 1.0)
    assert rig.sent("PARAM_VALUE") == []
    rig.give(MAV.MAVLink_param_request_list_message(1, 1), 1.0)
    got = {m.param_id: m.param_value for m in rig.sent("PARAM_VALUE")}
    assert got["ATC_STR_RAT_MAX"] == pytest.approx(math.degrees(1.0)) and got["FS_GCS_ENABLE"] == 1.0
    assert got["FS_ACTION"] == 2.0 and got["SYSID_MYGCS"] == 255.0 and len(got) == len(rig.rover.params)


def test_the_gcs_failsafe_holds_an_armed_rover_after_fs_gcs_timeout_plus_fs_timeout() -> None:
    rig = Rig(params={"FS_GCS_ENABLE": 1.0}).driving()
    rig.give(MAV.MAVLink_heartbeat_message(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3), 2.0)
    assert rig.rover.gcs_seen == 2.0
    rig.setpoint(0.5, 0.0, 2.0)
    rig.rover._gcs_failsafe(7.5)  # 5.5 s without the GCS: the failsafe starts
    assert rig.rover.failsafe_since == 7.5 and rig.rover.mode_name == "GUIDED"
    rig.rover._gcs_failsafe(9.0)  # it has held FS_TIMEOUT (1.5 s), not more
    assert rig.rover.mode_name == "GUIDED"
    rig.rover._gcs_failsafe(9.01)
    assert rig.rover.mode_name == "HOLD" and rig.rover.statustexts[-1] == "Failsafe: GCS" and not rig.vehicle.moving
    other = MAV.MAVLink(None, srcSystem=42, srcComponent=1)  # not SYSID_MYGCS: not the ground station
    rig.give(MAV.MAVLink_heartbeat_message(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3), 9.5, src=other)
    assert rig.rover.gcs_seen == 2.0
    rig.give(MAV.MAVLink_heartbeat_message(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3), 9.5)
    rig.rover._gcs_failsafe(9.6)  # a HEARTBEAT ends it; the mode stays
    assert rig.rover.failsafe_since is None and rig.rover.mode_name == "HOLD"


@pytest.mark.parametrize(
    "mode,armed,flags,status",
    [("MANUAL", False, MAV.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED, MAV.MAV_STATE_ACTIVE),
     ("GUIDED", True, MAV.MAV_MODE_FLAG_GUIDED_ENABLED | MAV.MAV_MODE_FLAG_SAFETY_ARMED, MAV.MAV_STATE_ACTIVE),
     ("HOLD", False, MAV.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED, MAV.MAV_STATE_STANDBY)],
)
def test_the_heartbeat_says_the_mode_arming_and_state(mode: str, armed: bool, flags: int, status: int) -> None:
    rig = Rig()
    rig.rover._update(2.0)
    rig.set_mode(R.MODES[mode], 2.0)
    if armed:
        rig.arm(True, 2.0)
    rig.sent("HEARTBEAT")
    rig.rover._heartbeat()
    (hb,) = rig.sent("HEARTBEAT")
    assert hb.type == MAV.MAV_TYPE_GROUND_ROVER and hb.autopilot == MAV.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.base_mode == CUSTOM | flags and hb.system_status == status and hb.custom_mode == R.MODES[mode]


def test_booting_heartbeat_is_calibrating() -> None:
    rig = Rig()
    rig.rover._heartbeat()
    (hb,) = rig.sent("HEARTBEAT")
    assert hb.system_status == MAV.MAV_STATE_CALIBRATING and hb.custom_mode == R.INITIALISING


def test_ardupilots_nan_arithmetic() -> None:
    assert R._safe_sqrt(4.0) == 2.0 and R._safe_sqrt(math.nan) == 0.0 and R._safe_sqrt(-1.0) == 0.0
    assert R._safe_sqrt(math.inf) == math.inf
    assert R._constrain(5.0, -1.0, 1.0, nan=0.3) == 1.0 and R._constrain(-math.inf, -1.0, 1.0, nan=0.3) == -1.0
    assert R._constrain(math.nan, -1.0, 1.0, nan=0.3) == 0.3 and R._constrain(0.2, -1.0, 1.0, nan=0.3) == 0.2
