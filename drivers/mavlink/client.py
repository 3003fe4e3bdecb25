"""The MAVLink connection to one vehicle and the command protocol on it: a pymavlink connection re-opened with
backoff, our ground station HEARTBEAT, and COMMAND_LONGs sent one at a time, re-sent until their COMMAND_ACK (that
names the command and, when MAVLink 2 carries them, addresses us) or out of tries.

Signing: pymavlink (2.4.x, ``MAVLink.check_signature`` of every generated dialect) records a message's signature
timestamp for its stream *before* it checks the signature, so one forged packet with a far-future timestamp makes
every genuine message of that stream "too old" until the link is re-opened. :func:`verify_before_recording` wraps
the check so the stream's timestamp only moves for a message whose signature verified, as the C library does
(``mavlink_signature_check``); docs/SECURITY.md has the report."""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bridge.core.backoff import Backoff
from drivers.base import SYSTEM, Clock, LinkHealth
from drivers.mavlink.config import MavlinkLinkConfig
from drivers.mavlink.dialect import Dialect, load_pymavlink

log = logging.getLogger("scmbridge.driver.mavlink")

NO_ACK = -1  # a command that got no COMMAND_ACK after all its tries
_BACKOFF0 = 0.25


def verify_before_recording(mav: Any) -> None:
    """Make ``mav`` (a pymavlink ``MAVLink``) advance a signing stream's timestamp only for a message whose signature
    verified: pymavlink's own ``check_signature`` records the timestamp first, so a forged message with a far-future
    timestamp would lock the genuine stream out (docs/SECURITY.md). The wrapper puts the stream's entry back as it
    was whenever the check fails; a pymavlink that checks in the right order is left unchanged in effect."""
    check = mav.check_signature
    if getattr(check, "verifies_before_recording", False):
        return

    def checked(msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        stamps = mav.signing.stream_timestamps
        stream = (msgbuf[-13], src_system, src_component)  # (link id, system, component), as pymavlink keys it
        had, before = stream in stamps, stamps.get(stream)
        ok = bool(check(msgbuf, src_system, src_component))
        if not ok:
            if had:
                stamps[stream] = before
            else:
                stamps.pop(stream, None)
        return ok

    checked.verifies_before_recording = True  # type: ignore[attr-defined]
    mav.check_signature = checked


def result_name(result: int) -> str:
    """``"MAV_RESULT_FAILED"`` for 4; ``"no COMMAND_ACK"`` for :data:`NO_ACK`."""
    if result == NO_ACK:
        return "no COMMAND_ACK"
    entry = load_pymavlink().mav.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT {result}"


@dataclass
class Command:
    """One COMMAND_LONG in flight: sent, re-sent without an ACK, then done with a result."""

    command: int
    params: tuple[float, ...]
    what: str  # "arming", "mode change to GUIDED", "LOCAL_POSITION_NED interval"
    tries: int = 0
    next_try: float = 0.0
    first_sent: float = math.inf
    result: int | None = None
    on_done: Callable[[Command], None] | None = None


class MavlinkClient:
    """The connection and the command protocol. Messages read while it waits for an ACK go to ``on_message`` (the
    driver's dispatch); the counts it keeps land in the driver's ``health`` and ``counts``. Deadlines (re-sends, our
    HEARTBEAT, reconnects) are at the ``now`` it is given; only its waits (:meth:`wait`, :meth:`run`, a blocking
    :meth:`receive`) read ``clock``, and :attr:`now` is the time the last of them returned at (what the message
    just read arrived at). Reads block on the connection in real time, and with no connection :meth:`receive` waits
    with the clock's ``wait`` (:mod:`drivers.base`)."""

    def __init__(self, config: MavlinkLinkConfig, dialect: Dialect, health: LinkHealth, counts: dict[str, int],
                 on_message: Callable[[Any], None], *, clock: Clock = SYSTEM) -> None:
        self.config = config
        self.clock = clock
        self._idle = threading.Event()  # never set: what a wait with no connection to read waits on
        self.dialect = dialect
        self.url, self.baud = config.url, config.baud
        self.target = (config.target_system, config.target_component)
        self.source_system, self.source_component = config.source_system, config.source_component
        self.health, self.counts, self.on_message = health, counts, on_message
        self.signing_key: bytes | None = None  # read at open (the driver host checks the file at start)
        self.conn: Any = None
        self.failed: str | None = None  # why the connection failed since the last service (None: it did not)
        self.lost_reason = ""
        self.conn_time = math.inf  # when the connection was opened
        self.now = clock()  # the time the last wait returned at (see the class docstring)
        self.backoff = Backoff(_BACKOFF0, config.reconnect_max_s)
        self._bad_sig_before = 0  # refused signatures on connections closed since
        self._warned_unsigned = False
        self._reconnect_due = 0.0
        self._hb_due = 0.0
        self._queue: deque[Command] = deque()  # commands, one at a time (an ACK names only the command)

    # ---------------------------------------------------------------------------------------- connection
    def connect(self, now: float) -> None:
        """Open the pymavlink connection once (no retries inside pymavlink: the caller backs off)."""
        conn = self.dialect.mavutil.mavlink_connection(
            self.url, baud=self.baud, source_system=self.source_system,
            source_component=self.source_component, dialect="ardupilotmega", autoreconnect=False, retries=0)
        if self.signing_key is not None:  # MAVLink 2 signing: ours signed, unsigned or forged ones refused
            conn.setup_signing(self.signing_key, sign_outgoing=True, allow_unsigned_callback=None)
            verify_before_recording(conn.mav)
        elif not self._warned_unsigned:
            self._warned_unsigned = True
            log.warning("MAVLink signing is off on %s (no signing_key_file): anyone on the link can command the "
                        "vehicle; make a key with scmbridge keys mavlink and give it to both ends", self.url)
        if hasattr(conn, "handle_eof"):  # TCP: pymavlink prints and would reconnect itself on EOF; we do it
            def failed() -> None:
                self.failed = "connection closed by the vehicle"
            conn.handle_eof = failed
            conn.handle_disconnect = failed
        self.conn = conn
        self.failed = None
        self.conn_time = now  # the vehicle counts as heard only once it speaks on this connection

    def close(self) -> None:
        """Close the pymavlink connection if there is one (a failing close is not an error worth more)."""
        self._bad_sig_before = self.bad_signatures()
        try:
            if self.conn is not None:
                self.conn.close()
        except OSError:
            pass
        self.conn = None

    def _drop(self, reason: str, now: float) -> None:
        log.warning("MAVLink connection %s lost: %s; re-opening in %.2f s", self.url, reason, self.backoff.delay)
        self.health.errors += 1
        self.lost_reason = reason
        self.close()
        self.failed = None
        self._reconnect_due = now + self.backoff.delay
        self.backoff.grow()

    def _try_reconnect(self, now: float) -> None:
        if self.conn is not None or now < self._reconnect_due:
            return
        try:
            self.connect(now)
        except Exception as exc:  # pymavlink raises OSError, SerialException, ConnectionRefusedError...
            log.debug("re-opening %s failed: %s", self.url, exc)
            self._reconnect_due = now + self.backoff.delay
            self.backoff.grow()
            return
        self.counts["reconnects"] += 1
        log.info("MAVLink connection %s re-opened", self.url)
        self.heartbeat(now, force=True)

    def heartbeat(self, now: float, force: bool = False) -> None:
        """Our HEARTBEAT, ``heartbeat_hz`` (1 Hz by default; ArduPilot's GCS failsafe and a udp peer's address
        depend on it): a ground station's, or a companion computer's when we speak with the vehicle's own system id
        (``config.companion``)."""
        if self.conn is None or not (force or now >= self._hb_due):
            return
        mav = self.dialect.mav
        kind = mav.MAV_TYPE_ONBOARD_CONTROLLER if self.config.companion else mav.MAV_TYPE_GCS
        try:
            self.conn.mav.heartbeat_send(kind, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE)
            self.health.frames_sent += 1
        except OSError as exc:
            self.failed = str(exc)
        self._hb_due = now + 1.0 / self.config.heartbeat_hz

    def service(self, now: float) -> None:
        """Housekeeping every call does: reconnect, our heartbeat, commands in flight (at ``now``: the latest time)."""
        self.now = max(self.now, now)
        if self.failed is not None and self.conn is not None:
            self._drop(self.failed, now)
        self._try_reconnect(now)
        self.heartbeat(now)
        self._service_commands(now)

    def bad_signatures(self) -> int:
        """Messages refused by MAVLink 2 signing (unsigned, forged or replayed), over every connection so far."""
        sig = getattr(getattr(self.conn, "mav", None), "signing", None)
        now = (sig.badsig_count + sig.reject_count) if sig is not None and self.signing_key is not None else 0
        return self._bad_sig_before + now

    def send(self, send: Callable[[Any], None]) -> bool:
        """Send one message with ``send(conn.mav)`` (counted); a failure marks the connection failed."""
        if self.conn is None:
            return False
        try:
            send(self.conn.mav)
        except OSError as exc:
            self.failed = str(exc)
            return False
        self.health.frames_sent += 1
        return True

    # -------------------------------------------------------------------------------------------- receive
    def receive(self, block: float, handle: Callable[[Any], None]) -> None:
        """Hand each message that arrived to ``handle``: waiting (a real blocking read) up to ``block`` s for the first
        one, then what is already there."""
        if self.conn is None:
            if block > 0:
                self.clock.wait(self._idle, block)
                self.now = self.clock()
            return
        timeout = block
        while self.conn is not None and self.failed is None:
            try:
                msg = self.conn.recv_match(blocking=timeout > 0, timeout=timeout if timeout > 0 else None)
            except Exception as exc:  # a serial port unplugged, a socket reset
                self.failed = f"{type(exc).__name__}: {exc}"
                break
            if msg is None:
                break
            if timeout > 0:
                self.now = self.clock()  # a blocking read: the message arrived now, not when the wait began
            timeout = 0.0
            handle(msg)

    def ack(self, msg: Any) -> None:
        """A COMMAND_ACK: the result of the command in flight if it names it and addresses us, else a stray."""
        ours = (getattr(msg, "target_system", 0) in (0, self.source_system)
                and getattr(msg, "target_component", 0) in (0, self.source_component))
        head = self._queue[0] if self._queue else None
        if ours and head is not None and head.tries > 0 and head.result is None and msg.command == head.command:
            head.result = int(msg.result)
        else:
            self.counts["stray_acks"] += 1

    # -------------------------------------------------------------------------------------------- commands
    def in_flight(self, command: int, param1: float) -> bool:
        """Whether ``command`` with this first parameter is queued and not done."""
        return any(c.command == command and c.params[0] == param1 for c in self._queue)

    def submit(self, command: int, params: tuple[float, ...], what: str,
               on_done: Callable[[Command], None] | None = None) -> Command:
        """Queue a COMMAND_LONG (sent when those before it are done); ``on_done`` gets it with its result."""
        c = Command(command, tuple(float(p) for p in params) + (0.0,) * (7 - len(params)), what, on_done=on_done)
        self._queue.append(c)
        self._service_commands(self.now)
        return c

    def _service_commands(self, now: float) -> None:
        while self._queue:
            c = self._queue[0]
            if c.result is not None:
                self._queue.popleft()
                if c.on_done is not None:
                    c.on_done(c)
                continue
            if now < c.next_try or self.conn is None:
                return
            if c.tries > self.config.command_retries:
                c.result = NO_ACK
                continue
            try:  # confirmation counts the re-sends, as the MAVLink command protocol asks
                self.conn.mav.command_long_send(self.target[0], self.target[1], c.command, c.tries, *c.params)
                self.health.frames_sent += 1
            except OSError as exc:
                self.failed = str(exc)
                return
            c.first_sent = min(c.first_sent, now)
            c.tries += 1
            c.next_try = now + self.config.ack_timeout
            return

    def wait(self, done: Callable[[], bool], t_end: float) -> bool:
        """Receive and service until ``done()`` or ``t_end``."""
        while True:
            now = self.now = self.clock()
            self.service(now)
            if done():
                return True
            if now >= t_end:
                return False
            self.receive(min(0.05, max(0.0, t_end - now)), self.on_message)

    def run(self, command: int, params: tuple[float, ...], what: str, t_end: float,
            done: Callable[[], bool] | None = None) -> int:
        """Send a command and wait for its ACK (or ``done()``, or ``t_end``); the MAV_RESULT, or NO_ACK."""
        c = self.submit(command, params, what)
        self.wait(lambda: c.result is not None or (done is not None and done()), t_end)
        by_state = c.result is None and done is not None and done()
        if c.result is None:  # out of time (or confirmed by the vehicle's state) before an ACK
            c.result = NO_ACK
            self._service_commands(self.now)
        return self.dialect.mav.MAV_RESULT_ACCEPTED if by_state else c.result
