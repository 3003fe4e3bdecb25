"""CAN link: a differential-drive base with one ODrive-style CANSimple motor controller per wheel.

Frames as ODrive firmware 0.6.x defines them, from ``odrive_cansimple.dbc`` (node 0 layout; the node offset is
added at run time: arbitration id = node_id << 5 | cmd_id, 11-bit, little endian, IEEE float32). The driver puts
both axes in closed-loop velocity control, turns (v, omega) into wheel turn rates with the wheel radius and track
width, and integrates odometry from the encoder estimates the controllers send.

Configuration: :class:`bridge.config.CanLinkConfig` (``[link.can]`` in the driver host's file).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from importlib import resources
from typing import Any

import can
import cantools

from bridge.config import CanLinkConfig
from drivers.base import DriverError, LinkHealth, Pose

AXIS_STATE_IDLE = 1
AXIS_STATE_CLOSED_LOOP = 8
AXIS_ERROR_WATCHDOG = 0x800  # ODrive 0.6 AxisError.WATCHDOG_TIMER_EXPIRED

_DB: cantools.database.can.Database | None = None


def database() -> cantools.database.can.Database:
    """The shipped CANSimple DBC (loaded once)."""
    global _DB
    if _DB is None:
        text = resources.files("drivers").joinpath("odrive_cansimple.dbc").read_text()
        _DB = cantools.database.load_string(text, database_format="dbc")
    return _DB


def encode(node: int, name: str, signals: dict[str, float] | None = None) -> can.Message:
    """A CANSimple frame for ``node`` (0..63)."""
    if not 0 <= node < 64:
        raise ValueError(f"CANSimple node id must be 0..63, got {node}")
    msg = database().get_message_by_name(name)
    data = msg.encode(signals or {}) if msg.signals else b""
    return can.Message(arbitration_id=(node << 5) | msg.frame_id, data=data, is_extended_id=False)


def decode(frame: can.Message) -> tuple[int, str, dict[str, Any]]:
    """(node, message name, signals) of a CANSimple frame; ValueError for anything that is not one."""
    if frame.is_extended_id or frame.is_error_frame:
        raise ValueError("not a CANSimple frame (extended id or error frame)")
    node, cmd = frame.arbitration_id >> 5, frame.arbitration_id & 0x1F
    try:
        msg = database().get_message_by_frame_id(cmd)
    except KeyError:
        raise ValueError(f"unknown CANSimple command 0x{cmd:02x}") from None
    if frame.is_remote_frame:
        return node, msg.name, {"_rtr": True}
    if len(frame.data) != msg.length:
        raise ValueError(f"{msg.name}: {len(frame.data)} data bytes, expected {msg.length}")
    sig = msg.decode(bytes(frame.data), decode_choices=False) if msg.signals else {}
    for k, v in sig.items():
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{msg.name}.{k} is not finite")
    return node, msg.name, dict(sig)


@dataclass
class _Axis:
    node: int
    sign: float
    state: int = 0
    error: int = 0
    pos: float | None = None  # rev
    vel: float = 0.0  # rev/s
    fresh: bool = False


class CanDriver:
    """The CAN link behind the :class:`drivers.base.Driver` protocol (see the module docstring)."""

    name = "can"

    def __init__(self, config: CanLinkConfig) -> None:
        self.config = config
        self.interface, self.channel, self.bitrate = config.interface, config.channel, config.bitrate
        self.radius, self.track = config.wheel_radius, config.track_width
        self.left = _Axis(config.left_node, config.left_sign)
        self.right = _Axis(config.right_node, config.right_sign)
        self.open_timeout = config.open_timeout
        self.pose = [float(a) for a in config.initial_pose]
        self.bus: can.BusABC | None = None
        self._health = LinkHealth()

    # ----------------------------------------------------------------------------------------------- link
    def open(self, now: float) -> None:
        kwargs: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.interface == "socketcan":
            pass  # the bitrate of a SocketCAN device is set with `ip link`, not here
        elif self.interface == "udp_multicast":
            kwargs["fd"] = self.config.fd
        else:
            kwargs["bitrate"] = self.bitrate
        try:
            self.bus = can.Bus(**kwargs)
        except (can.CanError, OSError, ValueError) as exc:
            raise DriverError(f"cannot open CAN bus {self.interface}:{self.channel}: {exc}") from exc
        for ax in (self.left, self.right):
            self._send(encode(ax.node, "Clear_Errors", {"Identify": 0}))
            self._send(encode(ax.node, "Set_Axis_State", {"Axis_Requested_State": AXIS_STATE_CLOSED_LOOP}))
        self._health.connected = True
        self._wait_ready()

    def _wait_ready(self) -> None:
        """Block (at most ``open_timeout``) until both axes report closed-loop control in their heartbeats."""
        t_end = time.monotonic() + self.open_timeout
        while time.monotonic() < t_end:
            self.poll(time.monotonic(), block=0.02)
            if self.left.state == AXIS_STATE_CLOSED_LOOP and self.right.state == AXIS_STATE_CLOSED_LOOP:
                self._health.ok, self._health.text = True, "ready"
                return
        raise DriverError(f"motor controllers not in closed loop after {self.open_timeout} s "
                          f"(left state {self.left.state} error 0x{self.left.error:x}, "
                          f"right state {self.right.state} error 0x{self.right.error:x})")

    def wheel_turn_rates(self, v: float, omega: float) -> tuple[float, float]:
        """(left, right) Input_Vel in rev/s for body speed v (m/s) and yaw rate omega (rad/s), signs applied."""
        vl = v - omega * self.track / 2.0
        vr = v + omega * self.track / 2.0
        k = 1.0 / (2.0 * math.pi * self.radius)
        return self.left.sign * vl * k, self.right.sign * vr * k

    def send(self, v: float, omega: float, now: float) -> None:
        ql, qr = self.wheel_turn_rates(v, omega)
        if self.left.state != AXIS_STATE_CLOSED_LOOP or self.right.state != AXIS_STATE_CLOSED_LOOP:
            # an axis fell out of closed loop (its watchdog, an error): clear and re-arm it
            for ax in (self.left, self.right):
                if ax.state != AXIS_STATE_CLOSED_LOOP:
                    self._send(encode(ax.node, "Clear_Errors", {"Identify": 0}))
                    self._send(encode(ax.node, "Set_Axis_State", {"Axis_Requested_State": AXIS_STATE_CLOSED_LOOP}))
        self._send(encode(self.left.node, "Set_Input_Vel", {"Input_Vel": ql, "Input_Torque_FF": 0.0}))
        self._send(encode(self.right.node, "Set_Input_Vel", {"Input_Vel": qr, "Input_Torque_FF": 0.0}))

    def stop(self, now: float) -> None:
        if self.bus is None:
            return
        for ax in (self.left, self.right):
            self._send(encode(ax.node, "Set_Input_Vel", {"Input_Vel": 0.0, "Input_Torque_FF": 0.0}))

    def poll(self, now: float, block: float = 0.0) -> list[Pose]:
        if self.bus is None:
            return []
        out: list[Pose] = []
        timeout = block
        while True:
            frame = self.bus.recv(timeout=timeout)
            timeout = 0.0
            if frame is None:
                break
            self._health.frames_received += 1
            try:
                node, name, sig = decode(frame)
            except ValueError:
                self._health.malformed += 1
                continue
            ax = self.left if node == self.left.node else self.right if node == self.right.node else None
            if ax is None or sig.get("_rtr"):
                continue
            if name == "Heartbeat":
                ax.state, ax.error = int(sig["Axis_State"]), int(sig["Axis_Error"])
            elif name == "Get_Encoder_Estimates":
                pose = self._encoder(ax, float(sig["Pos_Estimate"]), float(sig["Vel_Estimate"]), now)
                if pose is not None:
                    out.append(pose)
        return out

    def _encoder(self, ax: _Axis, pos: float, vel: float, now: float) -> Pose | None:
        if ax.pos is None:
            ax.pos, ax.vel = pos, vel
            return None
        ax.fresh = True
        ax._new = (pos, vel)  # type: ignore[attr-defined]
        if not (self.left.fresh and self.right.fresh):
            return None
        # both wheels have a new estimate: one odometry step (midpoint heading)
        circ = 2.0 * math.pi * self.radius
        (pl, vl_), (pr, vr_) = self.left._new, self.right._new  # type: ignore[attr-defined]
        dl = (pl - self.left.pos) * circ * self.left.sign
        dr = (pr - self.right.pos) * circ * self.right.sign
        self.left.pos, self.right.pos = pl, pr
        self.left.vel, self.right.vel = vl_, vr_
        self.left.fresh = self.right.fresh = False
        ds = 0.5 * (dl + dr)
        dth = (dr - dl) / self.track
        x, y, th = self.pose
        x += ds * math.cos(th + 0.5 * dth)
        y += ds * math.sin(th + 0.5 * dth)
        th += dth
        self.pose = [x, y, th]
        v = 0.5 * circ * (vl_ * self.left.sign + vr_ * self.right.sign)
        w = circ * (vr_ * self.right.sign - vl_ * self.left.sign) / self.track
        return Pose(now, x, y, th, v, w)

    def _send(self, frame: can.Message) -> None:
        assert self.bus is not None
        try:
            self.bus.send(frame, timeout=0.05)
            self._health.frames_sent += 1
        except can.CanError:
            self._health.errors += 1

    def health(self) -> LinkHealth:
        self._health.detail = {"left_state": self.left.state, "right_state": self.right.state,
                               "left_error": self.left.error, "right_error": self.right.error}
        return self._health

    def clear_faults(self, now: float) -> None:
        for ax in (self.left, self.right):
            self._send(encode(ax.node, "Clear_Errors", {"Identify": 0}))
            self._send(encode(ax.node, "Set_Axis_State", {"Axis_Requested_State": AXIS_STATE_CLOSED_LOOP}))

    def close(self) -> None:
        if self.bus is None:
            return
        try:
            self.stop(0.0)
            for ax in (self.left, self.right):
                self._send(encode(ax.node, "Set_Axis_State", {"Axis_Requested_State": AXIS_STATE_IDLE}))
        finally:
            self.bus.shutdown()
            self.bus = None
            self._health.connected = self._health.ok = False
            self._health.text = "closed"

