"""UDP shim link for small microcontroller robots: MessagePack datagrams of the same msgspec structs.

The driver sends :class:`bridge.core.wire.Command` datagrams to the robot, each carrying the driver's ``epoch`` (picked
once per driver, :func:`bridge.core.wire.new_epoch`), ``sender = "driver"`` and the driver's own increasing ``seq``;
the robot answers with :class:`bridge.core.wire.LearnerState` datagrams carrying the robot's epoch (picked at boot) and
its own ``seq``. The robot obeys only its configured peer, stops on its own watchdog when commands stop and applies
its own hard limits (see :mod:`sim_learner.udp_robot`).

What the driver trusts, in order:

0. the datagram's keyed tag (:mod:`bridge.core.auth`; ``key_file``, made by ``scmbridge keys udp``): pinning an
   address is not authentication, anyone on the segment can send from it. A datagram without a valid tag is counted
   (``unauthenticated``) and dropped; the commands this driver sends are sealed with the same key (see "Session");
1. the source address: only datagrams from ``robot_host:robot_port`` (resolved once, at ``open``) are read; all
   others are counted as ``foreign`` and dropped undecoded;
2. the payload: a datagram that does not decode and validate as a ``LearnerState`` is ``malformed``;
3. the robot's ``(epoch, seq)`` stream, through :class:`bridge.core.gate.SeqGate`: within the epoch it follows, a
   state is taken only if its seq is above the last one (``state_out_of_order`` otherwise) and not further above
   it than the robot could have counted since (``state_seq_jump``: one forged seq of ``2**63 - 1`` cannot lock the
   real robot out); a new epoch (a rebooted robot) is taken once the followed stream has been silent for
   ``state_timeout_s`` (``state_foreign_epoch`` until then, ``robot_restarts`` counts the changes); an epoch left
   behind is never taken again (``state_old_epoch``). Seqs skipped inside an epoch are counted as ``state_gaps``.

Session: what the robot obeys is bound to one boot of the robot and to a recent reading of its clock, so that
datagrams recorded off the wire move nothing after the robot reboots, nor long after they were sent: a key alone
would let a recording of keyed commands drive a robot that has just rebooted (it remembers no sender) or drive it
long after they were sent (a key says nothing of age). The robot, a small MCU, keeps nothing across a reboot and
shares no clock with the driver, so both checks compare the robot's own numbers:

1. at each boot the robot draws a fresh random boot nonce (the ``epoch`` of its states, 62 bits; firmware takes it
   from a hardware RNG or a flash boot counter, never repeated) and streams it, sealed, in every state with a
   reading of its clock (``stamp``, its microsecond counter as seconds);
2. the driver takes the nonce and the clock reading only from states it accepted (tag, address and the robot's
   ``(epoch, seq)`` stream below; so a rebooted robot's nonce once the old stream is silent) and seals each command
   as a session datagram (:func:`bridge.core.auth.seal_session`): the nonce and the newest clock reading in whole
   microseconds, in a header the tag covers, then the ``Command``. Before its first state it sends nonce 0, which
   no robot holds (the hello that pins a ``first``-mode robot);
3. the robot obeys a command only if its tag verifies, it carries the robot's current nonce (``stale_session``:
   everything sealed before a reboot), the clock reading it echoes is not in the robot's future and at most
   ``SESSION_FRESH_S`` (0.5 s) old (``stale``: a datagram held back and released later, or replayed from earlier in
   this boot), then it goes through the driver's ``(epoch, seq)`` stream (a replay inside the window is not above
   the last seq) and the robot's limits; an applied command lasts at most ``valid_ms`` (and the robot's watchdog).

So a recording is worthless after a reboot, and inside one boot a datagram can be delayed by at most the window,
only if nothing later was accepted meanwhile. A robot the driver cannot hear (its states lost) stops obeying within
the window: the driver has no fresh reading to echo. Left open: states replayed to a driver host that has just
started are taken for a robot (it has nothing to compare them with); the commands it then seals carry a stale nonce
and move nothing, and the real robot's stream takes over after ``state_timeout_s`` of the recording's silence.

Without a key there is no authentication and so no session: anyone on the segment can drive the robot. The driver
refuses to run so unless ``insecure = true`` (loopback tests), and says so in the log when it opens.

Datagrams the kernel dropped because the socket's receive buffer was full (a flood between two polls) are counted
too (``dropped_by_kernel``, Linux ``SO_RXQ_OVFL``); the robot's own states lost that way also show as ``state_gaps``.

Poses are stamped at the robot's own ``stamp`` (its clock at the sample), put on the driver host's monotonic clock
with the sliding-window minimum of ``receipt - stamp`` (:class:`bridge.core.clock.ClockOffset`,
``clock_window_s``; a new
robot epoch, or a confirmed step of its clock (``bridge.core.clock``), starts it again: ``clock_restarts``;
a stamp that does not advance, not being a clock, gives the receipt: ``stamp_fallbacks``), not at the poll that read
them: the driver host polls at its tick, and receipt stamps on that 20 ms grid would add error to the pairs
(``scmbridge bench pairing --link udp`` measures it; docs/RELIABILITY.md). A datagram's receipt is the poll's
``now`` less how much earlier than the poll's newest one the kernel received it (Linux ``SO_TIMESTAMPNS``).

Health is truthful: ``ok`` only while the socket is open and the robot's last accepted state is younger than
``state_timeout_s`` (so False until the first state); ``text`` says how long the robot has been silent.

Configuration: :class:`UdpLinkConfig` (``[link.udp]`` in the driver host's file).
"""

