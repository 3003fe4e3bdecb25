"""An emulated ArduPilot Rover (4.x) on MAVLink 2, driving the software learner.

What it honours, as ArduPilot Rover does: HEARTBEAT at 1 Hz (GROUND_ROVER, ARDUPILOTMEGA, custom mode, armed flag);
MAV_CMD_DO_SET_MODE (custom mode 15 = GUIDED; a mode set during the first ``init_s`` seconds is lost, as while the
vehicle is still initialising), MAV_CMD_COMPONENT_ARM_DISARM and MAV_CMD_SET_MESSAGE_INTERVAL, each answered with
COMMAND_ACK; SET_POSITION_TARGET_LOCAL_NED honoured only in GUIDED, armed, in MAV_FRAME_BODY_NED with a velocity
type_mask (acceleration ignored), silently dropped otherwise (no ACK, like ArduPilot); speed capped by WP_SPEED and
turn rate by ATC_STR_RAT_MAX; a set-point is kept ``target_timeout`` (3 s) after the last one, then STATUSTEXT
"target not received last 3secs, stopping" and a stop; LOCAL_POSITION_NED and ATTITUDE streamed at the requested
intervals (1 Hz until asked). NED frame: x north, y east, yaw clockwise from north.
"""

from __future__ import annotations

import math
import os
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from sim_learner.device import ThreadedDevice  # noqa: E402
from sim_learner.vehicle import SimVehicle  # noqa: E402

GUIDED = 15
HOLD = 4
VELOCITY_YAWRATE_MASK = 0x05E7  # ArduPilot's documented "velocity + yaw rate" type_mask


