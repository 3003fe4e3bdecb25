"""The MAVLink link against the emulated ArduPilot Rover: real pymavlink framing over UDP or TCP on 127.0.0.1.

The emulator (:mod:`sim_learner.mavlink_rover`) follows ArduPilot's source, so each test here states something the
real vehicle does and checks the driver copes with it: the operator's RC switch wins, commands are acknowledged or
refused with a reason, a disarm can be lost on close, the EKF origin comes late, the radio drops out, the vehicle
reboots, other systems share the link.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers import DriverError, open_driver
from drivers.base import Driver, LinkHealth
from drivers.mavlink import TYPE_MASK_VEL_YAWRATE, MavlinkLinkConfig
from sim_learner.dynamics import LearnerModel, mpc_learner
from sim_learner.mavlink_dialect import MAV, mavutil_v2
from sim_learner.mavlink_rover import GUIDED, MODES, MavlinkRover
from sim_learner.vehicle import SimVehicle
from tests.wait import until


def health(driver: Driver) -> LinkHealth:
    """The driver's health now (as the driver host asks for it each tick)."""
    return driver.health(time.monotonic())

MODE_OR_ARM = (MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_CMD_COMPONENT_ARM_DISARM)
REVERSIBLE = LearnerModel((-0.5, 0.5), (-1.0, 1.0), name="reversible")


@contextmanager
def rig(transport: str = "udp", *, model: LearnerModel | None = None, open_link: bool = True,
        rover_kw: dict[str, Any] | None = None, **cfg_kw: Any) -> Iterator[tuple[Any, MavlinkRover, SimVehicle]]:
    """A rover (fast boot: 0.2 s, EKF ready at 0.4 s, GUID_TIMEOUT 0.6 s) and a driver on it; both cleaned up."""
    vehicle = SimVehicle(model or mpc_learner(), (1.0, 2.0, 0.3), now=time.monotonic())
    rover = MavlinkRover(vehicle, transport=transport,
                         **({"init_s": 0.2, "ekf_position_s": 0.4, "guid_timeout": 0.6} | (rover_kw or {}))).start()
    url = f"udpout:127.0.0.1:{rover.port}" if transport == "udp" else f"tcp:127.0.0.1:{rover.port}"
    cfg = MavlinkLinkConfig(url=url, **({"open_timeout": 10.0, "ack_timeout": 0.3, "heartbeat_timeout": 1.5}
                                        | cfg_kw))
    driver = open_driver("mavlink", cfg)
    try:
        if open_link:
            driver.open(time.monotonic())
            driver.engage(time.monotonic())  # a person's act: GUIDED and armed
        yield driver, rover, vehicle
    finally:
        driver.close()
        rover.stop()


def drive(driver: Any, seconds: float, v: float, w: float, poses: list | None = None) -> None:
    """What the driver host does at 50 Hz: send, then poll (paced on a deadline schedule, as the host's loop)."""
    t_next = time.monotonic()
    t_end = t_next + seconds
    while time.monotonic() < t_end:
        driver.send(v, w, time.monotonic())
        got = driver.poll(time.monotonic())
        if poses is not None:
            poses += got
        t_next += 0.02
        time.sleep(max(0.0, t_next - time.monotonic()))  # pacing: the host's 50 Hz tick


def wait_for(driver: Any, pred: Callable[[], bool], timeout: float) -> bool:
    """Poll the driver (as the host does) until ``pred()``."""
    def look() -> bool:
        driver.poll(time.monotonic())
        return pred()

    return bool(until(look, timeout))


def commands_after(rover: MavlinkRover, t: float, kinds: tuple[int, ...] = MODE_OR_ARM) -> list[dict]:
    return [c for c in rover.commands if c["t"] > t and c["command"] in kinds]


# ------------------------------------------------------------------------------------------------ basics
def test_open_reaches_guided_and_armed_with_position_streaming() -> None:
    with rig() as (driver, rover, _):
        h = health(driver)
        assert h.ok and h.connected and h.text == "driving: GUIDED, armed" and h.reason == "ok"
        assert rover.custom_mode == GUIDED and rover.armed
        assert rover.intervals[32] == pytest.approx(0.05) and rover.intervals[30] == pytest.approx(0.05)
        assert all(c["result"] == MAV.MAV_RESULT_ACCEPTED for c in rover.commands)  # each one acked