from __future__ import annotations

import logging
import math
import socket
from dataclasses import dataclass, replace
from typing import Annotated

from bridge.core import wire as M
from bridge.core.auth import KeyFileError, load_key, open_sealed, seal_session
from bridge.core.clock import ClockOffset
from bridge.core.config import Cfg, Port, Rule, meta
from bridge.core.gate import SeqGate
from drivers.base import SYSTEM, Clock, DriverError, FailsafeReport, LinkBase, LinkHealth, Pose, Verdict, whole_numbers

log = logging.getLogger("scmbridge.driver.udp")

#: seqs a state may jump ahead of the last one beyond what ``max_state_rate_hz`` allows for the time elapsed
STATE_SEQ_SLACK = 10
#: datagrams read per ``poll`` at most, so a flood cannot hold the driver host's loop (the rest waits a tick)
MAX_DATAGRAMS_PER_POLL = 512
#: how long a command may be applied after the robot receives it (the robot's watchdog usually acts first)
CMD_VALID_MS = 300
_REFUSALS = ("out_of_order", "seq_jump", "old_epoch", "foreign_epoch")
#: s between two hellos (stops) while ``open`` waits for the robot's first state, and between two stops while
#: ``close`` waits for the robot to report it has stopped
GREET_PERIOD_S = 0.02
#: Linux: each datagram carries the socket's count of datagrams dropped for want of buffer space (socket(7))
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
#: Linux: each datagram carries the kernel's wall-clock time of its arrival (struct timespec, socket(7))
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_ANC_SPACE = socket.CMSG_SPACE(4) + socket.CMSG_SPACE(16)


