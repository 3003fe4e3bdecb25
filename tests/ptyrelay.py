"""A serial port for SITL: a pseudo-terminal pair whose far end is SITL's TCP port, so that a program opens
``/dev/pts/N`` at a baud rate as it opens a telemetry radio's ``/dev/ttyUSB0`` (pyserial, termios and all).

What it relays is bytes, as a radio does, and like a radio it drops what nobody reads: a write to the terminal that
would block (its buffer full, the port not opened yet) is dropped, never waited on. Bounded: :meth:`PtyRelay.close`
stops the thread and closes both ends and the socket. Traffic only on 127.0.0.1.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import threading
import tty


class PtyRelay:
    """``PtyRelay(port)``: a pseudo-terminal (:attr:`path`) relayed to TCP ``127.0.0.1:port`` (a SITL serial port)."""

    def __init__(self, port: int, timeout: float = 5.0) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
        self.sock.setblocking(False)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no line editing before the opener sets its own mode (pyserial: raw too)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.dropped = 0  # bytes from the vehicle nobody read in time (a radio drops them too)
        self.relayed = [0, 0]  # bytes vehicle -> port, port -> vehicle
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pty-relay", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.master, self.sock], [], [], 0.1)
            except (OSError, ValueError):
                return
            for src in ready:
                try:
                    data = self.sock.recv(4096) if src is self.sock else os.read(self.master, 4096)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:  # EIO: nobody holds the port open right now; the vehicle closed: stop
                    if src is self.sock:
                        return
                    data = b""
                    continue
                if src is self.sock:
                    if not data:
                        return
                    try:
                        n = os.write(self.master, data)
                    except BlockingIOError:
                        n = 0
                    self.relayed[0] += n
                    self.dropped += len(data) - n
                elif data:
                    with contextlib.suppress(BlockingIOError):
                        self.sock.sendall(data)
                        self.relayed[1] += len(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        with contextlib.suppress(OSError):
            self.sock.close()

    def __enter__(self) -> PtyRelay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