def test_velocity_set_points_follow_ardupilot_semantics_and_the_pose_comes_back_in_enu() -> None:
    with rig() as (driver, rover, vehicle):
        poses: list = []
        drive(driver, 1.2, 0.25, 0.1, poses)
        sp = rover.setpoints[-1]
        assert sp["frame"] == MAV.MAV_FRAME_BODY_NED and sp["type_mask"] == TYPE_MASK_VEL_YAWRATE == 0x05E7
        assert sp["vx"] == pytest.approx(0.25) and sp["yaw_rate"] == pytest.approx(-0.1)  # NED is clockwise
        body = vehicle.advance(time.monotonic())
        moving = poses[-1]  # at a steady speed: the pose's speed is the vehicle's whenever the pose was sent
        assert body.x > 1.1 and moving.v == pytest.approx(body.v, abs=1e-3) and moving.v > 0.1
        # where it is, in ENU: compared at rest, where a pose read late (a loaded machine) is still where it is
        rest: list = []

        def stopped() -> bool:
            driver.send(0.0, 0.0, time.monotonic())
            rest.extend(driver.poll(time.monotonic()))
            st = vehicle.advance(time.monotonic())
            return st.v == 0.0 and st.omega == 0.0 and bool(rest) and rest[-1].v == 0.0 and rest[-1].omega == 0.0

        assert until(stopped, 5.0), rest[-1:]
        body, last = vehicle.advance(time.monotonic()), rest[-1]
        assert math.hypot(last.x - body.x, last.y - body.y) < 0.03 and abs(last.theta - body.theta) < 0.02


def test_reverse_speed_keeps_its_sign() -> None:
    """Finding: ``_vel = hypot(vx, vy)`` reported a rover backing up as driving forward."""
    with rig(model=REVERSIBLE) as (driver, _, vehicle):
        poses: list = []
        drive(driver, 1.0, -0.2, 0.0, poses)
        assert vehicle.state.v == pytest.approx(-0.2)
        assert poses[-1].v == pytest.approx(-0.2, abs=0.01)


def test_pairs_from_the_link_recover_the_learners_response() -> None:
    """The station's pairing on this link's poses as the driver host feeds them (50 Hz ticks, a new command every 0.1
    s, 20 Hz telemetry): ``scmbridge bench pairing`` for 6 s. Nearly every command pairs (here 98 %; the test
    asks 75 %, a margin for a loaded machine), and each pair is the learner's true response. Findings (the
    bench, 20 s): poses stamped on receipt fell on the host's 20 ms tick grid and took the heading of an
    ATTITUDE up to a period older, 0.014 m/s and 0.013 rad/s median error; and a minimum span of exactly dt / 2
    rejected 117 of 197 intervals."""
    from bench.pairing import measure

    res = measure("mavlink", 6.0, seed=5)
    assert res["formed"] >= 0.75 * res["commands"] and res["rejected"] <= 0.1 * res["commands"], res  # load margin
    assert res["error_v_mps"]["median"] < 0.004 and res["error_omega_radps"]["median"] < 0.004, res


def test_rover_stops_when_set_points_stop() -> None:
    with rig() as (driver, rover, vehicle):
        drive(driver, 0.3, 0.3, 0.0)
        assert vehicle.advance(time.monotonic()).v > 0
        # GUID_TIMEOUT (0.6 s here; ArduPilot's 3 s by default) stops it: waited for, not slept through
        assert wait_for(driver, lambda: "target not received last 0.6secs, stopping" in rover.statustexts
                        and vehicle.advance(time.monotonic()).v == 0.0, 10.0), rover.statustexts[-3:]
        assert vehicle.advance(time.monotonic()).v == 0.0
        assert "target not received last 0.6secs, stopping" in rover.statustexts  # the firmware's words
        assert MavlinkRover(vehicle).guid_timeout == 3.0


