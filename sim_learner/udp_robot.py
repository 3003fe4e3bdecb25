"""An emulated UDP-shim robot: a microcontroller that takes Command datagrams and streams LearnerState datagrams.

Like the firmware it stands in for, it drops commands that do not decode or validate (counted), that are not newer
than the last one (sequence numbers), and stops on its own watchdog when no command arrives for ``watchdog`` s. It
streams its pose at ``rate`` Hz to whoever sent the last valid command. The body is a
:class:`sim_learner.vehicle.SimVehicle` (the learner's degraded dynamics).
"""

from __future__ import annotations

import socket
import time

from bridge import wire as M
from sim_learner.device import ThreadedDevice
from sim_learner.vehicle import SimVehicle


class UdpRobot(ThreadedDevice):
    """See the module docstring. ``port`` 0 picks a free port (read ``.port`` after ``start``)."""

    thread_name = "udp-robot"

    def __init__(self, vehicle: SimVehicle, host: str = "127.0.0.1", port: int = 0, *, watchdog: float = 0.5,
                 rate: float = 50.0) -> None:
        super().__init__()
        self.vehicle = vehicle
        self.addr = (host, int(port))
        self.watchdog = float(watchdog)
        self.period = 1.0 / float(rate)
        self.malformed = 0
        self.dropped_old = 0
        self.last_cmd: M.Command | None = None
        self.last_cmd_time = -float("inf")
        self.peer: tuple[str, int] | None = None
        self.port = 0
        self._seq = 0
        self.sock: socket.socket | None = None

    def _open(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(self.addr)
        self.sock.settimeout(0.005)
        self.port = self.sock.getsockname()[1]

    def _close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    def _run(self) -> None:
        assert self.sock is not None
        t_next = time.monotonic()
        moving = False
        while not self._stop.is_set():
            try:
                data, src = self.sock.recvfrom(65536)
            except TimeoutError:
                data = None
            except OSError:
                break
            now = time.monotonic()
            if data is not None:
                try:
                    cmd = M.decode(data, M.Command)
                except M.MessageError:
                    self.malformed += 1
                    cmd = None
                if cmd is not None:
                    if self.last_cmd is not None and cmd.seq <= self.last_cmd.seq and src == self.peer:
                        self.dropped_old += 1
                    else:
                        self.peer, self.last_cmd, self.last_cmd_time = src, cmd, now
                        if cmd.method == "stop" or (cmd.v == 0.0 and cmd.omega == 0.0):
                            self.vehicle.stop(now)
                            moving = False
                        else:
                            self.vehicle.command(cmd.v, cmd.omega, now)
                            moving = True
            if moving and now - self.last_cmd_time > self.watchdog:
                self.vehicle.stop(now)  # the firmware's own watchdog
                moving = False
            if now >= t_next and self.peer is not None:
                x, y, th = self.vehicle.measured_pose(now)
                st = self.vehicle.state
                msg = M.LearnerState(stamp=now, seq=self._seq, x=x, y=y, theta=th, v=st.v, omega=st.omega,
                                     source="udp-robot")
                self._seq += 1
                try:
                    self.sock.sendto(M.encode(msg), self.peer)
                except OSError:
                    pass
                t_next = now + self.period
