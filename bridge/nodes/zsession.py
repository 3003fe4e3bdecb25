"""Opening Zenoh sessions the way this project needs them (docs/ARCHITECTURE.md section 8).

Every endpoint is explicit (the defaults listen on all interfaces and scout by multicast), multicast scouting
is off, and connect retries are short so a late peer is found in ~0.1 s. Always use the session as a context
manager (or close it in ``finally``): a process that exits with a callback subscriber still declared hangs.
"""

from __future__ import annotations

import json
import logging
import os
import re
import socket
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

import zenoh

from bridge.core import ports
from bridge.core.backoff import Backoff
from bridge.core.clock import SYSTEM, Clock
from bridge.core.errors import UsageError
from bridge.core.paths import TEXT_FILE, read_bounded
from bridge.nodes import systemd, tlsid

log = logging.getLogger("scmbridge.zenoh")
H = TypeVar("H")


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on ``host`` for a Zenoh endpoint (for tests and the demo; never a fixed port), drawn
    where no outgoing connection takes it meanwhile (:func:`bridge.core.ports.free_port`)."""
    return ports.free_port(host, socket.SOCK_STREAM)


def tcp(port: int, host: str = "127.0.0.1") -> str:
    """The Zenoh endpoint string ``tcp/<host>:<port>``."""
    return f"tcp/{host}:{port}"


def config_error(text: str, limit: int = 300) -> str:
    """Zenoh's complaint about a config file as one line of at most ``limit`` characters, saying where.

    Zenoh's errors are multi-line parser reports (json5's ``--> 1:9`` with a caret under the line and ``= expected
    ...``) or a serde ``Message { msg: "...", location: Some(Location { line: 1, column: 3 }) }``, both ending in the
    Rust source file that raised them; an operator needs the message and the file's line and column.
    """
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?\s*$", "", text.strip())
    msg = re.search(r'msg: "(.*?)"(?:, location: Some\(Location \{ line: (\d+), column: (\d+))?', text, re.S)
    pest = re.search(r"-->\s*(\d+):(\d+)", text)
    if msg is not None:
        line = msg.group(1)
        if msg.group(2):
            line = f"line {msg.group(2)}, column {msg.group(3)}: {line}"
    elif pest is not None:
        said = [m.strip() for m in re.findall(r"^\s*=\s*(.+)$", text, re.M)]
        line = f"line {pest.group(1)}, column {pest.group(2)}: {'; '.join(said) or 'not JSON5'}"
    else:
        line = " ".join(part.strip() for part in text.splitlines() if part.strip())
    return line if len(line) <= limit else line[: limit - 3] + "..."


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
        try:  # a regular file of bounded size (a FIFO or /dev/zero would hang or fill the process)
            text = read_bounded(Path(config_file), TEXT_FILE).decode()
            conf = zenoh.Config.from_json5(text)
        except (zenoh.ZError, OSError, UnicodeDecodeError) as exc:
            raise UsageError(f"--zenoh-config {config_file}: {config_error(str(exc))}") from None
        safe_defaults(conf, text, mode)
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


def _states(text: str, name: str) -> bool:
    """Whether the lab's file names ``name`` (as a key, quoted or not, anywhere in it)."""
    return re.search(rf"(^|[^A-Za-z0-9_]){re.escape(name)}\s*[\"']?\s*:", text, re.MULTILINE) is not None


def safe_defaults(conf: zenoh.Config, text: str, mode: str) -> None:
    """What a lab's ``--zenoh-config`` file does not say gets the built-in configuration's safe values, not Zenoh's
    (a peer listening on every interface with multicast scouting on): client mode (a router's own file: router),
    no multicast scouting, no shared memory, and a peer listening on loopback only."""
    if not _states(text, "mode"):
        conf.insert_json5("mode", json.dumps("router" if mode == "router" else "client"))
    if not _states(text, "multicast"):
        conf.insert_json5("scouting/multicast/enabled", "false")
    if not _states(text, "shared_memory"):  # off unless the lab's file says otherwise
        conf.insert_json5("transport/shared_memory/enabled", "false")
    if not _states(text, "listen"):
        chosen = json.loads(conf.get_json("mode"))
        if chosen == "peer":  # (a router's file must name its endpoints: bridge/nodes/router.py refuses it)
            conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))


