"""A bare look at the vehicle over the driver's link, for a person's tools (``scmbridge keys mavlink --install``,
``scmbridge doctor --link mavlink``): a pymavlink connection with the driver's url and ids that reads the vehicle's
HEARTBEAT, SYS_STATUS, PARAM_VALUEs and the COMMAND_ACKs addressed to us, and sends only reads (PARAM_REQUEST_READ,
MAV_CMD_REQUEST_MESSAGE) and our own HEARTBEAT. It never changes the vehicle's mode, arming or parameters."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

from drivers.base import SYSTEM, Clock
from drivers.mavlink.config import MavlinkLinkConfig
from drivers.mavlink.dialect import load_pymavlink


class Probe:
    """The connection and what the vehicle (``target_system``/``target_component``) said on it. Its deadlines and
    the stamps of the ACKs are on ``clock`` (:class:`bridge.core.clock.Clock`); its reads block on the connection, at
    most 0.1 s each."""

    def __init__(self, config: MavlinkLinkConfig, *, clock: Clock = SYSTEM) -> None:
        self.clock = clock
        self.d = load_pymavlink()
        self.config = config
        self.target = (config.target_system, config.target_component)
        self.conn = self.d.mavutil.mavlink_connection(
            config.url, baud=config.baud, source_system=config.source_system,
            source_component=config.source_component, dialect="ardupilotmega", autoreconnect=False, retries=0)
        self.acks: list[tuple[float, int, int]] = []
        self.heartbeat: Any = None  # the vehicle's last HEARTBEAT
        self.sys_status: Any = None
        self.params: dict[str, float] = {}
        self.texts: list[str] = []
        self.heartbeats = 0
        self.signed_from_vehicle = 0  # HEARTBEATs whose signature verified with our key
        self.carrying_signature = 0  # HEARTBEATs with a signature, verified or not (no key: not judged)
        self._hb_due = 0.0

    def pump(self, until: float) -> None:
        """Read until ``until`` (on ``clock``), sending our 1 Hz HEARTBEAT meanwhile as the driver does."""
        mav = self.d.mav
        while True:
            now = self.clock()
            if now >= self._hb_due:
                kind = mav.MAV_TYPE_ONBOARD_CONTROLLER if self.config.companion else mav.MAV_TYPE_GCS
                self.conn.mav.heartbeat_send(kind, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE)
                self._hb_due = now + 1.0
            if now >= until:
                return
            msg = self.conn.recv_match(blocking=True, timeout=min(0.1, until - now))
            if msg is not None and msg.get_type() != "BAD_DATA" and (msg.get_srcSystem(),
                                                                     msg.get_srcComponent()) == self.target:
                self._handle(msg)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self.heartbeat = msg
            self.heartbeats += 1
            self.signed_from_vehicle += bool(getattr(msg, "_signed", False))
            header = getattr(msg, "_header", None)
            self.carrying_signature += bool(header is not None and getattr(header, "incompat_flags", 0) & 1)
        elif kind == "SYS_STATUS":
            self.sys_status = msg
        elif kind == "PARAM_VALUE":
            if math.isfinite(msg.param_value):
                self.params[str(msg.param_id).rstrip("\x00")] = float(msg.param_value)
        elif kind == "STATUSTEXT":
            self.texts.append(str(msg.text).rstrip("\x00"))
        elif kind == "COMMAND_ACK":
            ours = (getattr(msg, "target_system", 0) in (0, self.config.source_system)
                    and getattr(msg, "target_component", 0) in (0, self.config.source_component))
            if ours:
                self.acks.append((self.clock(), int(msg.command), int(msg.result)))

    def wait(self, pred: Callable[[], bool], timeout: float) -> bool:
        """Read until ``pred()`` or ``timeout`` s."""
        t_end = self.clock() + timeout
        while not pred():
            if self.clock() >= t_end:
                return False
            self.pump(min(t_end, self.clock() + 0.1))
        return True

    def read_params(self, names: Iterable[str], timeout: float) -> dict[str, float]:
        """The parameters among ``names`` the vehicle answers within ``timeout`` s (each asked again every second;
        a name this firmware does not have stays out)."""
        names = list(names)
        t_end = self.clock() + timeout
        while self.clock() < t_end:
            missing = [n for n in names if n not in self.params]
            if not missing:
                break
            for n in missing:
                self.conn.mav.param_request_read_send(*self.target, n.encode(), -1)
            self.wait(lambda: all(n in self.params for n in names), min(1.0, max(0.0, t_end - self.clock())))
        return {n: self.params[n] for n in names if n in self.params}

    def request(self, msg_id: int, timeout: float) -> int | None:
        """MAV_CMD_REQUEST_MESSAGE ``msg_id`` (a read), sent three times a second until its COMMAND_ACK: its result,
        or None without one within ``timeout``."""
        cmd = self.d.mav.MAV_CMD_REQUEST_MESSAGE
        t0 = self.clock()
        t_end, tries = t0 + timeout, 0
        while self.clock() < t_end:
            self.conn.mav.command_long_send(*self.target, cmd, tries, msg_id, 0, 0, 0, 0, 0, 0)
            tries += 1
            if self.wait(lambda: any(t >= t0 and c == cmd for t, c, _ in self.acks),
                         min(1.0 / 3.0, max(0.0, t_end - self.clock()))):
                return [r for t, c, r in self.acks if t >= t0 and c == cmd][-1]
        return None

    def close(self) -> None:
        try:
            self.conn.close()
        except OSError:
            pass
