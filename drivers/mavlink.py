"""MAVLink link: an ArduPilot Rover in GUIDED mode (pymavlink, MAVLink 2, ardupilotmega).

open(): wait for the vehicle's HEARTBEAT, ask for LOCAL_POSITION_NED and ATTITUDE at the control rate
(MAV_CMD_SET_MESSAGE_INTERVAL), set GUIDED (MAV_CMD_DO_SET_MODE, base mode 1, custom mode 15) and arm
(MAV_CMD_COMPONENT_ARM_DISARM), retrying until the HEARTBEAT says so, all bounded. send(v, omega):
SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_NED with type_mask 0x05E7 (velocity + yaw rate; position, vz,
acceleration and yaw ignored), vx = v, yaw_rate = -omega (NED is clockwise-positive). While driving, a HEARTBEAT
whose custom mode is not GUIDED re-asserts GUIDED (a mode set while the autopilot initialises can be lost).
poll(): LOCAL_POSITION_NED + ATTITUDE -> ENU poses (x_enu = y_ned, y_enu = x_ned, theta = pi/2 - yaw).

Configuration: :class:`bridge.config.MavlinkLinkConfig` (``[link.mavlink]`` in the driver host's file).
"""

from __future__ import annotations

import math
import os
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from bridge.config import MavlinkLinkConfig  # noqa: E402
from drivers.base import DriverError, LinkHealth, Pose  # noqa: E402

GUIDED = 15
TYPE_MASK_VEL_YAWRATE = 0x05E7


class MavlinkDriver:
    """The MAVLink link behind the :class:`drivers.base.Driver` protocol (see the module docstring)."""

    name = "mavlink"

    def __init__(self, config: MavlinkLinkConfig) -> None:
        self.config = config
        self.url, self.baud = config.url, config.baud
        self.target = (config.target_system, config.target_component)
        self.source_system = config.source_system
        self.rate_hz = config.rate_hz
        self.open_timeout = config.open_timeout
        self.disarm_on_close = config.disarm_on_close
        self.conn = None
        self.custom_mode: int | None = None
        self.armed = False
        self.driving = False
        self._pos: tuple[float, float] | None = None
        self._att: tuple[float, float] | None = None
        self._vel = 0.0
        self._t0 = time.monotonic()
        self._hb_due = 0.0
        self.statustexts: list[str] = []
        self._health = LinkHealth()

    # ---------------------------------------------------------------------------------------------- link
    def open(self, now: float) -> None:
        try:
            self.conn = mavutil.mavlink_connection(self.url, baud=self.baud, source_system=self.source_system,
                                                   source_component=mavutil.mavlink.MAV_COMP_ID_MISSIONPLANNER,
                                                   dialect="ardupilotmega")
        except Exception as exc:  # pymavlink raises plain OSError/SerialException/...
            raise DriverError(f"cannot open MAVLink connection {self.url}: {exc}") from exc
        t_end = time.monotonic() + self.open_timeout
        while self.custom_mode is None:
            self._heartbeat(time.monotonic(), force=True)
            self._pump(0.1)
            if time.monotonic() > t_end:
                raise DriverError(f"no HEARTBEAT from the vehicle on {self.url} within {self.open_timeout} s")
        period_us = 1e6 / self.rate_hz
        for mid in (mavutil.mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavutil.mavlink.MAVLINK_MSG_ID_ATTITUDE):
            self._command(mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mid, period_us)
        while not (self.custom_mode == GUIDED and self.armed):
            if self.custom_mode != GUIDED:
                self._command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                              GUIDED)
            elif not self.armed:
                self._command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            self._pump(0.3)
            if time.monotonic() > t_end:
                raise DriverError(f"vehicle not GUIDED and armed within {self.open_timeout} s "
                                  f"(mode {self.custom_mode}, armed {self.armed})")
        self._health.connected = self._health.ok = True
        self._health.text = "ready"

    def _command(self, command: int, p1: float = 0, p2: float = 0) -> None:
        self.conn.mav.command_long_send(self.target[0], self.target[1], command, 0, p1, p2, 0, 0, 0, 0, 0)
        self._health.frames_sent += 1

    def _heartbeat(self, now: float, force: bool = False) -> None:
        if force or now >= self._hb_due:
            self.conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self._hb_due = now + 1.0

    def _setpoint(self, v: float, omega: float) -> None:
        boot_ms = int((time.monotonic() - self._t0) * 1000) & 0xFFFFFFFF
        self.conn.mav.set_position_target_local_ned_send(
            boot_ms, self.target[0], self.target[1], mavutil.mavlink.MAV_FRAME_BODY_NED, TYPE_MASK_VEL_YAWRATE,
            0, 0, 0, float(v), 0, 0, 0, 0, 0, 0, float(-omega))
        self._health.frames_sent += 1

    def send(self, v: float, omega: float, now: float) -> None:
        self._heartbeat(now)
        if self.custom_mode != GUIDED:  # the mode changed under us (or a set was lost): re-assert GUIDED
            mav = mavutil.mavlink
            self._command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED)
        self._setpoint(v, omega)
        self.driving = True

    def stop(self, now: float) -> None:
        if self.conn is None:
            return
        self._heartbeat(now)
        self._setpoint(0.0, 0.0)

    def _pump(self, block: float) -> list[Pose]:
        out: list[Pose] = []
        t_end = time.monotonic() + block
        while True:
            msg = self.conn.recv_match(blocking=block > 0, timeout=max(0.0, t_end - time.monotonic()) or 0.001)
            if msg is None:
                break
            self._health.frames_received += 1
            t = msg.get_type()
            if t == "BAD_DATA":
                self._health.malformed += 1
            elif t == "HEARTBEAT" and msg.get_srcSystem() == self.target[0]:
                self.custom_mode = int(msg.custom_mode)
                self.armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif t == "LOCAL_POSITION_NED":
                self._pos = (float(msg.y), float(msg.x))  # ENU
                self._vel = math.hypot(msg.vx, msg.vy)
                if self._att is not None:
                    yaw, rate = self._att
                    out.append(Pose(time.monotonic(), self._pos[0], self._pos[1], math.pi / 2 - yaw, self._vel,
                                    -rate))
            elif t == "ATTITUDE":
                self._att = (float(msg.yaw), float(msg.yawspeed))
            elif t == "STATUSTEXT":
                self.statustexts.append(str(msg.text))
            if time.monotonic() >= t_end and block > 0:
                break
        return out

    def poll(self, now: float) -> list[Pose]:
        if self.conn is None:
            return []
        self._heartbeat(now)
        return self._pump(0.0)

    def health(self) -> LinkHealth:
        self._health.detail = {"custom_mode": self.custom_mode, "armed": self.armed}
        return self._health

    def clear_faults(self, now: float) -> None:
        """Nothing to clear on this link (see :meth:`drivers.base.Driver.clear_faults`)."""

    def close(self) -> None:
        if self.conn is None:
            return
        try:
            self._setpoint(0.0, 0.0)
            if self.disarm_on_close:
                self._command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0)
        finally:
            self.conn.close()
            self.conn = None
            self._health.connected = self._health.ok = False
            self._health.text = "closed"
