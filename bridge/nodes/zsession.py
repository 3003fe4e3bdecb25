"""Opening Zenoh sessions the way this project needs them (docs/ARCHITECTURE.md section 8).

Every endpoint is explicit (the defaults listen on all interfaces and scout by multicast), multicast scouting
is off, and connect retries are short so a late peer is found in ~0.1 s. Always use the session as a context
manager (or close it in ``finally``): a process that exits with a callback subscriber still declared hangs.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Sequence
from pathlib import Path

import zenoh


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port the OS says is free right now on ``host`` (for tests and the demo; never a fixed port)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def tcp(port: int, host: str = "127.0.0.1") -> str:
    """The Zenoh endpoint string ``tcp/<host>:<port>``."""
    return f"tcp/{host}:{port}"


def make_config(
    *,
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: str | Path | None = None,
) -> zenoh.Config:
    """A Zenoh config: from ``config_file`` when given (a lab's deploy/ file), else loopback-safe defaults.

    ``listen``/``connect`` given here override the file's endpoints, so one deploy file can serve several
    processes that differ only in their ports.
    """
    if mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode must be peer, client or router, not {mode!r}")
    if config_file is not None:
        conf = zenoh.Config.from_file(str(config_file))
        if "shared_memory" not in Path(config_file).read_text():  # off unless the lab's file says otherwise
            conf.insert_json5("transport/shared_memory/enabled", "false")
    else:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
        # No shared-memory transport (docs/ARCHITECTURE.md, section 8): each same-machine sender's 16 MiB pool stayed
        # mapped in the receiver after the sender closed (a driver host: 66 -> 153 MB over four senders).
        conf.insert_json5("transport/shared_memory/enabled", "false")
        # Retry quickly: a peer started a moment later is found in ~0.1 s instead of seconds.
        conf.insert_json5("connect/retry", json.dumps({"period_init_ms": 50, "period_max_ms": 500}))
        return conf
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return conf


def open_session(conf: zenoh.Config) -> zenoh.Session:
    """Open a session (use it as ``with open_session(conf) as s:``)."""
    return zenoh.open(conf)