# ---------------------------------------------------------------------------------------- the operator wins
def test_an_rc_mode_switch_is_never_fought_and_driving_resumes_when_the_operator_gives_guided_back() -> None:
    """Finding: a HEARTBEAT outside GUIDED made send() switch the vehicle back to GUIDED at the command rate."""
    with rig() as (driver, rover, vehicle):
        t_open = time.monotonic()
        drive(driver, 0.3, 0.25, 0.0)
        assert rover.rc_mode_switch("HOLD")  # ArduPilot sends a HEARTBEAT at once on a mode change
        drive(driver, 0.1, 0.25, 0.0)  # (a set-point already on its way when the switch came is ignored)
        ignored = rover.ignored_setpoints.get("not GUIDED", 0)
        drive(driver, 1.5, 0.25, 0.0)  # a host that keeps calling send(): over a second of HEARTBEATs
        for _ in range(5):  # and what the new host does when health() is not ok
            driver.stop(time.monotonic())
        # the rover has read what the driver sent after those stops (its next HEARTBEAT, same socket, in order)
        t_stops = time.monotonic()
        assert wait_for(driver, lambda: rover.gcs_seen > t_stops, 10.0)
        assert rover.mode_name == "HOLD" and commands_after(rover, t_open) == []
        assert rover.ignored_setpoints.get("not GUIDED", 0) == ignored  # none sent: withheld, not ignored
        h = health(driver)
        assert not h.ok and h.connected and h.text == "operator took control: mode HOLD" and h.reason == "operator"
        assert vehicle.advance(time.monotonic()).v == 0.0
        assert rover.rc_mode_switch("GUIDED")
        assert wait_for(driver, lambda: health(driver).ok, 10.0), health(driver).text
        n = len(rover.setpoints)
        drive(driver, 0.3, 0.25, 0.0)
        assert len(rover.setpoints) > n and vehicle.advance(time.monotonic()).v > 0
        assert commands_after(rover, t_open) == []


def test_an_operator_disarm_is_reported_and_never_undone() -> None:
    with rig() as (driver, rover, _):
        t_open = time.monotonic()
        assert rover.rc_arm(False)
        drive(driver, 1.2, 0.25, 0.0)
        h = health(driver)
        assert not h.ok and h.text == "vehicle disarmed in GUIDED: waiting for the operator to arm it"
        assert h.reason == "disarmed"
        assert not rover.armed and commands_after(rover, t_open) == []
        assert rover.rc_arm(True)
        assert wait_for(driver, lambda: health(driver).ok, 10.0), health(driver).text


def test_close_leaves_a_vehicle_the_operator_has_taken_alone() -> None:
    with rig() as (driver, rover, _):
        assert rover.rc_mode_switch("MANUAL")
        assert wait_for(driver, lambda: driver.custom_mode == MODES["MANUAL"], 10.0)
        t = time.monotonic()
        driver.close()
        # absence can only be watched over time (the closed driver sends nothing that could mark the end of its
        # traffic): anything it sent has reached the vehicle within this window
        time.sleep(0.2)  # absence: watched over a window (see above)
        assert rover.armed and rover.mode_name == "MANUAL" and commands_after(rover, t) == []


# ----------------------------------------------------------------------------------------- acknowledgements
def test_arming_refused_is_reported_with_its_mav_result_and_the_prearm_text() -> None:
    """Finding: commands were fire-and-forget; a refusal was only 'not armed within N s'. The ACK must also be ours:
    another ground station's ACCEPTED for the same command (same vehicle, target 42/190) must not count."""
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with MavlinkRover(vehicle, init_s=0.2, ekf_position_s=0.3) as rover:
        rover.safety_switch = True
        stop = threading.Event()

        def other_gcs_acks() -> None:
            m = rover.foreign(1, 1)  # the vehicle itself answering a second ground station
            while not stop.wait(0.05):
                m.command_ack_send(MAV.MAV_CMD_COMPONENT_ARM_DISARM, MAV.MAV_RESULT_ACCEPTED, 0, 0, 42, 190)

        th = threading.Thread(target=other_gcs_acks, daemon=True)
        driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:127.0.0.1:{rover.port}", open_timeout=3.0,
                                                          ack_timeout=0.3))
        th.start()
        t0 = time.monotonic()
        try:
            driver.open(t0)  # never arms: that is engage's
            with pytest.raises(DriverError, match=r"arming refused: MAV_RESULT_FAILED \(PreArm: Hardware safety "
                                                  r"switch\)"):
                driver.engage(t0)
        finally:
            stop.set()
            th.join(1.0)
            driver.close()
        assert time.monotonic() - t0 < 2 * 3.0 + 2.0  # open and engage, each bounded by open_timeout
        arms = [c for c in rover.commands if c["command"] == MAV.MAV_CMD_COMPONENT_ARM_DISARM]
        assert arms and all(c["result"] == MAV.MAV_RESULT_FAILED for c in arms)
        assert not rover.armed and "arming refused: MAV_RESULT_FAILED" in health(driver).detail.last_refusal


