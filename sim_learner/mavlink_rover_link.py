"""The emulated rover's transport (:mod:`sim_learner.mavlink_rover`).

``udp``: answers the last peer it heard from, like a telemetry bridge (pymavlink udpin). ``tcp``: like
SITL's TCP serial port (libraries/AP_HAL_SITL/UARTDriver.cpp): one client at a time, the next accepted when it
leaves; bytes move from the socket into a read buffer whenever they arrive, but the GCS code parses that buffer only
at its scheduler tick (``GCS::update_receive``, 400 Hz in Rover/Rover.cpp) and only while the port is connected, and
EOF marks the port disconnected at once. So a command that arrives just before its sender closes the socket is
never handled (a disarm sent by a driver that closes without waiting for the ACK).
"""

from __future__ import annotations

import socket
import threading
import time
from typing import Any


class Tx:
    """The file pymavlink's encoder writes to: the rover's transport."""

    def __init__(self, rover: Any) -> None:
        self.rover = rover

    def write(self, data: bytes) -> None:
        self.rover._transmit(bytes(data))


class LinkMixin:
    """The rover's socket: udp (the last peer heard) or tcp (one client at a time, as SITL's serial port)."""

    host: str
    port: int
    transport: str
    blackout: bool
    dropped_on_disconnect: int
    t0: float
    _tx_lock: threading.Lock
    _rx: bytearray
    _sock: socket.socket | None
    _client: socket.socket | None
    _peer: tuple[str, int] | None

    def _open(self) -> None:
        if self.transport == "udp":
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        else:
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as SITL: a restarted vehicle rebinds at once
        s.bind((self.host, self.port))
        if self.transport == "tcp":
            s.listen(5)
        s.setblocking(False)
        self._sock = s
        self.port = s.getsockname()[1]
        self.t0 = time.monotonic()

    def _close(self) -> None:
        for s in (self._client, self._sock):
            if s is not None:
                s.close()
        self._client = self._sock = None

    @property
    def connected(self) -> bool:
        """tcp: a client is connected; udp: a peer has been heard."""
        return self._client is not None if self.transport == "tcp" else self._peer is not None

    def _transmit(self, data: bytes) -> None:
        if self.blackout:
            return
        with self._tx_lock:
            try:
                if self.transport == "tcp":
                    if self._client is not None:
                        self._client.sendall(data)
                elif self._peer is not None and self._sock is not None:
                    self._sock.sendto(data, self._peer)
            except OSError:
                pass  # the peer went away; the receive side notices

    def _drain(self) -> None:
        """The serial driver's timer: move what arrived into the read buffer; accept/notice tcp clients."""
        if self._sock is None:
            return
        if self.transport == "udp":
            while True:
                try:
                    data, addr = self._sock.recvfrom(65536)
                except (BlockingIOError, InterruptedError):
                    return
                except OSError:  # ICMP port unreachable from a peer that left
                    continue
                if not self.blackout:
                    self._peer = addr
                    self._rx += data
        if self._client is None:
            try:
                self._client, _ = self._sock.accept()
                self._client.setblocking(False)
                self._client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except (BlockingIOError, InterruptedError):
                return
        while self._client is not None:
            try:
                data = self._client.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                data = b""
            if not data:  # EOF: the port is disconnected now; what is still in the buffer is not parsed
                self.dropped_on_disconnect += len(self._rx)
                self._rx.clear()  # (SITL keeps it for the next client; it is never parsed for this one)
                with self._tx_lock:
                    self._client.close()
                    self._client = None
                return
            if not self.blackout:
                self._rx += data

    def _fds(self) -> list[socket.socket]:
        return [s for s in (self._sock, self._client) if s is not None]


__all__ = ["LinkMixin", "Tx"]