def _endpoints(conf: zenoh.Config) -> str:
    try:
        eps = json.loads(conf.get_json("connect/endpoints")) or json.loads(conf.get_json("listen/endpoints"))
    except Exception:  # a config without them (the defaults)
        eps = []
    return ", ".join(str(e) for e in eps) or "the Zenoh defaults"


#: what a node without TLS says at its start, and ``scmbridge doctor`` too: who may command the robot then
NO_TLS_WARNING = ("this Zenoh session has no TLS: anyone who can reach this Zenoh session — on the loopback default, "
                  "any user of this machine — may engage, start missions and release estops, and publish commands "
                  "(for the demo and tests only; a lab uses the TLS and access-control configuration `scmbridge "
                  "deploy` makes, deploy/README.md)")


def secured(conf: zenoh.Config) -> bool:
    """Whether the configuration speaks TLS only (mutual: a certificate of the lab's CA, checked by the router)."""
    try:
        protocols = json.loads(conf.get_json("transport/link/protocols")) or []
        tls = json.loads(conf.get_json("transport/link/tls")) or {}
    except Exception:  # keys the config does not have
        return False
    return protocols == ["tls"] and bool(tls.get("root_ca_certificate"))


def tls_file_problem(conf: zenoh.Config) -> str:
    """What is wrong with the TLS files a configuration names, in one line with the fix ("" when each is a readable
    file): Zenoh says only "Invalid TLS private key file: No such file or directory", without the file."""
    try:
        tls = json.loads(conf.get_json("transport/link/tls")) or {}
    except Exception:  # no TLS section
        return ""
    for key in ("root_ca_certificate", "listen_private_key", "listen_certificate", "connect_private_key",
                "connect_certificate"):
        path = tls.get(key)
        if not isinstance(path, str) or not path:
            continue
        p = Path(path)
        why = "no such file" if not p.exists() else "not a file" if not p.is_file() else (
            "not readable by this user" if not os.access(p, os.R_OK) else "")
        if why:
            return (f"TLS file {path} ({key}): {why}: install the lab's certificates there (deploy/README.md, step 2), "
                    "or make a lab that runs on this machine with its certificates where it is written: scmbridge "
                    "deploy lab --local --robots R --out DIR")
    return ""


def open_session(conf: zenoh.Config, wait: threading.Event | None = None, what: str = "") -> zenoh.Session:
    """Open a session (use it as ``with open_session(conf) as s:``).

    A tool (``wait`` None) tries once: a router that cannot be reached is one line (:class:`UsageError`). A service
    passes its stop event: it keeps trying with a backoff (0.1 s doubling to 5 s), logs once what it waits for and
    tells systemd, until it connects or ``wait`` is set (then :class:`UsageError` too: stopped while waiting). The
    same error covers a router that is down and one that refused this TLS identity (wrong address, an expired
    certificate): ``scmbridge doctor`` tells them apart; a certificate of another CA than the lab's is named as such
    (:func:`bridge.nodes.tlsid.refused_because`)."""
    backoff, said = Backoff(0.1, 5.0), ""
    problem = tls_file_problem(conf)
    if problem:  # no retry mends a missing file
        raise UsageError(f"{what}: {problem}" if what else problem)
    if what and not secured(conf):
        log.warning("%s: %s", what, NO_TLS_WARNING)
    while True:
        try:
            session = zenoh.open(conf)
            if wait is not None and _connects(conf):  # a service: say when it loses the router, and when it is back
                RouterWatch(session, _endpoints(conf), wait, what).start()
            return session
        except zenoh.ZError as exc:
            reason = str(exc).split(" at ", 1)[0].strip()
            refused = tlsid.refused_because(conf) if secured(conf) else ""
            if refused:
                text = f"cannot open a session with the Zenoh router at {_endpoints(conf)}: {refused}"
            else:
                text = (f"cannot reach the Zenoh router at {_endpoints(conf)} ({reason}): is it up (scmbridge "
                        "router, scmbridge-router.service), and does it accept this identity? (scmbridge doctor "
                        "tells them apart)")
            if wait is None:
                raise UsageError(text) from None
            if text != said:
                log.warning("%s%s; retrying", f"{what}: " if what else "", text)
                systemd.status(f"waiting for the Zenoh router at {_endpoints(conf)}")
                said = text
            if wait.wait(backoff.delay):
                raise UsageError(f"stopped while waiting for the Zenoh router at {_endpoints(conf)}") from None
            backoff.grow()