def test_open_waits_for_the_ekf_origin_before_reporting_ready() -> None:
    """Finding: a rover without GPS has a position estimate (it accepts GUIDED and arms) but no EKF origin, and
    ArduPilot silently ignores every set-point until it has one: the first commands were 'applied' to a vehicle that
    did not move. LOCAL_POSITION_NED only streams once there is an origin."""
    with rig(rover_kw={"ekf_position_s": 0.0, "ekf_origin_s": 1.5}) as (driver, rover, vehicle):
        assert rover.has_origin(time.monotonic())  # open() returned only once set-points count
        drive(driver, 0.5, 0.25, 0.0)
        assert rover.ignored_setpoints.get("no EKF origin", 0) == 0
        assert rover.setpoints and vehicle.advance(time.monotonic()).v > 0


def test_close_stops_disarms_and_waits_for_the_ack_over_tcp() -> None:
    """Finding: close() sent the disarm and closed at once. ArduPilot's TCP port drops what arrives just before its
    peer closes (SITL UARTDriver), so the vehicle stayed armed after `scmbridge driver` exited."""
    with rig("tcp") as (driver, rover, _):
        drive(driver, 0.3, 0.25, 0.0)
        t0 = time.monotonic()
        driver.close()
        assert time.monotonic() - t0 < 3.0
        assert not rover.armed
        disarm = [c for c in rover.commands if c["command"] == MAV.MAV_CMD_COMPONENT_ARM_DISARM][-1]
        assert disarm["params"][0] == 0.0 and disarm["result"] == MAV.MAV_RESULT_ACCEPTED
        before = [s for s in rover.setpoints if s["t"] <= disarm["t"]]
        assert before[-1]["vx"] == 0.0 and before[-1]["yaw_rate"] == 0.0  # stopped first


def test_close_over_udp_returns_only_once_the_disarm_is_acknowledged() -> None:
    with rig() as (driver, rover, _):
        drive(driver, 0.2, 0.25, 0.0)
        driver.close()
        assert not rover.armed  # no sleep: close() waited for the vehicle's answer


# ------------------------------------------------------------------------------------------ supervision
def test_heartbeat_loss_is_reported_and_recovery_touches_neither_mode_nor_arming() -> None:
    """Finding: `connected` never turned false."""
    with rig(heartbeat_timeout=1.5) as (driver, rover, _):
        t_open = time.monotonic()
        drive(driver, 0.2, 0.2, 0.0)
        rover.radio_blackout(True)
        assert wait_for(driver, lambda: not health(driver).connected, 10.0)
        h = health(driver)
        assert not h.ok and h.text.startswith("no heartbeat for ") and float(h.text.split()[3]) >= 1.5
        assert h.reason == "link_down"
        n = len(rover.setpoints)
        drive(driver, 0.3, 0.2, 0.0)  # the host keeps calling: nothing goes out while the link is down
        rover.radio_blackout(False)
        assert wait_for(driver, lambda: health(driver).ok, 10.0), health(driver).text
        assert len(rover.setpoints) == n and commands_after(rover, t_open) == []
        assert health(driver).detail.link_losses == 1


