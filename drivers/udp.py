"""UDP shim link for small microcontroller robots: MessagePack datagrams of the same msgspec structs.

The driver sends :class:`bridge.messages.Command` datagrams (its own increasing ``seq``) to the robot; the robot
answers with :class:`bridge.messages.LearnerState` datagrams carrying the robot's own ``seq``. Every datagram is
decoded and validated; malformed ones are counted and dropped, duplicated or reordered states (seq not above the
last one) are dropped, and gaps in the robot's sequence are counted. The robot stops on its own watchdog when
commands stop (see :mod:`sim_learner.udp_robot`).

Config keys (``[link.udp]``): robot_host, robot_port, bind_host (default 127.0.0.1), bind_port (0: any free),
open_timeout (s).
"""

from __future__ import annotations

import socket
import time
from typing import Any

from bridge import messages as M
from drivers.base import DriverError, LinkHealth, Pose


class UdpDriver:
    """The UDP shim behind the :class:`drivers.base.Driver` protocol (see the module docstring)."""

    name = "udp"

    def __init__(self, config: dict[str, Any]) -> None:
        self.robot = (str(config.get("robot_host", "127.0.0.1")), int(config.get("robot_port", 47800)))
        self.bind = (str(config.get("bind_host", "127.0.0.1")), int(config.get("bind_port", 0)))
        self.open_timeout = float(config.get("open_timeout", 2.0))
        self.sock: socket.socket | None = None
        self.seq = 0
        self.last_state_seq = -1
        self.gaps = 0
        self.out_of_order = 0
        self._health = LinkHealth()

    def open(self, now: float) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(self.bind)
        self.sock.setblocking(False)
        self._health.connected = True
        t_end = time.monotonic() + self.open_timeout
        while time.monotonic() < t_end:
            self.stop(time.monotonic())  # a stop is also the hello that tells the robot where we are
            time.sleep(0.02)
            if self.poll(time.monotonic()):
                return
        raise DriverError(f"no state from the UDP robot at {self.robot[0]}:{self.robot[1]} "
                          f"within {self.open_timeout} s")

    def _send_cmd(self, v: float, omega: float, method: str, now: float) -> None:
        if self.sock is None:
            return
        self.seq += 1
        msg = M.Command(stamp=now, seq=self.seq, v=v, omega=omega, method=method, valid_ms=300)
        try:
            self.sock.sendto(M.encode(msg), self.robot)
            self._health.frames_sent += 1
        except OSError:
            self._health.errors += 1

    def send(self, v: float, omega: float, now: float) -> None:
        self._send_cmd(v, omega, "scm", now)

    def stop(self, now: float) -> None:
        self._send_cmd(0.0, 0.0, "stop", now)

    def poll(self, now: float) -> list[Pose]:
        out: list[Pose] = []
        if self.sock is None:
            return out
        while True:
            try:
                data, _ = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._health.errors += 1
                break
            self._health.frames_received += 1
            try:
                st = M.decode(data, M.LearnerState)
            except M.MessageError:
                self._health.malformed += 1
                continue
            if st.seq <= self.last_state_seq:
                self.out_of_order += 1
                continue
            if self.last_state_seq >= 0 and st.seq > self.last_state_seq + 1:
                self.gaps += st.seq - self.last_state_seq - 1
            self.last_state_seq = st.seq
            out.append(Pose(now, st.x, st.y, st.theta, st.v, st.omega))
        return out

    def health(self) -> LinkHealth:
        self._health.detail = {"state_gaps": self.gaps, "state_out_of_order": self.out_of_order}
        return self._health

    def close(self) -> None:
        if self.sock is None:
            return
        try:
            self.stop(time.monotonic())
        finally:
            self.sock.close()
            self.sock = None
            self._health.connected = False