class UdpLinkConfig(Cfg):
    """``[link.udp]``: MessagePack datagrams to a small robot (the UDP shim).

    Both ends pin each other: the driver takes datagrams only from ``robot_host:robot_port`` and the robot obeys
    (and streams its state to) only its configured peer, which is this driver's ``bind_host:bind_port``. So the
    driver's port is fixed (``bind_port``), and the robot's firmware is configured with it.
    """

    robot_host: Annotated[str, meta("the robot's address (resolved once, when the link opens)", min_length=1)] = (
        "127.0.0.1")
    robot_port: Annotated[Port, meta("the robot's UDP port")] = 47800
    bind_host: Annotated[str, meta("our address (127.0.0.1 for loopback tests)")] = "127.0.0.1"
    bind_port: Annotated[Port, meta("our UDP port: the robot's configured peer, so fixed; 0: any free (only for a "
                                    "robot that pins its first sender)")] = 47801
    open_timeout: Annotated[float, meta("s to wait for the robot's first state", gt=0.0, le=120.0)] = 2.0
    state_timeout_s: Annotated[float, meta("the robot's state older than this: the link is not ok (the host stops); "
                                           "also the silence after which a new robot epoch (a reboot) is taken, s",
                                           gt=0.0, le=60.0)] = 0.5
    max_state_rate_hz: Annotated[float, meta("the fastest the robot may count its state seq (it streams at ~50 Hz): "
                                             "a state whose seq jumps further ahead than this allows is refused, Hz",
                                             gt=0.0, le=100_000.0)] = 200.0
    clock_window_s: Annotated[float, meta("window of the robot-clock offset estimate that stamps poses at the robot's "
                                          "own stamps, s", gt=0.0, le=600.0)] = 5.0
    key_file: Annotated[str, meta("the datagram key both ends use (scmbridge keys udp): every datagram carries a keyed "
                                  "tag and unauthenticated ones are dropped; commands are bound to the robot's boot "
                                  "and clock (the session); empty: refused unless insecure")] = ""
    insecure: Annotated[bool, meta("run without a key_file: no authentication, no replay protection, anyone on the "
                                   "segment drives the robot (loopback tests only; warned in the log)")] = False

    def __post_init__(self) -> None:
        if self.robot_port == 0:
            raise Rule("robot_port must be the robot's port (1-65535)")

    def unauthenticated(self) -> str:
        """Why anyone on the network can drive the robot through this link ("" when every datagram is keyed): the
        driver host's status and ``scmbridge doctor`` say it (drivers.base.link_unauthenticated)."""
        return "" if self.key_file else "the UDP link runs insecure = true (no key_file)"


@dataclass(frozen=True, slots=True)
class UdpHealthDetail:
    """The UDP link's counts in :class:`drivers.base.LinkHealth` (only grow)."""

    foreign: int = 0  # datagrams from another address than the robot's, dropped
    unauthenticated: int = 0  # datagrams without a valid tag (a key is configured), dropped
    state_gaps: int = 0  # states the robot counted that never arrived
    robot_restarts: int = 0  # a new robot epoch taken (it rebooted)
    dropped_by_kernel: int = 0  # datagrams the socket's buffer had no room for
    clock_restarts: int = 0  # the robot-clock offset estimate restarted
    stamp_fallbacks: int = 0  # states stamped at their receipt (the robot's stamp did not advance)
    state_out_of_order: int = 0  # states refused by the (epoch, seq) stream, by reason
    state_seq_jump: int = 0
    state_old_epoch: int = 0
    state_foreign_epoch: int = 0

    def status_counters(self) -> dict[str, int]:
        return whole_numbers(self)


def link_key(config: UdpLinkConfig) -> bytes | None:
    """The link's datagram key (None: ``insecure``), checked as the driver opens it and as ``scmbridge config
    check`` does: without a key and without ``insecure`` refused, a key file missing, short, all zeros or readable
    by others refused (:class:`bridge.core.auth.KeyFileError`: one line)."""
    if not config.key_file and not config.insecure:
        raise KeyFileError("the UDP link has no key_file: make one (scmbridge keys udp --robot NAME) and name it "
                           "in [link.udp] key_file, or set insecure = true there (loopback tests only)")
    return load_key(config.key_file, "udp") if config.key_file else None


def resolve_ipv4(host: str, port: int) -> tuple[str, int]:
    """``(ip, port)`` of ``host`` as the source address ``recvfrom`` reports it (numeric IPv4)."""
    try:
        infos = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
    except socket.gaierror as exc:
        raise DriverError(f"cannot resolve the UDP robot's address {host!r}: {exc.strerror or exc}") from None
    ip, p = infos[0][4][:2]
    return str(ip), int(p)


