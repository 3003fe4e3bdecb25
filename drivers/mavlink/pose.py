"""ENU poses from the vehicle's LOCAL_POSITION_NED and ATTITUDE, each position with the heading at its own vehicle
time. Pure: stamps come in with the messages' values, nothing here reads a clock or does I/O."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from drivers.base import Pose

#: the most the ATTITUDE and LOCAL_POSITION_NED samples may be apart for the heading to be carried to the position's
#: time with the reported yaw rate (two 20 Hz periods); further apart, the last heading is used as it is
ATTITUDE_MAX_LAG = 0.1
#: Telemetry a vehicle can really send (the wire's own ranges are wider still): |x|, |y| in m, speeds in m/s, yaw in
#: rad (ArduPilot sends [-pi, pi]; a full turn either way is tolerated), yaw rate in rad/s. A message outside them,
#: NaN/inf included, is counted malformed (``detail.invalid_values``) and dropped before it can reach a pose.
POSITION_MAX, SPEED_MAX, YAW_MAX, YAW_RATE_MAX = 1e6, 100.0, 2 * math.pi, 100.0


def telemetry_valid(msg: Any) -> bool:
    """A LOCAL_POSITION_NED or ATTITUDE whose values are finite and within the bounds above (other types: True)."""
    t = msg.get_type()
    if t == "LOCAL_POSITION_NED":
        bounded = ((msg.x, POSITION_MAX), (msg.y, POSITION_MAX), (msg.vx, SPEED_MAX), (msg.vy, SPEED_MAX))
    elif t == "ATTITUDE":
        bounded = ((msg.yaw, YAW_MAX), (msg.yawspeed, YAW_RATE_MAX))
    else:
        return True
    return all(math.isfinite(val) and abs(val) <= lim for val, lim in bounded)


@dataclass(frozen=True, slots=True)
class Position:
    """One LOCAL_POSITION_NED: the vehicle's time of it, its stamp on our clock, NED position and velocity."""

    ms: int
    stamp: float
    x: float
    y: float
    vx: float
    vy: float


@dataclass(frozen=True, slots=True)
class Attitude:
    """One ATTITUDE: the vehicle's time of it, yaw (NED, clockwise from north, rad) and yaw rate (clockwise, rad/s)."""

    ms: int
    yaw: float
    yawspeed: float


def ground_speed(p: Position | None) -> float | None:
    """The vehicle's own speed over ground from a LOCAL_POSITION_NED, m/s (None without one)."""
    return None if p is None else math.hypot(p.vx, p.vy)


def enu_pose(p: Position, att: Attitude, prev: Attitude | None) -> Pose:
    """An ENU pose from a position and the heading at its time: interpolated between the ATTITUDEs around it
    (``prev``, ``att``), else carried from the nearest one with its yaw rate (at most ``ATTITUDE_MAX_LAG`` away).
    ArduPilot schedules each message on its own interval, so the last ATTITUDE can be up to a period older than the
    position; the heading at the position's own time keeps the previous command's turn out of the pairs."""
    yaw = att.yaw
    if prev is not None and prev.ms <= p.ms < att.ms:
        yaw = prev.yaw + math.remainder(att.yaw - prev.yaw, 2.0 * math.pi) * (p.ms - prev.ms) / (att.ms - prev.ms)
    elif abs(p.ms - att.ms) <= 1000.0 * ATTITUDE_MAX_LAG:
        yaw += att.yawspeed * (p.ms - att.ms) / 1000.0
    yaw = math.remainder(yaw, 2.0 * math.pi)
    speed = p.vx * math.cos(yaw) + p.vy * math.sin(yaw)  # signed: on the heading
    # x_enu = y_ned, y_enu = x_ned; theta = pi/2 - yaw, in [-pi/2, 3pi/2]: the station's MPC is not robust to the jump
    # a wrap to [-pi, pi] puts at a westward heading (the mavlink demo drifts off its S-path with it)
    return Pose(p.stamp, p.y, p.x, math.pi / 2 - yaw, speed, -att.yawspeed)


class PoseBuilder:
    """Pairs each position with the ATTITUDE at or after its vehicle time (usually in the same burst); a position
    that none follows before the next position gets the last heading carried forward."""

    def __init__(self) -> None:
        self.att: Attitude | None = None
        self.prev: Attitude | None = None  # the ATTITUDE before ``att``
        self.pending: Position | None = None  # a position waiting for the ATTITUDE at or after its time

    def position(self, p: Position) -> list[Pose]:
        """The poses a new position completes (the one held back, itself when its heading is known)."""
        out: list[Pose] = []
        if self.pending is not None and self.att is not None:
            out.append(enu_pose(self.pending, self.att, self.prev))  # no ATTITUDE came after it: carried forward
        self.pending = None
        if self.att is not None and self.att.ms >= p.ms:
            out.append(enu_pose(p, self.att, self.prev))
        else:
            self.pending = p
        return out

    def attitude(self, att: Attitude) -> list[Pose]:
        """The pose a new ATTITUDE completes (the position waiting for it), if any."""
        self.prev, self.att = self.att, att
        if self.pending is not None and att.ms >= self.pending.ms:
            p, self.pending = self.pending, None
            return [enu_pose(p, att, self.prev)]
        return []

    def reset(self) -> None:
        """Forget every time of the vehicle's old clock (it rebooted)."""
        self.att, self.prev, self.pending = None, None, None