def test_tcp_reconnects_after_a_reboot_and_waits_for_the_operator() -> None:
    """A rebooted vehicle comes back in INITIAL_MODE, disarmed: the driver re-opens the connection, asks for its
    streams again, says so, and waits for the operator instead of changing the mode or arming."""
    with rig("tcp", heartbeat_timeout=1.5, reconnect_max_s=0.5) as (driver, rover, vehicle):
        drive(driver, 1.5, 0.2, 0.0)  # up long enough that its clock going back to 0 tells a reboot (> 1 s)
        port = rover.port
        rover.stop()
        assert wait_for(driver, lambda: not health(driver).connected, 10.0)
        rover2 = MavlinkRover(vehicle, port=port, transport="tcp", init_s=0.2, ekf_position_s=0.4).start()
        try:
            assert wait_for(driver, lambda: health(driver).connected and rover2.intervals[32] == 0.05
                            and rover2.intervals[30] == 0.05, 10.0)
            assert wait_for(driver, lambda: health(driver).text.startswith("vehicle rebooted: mode MANUAL"), 10.0)
            assert "disarmed" in health(driver).text and not health(driver).ok
            assert health(driver).reason == "rebooted"  # not the operator: the host stays engaged
            assert {c["command"] for c in rover2.commands} == {MAV.MAV_CMD_SET_MESSAGE_INTERVAL}  # streams only
            assert health(driver).detail.reconnects >= 1
            assert rover2.rc_mode_switch("GUIDED")
            assert wait_for(driver, lambda: rover2.rc_arm(True), 10.0)
            assert wait_for(driver, lambda: health(driver).ok, 10.0), health(driver).text
            drive(driver, 0.3, 0.2, 0.0)
            assert rover2.setpoints
        finally:
            driver.close()
            rover2.stop()


def test_statustexts_are_logged_and_the_last_few_are_in_health(caplog: pytest.LogCaptureFixture) -> None:
    """Finding: STATUSTEXT went to an unbounded list nobody read."""
    with rig(statustext_keep=3) as (driver, rover, _), caplog.at_level(logging.INFO, "scmbridge.driver.mavlink"):
        for i in range(6):
            rover.text(f"PreArm: check {i}")
        assert wait_for(driver, lambda: driver.statustexts[-1:] == ["PreArm: check 5"], 10.0)
        assert health(driver).detail.statustexts == ("PreArm: check 3", "PreArm: check 4",
                                                                      "PreArm: check 5")
        assert "vehicle: PreArm: check 0" in caplog.text


