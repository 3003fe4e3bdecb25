"""Emulated ODrive-style motor controllers of a differential-drive learner, answering on a python-can bus.

Two axes behave like ODrive 0.6 CANSimple devices: a periodic Heartbeat (axis error, axis state), Set_Axis_State
(idle / closed loop), Set_Input_Vel honoured only in closed loop and feeding a watchdog (no set-point within
``watchdog`` s -> velocity zero, AxisError WATCHDOG_TIMER_EXPIRED, back to idle, as ODrive does), Estop, Clear_Errors,
and encoder estimates sent cyclically (and on a remote request). Malformed frames are counted and ignored.

The wheel set-points become a body command for the :class:`sim_learner.vehicle.SimVehicle` (the learner's degraded
dynamics), and the body's real motion drives the encoder counts.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import can

from drivers.can import AXIS_ERROR_WATCHDOG, AXIS_STATE_CLOSED_LOOP, AXIS_STATE_IDLE, decode, encode
from sim_learner.device import ThreadedDevice
from sim_learner.vehicle import SimVehicle


@dataclass
class _EcuAxis:
    node: int
    sign: float
    state: int = AXIS_STATE_IDLE
    error: int = 0
    setpoint: float = 0.0  # rev/s
    last_cmd: float = -math.inf
    pos: float = 0.0  # rev
    vel: float = 0.0  # rev/s


class DiffDriveEcus(ThreadedDevice):
    """Both wheels' controllers on one bus, driving a SimVehicle (see the module docstring)."""

    thread_name = "odrive-ecus"

    def __init__(self, bus_kwargs: dict[str, Any], vehicle: SimVehicle, *, left_node: int = 0, right_node: int = 1,
                 left_sign: float = 1.0, right_sign: float = -1.0, wheel_radius: float = 0.1,
                 track_width: float = 0.4, watchdog: float = 0.5, encoder_period: float = 0.01,
                 heartbeat_period: float = 0.1, clock=time.monotonic) -> None:
        super().__init__()
        self.bus_kwargs = dict(bus_kwargs)
        self.vehicle = vehicle
        self.axes = {left_node: _EcuAxis(left_node, left_sign), right_node: _EcuAxis(right_node, right_sign)}
        self.left, self.right = self.axes[left_node], self.axes[right_node]
        self.radius, self.track = float(wheel_radius), float(track_width)
        self.watchdog, self.encoder_period, self.heartbeat_period = watchdog, encoder_period, heartbeat_period
        self.clock = clock
        self.malformed = 0
        self.received: list[tuple[float, int, str, dict]] = []  # (time, node, name, signals), last 1000
        self._lock = threading.Lock()
        self.bus: can.BusABC | None = None

    def _open(self) -> None:
        self.bus = can.Bus(**self.bus_kwargs)

    def _close(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    # ------------------------------------------------------------------------------------------------ loop
    def _run(self) -> None:
        assert self.bus is not None
        t_enc = t_hb = self.clock()
        while not self._stop.is_set():
            frame = self.bus.recv(timeout=0.002)
            now = self.clock()
            if frame is not None:
                self._handle(frame, now)
            self._watchdog(now)
            if now >= t_enc:
                self._integrate(now)
                for ax in self.axes.values():
                    self._send(encode(ax.node, "Get_Encoder_Estimates", {"Pos_Estimate": ax.pos,
                                                                         "Vel_Estimate": ax.vel}))
                t_enc = now + self.encoder_period
            if now >= t_hb:
                for ax in self.axes.values():
                    self._send(encode(ax.node, "Heartbeat", {"Axis_Error": ax.error, "Axis_State": ax.state,
                                                             "Procedure_Result": 0, "Trajectory_Done_Flag": 1}))
                t_hb = now + self.heartbeat_period

    def _handle(self, frame: can.Message, now: float) -> None:
        try:
            node, name, sig = decode(frame)
        except ValueError:
            self.malformed += 1
            return
        ax = self.axes.get(node)
        if ax is None:
            return
        with self._lock:
            self.received.append((now, node, name, sig))
            del self.received[:-1000]
        if name == "Set_Input_Vel":
            if ax.state == AXIS_STATE_CLOSED_LOOP:
                ax.setpoint = float(sig["Input_Vel"])
                ax.last_cmd = now
                self._apply(now)
        elif name == "Set_Axis_State":
            req = int(sig["Axis_Requested_State"])
            if req == AXIS_STATE_CLOSED_LOOP and ax.error == 0:
                ax.state = AXIS_STATE_CLOSED_LOOP
                ax.last_cmd = now  # the watchdog starts counting when the axis is armed
            elif req == AXIS_STATE_IDLE:
                ax.state, ax.setpoint = AXIS_STATE_IDLE, 0.0
                self._apply(now)
        elif name == "Clear_Errors":
            ax.error = 0
        elif name == "Estop":
            ax.state, ax.setpoint, ax.error = AXIS_STATE_IDLE, 0.0, ax.error | 0x40  # ESTOP_REQUESTED
            self._apply(now)
        elif name == "Get_Encoder_Estimates" and sig.get("_rtr"):
            self._integrate(now)
            self._send(encode(ax.node, "Get_Encoder_Estimates", {"Pos_Estimate": ax.pos, "Vel_Estimate": ax.vel}))

    def _watchdog(self, now: float) -> None:
        tripped = False
        for ax in self.axes.values():
            if ax.state == AXIS_STATE_CLOSED_LOOP and now - ax.last_cmd > self.watchdog:
                ax.state, ax.setpoint, ax.error = AXIS_STATE_IDLE, 0.0, ax.error | AXIS_ERROR_WATCHDOG
                tripped = True
        if tripped:
            self._apply(now)

    def _apply(self, now: float) -> None:
        """Wheel set-points -> body command of the learner (a held wheel stops the body)."""
        circ = 2.0 * math.pi * self.radius
        if self.left.state != AXIS_STATE_CLOSED_LOOP or self.right.state != AXIS_STATE_CLOSED_LOOP:
            self.vehicle.stop(now)
            return
        vl = self.left.setpoint * self.left.sign * circ
        vr = self.right.setpoint * self.right.sign * circ
        self.vehicle.command(0.5 * (vl + vr), (vr - vl) / self.track, now)

    def _integrate(self, now: float) -> None:
        """Encoder counts follow the body's real motion (the learner's response, not the set-point): each wheel's
        travel is the body's path length -/+ its heading change times half the track."""
        st = self.vehicle.advance(now)
        circ = 2.0 * math.pi * self.radius
        turn = (st.theta - self.vehicle.theta0) * self.track / 2.0
        self.left.pos = self.left.sign * (self.vehicle.distance - turn) / circ
        self.right.pos = self.right.sign * (self.vehicle.distance + turn) / circ
        self.left.vel = self.left.sign * (st.v - st.omega * self.track / 2.0) / circ
        self.right.vel = self.right.sign * (st.v + st.omega * self.track / 2.0) / circ

    def _send(self, frame: can.Message) -> None:
        if self.bus is None:
            return
        with contextlib.suppress(can.CanError):
            self.bus.send(frame, timeout=0.05)

    def last(self, name: str, node: int) -> dict | None:
        """The last received frame ``name`` from the driver for ``node`` (tests and benchmarks)."""
        with self._lock:
            for _, n, nm, sig in reversed(self.received):
                if n == node and nm == name:
                    return sig
        return None