class Declared:
    """What a node declared on a Zenoh session (subscribers, queryables, publishers, liveliness tokens, matching
    listeners, :class:`bridge.nodes.node.StatusOut`), kept so that the node undeclares them itself. A handle that is
    dropped stays declared until the session closes (Zenoh runs a callback's subscriber or queryable in the
    background): a robot of a fleet whose loop stopped would go on taking samples, answering queries and holding its
    liveliness token on the process's one session. :meth:`undeclare` undeclares every one, the last declared first;
    later ones are undeclared as they are kept (the node has ended)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.handles: list[Any] = []
        self.ended = False

    def keep(self, handle: H) -> H:
        """``handle`` kept until :meth:`undeclare` (undeclared at once if that already ran); returned as it is."""
        with self.lock:
            if not self.ended:
                self.handles.append(handle)
                return handle
        _undeclare(handle)
        return handle

    def __len__(self) -> int:
        with self.lock:
            return len(self.handles)

    def undeclare(self) -> int:
        """Undeclare everything kept (once; a failure is logged, the rest still undeclared); how many were."""
        with self.lock:
            handles, self.handles, self.ended = self.handles, [], True
        return sum(_undeclare(h) for h in reversed(handles))


def _undeclare(handle: Any) -> bool:
    try:
        handle.undeclare()
        return True
    except Exception as exc:  # a session already closed: nothing of it is declared any more
        log.debug("undeclare %r: %s", handle, exc)
        return False


def _connects(conf: zenoh.Config) -> bool:
    """Whether the configuration connects to an endpoint (a client of the lab's router, a peer given one)."""
    try:
        return bool(json.loads(conf.get_json("connect/endpoints")))
    except Exception:  # no connect section
        return False


class RouterWatch:
    """A service's link to its router in its log: "lost the router at ..." when the session has neither a router
    nor a peer any more, "reconnected to the router at ... after N s" when it has one again (Zenoh reconnects by
    itself; what was declared is declared again). Looked at every :data:`WATCH_EVERY_S` by a daemon thread until
    ``stop`` is set or the session is closed."""

    WATCH_EVERY_S = 0.25

    def __init__(self, session: zenoh.Session, endpoints: str, stop: threading.Event, what: str = "",
                 clock: Clock = SYSTEM) -> None:
        self.session, self.endpoints, self.stop = session, endpoints, stop
        self.who = f"{what}: " if what else ""
        self.clock = clock
        self.lost_at: float | None = None

    def connected(self) -> bool | None:
        """Whether the session has a router or a peer now (None: the session is closed)."""
        try:
            info = self.session.info
            return bool(info.routers_zid()) or bool(info.peers_zid())
        except Exception:  # closed (the service is ending)
            return None

    def look(self) -> bool | None:
        """One look: logs a loss or a reconnection; returns :meth:`connected`."""
        up = self.connected()
        now = self.clock()
        if up is False and self.lost_at is None:
            self.lost_at = now
            log.warning("%slost the router at %s: retrying (a driver host stops its robot on its deadman meanwhile)",
                        self.who, self.endpoints)
            systemd.status(f"lost the Zenoh router at {self.endpoints}")
        elif up and self.lost_at is not None:
            log.warning("%sreconnected to the router at %s after %.1f s", self.who, self.endpoints,
                        now - self.lost_at)
            systemd.status(f"reconnected to the Zenoh router at {self.endpoints}")
            self.lost_at = None
        return up

    def start(self) -> RouterWatch:
        threading.Thread(target=self._run, name="router-watch", daemon=True).start()
        return self

    def _run(self) -> None:
        while not self.stop.wait(self.WATCH_EVERY_S):
            if self.look() is None:
                return