def test_other_systems_on_the_link_are_ignored_and_counted() -> None:
    """Finding: only HEARTBEAT was filtered by system id; a second vehicle's position was taken as ours."""
    with rig() as (driver, rover, vehicle):
        other, gcs = rover.foreign(2, 1), rover.foreign(200, 190)
        poses: list = []
        for _ in range(10):
            other.heartbeat_send(MAV.MAV_TYPE_GROUND_ROVER, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, MODES["HOLD"], 4)
            other.attitude_send(0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
            other.local_position_ned_send(0, 100.0, 100.0, 0.0, 1.0, 0.0, 0.0)
            gcs.command_ack_send(MAV.MAV_CMD_COMPONENT_ARM_DISARM, MAV.MAV_RESULT_ACCEPTED, 0, 0, 255, 190)
            drive(driver, 0.05, 0.2, 0.0, poses)
        h = health(driver)
        assert h.ok and driver.custom_mode == GUIDED and driver.armed
        body = vehicle.advance(time.monotonic())
        assert poses and all(math.hypot(p.x - body.x, p.y - body.y) < 0.5 for p in poses)
        assert h.detail.foreign >= 40 and (2, 1) in h.detail.foreign_ids


def test_set_points_repeat_at_the_set_point_rate_but_a_change_goes_at_once() -> None:
    """Finding: one set-point per send() call, 50 Hz: 56 % of a 57600-baud radio. Judged on the times the driver
    was called with and on what the rover got, never on how fast a loaded machine runs the loop."""
    period, min_gap = 0.1, 1.0 / 25.0
    with rig(setpoint_rate_hz=1.0 / period, max_setpoint_hz=1.0 / min_gap) as (driver, rover, _):
        def sent() -> int:
            return driver.health(time.monotonic()).detail.setpoints_sent

        def rover_has_all() -> bool:  # every set-point the driver sent reached the rover (taken or ignored)
            return len(rover.setpoints) + sum(rover.ignored_setpoints.values()) >= sent()

        drive(driver, 0.2, 0.2, 0.0)
        # pacing on the driver's own rule: a change within min_gap of the last set-point waits (the radio's
        # budget); this one must not, so min_gap passes first
        time.sleep(min_gap)  # pacing on the driver's rule (see above)
        n0, calls = sent(), []
        t_end = time.monotonic() + 20.0
        t_next = time.monotonic()
        while len(calls) < 50 and time.monotonic() < t_end:  # 50 calls, one changed command (sent at once), then
            calls.append(time.monotonic())                      # unchanged; counted, not timed: a stalled loop
            driver.send(0.3, 0.0, calls[-1])                    # takes longer
            driver.poll(time.monotonic())
            t_next += 0.02
            time.sleep(max(0.0, t_next - time.monotonic()))  # pacing: the host's 50 Hz tick
        expected, last = 1, calls[0]
        for t in calls[1:]:  # the rule: an unchanged command again once a period has passed since the last one
            if t - last >= period:
                expected, last = expected + 1, t
        assert sent() - n0 == expected < len(calls) / 2, (sent() - n0, expected, len(calls),
                                                          driver.health(time.monotonic()))
        assert wait_for(driver, rover_has_all, 10.0)
        n1 = len(rover.setpoints)
        time.sleep(min_gap)  # pacing on the driver's rule, as above: this change must go at once
        driver.send(0.1, 0.05, time.monotonic())  # a new command: now, not at the next period
        driver.stop(time.monotonic())  # and a stop right after it
        assert sent() - n0 == expected + 2
        assert wait_for(driver, rover_has_all, 10.0)
        assert [(s["vx"], s["yaw_rate"]) for s in rover.setpoints[n1:]] == [(pytest.approx(0.1), pytest.approx(-0.05)),
                                                                             (0.0, 0.0)]


# ------------------------------------------------------------------------------------------ the emulator
def test_the_emulated_rover_answers_like_ardupilot() -> None:
    """The emulator itself (raw pymavlink, no driver): ACKs addressed to the sender, refusals with their texts,
    set-points ignored silently outside GUIDED and without an EKF origin."""
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with MavlinkRover(vehicle, init_s=0.1, ekf_position_s=60.0) as rover:
        c = mavutil_v2().mavlink_connection(f"udpout:127.0.0.1:{rover.port}", source_system=250, source_component=190)
        try:
            c.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)

            def ask(command: int, *p: float) -> tuple[Any, list[str]]:
                c.mav.command_long_send(1, 1, command, 0, *p, *([0.0] * (7 - len(p))))
                ack, texts, t_end = None, [], time.monotonic() + 1.0
                while time.monotonic() < t_end:
                    m = c.recv_match(type=["COMMAND_ACK", "STATUSTEXT"], blocking=True, timeout=0.1)
                    if m is not None and m.get_type() == "COMMAND_ACK":
                        ack = m
                    elif m is not None:
                        texts.append(m.text)
                        if ack is not None:
                            break
                return ack, texts

            assert c.recv_match(type="HEARTBEAT", blocking=True, timeout=2.0) is not None
            assert until(lambda: rover.mode_name == "MANUAL", 10.0)  # boot over: INITIAL_MODE
            ack, texts = ask(MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 99)
            assert ack.result == MAV.MAV_RESULT_FAILED and "No such mode 99" in texts
            assert (ack.target_system, ack.target_component) == (250, 190)
            c.mav.set_position_target_local_ned_send(0, 1, 1, MAV.MAV_FRAME_BODY_NED, 0x05E7, 0, 0, 0, 0.3, 0, 0,
                                                     0, 0, 0, 0, 0)
            ack, _ = ask(MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED)  # disarmed: ok
            assert ack.result == MAV.MAV_RESULT_ACCEPTED and rover.ignored_setpoints == {"not GUIDED": 1}
            ack, texts = ask(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            assert ack.result == MAV.MAV_RESULT_FAILED and "PreArm: Need Position Estimate" in texts
            ack, _ = ask(MAV.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 1e5)
            assert ack.result == MAV.MAV_RESULT_FAILED
            ack, _ = ask(MAV.MAV_CMD_SET_MESSAGE_INTERVAL, MAV.MAVLINK_MSG_ID_ATTITUDE, 1e5)
            assert ack.result == MAV.MAV_RESULT_ACCEPTED and rover.intervals[30] == pytest.approx(0.1)
            c.mav.set_position_target_local_ned_send(0, 1, 1, MAV.MAV_FRAME_BODY_NED, 0x05E7, 0, 0, 0, 0.3, 0, 0,
                                                     0, 0, 0, 0, 0)
            assert until(lambda: rover.ignored_setpoints.get("no EKF origin"), 10.0)
            assert rover.ignored_setpoints.get("no EKF origin") == 1 and rover.setpoints == []
        finally:
            c.close()


@settings(max_examples=25, deadline=None)
@given(st.binary(min_size=1, max_size=80))
def test_random_bytes_on_the_link_are_counted_and_dropped(data: bytes) -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with MavlinkRover(vehicle) as rover, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(data, ("127.0.0.1", rover.port))
        s.sendto(b"\xfd" + data, ("127.0.0.1", rover.port))  # a MAVLink 2 start byte and garbage
        time.sleep(0.03)  # absence (no crash, no set-point) is watched over a window: garbage marks no event
        assert rover._thread is not None and rover._thread.is_alive()
        assert rover.setpoints == []


def test_the_emulated_rover_denies_non_finite_command_parameters_and_lives() -> None:
    """Found by the fuzz bench: a COMMAND_LONG whose mode or message id was NaN/inf killed the rover's thread."""
    mu = mavutil_v2()
    rover = MavlinkRover(SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())).start()
    conn = mu.mavlink_connection(f"udpout:127.0.0.1:{rover.port}", source_system=255)
    try:
        for bad in (float("nan"), float("inf"), float("-inf")):
            conn.mav.command_long_send(1, 1, mu.mavlink.MAV_CMD_DO_SET_MODE, 0, 1, bad, 0, 0, 0, 0, 0)
            conn.mav.command_long_send(1, 1, mu.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, bad, 1e5, 0, 0, 0, 0, 0)
            conn.mav.command_long_send(1, 1, mu.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, bad, 0, 0, 0, 0, 0, 0)
        until(lambda: len(rover.commands) >= 9, 10.0)
        assert rover._thread.is_alive()
        assert [c["result"] for c in rover.commands[-9:]] == [mu.mavlink.MAV_RESULT_DENIED] * 9
    finally:
        conn.close()
        rover.stop()


