"""Two ODrive 0.6 controllers played by a test on a real python-can ``virtual`` bus and a fake clock
(``tests/fakeclock.py``): the CAN driver's unit tests and the driver host's timing tests drive them, so every step
happens at a time the test chose and nothing sleeps. The full emulated controllers on real time are
``sim_learner/can_ecu.py``'s."""

from __future__ import annotations

import can

from drivers.can import decode, encode
from drivers.odrive import AxisState
from tests.fakeclock import FakeClock

IDLE = AxisState.IDLE
HEARTBEAT_PERIOD = 0.1  # ODrive's default
ENCODER_PERIOD = 0.01  # s between two encoder estimates (a cyclic message at 100 Hz)


class Controllers:
    """Two ODrive 0.6 controllers (nodes 0 and 1) on a virtual bus. :meth:`step` (run at each reading of the fake
    clock) takes the frames the driver sent, answers as a 0.6 device does (closed loop on request unless an error is
    set, Clear_Errors clears it) and sends its Heartbeats when one is due on the fake clock or its state changed,
    stamped with the fake wall clock as a receiving interface would stamp them. ``encoders``: they also send their
    encoder estimates every :data:`ENCODER_PERIOD` (the wheels turn at the rate last asked for), the telemetry a
    driver host needs fresh to drive."""

    def __init__(self, channel: str, clock: FakeClock, encoders: bool = False) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.clock = clock
        self.state = {0: int(IDLE), 1: int(IDLE)}
        self.error = {0: 0, 1: 0}
        self.input_vel = {0: 0.0, 1: 0.0}
        self.mode = {0: (0, 0), 1: (0, 0)}
        self.muted: set[int] = set()
        self.received: list[tuple[int, str, dict]] = []
        self._due = -float("inf")
        self.encoders = encoders
        self.pos = {0: 0.0, 1: 0.0}
        self._enc_at = clock.t

    def step(self) -> None:
        changed = False
        while (f := self.bus.recv(timeout=0)) is not None:
            node, name, sig = decode(f)
            if node not in self.state or node in self.muted:
                continue
            self.received.append((node, name, sig))
            if name == "Set_Axis_State":
                want = int(sig["Axis_Requested_State"])
                self.state[node] = want if want == IDLE or not self.error[node] else self.state[node]
                changed = True
            elif name == "Clear_Errors":
                self.error[node], changed = 0, True
            elif name == "Set_Controller_Mode":
                self.mode[node] = (int(sig["Control_Mode"]), int(sig["Input_Mode"]))
            elif name == "Set_Input_Vel":
                self.input_vel[node] = float(sig["Input_Vel"])
        if changed or self.clock.t >= self._due:
            self.heartbeats()
        if self.encoders and self.clock.t >= self._enc_at + ENCODER_PERIOD:
            dt, self._enc_at = self.clock.t - self._enc_at, self.clock.t
            for node in self.state:
                turning = self.state[node] == int(AxisState.CLOSED_LOOP_CONTROL) and node not in self.muted
                vel = self.input_vel[node] if turning else 0.0
                self.pos[node] += vel * dt
                if node not in self.muted:
                    f = encode(node, "Get_Encoder_Estimates", {"Pos_Estimate": self.pos[node], "Vel_Estimate": vel})
                    f.timestamp = self.clock.wall()
                    self.bus.send(f)

    def heartbeats(self) -> None:
        self._due = self.clock.t + HEARTBEAT_PERIOD
        for node in self.state:
            if node not in self.muted:
                f = encode(node, "Heartbeat", {"Axis_Error": self.error[node], "Axis_State": self.state[node],
                                               "Procedure_Result": 0, "Trajectory_Done_Flag": 0})
                f.timestamp = self.clock.wall()
                self.bus.send(f)

    def fault(self, node: int, error: int) -> None:
        """The controller stops on its own (an error disarms it), and says so in its next Heartbeat."""
        self.error[node], self.state[node] = error, int(IDLE)

    def sent(self, name: str) -> list[tuple[int, dict]]:
        """What the driver sent of message ``name`` so far, and forget it."""
        out = [(n, s) for n, nm, s in self.received if nm == name]
        self.received = [r for r in self.received if r[1] != name]
        return out