class MavlinkRover(ThreadedDevice):
    """See the module docstring. Listens on UDP ``host:port`` (0: a free port, read ``.port`` after start)."""

    thread_name = "mavlink-rover"

    def __init__(self, vehicle: SimVehicle, host: str = "127.0.0.1", port: int = 0, *, wp_speed: float = 2.0,
                 str_rat_max: float = 2.0, target_timeout: float = 3.0, init_s: float = 0.0) -> None:
        super().__init__()
        self.vehicle = vehicle
        self.host, self.port = host, int(port)
        self.wp_speed, self.str_rat_max = float(wp_speed), float(str_rat_max)
        self.target_timeout, self.init_s = float(target_timeout), float(init_s)
        self.custom_mode = HOLD
        self.armed = False
        self.intervals = {32: 1.0, 30: 1.0}  # message id -> period (s)
        self.last_target: tuple[float, float] | None = None
        self.last_target_time = -math.inf
        self.setpoints: list[dict] = []  # accepted SET_POSITION_TARGET_LOCAL_NED fields, last 200
        self.dropped_setpoints = 0
        self.lost_mode_sets = 0
        self.statustexts: list[str] = []
        self.bad = 0
        self.conn = None

    def _open(self) -> None:
        if self.port == 0:
            import socket

            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.bind((self.host, 0))
                self.port = s.getsockname()[1]
        self.conn = mavutil.mavlink_connection(f"udpin:{self.host}:{self.port}", source_system=1,
                                               source_component=1, dialect="ardupilotmega")
        self.t0 = time.monotonic()

    def _close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    # ------------------------------------------------------------------------------------------------ loop
    def _run(self) -> None:
        conn = self.conn
        m = conn.mav
        due = {32: 0.0, 30: 0.0, 0: 0.0}
        while not self._stop.is_set():
            msg = conn.recv_match(blocking=True, timeout=0.005)
            now = time.monotonic()
            if msg is not None:
                self._handle(msg, now)
            if self.last_target is not None and now - self.last_target_time > self.target_timeout:
                self.last_target = None
                self.vehicle.stop(now)
                self._text("target not received last 3secs, stopping")
            if not self._peer_known():
                continue
            if now >= due[0]:
                base = mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                if self.armed:
                    base |= mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED
                m.heartbeat_send(mavutil.mavlink.MAV_TYPE_GROUND_ROVER, mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                 base, self.custom_mode, mavutil.mavlink.MAV_STATE_ACTIVE)
                due[0] = now + 1.0
            if now >= due[32] or now >= due[30]:
                x, y, th = self.vehicle.measured_pose(now)
                st = self.vehicle.state
                boot_ms = int((now - self.t0) * 1000) & 0xFFFFFFFF
                if now >= due[32]:
                    # ENU (x east, y north) -> NED (x north, y east); body speed projected on the axes
                    m.local_position_ned_send(boot_ms, y, x, 0.0, st.v * math.sin(th), st.v * math.cos(th), 0.0)
                    due[32] = now + self.intervals[32]
                if now >= due[30]:
                    yaw = math.remainder(math.pi / 2 - th, 2 * math.pi)
                    m.attitude_send(boot_ms, 0.0, 0.0, yaw, 0.0, 0.0, -st.omega)
                    due[30] = now + self.intervals[30]

    def _peer_known(self) -> bool:
        """pymavlink's udpin answers only peers it has heard from."""
        return bool(getattr(self.conn, "clients", None)) or getattr(self.conn, "last_address", None) is not None

    def _text(self, text: str) -> None:
        self.statustexts.append(text)
        if self._peer_known():
            self.conn.mav.statustext_send(mavutil.mavlink.MAV_SEVERITY_WARNING, text.encode()[:50])

    def _ack(self, command: int, result: int) -> None:
        self.conn.mav.command_ack_send(command, result)

    def _handle(self, msg, now: float) -> None:
        t = msg.get_type()
        if t == "BAD_DATA":
            self.bad += 1
            return
        mav = mavutil.mavlink
        if t == "COMMAND_LONG":
            if msg.command == mav.MAV_CMD_DO_SET_MODE:
                if now - self.t0 < self.init_s:
                    self.lost_mode_sets += 1  # still initialising: the mode set is lost
                    return
                self.custom_mode = int(msg.param2)
                if self.custom_mode != GUIDED and self.last_target is not None:
                    self.last_target = None
                    self.vehicle.stop(now)
                self._ack(msg.command, mav.MAV_RESULT_ACCEPTED)
            elif msg.command == mav.MAV_CMD_COMPONENT_ARM_DISARM:
                self.armed = msg.param1 >= 0.5
                if not self.armed:
                    self.vehicle.stop(now)
                self._ack(msg.command, mav.MAV_RESULT_ACCEPTED)
            elif msg.command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
                mid, us = int(msg.param1), float(msg.param2)
                if mid in self.intervals and us > 0:
                    self.intervals[mid] = us / 1e6
                    self._ack(msg.command, mav.MAV_RESULT_ACCEPTED)
                else:
                    self._ack(msg.command, mav.MAV_RESULT_DENIED)
            else:
                self._ack(msg.command, mav.MAV_RESULT_UNSUPPORTED)
        elif t == "SET_POSITION_TARGET_LOCAL_NED":
            ok = (self.custom_mode == GUIDED and self.armed and msg.coordinate_frame == mav.MAV_FRAME_BODY_NED
                  and msg.type_mask & 0x0007 == 0x0007 and msg.type_mask & 0x01C0 == 0x01C0
                  and not msg.type_mask & 0x0008)  # position and acceleration ignored, vx used
            if not ok:
                self.dropped_setpoints += 1  # ArduPilot drops it silently
                return
            v = max(-self.wp_speed, min(self.wp_speed, msg.vx))
            yaw_rate = 0.0 if msg.type_mask & 0x0800 else msg.yaw_rate
            w = -max(-self.str_rat_max, min(self.str_rat_max, yaw_rate))  # NED clockwise -> ENU counter-clockwise
            self.last_target, self.last_target_time = (v, w), now
            self.setpoints.append({"vx": msg.vx, "vy": msg.vy, "yaw_rate": msg.yaw_rate, "frame": msg.coordinate_frame,
                                   "type_mask": msg.type_mask})
            del self.setpoints[:-200]
            if v == 0.0 and w == 0.0:
                self.vehicle.stop(now)
            else:
                self.vehicle.command(v, w, now)