def test_non_finite_set_points_reach_the_motors_as_ardupilots_arithmetic_leaves_them() -> None:
    """Found by the fuzz bench: a NaN velocity set-point drove the emulated rover at WP_SPEED (``min``/``max`` of a
    NaN) and a NaN turn rate reached the vehicle. ArduPilot's speed is ``safe_sqrt(vx^2 + vy^2)`` (NaN -> 0) and a
    NaN turn rate is constrained to the last one; an infinite speed is WP_SPEED."""
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with MavlinkRover(vehicle, init_s=0.1, ekf_position_s=0.2, wp_speed=0.4) as rover:
        c = mavutil_v2().mavlink_connection(f"udpout:127.0.0.1:{rover.port}", source_system=250, source_component=190)
        try:
            c.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            assert until(lambda: rover.has_origin(time.monotonic()), 10.0)  # booted, with an EKF origin
            assert rover.rc_mode_switch("GUIDED") and rover.rc_arm(True)

            def setpoint(vx: float, yaw_rate: float) -> tuple[float, float]:
                n = len(rover.setpoints)
                c.mav.set_position_target_local_ned_send(0, 1, 1, MAV.MAV_FRAME_BODY_NED, TYPE_MASK_VEL_YAWRATE, 0,
                                                         0, 0, vx, 0, 0, 0, 0, 0, 0, yaw_rate)
                until(lambda: len(rover.setpoints) != n, 10.0, 0.01)
                assert len(rover.setpoints) == n + 1
                return vehicle.cmd if vehicle.moving else (0.0, 0.0)

            assert setpoint(0.3, -0.2) == (pytest.approx(0.3), pytest.approx(0.2))
            assert setpoint(math.nan, -0.2) == (0.0, pytest.approx(0.2))  # NaN speed: 0, the turn goes on
            assert setpoint(0.3, math.nan) == (pytest.approx(0.3), pytest.approx(0.2))  # the last turn rate kept
            assert setpoint(math.inf, 0.0) == (pytest.approx(0.4), 0.0)  # WP_SPEED
            assert setpoint(0.1, -math.inf) == (pytest.approx(0.1), pytest.approx(2.0))  # ATC_STR_RAT_MAX
            assert rover.internal_errors == {"constraining_nan": 1}
            assert rover._thread is not None and rover._thread.is_alive()
        finally:
            c.close()


