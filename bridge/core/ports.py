"""A free local port for the processes the tests and the demo start on loopback (never a fixed port).

Asking the OS for port 0 hands out a port of the kernel's ephemeral range (``net.ipv4.ip_local_port_range``), and the
caller closes that socket so that the process it is for can bind the port later. Until then the kernel may hand the
same port out again to anyone who asks for port 0 or opens an outgoing connection (a Zenoh session's, a UDP robot's
own socket), and the later bind fails with "Address already in use". A port below that range is only ever taken by
an explicit bind: :func:`free_port` draws one there at random and checks that it binds now.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

#: where Linux says which ports it hands out for port 0 and outgoing connections
EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
#: the lowest port drawn (below it: well-known and registered services' ports, more often bound on a lab machine)
LOWEST = 10000
#: ports tried below the ephemeral range before asking the OS for one of that range after all
TRIES = 64

_draw = random.SystemRandom()  # not the random module's: a test that seeds it must not make two processes agree


def ephemeral_low(path: Path = EPHEMERAL_RANGE) -> int:
    """The lowest port of the kernel's ephemeral range (32768, Linux's default, where it cannot be read)."""
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_port(host: str = "127.0.0.1", kind: socket.SocketKind = socket.SOCK_STREAM) -> int:
    """A port of ``kind`` (TCP or UDP) that binds on ``host`` right now, below the ephemeral range where that range
    leaves room (the module docstring); one of the ephemeral range, from the OS, where it does not."""
    top = ephemeral_low()
    if top - LOWEST >= 1000:
        for _ in range(TRIES):
            port = _draw.randrange(LOWEST, top)
            with socket.socket(socket.AF_INET, kind) as s:
                try:
                    s.bind((host, port))
                except OSError:
                    continue
                return port
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


__all__ = ["EPHEMERAL_RANGE", "LOWEST", "ephemeral_low", "free_port"]
