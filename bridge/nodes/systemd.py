"""systemd's readiness protocol (``Type=notify``): a service says READY=1 once it is really up (its session open,
its link ready or waiting with a reason), STATUS=... whenever what it waits for changes, and STOPPING=1 when it
stops. Without ``$NOTIFY_SOCKET`` (not under systemd) every call does nothing."""

from __future__ import annotations

import os
import socket


def notify(*fields: str) -> bool:
    """Send ``fields`` (``"READY=1"``, ``"STATUS=waiting for the vehicle"``) to systemd; False if there is no
    notify socket or it cannot be reached (never raises: readiness is advice, not a reason to stop)."""
    path = os.environ.get("NOTIFY_SOCKET")
    if not path:
        return False
    if path.startswith("@"):  # an abstract socket
        path = "\0" + path[1:]
    data = "\n".join(f.replace("\n", " ") for f in fields).encode()
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(path)
            s.sendall(data)
    except OSError:
        return False
    return True


def ready(status: str = "") -> bool:
    """The service is up (``READY=1``), with an optional one-line status."""
    return notify("READY=1", *([f"STATUS={status}"] if status else []))


def status(text: str) -> bool:
    """What the service is doing or waiting for, shown by ``systemctl status``."""
    return notify(f"STATUS={text}")


def stopping() -> bool:
    return notify("STOPPING=1")