def test_telemetry_with_non_finite_or_absurd_values_is_counted_and_dropped() -> None:
    """Found by the fuzz bench: an ATTITUDE with an infinite yaw raised out of ``poll()`` (math.cos), so every later
    message went unread; a position of 1e30 m became a pose."""
    with rig() as (driver, rover, _):
        me = rover.foreign(1, 1)  # the vehicle's own ids: these are "its" messages
        before = health(driver).malformed
        for bad in (math.inf, math.nan, 1e30):
            me.attitude_send(0, 0.0, 0.0, bad, 0.0, 0.0, 0.0)
            me.local_position_ned_send(0, bad, 0.0, 0.0, 0.0, 0.0, 0.0)
        poses: list = []
        drive(driver, 0.3, 0.2, 0.0, poses)
        h = health(driver)
        assert h.malformed - before == 6 and h.detail.invalid_values == 6
        assert h.ok and poses and all(abs(p.x) < 100 and abs(p.y) < 100 and math.isfinite(p.theta) for p in poses)


def test_changing_commands_never_take_more_set_points_than_the_radio_budget() -> None:
    """Finding: changing commands produced 86 set-points/s (97 % of a 57600-baud radio); setpoint_rate_hz bounded
    only a steady stream. A stop after motion still goes at once."""
    with rig(max_setpoint_hz=20.0) as (driver, rover, _vehicle):
        n0 = len(rover.setpoints)
        t0 = time.monotonic()
        k = 0

        def deferred() -> int:
            return health(driver).detail.setpoints_deferred

        # a new command every 10 ms (100 changes a second) for at least 2 s and until over 50 were deferred: a
        # stalled loop makes fewer calls a second, so it runs longer (deadline-bound) instead of falling short
        t_next = t0
        while (time.monotonic() - t0 < 2.0 or deferred() <= 50) and time.monotonic() - t0 < 30.0:
            k += 1
            driver.send(0.2 + 0.001 * (k % 50), 0.0, time.monotonic())
            driver.poll(time.monotonic())
            t_next += 0.01
            time.sleep(max(0.0, t_next - time.monotonic()))  # pacing: the sender's 100 Hz
        span = time.monotonic() - t0
        sent = len(rover.setpoints) - n0
        assert sent <= span * 20 + 3, (sent, span)  # max_setpoint_hz 20 over the span the commands changed
        assert deferred() > 50
        driver.stop(time.monotonic())
        assert rover.setpoints[-1]["vx"] == 0.0 or _until_stop(rover)


def _until_stop(rover: MavlinkRover) -> bool:
    return bool(until(lambda: rover.setpoints[-1]["vx"] == 0.0, 10.0, 0.005))


@pytest.mark.parametrize("hz", [1.0, 5.0])
def test_the_hosts_heartbeat_rate_lets_a_short_gcs_failsafe_watch_it(hz: float) -> None:
    """With the GCS failsafe watching the host (FS_GCS_ENABLE, SYSID_MYGCS its source_system) a FS_GCS_TIMEOUT
    shorter than the gap between two of its HEARTBEATs holds a rover the host still drives; ``heartbeat_hz`` 5 keeps
    it driving, and once the host is gone the failsafe holds it (docs/SECURITY.md, "A killed MAVLink driver host")."""
    params = {"FS_GCS_ENABLE": 1.0, "FS_GCS_TIMEOUT": 0.5, "FS_TIMEOUT": 0.3, "FS_ACTION": 2.0}
    with rig(heartbeat_hz=hz, rover_kw={"params": params, "guid_timeout": 3.0}) as (driver, rover, vehicle):
        drive(driver, 2.0, 0.3, 0.0)
        held_while_driving = "Failsafe: GCS" in rover.statustexts
        assert held_while_driving == (hz == 1.0), rover.statustexts
        if hz == 1.0:
            return
        assert rover.mode_name == "GUIDED" and vehicle.moving
        t_dead = time.monotonic()  # the host dies: nothing more from it
        assert until(lambda: rover.mode_name == "HOLD", 3.0)
        assert time.monotonic() - t_dead < 3.0  # before GUIDED's own 3 s timeout
