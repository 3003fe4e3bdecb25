"""The driver host's safety logic, pure (times are arguments): which command the vehicle gets this tick.

:class:`SeqGate` follows one sender's ``(epoch, seq)`` stream (docs/ARCHITECTURE.md, "Senders, epochs and
sequence numbers"):

- within the epoch it follows, a message is new only if its ``seq`` is above the last one, and not further above it
  than a sender could have counted since (``max_rate_hz`` per second plus ``slack``): one forged or corrupted
  message with ``seq = 2**63 - 1`` cannot lock the real sender out;
- a message of another epoch is taken (the sender restarted: a new station run, a rebooted robot) once the stream
  it follows has been silent for ``silence_s``; while that stream is alive, a second sender is refused (counted);
- a message of an epoch it has left is refused unless its seq is above the last one seen from that epoch: a
  replayed or reordered message of an earlier run is refused, while a sender that was only silent can come back;
- within the epoch, a stamp later than its own receipt (on the sender's clock as the stream shows it) is refused,
  and a sender found behind a forged jump is followed again after a few messages; a sender whose least latency was
  learned during a stall (its first commands came late on a loaded machine) is followed again once a few
  messages in the sender's order (seqs and stamps rising) show its faster clock, even read in batches.

:class:`CommandGate` is the driver host's gate for ``cmd``: freshness (validity and the deadman), the estop latch
(released only by a source the configuration names), two senders on one epoch (a conflict: the vehicle stops),
clamping to the hard limits where that keeps the command's direction (otherwise a stop: never -99 m/s into +0.05),
and "a stop is a stop": a ``stop`` method, an exact zero command, the deadman or an estop reach the vehicle as
exactly zero, whatever the limits say.

Two senders on one epoch are a conflict, not a stream. One sender counts its seqs up by one from one thread and
Zenoh delivers one publisher's messages in order, so within the followed epoch a command at or below the last seq
taken that is not an exact copy of the command taken at that seq (a replay is a copy) was sent by someone else: a
forger who copied the station's epoch and publishes seq + 1 right after each real command (found by a hostile test:
341 forged commands of 341 applied over 6 s, the host saying "driving (cmd)"). The forged seq is taken first, so the
real command arrives at a seq already taken, with other content. The gate then stops the vehicle (``conflict``) until
no such command has come for the silence timeout, and :meth:`CommandGate.conflict` says so for the host's health.
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from dataclasses import dataclass, field

from bridge.core import wire as M
from bridge.core.clock import ClockOffset
from transfer.domain import Bounds

log = logging.getLogger("scmbridge.gate")

#: reasons under which the vehicle is driven (pairs may be formed); every other reason is a stop
DRIVING = ("cmd", "clamped")


class SeqGate:
    """Follows one ``(epoch, seq)`` stream; see the module docstring. ``accept`` returns None or why not.

    It remembers the last seq of the last ``remember`` epochs it followed: a message of an epoch it has left is a
    replay (refused, ``old_epoch``) unless its seq is above that epoch's last one, in which case that sender is
    simply back (after the usual silence). So a forged new epoch slipped in during a dropout holds the vehicle
    only until it goes silent; it cannot lock the real sender out.

    Within the followed epoch, messages that carry the sender's stamp are also checked against time: the least
    ``receipt - stamp`` of the stream (its clock offset plus the least latency) puts each stamp on this clock, and a
    message stamped more than ``stamp_tolerance`` after its own receipt cannot have been sent by that sender
    (``stamp_jump``). The first ``learn_clock`` stamped messages of an epoch only teach the gate that clock: a
    sender's first message is often its slowest (a new station's first tick, stamped at its start, includes the
    first solve), and what came faster after it is the sender, not a forger. If the sender keeps sending below a
    seq the gate took (``resync_after`` fresh messages in a
    row with rising seqs), the gate follows it again (``resync``): a forged jump inside the real epoch locks the real
    sender out for a few messages at most.
    """

    def __init__(self, silence_s: float, max_rate_hz: float = 1000.0, slack: int = 50, remember: int = 64,
                 stamp_tolerance: float = 0.05, resync_after: int = 3, fresh_s: float = 0.5,
                 learn_clock: int = 10, clock_window_s: float = 60.0) -> None:
        self.silence_s = float(silence_s)
        self.max_rate_hz = float(max_rate_hz)
        self.slack = int(slack)
        self.remember = int(remember)
        self.stamp_tolerance = float(stamp_tolerance)
        self.resync_after = int(resync_after)
        self.fresh_s = float(fresh_s)
        self.epoch: int | None = None
        self.last_seq = -1
        self.last_time = -math.inf
        self.left: dict[int, int] = {}  # epoch -> its last seq, for the epochs followed before (oldest first)
        # the followed sender's stamps on this clock; a long window, so a stall of a few seconds (every command late)
        # does not raise the learned minimum and make the sender look ahead once it is fast again (a command link's
        # two clocks drift by a few ms a minute at most, far inside stamp_tolerance)
        self.clock = ClockOffset(window_s=clock_window_s)
        self._behind: list[int] = []  # seqs refused in a row as out of order (rising, fresh)
        self._ahead: list[tuple[float, float, int]] = []  # (receipt, stamp, seq) of those refused in a row as ahead
        self.learn_clock = int(learn_clock)
        self._stamps = 0  # stamped messages taken from the followed epoch (its clock is learned from the first few)

    def accept(self, epoch: int, seq: int, now: float, stamp: float | None = None) -> str | None:
        """Take ``(epoch, seq)`` received at ``now`` (with the sender's ``stamp`` when it has one) if it is the next
        of the stream; else the reason it is not (``resync``: taken, after the sender was found behind a jump)."""
        if epoch != self.epoch:
            if seq <= self.left.get(epoch, -1):
                return "old_epoch"
            if self.epoch is not None and now - self.last_time < self.silence_s:
                return "foreign_epoch"
            if self.epoch is not None:
                self.left[self.epoch] = self.last_seq
                while len(self.left) > self.remember:
                    del self.left[next(iter(self.left))]
                log.info("sender epoch %x followed instead of %x after %.2f s of silence", epoch, self.epoch,
                         now - self.last_time)
            self.left.pop(epoch, None)
            self.clock.reset()  # a new sender's clock, learned from its first stamped messages
            self._stamps = 0
            self._take(epoch, seq, now, stamp)
            return None
        offset = self.clock.offset
        clock_resync = False
        # while the sender's clock is still being learned, a faster message only lowers the minimum
        judged = offset if self._stamps >= self.learn_clock else None
        if stamp is not None and judged is not None and stamp + judged > now + self.stamp_tolerance:
            # sent after it arrived, on the sender's clock as learned: forged, or the sender's least latency was
            # learned during a stall (a loaded start) and it is faster now. A run of such messages in the sender's
            # order (seqs and stamps rising, nothing in between that fits the old clock) is the sender: learn its
            # clock again from the whole run. Their latencies need not agree: a starved host reads the commands
            # queued during its stall in one batch, so one batch's latencies differ by the send period.
            run = self._ahead
            if run and (seq <= run[-1][2] or stamp <= run[-1][1]):
                run.clear()
            run.append((now, stamp, seq))
            if len(run) < self.resync_after:
                return "stamp_jump"
            self.clock.reset()
            for receipt, sent, _ in run[:-1]:
                self.clock.restamp(sent, receipt)
            run.clear()
            clock_resync = True
        else:
            self._ahead.clear()
        if seq <= self.last_seq:
            return self._out_of_order(seq, now, stamp, offset)
        if seq - self.last_seq > self.slack + self.max_rate_hz * max(0.0, now - self.last_time):
            return "seq_jump"
        self._take(epoch, seq, now, stamp)
        return "clock_resync" if clock_resync else None

    def _take(self, epoch: int, seq: int, now: float, stamp: float | None) -> None:
        self.epoch, self.last_seq, self.last_time = epoch, seq, now
        if stamp is not None:
            self.clock.restamp(stamp, now)
            self._stamps += 1
        self._behind.clear()

    def _out_of_order(self, seq: int, now: float, stamp: float | None, offset: float | None) -> str:
        """A message of the followed epoch at or below the last seq: a replay, a reordering, or the real sender
        behind a forged jump. A run of fresh ones with rising seqs is that sender, alive: follow it again."""
        fresh = stamp is not None and offset is not None and stamp + offset >= now - self.fresh_s
        if not fresh or (self._behind and seq <= self._behind[-1]):
            self._behind.clear()
        if fresh:
            self._behind.append(seq)
        if len(self._behind) >= self.resync_after:
            log.warning("command stream followed again: %d commands in a row came below seq %d (a forged jump?)",
                        len(self._behind), self.last_seq)
            self._take(self.epoch, seq, now, stamp)  # type: ignore[arg-type]
            return "resync"
        return "out_of_order"


#: refusals of a second or forged sender keep the command stream "in conflict" (health not ok) this long, s
CONFLICT_WINDOW_S = 2.0
#: the fastest a station may send commands (its configuration's rate bound is 200 Hz) and the seqs of slack on top
MAX_COMMAND_RATE_HZ = 250.0
COMMAND_SEQ_SLACK = 5
#: commands of the followed epoch kept (by seq) to tell a replayed copy from another sender's command at that seq
TAKEN_KEPT = 256


def in_range(value: float, limits: tuple[float, float]) -> float | None:
    """``value`` clamped into ``limits`` when that keeps its direction (a speed above the top, a turn sharper than
    allowed); None when the range has nothing in its direction: below a positive minimum (a vehicle that cannot
    crawl or reverse, asked for 0.02 m/s or for -1 m/s) or above a negative maximum. Clamping those would turn a
    request into motion the other way (-99 m/s into +0.05)."""
    lo, hi = limits
    if value < lo:
        return None if lo > 0.0 else lo
    if value > hi:
        return None if hi < 0.0 else hi
    return value


@dataclass(frozen=True)
class Decision:
    """What the vehicle gets this tick, and why."""

    v: float
    omega: float
    reason: str  # cmd | clamped | refused | stop | deadman | estop | stale | start | conflict
    cmd_seq: int | None = None

    @property
    def driving(self) -> bool:
        return self.reason in DRIVING


@dataclass
class CommandGate:
    """Freshness, clamping, the deadman and the estop latch (see the module docstring)."""

    limits: Bounds
    cmd_timeout: float = 0.3
    release_sources: tuple[str, ...] = ("operator",)
    seq: SeqGate | None = None
    latest: M.Command | None = None
    received_at: float = -math.inf
    estopped: bool = False
    estop_source: str = ""
    estop_reason: str = ""
    counters: dict[str, int] = field(default_factory=lambda: {
        "accepted": 0, "out_of_order": 0, "old_epoch": 0, "foreign_epoch": 0, "seq_jump": 0, "stamp_jump": 0,
        "resyncs": 0, "deadman_trips": 0, "stale": 0, "clamped": 0, "refused_range": 0, "stops": 0, "estops": 0,
        "estop_releases": 0, "estop_release_refused": 0, "seq_conflicts": 0, "conflict_stops": 0})
    refused_at: dict[str, float] = field(default_factory=dict)  # why -> when a command was last refused for it
    conflict_at: float = -math.inf  # when a second sender on the followed epoch was last seen
    _taken: OrderedDict[int, M.Command] = field(default_factory=OrderedDict)  # the followed epoch's, by seq
    _deadman_active: bool = True

    def __post_init__(self) -> None:
        if self.seq is None:
            # a station ticks at <= 200 Hz (its config's bound): a few seqs of slack, and stamps that must advance
            # like the receipts, keep a forged jump inside the real epoch from locking the station out
            self.seq = SeqGate(silence_s=self.cmd_timeout, max_rate_hz=MAX_COMMAND_RATE_HZ, slack=COMMAND_SEQ_SLACK)

    def offer(self, cmd: M.Command, now: float) -> bool:
        """A decoded command arrived at ``now``; False (and counted) if it is not the next of its sender's stream.
        A command of the followed epoch at a seq already passed that is not a copy of the one taken there is a second
        sender on that epoch: counted (``seq_conflicts``), and the vehicle stops (:meth:`decide`)."""
        followed = self.seq.epoch
        why = self.seq.accept(cmd.epoch, cmd.seq, now, cmd.stamp)
        if cmd.epoch == followed and why in ("out_of_order", "resync") and self._taken.get(cmd.seq) != cmd:
            if now - self.conflict_at >= self.seq.silence_s:
                log.warning("two senders on command epoch %x: seq %d came again with other content (a forger "
                            "copying the station's epoch?): the vehicle stops", cmd.epoch, cmd.seq)
            self.counters["seq_conflicts"] += 1
            self.conflict_at = now
        if why == "clock_resync":  # the real sender, only faster than its clock was learned: no forger after all
            self.counters["resyncs"] += 1
            self.refused_at.pop("stamp_jump", None)
        elif why == "resync":
            self.counters["resyncs"] += 1
        elif why is not None:
            self.counters[why] += 1
            self.refused_at[why] = now
            return False
        self.latest, self.received_at = cmd, now
        self.counters["accepted"] += 1
        if cmd.epoch != followed:
            self._taken.clear()
        self._taken[cmd.seq] = cmd
        while len(self._taken) > TAKEN_KEPT:
            self._taken.popitem(last=False)
        return True

    def conflict(self, now: float, window: float = CONFLICT_WINDOW_S) -> str | None:
        """Why the command stream cannot be trusted right now, or None: within ``window`` s, commands of a second
        sender (another epoch while the followed one is alive) or forged ones (a seq or stamp jump) were refused.
        The vehicle is still driven by the followed sender; health must say so (ok false), not "driving". Two
        senders on one epoch (:meth:`offer`) also stop the vehicle."""
        if now - self.conflict_at < window:
            return (f"two senders on one command epoch: {self.counters['seq_conflicts']} commands came at a seq "
                    "already taken, with other content (a forger copying the station's epoch); the vehicle is "
                    f"stopped until they have stopped for {self.seq.silence_s:g} s")
        recent = {why: t for why, t in self.refused_at.items() if now - t < window}
        if "foreign_epoch" in recent:
            return (f"a second sender on cmd: {self.counters['foreign_epoch']} commands of another epoch refused "
                    "(two stations for one robot, or a forger)")
        forged = [why for why in ("seq_jump", "stamp_jump") if why in recent]
        if forged:
            return f"forged commands on cmd ({', '.join(forged)}) refused"
        return None

    def estop(self, e: M.Estop) -> bool:
        """Engage (anyone allowed) or release (only a configured source) the latch. True if the latch changed."""
        if e.engaged:
            changed = not self.estopped
            if changed:
                self.counters["estops"] += 1
            self.estopped, self.estop_source, self.estop_reason = True, e.source, e.reason
            return changed
        if not self.estopped:
            return False
        if e.source not in self.release_sources:
            self.counters["estop_release_refused"] += 1
            log.warning("estop release from %r refused: not one of the configured release sources %s", e.source,
                        list(self.release_sources))
            return False
        self.counters["estop_releases"] += 1
        self.estopped, self.estop_source, self.estop_reason = False, e.source, e.reason
        return True

    def decide(self, now: float) -> Decision:
        if self.estopped:
            return Decision(0.0, 0.0, "estop")
        cmd = self.latest
        age = now - self.received_at
        if cmd is None or age >= self.cmd_timeout:
            if not self._deadman_active and cmd is not None:
                self.counters["deadman_trips"] += 1
                log.warning("deadman: no valid command for %.3f s, vehicle stopped", age)
            self._deadman_active = True
            return Decision(0.0, 0.0, "deadman" if cmd is not None else "start")
        self._deadman_active = False
        if age >= cmd.valid_ms / 1000.0:
            self.counters["stale"] += 1
            return Decision(0.0, 0.0, "stale", cmd.seq)
        if cmd.method == "stop" or (cmd.v == 0.0 and cmd.omega == 0.0):
            self.counters["stops"] += 1
            return Decision(0.0, 0.0, "stop", cmd.seq)  # a stop is a stop, whatever the limits
        if now - self.conflict_at < self.seq.silence_s:  # two senders on one epoch: which one is this?
            self.counters["conflict_stops"] += 1
            return Decision(0.0, 0.0, "conflict", cmd.seq)
        v, w = in_range(cmd.v, self.limits.v), in_range(cmd.omega, self.limits.w)
        if v is None or w is None:  # the vehicle cannot do it in that direction: a stop, never the other way
            self.counters["refused_range"] += 1
            return Decision(0.0, 0.0, "refused", cmd.seq)
        if (v, w) != (cmd.v, cmd.omega):
            self.counters["clamped"] += 1
            return Decision(v, w, "clamped", cmd.seq)
        return Decision(v, w, "cmd", cmd.seq)


__all__ = ["COMMAND_SEQ_SLACK", "CONFLICT_WINDOW_S", "DRIVING", "MAX_COMMAND_RATE_HZ", "CommandGate", "Decision",
           "SeqGate", "in_range"]
