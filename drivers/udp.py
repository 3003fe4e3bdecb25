"""UDP shim link for small microcontroller robots: MessagePack datagrams of the same msgspec structs.

The driver sends :class:`bridge.wire.Command` datagrams (its own increasing ``seq``) to the robot; the robot
answers with :class:`bridge.wire.LearnerState` datagrams carrying the robot's own ``seq``. Every datagram is
decoded and validated; malformed ones are counted and dropped, duplicated or reordered states (seq not above the
last one) are dropped, and gaps in the robot's sequence are counted. The robot stops on its own watchdog when
commands stop (see :mod:`sim_learner.udp_robot`).

Configuration: :class:`bridge.config.UdpLinkConfig` (``[link.udp]`` in the driver host's file).
"""

from __future__ import annotations

import socket
import time

from bridge import wire as M
from bridge.config import UdpLinkConfig
from drivers.base import DriverError, LinkHealth, Pose


class UdpDriver:
    """The UDP shim behind the :class:`drivers.base.Driver` protocol (see the module docstring)."""

    name = "udp"

    def __init__(self, config: UdpLinkConfig) -> None:
        self.config = config
        self.robot = (config.robot_host, config.robot_port)
        self.bind = (config.bind_host, config.bind_port)
        self.open_timeout = config.open_timeout
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
        self._health.connected = self._health.ok = True
        self._health.text = "ready"
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

    def clear_faults(self, now: float) -> None:
        """Nothing to clear on this link (see :meth:`drivers.base.Driver.clear_faults`)."""

    def close(self) -> None:
        if self.sock is None:
            return
        try:
            self.stop(time.monotonic())
        finally:
            self.sock.close()
            self.sock = None
            self._health.connected = self._health.ok = False
            self._health.text = "closed"