class UdpDriver(LinkBase):
    """The UDP shim behind the :class:`drivers.base.Driver` protocol (see the module docstring), on
    :class:`drivers.base.LinkBase`: a datagram read by a ``poll`` was received by its ``now``; ``open`` and ``close``
    wait between their stops with the clock's ``wait`` (a test on a fake clock runs them without real time)."""

    name = "udp"
    COUNTERS = UdpHealthDetail

    def __init__(self, config: UdpLinkConfig, *, clock: Clock = SYSTEM) -> None:
        super().__init__(clock)
        self.config = config
        self.bind = (config.bind_host, config.bind_port)
        self.open_timeout = config.open_timeout
        self.state_timeout = config.state_timeout_s
        self.epoch = M.new_epoch()  # this driver's run: a restarted driver host is a new epoch to the robot
        self.robot_addr: tuple[str, int] | None = None  # resolved at open
        self.sock: socket.socket | None = None
        self.seq = 0
        self.gate = SeqGate(silence_s=config.state_timeout_s, max_rate_hz=config.max_state_rate_hz,
                            slack=STATE_SEQ_SLACK)
        self.last_state_time = -math.inf  # driver-host monotonic time of the last accepted state
        self.key: bytes | None = None  # the datagram key, read at open (the driver host checks it at start)
        self._clock = ClockOffset(config.clock_window_s)  # the robot's stamps -> our monotonic clock
        self._robot_stamp = -math.inf  # the last robot stamp taken in this epoch
        self.session = (0, 0)  # (the robot's boot nonce, its newest clock reading in us) from its accepted states

    @property
    def robot_text(self) -> str:
        return f"{self.config.robot_host}:{self.config.robot_port}"

    def open(self, now: float) -> None:
        """Resolve the robot's address, bind, and greet the robot with stops until its first state arrives. Without
        a key and without ``insecure`` it refuses (:class:`bridge.core.auth.KeyFileError`: one line, no retry)."""
        self.key = link_key(self.config)
        if self.key is None:
            log.warning("the UDP link to %s runs insecure (no key_file): no authentication, no replay protection; "
                        "anyone on the segment can drive the robot", self.robot_text)
        self.robot_addr = resolve_ipv4(self.config.robot_host, self.config.robot_port)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(self.bind)
        except OSError as exc:
            sock.close()
            raise DriverError(f"cannot bind the UDP link to {self.bind[0]}:{self.bind[1]}: "
                              f"{exc.strerror or exc}") from None
        sock.setblocking(False)  # send() and poll() never wait
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
        except OSError:  # not Linux: kernel drops are not counted
            pass
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        except OSError:  # not Linux: a datagram's receipt is the poll's now
            pass
        self.sock = sock
        self._health.connected = True
        t_end = now + self.open_timeout
        while now < t_end:
            self.stop(now)  # a stop is also the hello (a robot in first-sender mode pins us)
            now = self._pause(GREET_PERIOD_S)
            if self.poll(now):
                return
        raise DriverError(f"no state from the UDP robot at {self.robot_text} within {self.open_timeout} s")

    def _send_cmd(self, v: float, omega: float, method: str, now: float) -> None:
        if self.sock is None or self.robot_addr is None:
            return
        self.seq += 1
        msg = M.Command(stamp=max(0.0, now), seq=self.seq, v=v, omega=omega, method=method, valid_ms=CMD_VALID_MS,
                        sender="driver", epoch=self.epoch)
        data = M.encode(msg)
        try:
            if self.key is not None:
                data = seal_session(self.key, self.session[0], self.session[1], data)
            self.sock.sendto(data, self.robot_addr)
            self._health.frames_sent += 1
        except OSError:  # a full socket buffer (non-blocking) or an unreachable network: dropped, counted
            self._health.errors += 1

    def send(self, v: float, omega: float, now: float) -> None:
        self._send_cmd(v, omega, "scm", now)

    def stop(self, now: float) -> None:
        self._send_cmd(0.0, 0.0, "stop", now)

    def poll(self, now: float) -> list[Pose]:
        """The robot's states that arrived by ``now``. Each one's receipt is ``now`` less how much earlier than the
        newest of this poll the kernel received it (Linux ``SO_TIMESTAMPNS``): states that waited in the socket
        keep their spacing, and no clock is read."""
        out: list[Pose] = []
        if self.sock is None:
            return out
        read: list[tuple[bytes, tuple, float | None]] = []
        for _ in range(MAX_DATAGRAMS_PER_POLL):
            try:
                data, anc, _, src = self.sock.recvmsg(65536, _ANC_SPACE)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. an ICMP error reported on the socket
                self._health.errors += 1
                break
            arrived = None
            for level, kind, value in anc:
                if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(value) >= 4:
                    self.counts["dropped_by_kernel"] = int.from_bytes(value[:4], "little")
                elif level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(value) >= 16:
                    arrived = int.from_bytes(value[:8], "little", signed=True) + int.from_bytes(
                        value[8:16], "little", signed=True) * 1e-9
            read.append((data, src, arrived))
        newest = max((a for _, _, a in read if a is not None), default=None)
        for data, src, arrived in read:
            receipt = now if arrived is None or newest is None else now - max(0.0, newest - arrived)
            self._health.frames_received += 1
            if src[:2] != self.robot_addr:
                self.counts["foreign"] += 1
                continue
            if self.key is not None:
                data = open_sealed(self.key, data)
                if data is None:
                    self.counts["unauthenticated"] += 1
                    continue
            try:
                st = M.decode(data, M.LearnerState)
            except M.MessageError:
                self._health.malformed += 1
                continue
            pose = self._take(st, now, receipt)
            if pose is not None:
                out.append(pose)
        return out

    def _take(self, st: M.LearnerState, now: float, receipt: float) -> Pose | None:
        """The pose of ``st`` if it is the next of the robot's stream (see the module docstring), else None."""
        prev_epoch, prev_seq = self.gate.epoch, self.gate.last_seq
        why = self.gate.accept(st.epoch, st.seq, now)
        if why is not None:
            self.counts[f"state_{why}"] += 1
            return None
        if prev_epoch is not None and st.epoch != prev_epoch:
            self.counts["robot_restarts"] += 1
            self._clock.reset()  # a rebooted robot: a new clock
            self._robot_stamp = -math.inf
        elif prev_epoch is not None and st.seq > prev_seq + 1:
            self.counts["state_gaps"] += st.seq - prev_seq - 1
        self.last_state_time = now
        self._changed()
        self.session = (st.epoch, round(st.stamp * 1e6))  # what the next commands echo (see "Session")
        if st.stamp <= self._robot_stamp:  # not a running clock (a firmware that sends 0): the receipt it is
            self.counts["stamp_fallbacks"] += 1
            return Pose(receipt, st.x, st.y, st.theta, st.v, st.omega)
        self._robot_stamp = st.stamp
        stamp, steady = self._clock.restamp_checked(st.stamp, receipt)
        self.counts["clock_restarts"] += not steady
        return Pose(stamp, st.x, st.y, st.theta, st.v, st.omega)

    def _judge_link(self, now: float) -> Verdict:
        age = now - self.last_state_time
        if age <= self.state_timeout:
            return True, "ok", "ready"
        if math.isinf(age):
            return False, "no_telemetry", f"no state from the robot yet ({self.robot_text})"
        return False, "no_telemetry", f"no state from the robot for {age:.1f} s"

    def health(self, now: float) -> LinkHealth:
        detail = self._counter_snapshot()
        if self.sock is None:
            return replace(self._health, ok=False, detail=detail)
        ok, reason, text = self._verdict(now)
        return replace(self._health, ok=ok, reason=reason, text=text, detail=detail)

    def clear_faults(self, now: float) -> None:
        """Nothing to clear on this link (see :meth:`drivers.base.Driver.clear_faults`)."""

    def engage(self, now: float, clear_faults: bool = False) -> None:
        """Nothing to switch on the robot: the driver host starts sending non-zero commands once engaged."""
        if self.sock is None:
            raise DriverError("UDP link not open")

    def failsafe(self) -> FailsafeReport:
        s = CMD_VALID_MS / 1000.0
        return FailsafeReport(drive_on_s=s, text=f"if the host dies the robot drives on for up to {s:g} s (each "
                              "command is valid that long on the robot)")

    def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0,
              now: float | None = None) -> None:
        if self.sock is None:
            return
        try:  # stops until the robot says it has stopped (from the host's now, else read once; then the waits move it)
            start = self.clock() if now is None else now
            self._stop_until_still(start, stop_speed, stop_timeout, GREET_PERIOD_S, self._reported_speed)
        finally:
            self.sock.close()
            self.sock = None
            self._closed_health()

    def _reported_speed(self, now: float) -> float | None:
        """Read the robot's states at ``now``; the speed the newest reports (None: none came, or none says it)."""
        poses = self.poll(now)
        return poses[-1].v if poses else None


#: the link's plugin entry (``drivers.LINKS``): its ``[link.udp]`` section, its driver, and whether ``scmbridge
#: learner`` emulates it (the UDP-shim robot, :mod:`sim_learner.udp_robot`)
CONFIG = UdpLinkConfig
DRIVER = UdpDriver
EMULATED = True
