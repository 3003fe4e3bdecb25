"""An emulated UDP-shim robot: a microcontroller that takes Command datagrams and streams LearnerState datagrams.

It behaves like the firmware it stands in for, which trusts nothing on the network:

- **One peer.** It obeys, and streams its state to, one configured peer: the driver host's ``(host, port)``
  (``DEFAULT_PEER`` is the driver's default ``bind_host:bind_port``). ``peer="first"`` pins the first sender of a
  valid command instead (convenient on a bench where the driver's port is not fixed, weaker: whoever speaks first
  owns the robot until it reboots; with a key, the first sender of an authenticated datagram, even of an old
  session, since the driver learns the session only from the states a pinned robot sends); it must be asked for.
  Datagrams from any other address are dropped undecoded and counted (``foreign``); the state goes to the peer
  only (none before a ``first`` peer is pinned).
- **Authentication and session** (with ``key``, the lab's case; the protocol is in :mod:`drivers.udp`'s
  docstring). A command must be a session datagram (:func:`bridge.core.auth.open_session`) whose keyed tag verifies
  (``unauthenticated`` otherwise). At boot the robot draws a fresh random 62-bit ``epoch`` (its boot nonce; firmware:
  the MCU's hardware RNG, or a boot counter kept in flash and bumped before use: it must never repeat) and streams it
  in every sealed state with its clock (``stamp``: its microsecond counter, as seconds). A command is obeyed only if it
  carries that nonce (``stale_session`` otherwise: everything recorded before a reboot) and echoes a reading of the
  robot's clock that is not in its future and at most ``fresh`` s old (``stale`` otherwise: a command held back and
  released later, or replayed from earlier in this boot). The robot keeps nothing across a reboot and needs no
  clock agreement with the driver: both checks compare the robot's own numbers. Without a key there is no
  authentication and so no session either (anyone on the segment can drive the robot: loopback tests only).
- **Validation.** A datagram that does not decode and validate as a ``Command`` is dropped (``malformed``).
- **The driver's stream.** Commands go through :class:`bridge.core.gate.SeqGate` on the driver's ``(epoch, seq)``: a
  command not above the last one (a replay, a reorder) is refused (``out_of_order``), so is a seq jump beyond what
  a driver can count (``seq_jump``), a second driver while the first one is alive (``foreign_epoch``) and any
  command of a driver run left behind (``old_epoch``). A restarted driver host (a new epoch) is taken once the
  old one has been silent for ``silence`` s (the watchdog's time by default).
- **Its own hard limits.** A command with ``|v| > v_max`` or ``|omega| > omega_max`` (or not finite) is *refused*,
  not clamped: a sender that asks for more than the robot can do is wrong about something, so the robot holds
  its wheels (``over_limits``) rather than drive at full speed on a guess. A ``stop`` method or an exact zero is a
  stop (wheels held).
- **Its watchdog and each command's validity.** No applied command for ``watchdog`` s holds the wheels
  (``watchdog_stops``); so does a command applied for its own ``valid_ms`` from its receipt (``expired_stops``):
  when the stops that should follow are dropped or held back on the way, the robot stops by itself within the
  command's validity, as drivers/udp.py's protocol says.

It streams its pose at ``rate`` Hz with its own epoch (picked at boot) and seq. Test hooks:
:meth:`UdpRobot.pause_telemetry` (a radio dropout: the seq keeps counting, nothing is sent) and
:meth:`UdpRobot.reboot` (a new epoch, seq from 0, the wheels held, the command stream forgotten). The body is a
:class:`sim_learner.vehicle.SimVehicle` (the learner's degraded dynamics). Every datagram is counted once in
``counters["received"]`` and once in exactly one of ``applied`` or the refusal counters.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from typing import Literal

from bridge.core import wire as M
from bridge.core.auth import open_session, seal
from bridge.core.gate import SeqGate
from bridge.core.stalls import StallWatch, Usage
from sim_learner.device import ThreadedDevice
from sim_learner.vehicle import SimVehicle

#: the driver host's default address (``drivers.udp.UdpLinkConfig``'s ``bind_host``, ``bind_port``)
DEFAULT_PEER: tuple[str, int] = ("127.0.0.1", 47801)

Peer = tuple[str, int] | Literal["first"]
log = logging.getLogger("scmbridge.learner")
#: a gap between two of the robot's states longer than this, s, is a stall of the emulator (a microcontroller never
#: has one): said in its log with why (:class:`bridge.core.stalls.StallWatch`), since the driver host, which sees
#: only the silence, stops the robot for it
STALL_S = 0.1
#: how old the robot's clock reading a command echoes may be, s (the driver echoes the newest state it took; states
#: stream at 50 Hz, so a live link echoes readings tens of milliseconds old)
SESSION_FRESH_S = 0.5


def _resolve(peer: tuple[str, int]) -> tuple[str, int]:
    """The peer as ``recvfrom`` reports a source: numeric IPv4 and port."""
    host, port = peer
    info = socket.getaddrinfo(host, int(port), socket.AF_INET, socket.SOCK_DGRAM)[0][4]
    return str(info[0]), int(info[1])


def _clock_us(now: float) -> int:
    """The robot's clock in whole microseconds (an MCU's ``micros()``): what states carry and commands echo."""
    return int(now * 1e6)


class UdpRobot(ThreadedDevice):
    """See the module docstring. ``port`` 0 picks a free port (read ``.port`` after ``start``)."""

    thread_name = "udp-robot"

    def __init__(self, vehicle: SimVehicle, host: str = "127.0.0.1", port: int = 0, *, peer: Peer = DEFAULT_PEER,
                 watchdog: float = 0.5, rate: float = 50.0, v_max: float = 1.0, omega_max: float = 2.0,
                 silence: float | None = None, epoch: int | None = None, key: bytes | None = None,
                 fresh: float = SESSION_FRESH_S) -> None:
        super().__init__()
        if not (v_max > 0.0 and omega_max > 0.0 and math.isfinite(v_max) and math.isfinite(omega_max)):
            raise ValueError(f"the robot's limits must be finite and > 0, not v_max={v_max}, omega_max={omega_max}")
        if peer != "first" and not (isinstance(peer, tuple) and len(peer) == 2):
            raise ValueError(f"peer must be (host, port) or 'first', not {peer!r}")
        self.vehicle = vehicle
        self.key = key  # the datagram key: commands must carry its tag, states carry it
        self.addr = (host, int(port))
        self.peer_config: Peer = peer
        self.peer: tuple[str, int] | None = None  # resolved at start, or the pinned first sender
        self.watchdog = float(watchdog)
        self.period = 1.0 / float(rate)
        self.v_max, self.omega_max = float(v_max), float(omega_max)
        self.silence = self.watchdog if silence is None else float(silence)
        self.epoch = M.new_epoch() if epoch is None else int(epoch)  # the boot nonce (states carry it)
        self.fresh_us = int(float(fresh) * 1e6)
        self.counters: dict[str, int] = dict.fromkeys(
            ("received", "applied", "malformed", "foreign", "unauthenticated", "stale_session", "stale",
             "out_of_order", "seq_jump", "old_epoch", "foreign_epoch", "over_limits", "watchdog_stops", "expired_stops",
             "states_sent", "states_paused", "reboots"), 0)
        self.gate = SeqGate(silence_s=self.silence)
        self.last_cmd: M.Command | None = None  # the last command applied (or the last stop)
        self.last_cmd_time = -math.inf
        self.cmd_until = -math.inf  # the applied command's validity ends (its receipt + valid_ms)
        self.moving = False
        self.port = 0
        self._seq = 0
        self._pause_until = -math.inf
        self._lock = threading.Lock()  # the loop's state against the test hooks
        self.sock: socket.socket | None = None
        self.stalls = StallWatch(max(STALL_S, 2.0 * self.period))  # checked at each state sent (see _run)

    # ------------------------------------------------------------------------------------------- test hooks
    def pause_telemetry(self, seconds: float) -> None:
        """Send no state for ``seconds`` from now (a radio dropout: the state seq keeps counting)."""
        self._pause_until = time.monotonic() + float(seconds)

    def reboot(self, epoch: int | None = None, silence: float = 0.0) -> None:
        """Simulate a reboot: wheels held, a new state epoch with seq from 0, the driver's stream forgotten (a fresh
        gate, a ``first`` peer unpinned), and no state for ``silence`` s (the boot)."""
        with self._lock:
            now = time.monotonic()
            self.vehicle.stop(now)
            self.moving = False
            self.epoch = M.new_epoch() if epoch is None else int(epoch)
            self._seq = 0
            self.gate = SeqGate(silence_s=self.silence)
            self.last_cmd, self.last_cmd_time = None, -math.inf
            if self.peer_config == "first":
                self.peer = None
            self._pause_until = now + float(silence)
            self.counters["reboots"] += 1

    # ----------------------------------------------------------------------------------------- life cycle
    def _open(self) -> None:
        self.peer = None if self.peer_config == "first" else _resolve(self.peer_config)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(self.addr)
        self.sock.settimeout(0.005)
        self.port = self.sock.getsockname()[1]

    def _close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    def _run(self) -> None:
        assert self.sock is not None
        t_next = time.monotonic()
        while not self._stop.is_set():
            try:
                data, src = self.sock.recvfrom(65536)
            except (TimeoutError, BlockingIOError, InterruptedError, ConnectionRefusedError):
                data, src = None, None
            except OSError:
                break  # the socket was closed under us
            with self._lock:
                now = time.monotonic()
                if data is not None:
                    self._handle(data, (str(src[0]), int(src[1])), now)
                if self.moving and now - self.last_cmd_time > self.watchdog:
                    self.vehicle.stop(now)  # the firmware's own watchdog
                    self.moving = False
                    self.counters["watchdog_stops"] += 1
                elif self.moving and now > self.cmd_until:
                    self.vehicle.stop(now)  # the command's own validity is over
                    self.moving = False
                    self.counters["expired_stops"] += 1
                if now >= t_next:
                    self._send_state(now)
                    t_next = now + self.period
                    stalled = self.stalls.check(now, Usage.now())
                    if stalled:  # the silence the driver host saw is the emulator's own: said, with why
                        log.warning("robot on port %d sent no state meanwhile: %s", self.port, stalled)

    # ---------------------------------------------------------------------------------------------- inside
    def _handle(self, data: bytes, src: tuple[str, int], now: float) -> None:
        """One datagram: peer, payload, the driver's stream, the limits, then the wheels."""
        c = self.counters
        c["received"] += 1
        if self.peer is not None and src != self.peer:
            c["foreign"] += 1
            return
        if self.key is not None:
            opened = open_session(self.key, data)
            if opened is None:
                c["unauthenticated"] += 1
                return
            boot, echo_us, data = opened
            if self.peer is None:  # "first", keyed: the driver learns the session from the states a pinned robot sends
                self.peer = src
            if boot != self.epoch:  # sealed for another boot of this robot (a recording), or before the first state
                c["stale_session"] += 1
                return
            age_us = _clock_us(now) - echo_us
            if not 0 <= age_us <= self.fresh_us:  # held back, or replayed from earlier in this boot
                c["stale"] += 1
                return
        try:
            cmd = M.decode(data, M.Command)
        except M.MessageError:
            c["malformed"] += 1
            return
        why = self.gate.accept(cmd.epoch, cmd.seq, now)
        if why is not None:
            c[why] += 1
            return
        if self.peer is None:  # "first": the first valid command's sender owns the robot until it reboots
            self.peer = src
        if cmd.method == "stop" or (cmd.v == 0.0 and cmd.omega == 0.0):
            self.vehicle.stop(now)
            self.moving = False
        elif not (math.isfinite(cmd.v) and math.isfinite(cmd.omega) and abs(cmd.v) <= self.v_max
                  and abs(cmd.omega) <= self.omega_max):
            c["over_limits"] += 1
            self.vehicle.stop(now)  # refused, and the wheels held: never "keep the last one" after a bad one
            self.moving = False
            return
        else:
            self.vehicle.command(cmd.v, cmd.omega, now)
            self.moving = True
        c["applied"] += 1
        self.last_cmd, self.last_cmd_time = cmd, now
        self.cmd_until = now + cmd.valid_ms / 1000.0

    def _send_state(self, now: float) -> None:
        if self.peer is None or self.sock is None:
            return
        x, y, th = self.vehicle.measured_pose(now)
        st = self.vehicle.state
        msg = M.LearnerState(stamp=_clock_us(now) / 1e6, seq=self._seq, x=x, y=y, theta=th, v=st.v, omega=st.omega,
                             source="udp-robot", epoch=self.epoch)
        self._seq += 1
        if now < self._pause_until:
            self.counters["states_paused"] += 1
            return
        try:
            data = M.encode(msg)
            self.sock.sendto(seal(self.key, data) if self.key is not None else data, self.peer)
            self.counters["states_sent"] += 1
        except OSError:
            pass
