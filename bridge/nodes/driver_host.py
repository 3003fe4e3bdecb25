"""``scmbridge driver``: the driver host, between Zenoh and one vehicle link (docs/ARCHITECTURE.md).

It subscribes to ``scm/<robot>/cmd`` and ``scm/<robot>/estop`` and answers queries on the estop key with its latch
state. A person is in charge: the host starts *not engaged* (a restart never takes a vehicle back) and sends nothing
but stops until a person engages it (``scmbridge engage``: a query on ``scm/<robot>/engage``; MAVLink: also the
operator selecting GUIDED and arming while the host runs; ``engage_on_start`` in the config). The estop latch is
kept in the state directory and re-read at start, so it survives a restart or a reboot; it fails safe: a latch that
could not be saved stops the host and refuses engage until a release is saved (status reason ``latch_unsaved``), and
a latch file missing beside the install marker, unreadable or not signed by this host starts latched
(``inspect_latch``). The state directory must stay the same across restarts (``SCMBRIDGE_STATE_DIR``): a host given
a fresh one says "first start in this state directory: no estop history". A link anyone on the network can drive
(UDP ``insecure``, ``--insecure``; MAVLink without signing) is said in the log and on status
(``unauthenticated_link``). Closing stops the vehicle, waits until it reports it has stopped, and only then disarms
(a vehicle engaged by this host). Every command is decoded (so validated: finite, in wire range) and goes through
the pure :class:`bridge.core.gate.CommandGate`: the next of its sender's ``(epoch, seq)`` stream, fresh (received
less than min(valid_ms, cmd_timeout) ago), a stop applied as exactly zero, anything else clamped to the configured
hard limits. The host hands the result to the link driver only while the link says the vehicle is fit to drive
(``health().ok``) and its telemetry is fresh; otherwise it stops the vehicle and says why. Each tick it echoes what
the vehicle really got on ``applied``, publishes the link's poses as ``state`` (its own epoch and sequence) and a
truthful ``status``, each second and at once when it changes. Commands are applied as they arrive (latency is not a
multiple of the period), but the link never gets more than ``max_send_hz`` of them. An estop latches a stop; only a
source named in ``estop_release_sources`` releases it, and a release is the operator action that lets the link clear
its controllers' latched faults. All stamps are this host's ``time.monotonic()``, so the station pairs ``applied``
with ``state`` without any clock synchronisation.

``--emulate`` (CAN only) hosts the emulated motor controllers on the same python-can ``virtual`` channel inside
this process: the wire between driver and controllers is python-can, not a shortcut. The host lets them send what
is due before each read of the bus, as controllers on their own hardware would have.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import secrets
import stat
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import zenoh

from bridge.core import wire as M
from bridge.core.acts import ActGuard, Refusal
from bridge.core.args import pose_arg, positive_float, robot_arg
from bridge.core.auth import KEY_BYTES, load_key, record_tag, record_tag_ok
from bridge.core.backoff import Backoff
from bridge.core.clock import HOST, ClockOffset
from bridge.core.errors import UsageError
from bridge.core.gate import CommandGate, Decision
from bridge.core.paths import save_atomic, state_dir
from bridge.nodes import systemd
from bridge.nodes.driver_config import DriverConfig, load_driver
from bridge.nodes.node import (
    BlockedLoop,
    FixedRate,
    Inputs,
    StallWatch,
    Usage,
    add_zenoh_args,
    stop_on_signals,
    zenoh_config,
)
from bridge.nodes.zsession import open_session
from drivers import link_names, open_driver
from drivers.base import Driver, DriverError, FailsafeReport, LinkHealth, link_unauthenticated

log = logging.getLogger("scmbridge.driver")


#: the first and the longest wait between attempts to open a link that is not there yet, s
OPEN_BACKOFF = (0.5, 10.0)
#: s between two loop iterations beyond which the log says why the loop was late (bridge.nodes.node.StallWatch)
STALL_REPORT_S = 0.25
#: ticks the link may get back to back (the send budget, a token bucket of ``max_send_hz``): a command that arrives
#: just after a periodic tick is sent at once; over any T seconds the link gets at most SEND_BURST + max_send_hz * T
SEND_BURST = 2
#: s ``close()`` waits for a latch save still under way before the process ends
LATCH_FLUSH_S = 2.0
#: the end of the status text of a host whose link does not authenticate (drivers.base.link_unauthenticated)
UNAUTHENTICATED = " (link unauthenticated: anyone on the network can drive it)"
#: s an estop query's answer says why the last release was refused
RELEASE_REFUSED_SHOWN_S = 10.0
#: a status goes out each this many seconds, and at once on a change of ok, state or reason, but at most
#: STATUS_MAX_HZ a second (a flapping link cannot flood the station)
STATUS_EVERY_S = 1.0
STATUS_MAX_HZ = 20.0


class Latch(msgspec.Struct, kw_only=True):
    """The estop latch as kept on the robot's disk. ``tag``: :func:`bridge.core.auth.record_tag` over the other
    three fields under the robot's latch key (:func:`latch_marker`), so a file this host did not write reads as
    latched (:func:`inspect_latch`); empty in memory and in a file older than the tag."""

    latched: bool
    source: str = ""
    reason: str = ""
    tag: bytes = b""


def latch_file(robot: str) -> Path:
    """Where a robot's estop latch is kept (the state directory survives restarts and reboots)."""
    return state_dir() / f"estop-{robot}.bin"


def latch_marker(path: Path) -> Path:
    """The install marker beside the latch file ``path`` (``estop-<robot>.installed``): written atomically at the
    first start in a state directory, and never again. It holds the robot's latch key (32 random bytes as hex, mode
    0600), which signs every latch the host saves; its presence says this directory has an estop history, so a
    latch file missing beside it counts as latched."""
    return path.with_name(path.stem + ".installed")


def _unsigned(latch: Latch) -> bytes:
    return M.encode(Latch(latched=latch.latched, source=latch.source, reason=latch.reason))


def sign_latch(key: bytes, latch: Latch) -> Latch:
    """``latch`` with its tag under ``key`` (what :class:`LatchWriter` saves)."""
    return Latch(latched=latch.latched, source=latch.source, reason=latch.reason,
                 tag=record_tag(key, _unsigned(latch)))


def read_marker(path: Path) -> bytes | None:
    """The latch key in the install marker ``path``; None if there is none. Raises ValueError for a marker that is
    not a key or that others may read (a key others know signs releases for them), OSError for one unreadable."""
    try:
        st = path.stat()
        text = path.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        return None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a key ({exc})") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ValueError(f"{path} is readable by others (mode {stat.S_IMODE(st.st_mode):o})")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise ValueError(f"{path}: not a key ({KEY_BYTES} bytes as hex)")
    return key


def inspect_latch(path: Path, key: bytes | None = None) -> tuple[Latch, str]:
    """The latch a host starting now would take from ``path``, and the problem that made it latched ("" when the
    file says it as this host saved it). ``key``: the latch key (None: read from :func:`latch_marker`).

    Fail safe: only a latch file whose tag verifies under the robot's key says released; missing beside the
    install marker, unreadable, unsigned or forged, it is latched (the source says which). No marker and no latch
    file: this state directory has never seen an estop (a first start: released; the caller writes the marker).

    Why a keyed tag (and not only "a release must name the latch it releases"): the threat found was a
    ``released`` file written by someone else (or left by another state directory, or by an older version without
    tags); without the key nobody makes a tag that verifies. What it cannot stop: whoever can read the marker (this
    robot's user, root) can sign, and an older released file of this same host, copied back, verifies. The state
    directory is the host's alone (0700, ``scmbridge doctor`` checks it) and must stay the same across restarts
    (``SCMBRIDGE_STATE_DIR``): a host given an empty one cannot know an estop was latched elsewhere, so its start
    log and ``doctor`` say "first start in this state directory: no estop history"."""
    marker = latch_marker(path)
    marker_problem = ""
    if key is None:
        try:
            key = read_marker(marker)
        except (OSError, ValueError) as exc:
            marker_problem = f"latch key {marker} unusable: {getattr(exc, 'strerror', None) or exc}"
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        if key is None and not marker_problem and not os.path.lexists(marker):
            return Latch(latched=False), ""  # never latched in this state directory
        return (Latch(latched=True, source="missing latch file", reason=f"{path} is missing"),
                f"latch file {path} missing (this state directory has an estop history: {marker.name})")
    except OSError as exc:
        problem = f"latch file {path} unreadable: {exc.strerror or exc}"
        return Latch(latched=True, source="unreadable latch file", reason=problem[:200]), problem
    try:
        saved = M.decode(data, Latch)
    except M.MessageError as exc:
        problem = f"latch file {path} unreadable: {exc}"
        return Latch(latched=True, source="unreadable latch file", reason=problem[:200]), problem
    plain = Latch(latched=saved.latched, source=saved.source, reason=saved.reason)
    if key is not None and saved.tag and record_tag_ok(key, _unsigned(saved), saved.tag):
        return plain, ""
    if saved.latched:  # latched whoever wrote it
        return plain, ""
    why = (marker_problem or f"no latch key ({marker.name} missing)" if key is None
           else "not signed by this host" if not saved.tag else "its tag does not verify (written by someone else)")
    problem = f"latch file {path} says released but {why}"
    return Latch(latched=True, source="unverified latch file", reason=problem[:200]), problem


def read_latch(path: Path, key: bytes | None = None) -> Latch:
    """The latch a host starting now would take (:func:`inspect_latch`), without its tag; a problem is said in the
    log (the host starts latched: release it with scmbridge estop --release)."""
    latch, problem = inspect_latch(path, key)
    if problem:
        log.error("estop %s: starting latched; release it with scmbridge estop --release", problem)
    return latch


class LatchWriter:
    """Keeps the estop latch on disk off the control path: :meth:`submit` hands over the latch and returns at once;
    one thread saves it (``save``: write, fsync, rename, fsync the directory; milliseconds on a fast disk, seconds on
    a slow or failing one). The latest latch wins: what is submitted while a save runs is saved once, after it.
    ``done(latch, error)`` is called in that thread after each save with None or what went wrong: the one place where
    a save's result is known. A stop never waits for the disk (measured: with each fsync delayed 0.5 s the first
    stop came 1.02 s after the estop while the save ran under the lock the loop needs); a confirmation of the latch
    does (:meth:`defer`)."""

    def __init__(self, path: Path, done: Callable[[Latch, Exception | None], None],
                 save: Callable[[Path, bytes], None] = save_atomic) -> None:
        self.path, self.done, self.save = path, done, save
        self.cond = threading.Condition()
        self.pending: Latch | None = None
        self.submitted = self.saved = 0  # versions: every latch submitted up to ``saved`` was saved (or tried)
        self.waiters: list[tuple[int, Callable[[], None]]] = []
        self.closing = False
        self.thread = threading.Thread(target=self._run, name="latch-writer", daemon=True)
        self.thread.start()

    def submit(self, latch: Latch) -> None:
        """Save ``latch`` soon (never blocks on the disk: callers may hold the host's lock, to keep the order)."""
        with self.cond:
            self.pending = latch
            self.submitted += 1
            self.cond.notify_all()

    def defer(self, fn: Callable[[], None]) -> bool:
        """True: ``fn`` runs in the writer's thread once every latch submitted so far has been saved (or its save
        failed); False: nothing is waiting to be saved (``fn`` is not called: the caller goes on at once)."""
        with self.cond:
            if self.saved >= self.submitted:
                return False
            self.waiters.append((self.submitted, fn))
            return True

    def _run(self) -> None:
        while True:
            with self.cond:
                while self.pending is None and not self.closing:
                    self.cond.wait()
                if self.pending is None:
                    return
                latch, version, self.pending = self.pending, self.submitted, None
            error: Exception | None = None
            try:
                self.save(self.path, M.encode(latch))
            except Exception as exc:  # a full disk, a read-only file system, a bug: said and counted by done()
                error = exc
            try:
                self.done(latch, error)
            except Exception:
                log.exception("estop latch: handling the save's result failed")
            with self.cond:
                self.saved = version
                ready = [fn for v, fn in self.waiters if v <= version]
                self.waiters = [(v, fn) for v, fn in self.waiters if v > version]
                self.cond.notify_all()
            for fn in ready:
                try:
                    fn()
                except Exception:
                    log.exception("estop latch: answering after the save failed")

    def close(self, timeout: float) -> bool:
        """Save what is still pending, bounded by ``timeout`` s, and end the thread; False if it did not finish."""
        with self.cond:
            self.closing = True
            self.cond.notify_all()
        self.thread.join(timeout)
        return not self.thread.is_alive()


def blocked_reason(health: LinkHealth) -> str:
    """The ``applied`` reason for a vehicle the link says is not fit to drive (from its typed reason, never its
    words)."""
    if not health.connected:
        return "link_down"
    return "operator" if health.reason == "operator" else "fault"


class DriverHost:
    """One robot's driver host: the gate, the link and the Zenoh side (see the module docstring)."""

    def __init__(self, cfg: DriverConfig, link: str, driver: Driver, robot: str, rate_hz: float, *,
                 dry_run: bool = False, latch_path: Path | None = None,
                 latch_saver: Callable[[Path, bytes], None] = save_atomic) -> None:
        """``dry_run``: run the whole loop and publish what would be applied, sending nothing to the vehicle;
        ``latch_path``: where the estop latch is kept (None: in memory only; its install marker beside it,
        :func:`latch_marker`); ``latch_saver``: how the writer saves it (atomically; a test slows it down or has it
        fail as a full disk does). The first start's marker and released latch are written with
        :func:`save_atomic` (:meth:`open_latch`)."""
        d = cfg.driver
        self.link, self.driver, self.robot = link, driver, robot
        self.keys = M.Keys(robot)
        self.period = 1.0 / rate_hz
        self.max_send_hz = d.max_send_hz
        self.max_telemetry_age = d.max_telemetry_age_s
        self.gate = CommandGate(d.hard_limits.bounds(), d.cmd_timeout, tuple(d.estop_release_sources))
        self.inputs = Inputs()
        self.lock = threading.Lock()  # the gate is shared with Zenoh's callback threads
        self.wake = threading.Event()
        self.clear_requested = False
        self.epoch = M.new_epoch()
        self.seq = {"applied": 0, "state": 0, "status": 0}
        self.last_pose = -math.inf
        self.last_decision = Decision(0.0, 0.0, "start")
        self.health = LinkHealth()
        self.ticker: FixedRate | None = None  # the loop's scheduler (deadlines, wake-ups, the send budget)
        #: a loop iteration later than this says why in the log (the controllers' watchdog is 0.5 s on ODrive's
        #: example; the deadman a few periods), and where it is blocked while it is (two periods at a slow rate)
        self.stall_report_s = max(STALL_REPORT_S, 2.0 * self.period)
        self.stall_watch = StallWatch(self.stall_report_s)
        self.ticks: deque[float] = deque(maxlen=500)  # start times of the periodic ticks
        self.late: deque[float] = deque(maxlen=500)  # s each periodic tick came after its deadline (jitter)
        self.pubs: dict[str, zenoh.Publisher] = {}
        self.pose_source = d.pose_source
        self.mocap_clock = ClockOffset(d.mocap_window_s)
        self.mocap: list[M.LearnerState] = []  # restamped samples waiting for the loop
        self.dry_run = dry_run
        self.engaged = False  # a person engaged the vehicle since this host started
        self.engage_on_start = d.engage_on_start
        #: emulated devices hosted in this process (``--emulate``): each ``emit_due()`` runs before the link is read
        self.co_located: list[Any] = []
        self.operator_engages = bool(getattr(driver, "operator_engages", False))
        self.engage_queries: list[tuple[zenoh.Query, M.EngageRequest]] = []  # answered by the loop thread
        #: engage requests and estop releases are taken fresh and once (bridge.core.acts); under the lock
        self.acts = ActGuard()
        self.release_refused: tuple[str, float] = ("", -math.inf)  # why the last release was refused, and when
        self.stop_speed, self.stop_timeout, self.max_drive_on = d.stop_speed, d.stop_timeout, d.max_drive_on_s
        self.failsafe_report: FailsafeReport | None = None
        self.was_ok = False  # the link's health last tick (an operator's GUIDED + arming is a transition)
        self.last_health_connected = False
        self.last_state = ""
        #: why anyone on the network can drive this robot through its link ("" when the link authenticates)
        self.unauthenticated = link_unauthenticated(getattr(driver, "config", None))
        #: the last status sent: (ok, state, reason), when, and when the next periodic one is due (status_due)
        self.status_sent: tuple[bool, str, str] | None = None
        self.status_at, self.status_next = -math.inf, -math.inf
        self.latch_path = latch_path
        #: why the latch on disk is not the gate's (its save failed): while set the host stops and refuses to engage;
        #: cleared by the next save that succeeds (a person's release, on a disk that takes it)
        self.latch_unsaved = ""
        self.latch_saver = latch_saver
        self.latch_key = b""  # signs every latch saved (the install marker holds it)
        self.marker_saved = False  # the install marker is on disk (else the next latch save writes it first)
        self.fresh_state = False  # first start in this state directory: no estop history
        self.latch_writer: LatchWriter | None = None
        if latch_path is not None:
            self.open_latch(latch_path)
            self.latch_writer = LatchWriter(latch_path, self.latch_saved, self.save_latch_file)

    # ----------------------------------------------------------------------------------------------- latch
    def open_latch(self, path: Path) -> None:
        """Take the saved latch (:func:`inspect_latch`: anything but a release this host signed is latched) and make
        sure the install marker is on disk; at the first start in a state directory write it and a released latch
        (marker first: a crash between the two leaves a marker without a latch file, which reads latched). These
        writes are the start's, with :func:`save_atomic` (a failure is logged; the first latch save tries the
        marker again)."""
        marker = latch_marker(path)
        self.fresh_state = not os.path.lexists(marker) and not os.path.lexists(path)
        try:
            key = read_marker(marker)
        except (OSError, ValueError):
            key = None  # inspect_latch says why, and the latch reads latched
        saved = read_latch(path, key)
        self.marker_saved = key is not None
        self.latch_key = key if key is not None else secrets.token_bytes(KEY_BYTES)
        log.info("estop latch %s (state directory %s)", path, path.parent)
        if self.fresh_state:
            log.warning("first start in this state directory: no estop history (%s); the state directory must stay "
                        "the same across restarts (SCMBRIDGE_STATE_DIR): a host started with another one cannot know "
                        "an estop latched in this one", path.parent)
        try:
            if not self.marker_saved:
                save_atomic(marker, self.latch_key.hex().encode() + b"\n")
                self.marker_saved = True
            if self.fresh_state:
                save_atomic(path, M.encode(sign_latch(self.latch_key, Latch(latched=False, reason="first start"))))
        except OSError as exc:
            log.error("estop latch: cannot write %s (%s): an estop is kept in memory only until a save succeeds",
                      marker if not self.marker_saved else path, exc.strerror or exc)
        if saved.latched:
            self.gate.estop(M.Estop(stamp=0.0, engaged=True, source=saved.source, reason=saved.reason))
            log.warning("estop latched by %s (kept from before this start): %s", saved.source or "unknown",
                        saved.reason or "no reason given")

    def save_latch_file(self, path: Path, data: bytes) -> None:
        """The writer's save: the install marker first if it is not on disk yet, then the latch (both with the
        host's ``latch_saver``)."""
        if not self.marker_saved:
            self.latch_saver(latch_marker(path), self.latch_key.hex().encode() + b"\n")
            self.marker_saved = True
        self.latch_saver(path, data)

    def forget_latch_file(self) -> str:
        """After a latched save failed: remove the latch file on disk (possible on a full disk; it may say
        released), so a restart finds it missing beside the install marker and starts latched. Returns what a
        restart would do, in words, when that cannot be made sure."""
        path = self.latch_path
        if path is None:
            return ""
        if not self.marker_saved:
            return "no install marker on disk either: a restart would not know of this estop"
        try:
            path.unlink(missing_ok=True)
            dfd = os.open(path.parent, os.O_DIRECTORY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError as exc:
            return f"the old latch file could not be removed either ({exc.strerror or exc}): a restart may read it"
        return ""

    # ---------------------------------------------------------------------------------------------- inputs
    def on_mocap(self, st: M.LearnerState, now: float) -> None:
        """A motion-capture sample: its own stamp put on this host's clock (:mod:`bridge.core.clock`). A sample
        stamped ahead of any possible delivery is dropped (``mocap_dropped``: forged, or a clock step not yet
        confirmed); a confirmed step of the bridge's clock restarts the estimate (``mocap_clock_restarts``)."""
        with self.lock:
            t, verdict = self.mocap_clock.judge(st.stamp, now)
            if verdict != "ok":
                self.inputs.count("mocap_clock_restarts" if verdict == "restarted" else "mocap_dropped")
            if t is not None and t > 0:
                self.mocap.append(msgspec.structs.replace(st, stamp=t))

    def on_cmd(self, cmd: M.Command, now: float) -> None:
        with self.lock:
            accepted = self.gate.offer(cmd, now)
        if accepted:
            self.wake.set()  # apply it now, not at the next tick

    def on_estop(self, e: M.Estop, now: float) -> None:
        """The gate latches (or releases) under the lock and the loop is woken to send the stop at once; the latch
        is saved after, by the writer's thread: no file I/O under a lock the loop or a callback takes. A stop is
        always taken; a release only when fresh and new (:mod:`bridge.core.acts`) and from a configured source."""
        with self.lock:
            why = self.acts.check(e.wall_time, e.nonce, time.time()) if not e.engaged and self.gate.estopped else None
            if why is not None:
                self.inputs.count(f"estop_release_refused_{why.kind}")
            refused = self.gate.counters["estop_release_refused"]
            changed = why is None and self.gate.estop(e)
            if self.gate.counters["estop_release_refused"] > refused:  # (the gate logged it)
                why = Refusal("source", f"refused: {e.source!r} is not one of this host's estop_release_sources "
                              f"{list(self.gate.release_sources)}")
            if why is not None:
                self.release_refused = (why.text, now)
            if changed and not e.engaged:
                self.clear_requested = True
            if changed:
                self.save_latch()
        self.wake.set()
        if changed:
            log.warning("estop %s by %r: %s", "engaged" if e.engaged else "released", e.source, e.reason)
        elif why is not None and why.kind != "source":
            log.warning("estop release by %r %s", e.source, why.text)

    def save_latch(self) -> None:
        """Have the latch kept on disk (called under the lock, at each change, so the last latch handed over is the
        gate's latest, and a query answered after it waits for its save): :class:`LatchWriter` returns at once; the
        save's result comes to :meth:`latch_saved`."""
        if self.latch_writer is None:
            return
        g = self.gate
        self.latch_writer.submit(sign_latch(self.latch_key, Latch(latched=g.estopped, source=g.estop_source,
                                                                  reason=g.estop_reason)))

    def latch_saved(self, latch: Latch, error: Exception | None) -> None:
        """A save's result (the writer's thread). Fail safe: a latch that could not be saved must not come back
        released after a restart, nor be released in memory while the disk cannot say so. A failed latched save
        removes the latch file (a restart then finds the marker without it: latched) and sets ``latch_unsaved``;
        a failed release latches the gate again; either way the host stops, refuses to engage and says why on
        status (reason ``latch_unsaved``) until a save succeeds: a person's release on a disk that takes it."""
        if error is None:
            with self.lock:
                was, self.latch_unsaved = self.latch_unsaved, ""
            if was:
                log.warning("estop latch saved to %s (%s)", self.latch_path,
                            "latched" if latch.latched else "released: the host may be engaged again")
            return
        self.inputs.count("latch_save_failures")
        why = getattr(error, "strerror", None) or str(error)
        if latch.latched:
            text = f"estop latched but NOT saved to {self.latch_path}: {why}; engage refused until it is saved"
            restart = self.forget_latch_file()
        else:
            text = (f"estop release NOT saved to {self.latch_path}: {why}; latched again, engage refused until a "
                    "release is saved")
            restart = ""
        with self.lock:
            self.latch_unsaved = text
            if not latch.latched and not self.gate.estopped:  # (a newer estop may have latched it meanwhile)
                self.gate.estop(M.Estop(stamp=0.0, engaged=True, source="unsaved release", reason=text[:200]))
        log.error("%s%s", text, f" ({restart})" if restart else "")

    def on_engage_query(self, query: zenoh.Query) -> None:
        """A person's ``scmbridge engage``: handed to the loop (which owns the link) and answered from there."""
        try:
            payload = query.payload
            req = M.decode(payload.to_bytes() if payload is not None else b"", M.EngageRequest)
        except M.MessageError as exc:
            self.inputs.count("malformed_engage")
            query.reply(self.keys.engage, M.encode(M.EngageState(
                stamp=time.monotonic(), node=f"driver-{self.link}", engaged=self.engaged, accepted=False,
                text=f"malformed request: {exc}"[:1024])))
            return
        with self.lock:  # engaging is taken fresh and once (bridge.core.acts); handing the vehicle back always
            why = self.acts.check(req.wall_time, req.nonce, time.time()) if req.engaged else None
            if why is None:
                self.engage_queries.append((query, req))
        if why is not None:
            self.inputs.count(f"engage_refused_{why.kind}")
            log.warning("engage by %r %s", req.source, why.text)
            query.reply(self.keys.engage, M.encode(M.EngageState(
                stamp=time.monotonic(), node=f"driver-{self.link}", engaged=self.engaged, accepted=False,
                text=why.text[:1024])))
            return
        self.wake.set()

    def handle_engage(self, req: M.EngageRequest, now: float, clear: bool = False) -> M.EngageState:
        """Engage (or hand back) the vehicle, in the loop thread; the answer says what was done or why not."""
        node = f"driver-{self.link}"
        who = f" by {req.source}" if req.source else ""
        if not req.engaged:
            was, self.engaged = self.engaged, False
            log.warning("disengaged%s: the vehicle gets stops only", who)
            return M.EngageState(stamp=now, node=node, engaged=False, text="disengaged" if was else "not engaged")
        if self.engaged:
            return M.EngageState(stamp=now, node=node, engaged=True, text="already engaged")
        with self.lock:
            latched, source = self.gate.estopped, self.gate.estop_source
        if self.latch_unsaved:  # (latched, or released in memory while the release is not on disk)
            return M.EngageState(stamp=now, node=node, engaged=False, accepted=False,
                                 text=f"refused: {self.latch_unsaved}"[:1024])
        if latched:
            return M.EngageState(stamp=now, node=node, engaged=False, accepted=False,
                                 text=f"refused: estop latched by {source or 'unknown'}")
        if not self.dry_run:
            try:
                self.driver.engage(now, clear_faults=clear)
            except DriverError as exc:
                log.warning("engage%s refused: %s", who, exc)
                return M.EngageState(stamp=now, node=node, engaged=False, accepted=False, text=str(exc)[:1024])
        self.engaged = True
        log.warning("engaged%s: the vehicle follows the station's commands", who)
        return M.EngageState(stamp=now, node=node, engaged=True, text="engaged" + (" (dry run)" if self.dry_run
                                                                                  else ""))

    def answer_engage_queries(self) -> None:
        with self.lock:
            pending, self.engage_queries = self.engage_queries, []
        for query, req in pending:
            ans = self.handle_engage(req, time.monotonic(), req.clear_faults)
            try:
                query.reply(self.keys.engage, M.encode(ans))
            finally:
                query.drop()

    def on_estop_query(self, query: zenoh.Query) -> None:
        """Answered with the latch state; while a change of it is being saved, from the writer's thread once saved
        (a confirmed latch survives a restart, as when the save ran in the estop's callback)."""
        if self.latch_writer is not None and self.latch_writer.defer(lambda: self.answer_estop_query(query, True)):
            return
        self.answer_estop_query(query)

    def answer_estop_query(self, query: zenoh.Query, deferred: bool = False) -> None:
        with self.lock:  # an unsaved latch is latched, and says so (estop prints it beside LATCHED)
            now = time.monotonic()
            why, at = self.release_refused
            st = M.EstopState(stamp=now, node=f"driver-{self.link}",
                              latched=self.gate.estopped or bool(self.latch_unsaved), source=self.gate.estop_source,
                              reason=(self.latch_unsaved or self.gate.estop_reason)[:1024],
                              release_refused=why[:1024] if now - at < RELEASE_REFUSED_SHOWN_S else "")
        try:
            query.reply(self.keys.estop, M.encode(st))
        finally:
            if deferred:
                query.drop()

    # ------------------------------------------------------------------------------------------------ tick
    def follow_operator(self, health: LinkHealth) -> None:
        """MAVLink: the operator taking the vehicle (leaving GUIDED) disengages; the operator putting it in GUIDED
        and arming it while the host runs (a transition, never a state found at start) engages."""
        if not self.operator_engages or self.dry_run:
            return
        operator = health.connected and not health.ok and health.reason == "operator"
        if self.engaged and operator:
            self.engaged = False
            log.warning("disengaged: %s", health.text)
        elif not self.engaged and health.ok and not self.was_ok and self.last_health_connected:
            self.engaged = True
            log.warning("engaged by the operator: %s", health.text)

    def decide(self, now: float) -> Decision:
        """The gate's decision, overruled by engagement, the link's health and the telemetry's age."""
        self.health = self.driver.health(now)
        self.follow_operator(self.health)
        self.was_ok, self.last_health_connected = self.health.ok, self.health.connected
        with self.lock:
            d = self.gate.decide(now)
            clear, self.clear_requested = self.clear_requested, False
            unsaved = self.latch_unsaved
        if clear:
            log.warning("operator released the estop: clearing the link's latched faults")
            self.driver.clear_faults(now)
        if d.driving and unsaved:  # released in memory, but not on disk (yet): a stop until the release is saved
            return Decision(0.0, 0.0, "estop", d.cmd_seq)
        if d.driving and not self.engaged:
            return Decision(0.0, 0.0, "disengaged", d.cmd_seq)
        if d.driving and not self.health.ok and not self.dry_run:
            return Decision(0.0, 0.0, blocked_reason(self.health), d.cmd_seq)
        if d.driving and now - self.last_pose > self.max_telemetry_age:
            return Decision(0.0, 0.0, "no_telemetry", d.cmd_seq)
        return d

    def tick(self, now: float) -> None:
        """Read the link, then decide and send. Finding (the shard test beside two busy loops): the host judged the
        link's health before reading it, so after a stall of its own (0.6 s) the controllers' Heartbeats waiting
        unread on the bus counted as lost, the status said "no heartbeat" and the station paused the mission. Health
        and the telemetry's age are now judged on what has arrived; a link that really went silent still fails."""
        if self.engage_queries:
            self.answer_engage_queries()
        for st in self.read_link(now):
            try:
                self._put("state", M.validated(st))
            except M.MessageError:
                self.inputs.count("telemetry_out_of_range")
                log.warning("telemetry out of range, not published: %s", st)
                continue
            self.seq["state"] += 1
            self.last_pose = max(self.last_pose, now)
        d = self.decide(now)
        if self.dry_run:
            pass  # what would be sent is published on applied; the vehicle gets nothing
        elif d.driving:
            self.driver.send(d.v, d.omega, now)
        else:
            self.driver.stop(now)
        if d.reason != self.last_decision.reason:
            if not d.driving:
                log.info("vehicle stopped: %s", d.reason)
            elif not self.last_decision.driving:
                log.info("vehicle driving (%s)", d.reason)
        self.last_decision = d
        self._put("applied", M.Applied(stamp=now, seq=self.seq["applied"], v=d.v, omega=d.omega, reason=d.reason,
                                       cmd_seq=d.cmd_seq))
        self.seq["applied"] += 1

    def read_link(self, now: float) -> list[M.LearnerState]:
        """Let the co-located emulated devices send what is due, read the link, and return this tick's poses: the
        link's telemetry, or the motion-capture samples (the link is read either way: its frames carry the vehicle's
        health)."""
        for device in self.co_located:
            device.emit_due()
        link = self.driver.poll(now)
        if self.pose_source == "mocap":
            with self.lock:
                samples, self.mocap = self.mocap, []
            return [msgspec.structs.replace(s, seq=self.seq["state"] + i, epoch=self.epoch, source="mocap")
                    for i, s in enumerate(sorted(samples, key=lambda s: s.stamp))]
        return [M.LearnerState(stamp=p.stamp, seq=self.seq["state"] + i, x=p.x, y=p.y, theta=p.theta, v=p.v,
                               omega=p.omega, source=self.link, epoch=self.epoch) for i, p in enumerate(link)]

    def assess(self, now: float) -> tuple[list[str], M.NodeState, M.Reason, float]:
        """What stands in the way of driving now (in words, most important first), the state and typed reason they
        give, and the pose's age: cheap enough for every tick (:meth:`status_due` compares it with the last status
        sent)."""
        h = self.health
        with self.lock:
            estop = (self.gate.estopped, self.gate.estop_source)
            unsaved = self.latch_unsaved
            conflict = self.gate.conflict(now)
        pose_age = now - self.last_pose
        problems = []
        if not h.ok:
            problems.append(h.text)
        if pose_age > self.max_telemetry_age:
            problems.append("no telemetry yet" if math.isinf(pose_age) else f"no telemetry for {pose_age:.1f} s")
        if estop[0]:
            problems.insert(0, f"estop latched by {estop[1] or 'unknown'}")
        if unsaved:
            problems.insert(0, unsaved)
        if conflict:
            problems.append(conflict)
        if not self.engaged and not estop[0] and not unsaved:
            if self.operator_engages and h.connected and not h.ok:
                problems.insert(0, f"waiting for the operator: {h.text.split(': ', 1)[-1]} "
                                   f"(or scmbridge engage --robot {self.robot})")
            else:
                problems.insert(0, f"waiting for engage (scmbridge engage --robot {self.robot})")
        state, reason = self.node_state(estop[0] or bool(unsaved), h, pose_age, problems, bool(unsaved))
        return problems, state, reason, pose_age

    def status_due(self, now: float) -> tuple[list[str], M.NodeState, M.Reason, float] | None:
        """This tick's assessment when a status should go out now: each second, and at once (at most
        ``STATUS_MAX_HZ`` a second) when ``ok``, the state or the typed reason changed since the last one sent. The
        station judges the robot's fitness on this status: an engage, a release or a restart reaches it in the tick
        that made it, not up to a second later (issue 32: a `mission resume` right after `engage` was refused)."""
        assessed = self.assess(now)
        problems, state, reason, _ = assessed
        key = (not problems and not self.dry_run, state, reason)
        if now >= self.status_next:  # the periodic ones keep their own grid, whatever went out between them
            self.status_next = now + STATUS_EVERY_S
            return assessed
        if key != self.status_sent and now - self.status_at >= 1.0 / STATUS_MAX_HZ:
            return assessed
        return None

    def status(self, now: float, assessed: tuple[list[str], M.NodeState, M.Reason, float] | None = None) -> M.Status:
        """Health as it is: ok only if the link is fit, the telemetry fresh and no estop is latched."""
        h = self.health
        with self.lock:
            counters = dict(self.gate.counters)
        counters.update(self.inputs.snapshot())
        # (not ``link_unauthenticated``: that is the UDP link's count of datagrams dropped for a bad tag)
        counters["unauthenticated_link"] = int(bool(self.unauthenticated))
        missed = self.ticker.missed if self.ticker is not None else 0
        counters.update({"link_malformed": h.malformed, "link_errors": h.errors, "missed_deadlines": missed,
                         "loop_stalls": self.stall_watch.stalls,
                         "frames_sent": h.frames_sent, "frames_received": h.frames_received, "ticks": len(self.ticks)})
        if h.detail is not None:
            counters.update({f"link_{k}": v for k, v in h.detail.status_counters().items()})
        problems, state, reason, pose_age = assessed or self.assess(now)
        if state != self.last_state:
            log.info("%s: %s", state, "; ".join(problems) or "driving")
            self.last_state = state
        lat = {"telemetry_age": min(pose_age, 1e6) * 1e3}
        if len(self.late) > 2:
            dev = np.asarray(self.late) * 1e3
            lat.update({"jitter_p50": float(np.percentile(dev, 50)), "jitter_p99": float(np.percentile(dev, 99)),
                        "jitter_max": float(dev.max())})
        if self.failsafe_report is not None and (self.failsafe_report.drive_on_s is None
                                                 or self.failsafe_report.drive_on_s > self.max_drive_on):
            lat["failsafe_drive_on"] = min(1e9, 1e3 * (self.failsafe_report.drive_on_s or 1e6))
        text = f"link {self.link}: " + ("; ".join(problems) if problems else f"driving ({self.last_decision.reason})")
        if self.dry_run:
            text = "DRY RUN (nothing is sent to the vehicle): " + text
        if self.unauthenticated:  # said whatever else is cut (the text's limit is 1024)
            text = text[:1024 - len(UNAUTHENTICATED)] + UNAUTHENTICATED
        ok = not problems and not self.dry_run
        msg = M.Status(stamp=now, seq=self.seq["status"], node="driver", ok=ok, state=state, reason=reason,
                       rates_hz={"loop": 1.0 / self.period}, latencies_ms=lat, counters=counters, text=text[:1024],
                       host=HOST)
        self.seq["status"] += 1
        self.status_sent, self.status_at = (ok, state, reason), now
        return msg

    def node_state(self, estop: bool, h: LinkHealth, pose_age: float, problems: list[str],
                   unsaved: bool = False) -> tuple[M.NodeState, M.Reason]:
        """The one word ``scmbridge status`` shows for this host, and its typed reason (what the station decides
        on: a latched estop is ``estop`` also in a dry run, ``latch_unsaved`` when it is not on disk); from typed
        values only, never from a text."""
        latched: M.Reason = "latch_unsaved" if unsaved else "estop"
        if self.dry_run:
            return "dry_run", latched if estop else "dry_run"
        if estop:
            return "estop", latched
        if not h.connected:
            return "link_down", "link_down"
        if not self.engaged:
            return "waiting", "not_engaged"
        if not h.ok:
            return ("operator", "operator") if h.reason == "operator" else ("fault", "fault")
        if pose_age > self.max_telemetry_age:
            return "no_pose", "no_telemetry"
        return ("driving", "ok") if not problems else ("fault", "conflict")  # (the one problem left: two senders)

    # ------------------------------------------------------------------------------------------------ run
    def _put(self, topic: str, msg: msgspec.Struct) -> None:
        self.pubs[topic].put(M.encode(msg))

    def serve(self, session: zenoh.Session, stop: threading.Event, duration: float | None) -> None:
        """Declare the host's keys, open the link and run the loop until ``stop`` or ``duration``."""
        k = self.keys
        self.inputs.subscribe(session, k.cmd, M.Command, "cmd", self.on_cmd)
        self.inputs.subscribe(session, k.estop, M.Estop, "estop", self.on_estop)
        session.declare_queryable(k.estop, self.on_estop_query)
        session.declare_queryable(k.engage, self.on_engage_query)
        self.alive = session.liveliness().declare_token(M.alive_key(self.robot, "driver"))
        if self.pose_source == "mocap":
            self.inputs.subscribe(session, k.mocap, M.LearnerState, "mocap", self.on_mocap)
        self.pubs = {"applied": session.declare_publisher(k.applied), "state": session.declare_publisher(k.state),
                     "status": session.declare_publisher(M.status_key(self.robot, "driver"))}
        self._put("status", M.Status(stamp=time.monotonic(), seq=self.seq["status"], node="driver", ok=False,
                                     state="starting", reason="starting",
                                     text=f"link {self.link}: opening (vehicle not yet ready)"))
        self.seq["status"] += 1
        if not self.open_link(stop):
            return
        self.failsafe_report = self.driver.failsafe()
        too_long = self.failsafe_report.drive_on_s is None or self.failsafe_report.drive_on_s > self.max_drive_on
        (log.warning if too_long else log.info)("vehicle failsafe: %s%s", self.failsafe_report.text,
                                                f" (more than max_drive_on_s = {self.max_drive_on:g} s)"
                                                if too_long else "")
        log.info("driver host for %s on link %s at %.0f Hz (epoch %x)%s", self.robot, self.link, 1 / self.period,
                 self.epoch, ": DRY RUN, nothing is sent to the vehicle" if self.dry_run else "")
        if self.unauthenticated:
            log.warning("link %s unauthenticated: %s: anyone on the network can drive it (status counter "
                        "unauthenticated_link = 1)", self.link, self.unauthenticated)
        if self.engage_on_start:
            ans = self.handle_engage(M.EngageRequest(stamp=0.0, source="engage_on_start"), time.monotonic())
            if not ans.engaged:
                log.error("engage_on_start: %s", ans.text)
        systemd.ready(f"{self.robot}: link {self.link} open, " + ("engaged" if self.engaged else "waiting for engage"))
        self.loop(stop, duration)

    def open_link(self, stop: threading.Event) -> bool:
        """Open the link, retrying with a backoff while the vehicle (or the CAN interface) is not there, saying what
        it waits for on status, in the log (once per reason) and to systemd; False if stopped meanwhile."""
        backoff, said = Backoff(*OPEN_BACKOFF), ""
        while not stop.is_set():
            try:
                self.driver.open(time.monotonic())  # bounded by the link's open_timeout
                return True
            except DriverError as exc:
                text = f"link {self.link}: waiting for the vehicle: {exc}"
                if text != said:
                    log.warning("%s; trying again (every %.0f s at most)", text, backoff.maximum)
                    said = text
                systemd.status(text[:200])
                self._put("status", M.Status(stamp=time.monotonic(), seq=self.seq["status"], node="driver",
                                             ok=False, state="starting", reason="link_down", text=text[:1024]))
                self.seq["status"] += 1
                self.driver.close(disarm=False, stop_timeout=0.0)  # a half-open link is let go before the retry
                stop.wait(backoff.delay)
                backoff.grow()
        return False

    def close(self) -> None:
        """Stop, wait until the vehicle has stopped, then disarm / idle (only what this host engaged); then let a
        latch save still under way finish (bounded: ``LATCH_FLUSH_S``)."""
        systemd.stopping()
        try:
            if self.dry_run:
                self.driver.close(disarm=False, stop_speed=self.stop_speed, stop_timeout=0.0)
                return
            self.driver.close(disarm=self.engaged, stop_speed=self.stop_speed, stop_timeout=self.stop_timeout)
        finally:
            if self.latch_writer is not None and not self.latch_writer.close(LATCH_FLUSH_S):
                log.error("estop latch: the save to %s did not finish within %.0f s of closing", self.latch_path,
                          LATCH_FLUSH_S)

    def loop(self, stop: threading.Event, duration: float | None) -> None:
        """Periodic ticks, plus an immediate tick for each accepted command, estop or engage query (the wake); the
        scheduler is the station's (:class:`FixedRate`). A woken tick re-phases the period (the link got a command:
        the periodic re-send is due a period later) and the link's send budget (``max_send_hz``, a burst of
        ``SEND_BURST``) bounds the send rate whatever arrives. Finding (``scmbridge bench bridge``): with ticks never
        closer than 1 / max_send_hz on a fixed schedule, a command published within that gap after a periodic tick
        waited out the rest of it (9.0 ms median for those published 0-2 ms after a tick, 0.25 ms for those 10-15 ms
        after), and a periodic tick after a command tick was pushed back the same way (loop jitter p99 9.9 ms); a
        token bucket alone on the fixed schedule sent 100 ticks a second against a budget of 100 and queued (2.4 ms
        median)."""
        t_start = time.monotonic()
        self.ticker = ticker = FixedRate(1.0 / self.period, stop, wake=self.wake, max_hz=self.max_send_hz,
                                         burst=SEND_BURST, rephase=True)
        periodic = True
        blocked = BlockedLoop(self.stall_report_s, stop, log).start()
        try:
            while not stop.is_set():
                blocked.beat()
                now = time.monotonic()
                if duration is not None and now - t_start >= duration:
                    return
                stalled = self.stall_watch.check(now, Usage.now())
                if stalled:
                    log.warning("%s", stalled)
                if periodic:
                    self.ticks.append(now)
                self.tick(now)
                assessed = self.status_due(now)
                if assessed is not None:
                    self._put("status", self.status(now, assessed))
                periodic = ticker.wait()
                if periodic:
                    self.late.append(ticker.late)
        finally:
            blocked.done()


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--link", choices=link_names(), required=True)
    ap.add_argument("--config", help="driver TOML (scmbridge config show --kind driver; deploy/driver*.example.toml)")
    ap.add_argument("--robot", type=robot_arg, default=None, help="robot name (overrides the config)")
    add_zenoh_args(ap)
    ap.add_argument("--rate", type=positive_float, default=None, help="control loop rate, Hz (overrides the config)")
    ap.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    ap.add_argument("--emulate", action="store_true", help="host emulated CAN motor controllers in-process")
    ap.add_argument("--model", default="mpc", help="learner model for --emulate (mpc, experiment, scaled)")
    ap.add_argument("--x0", type=pose_arg, default=(0.0, 0.0, 0.0), help="start pose x,y,theta for --emulate")
    ap.add_argument("--drift", default=None, metavar="KIND[:AT[:OVER[:AMOUNT]]]",
                    help="for --emulate: the learner changes at run time, battery (the motors' top speed falls) or "
                         "wheel (the left wheel drags), AT s after the wheels first turn, over OVER s (default 20:10)")
    ap.add_argument("--engage", action="store_true",
                    help="engage the vehicle at start, as engage_on_start (a person at the keyboard; never in a unit "
                         "that restarts)")
    ap.add_argument("--dry-run", action="store_true",
                    help="run the whole loop and publish applied, but send nothing to the vehicle (bring-up)")
    ap.add_argument("--insecure", action="store_true",
                    help="UDP link without a key_file ([link.udp] insecure = true): no authentication, anyone on the "
                         "network can drive the robot (loopback tests; said in the log and on status)")


def _emulated_ecus(cfg, model: str, x0: tuple[float, float, float], drift: str | None = None):
    """The learner's two emulated motor controllers on the driver's virtual CAN channel (``--emulate``), changing
    at run time as ``drift`` says (``--drift``)."""
    from sim_learner.can_ecu import DiffDriveEcus, Drift
    from sim_learner.dynamics import model_by_name
    from sim_learner.vehicle import SimVehicle

    vehicle = SimVehicle(model_by_name(model), x0, now=time.monotonic())
    return DiffDriveEcus({"interface": "virtual", "channel": cfg.channel}, vehicle, left_node=cfg.left_node,
                         right_node=cfg.right_node, left_sign=cfg.left_sign, right_sign=cfg.right_sign,
                         wheel_radius=cfg.wheel_radius, track_width=cfg.track_width,
                         drift=Drift.parse(drift) if drift else None).start()


def run(args: argparse.Namespace) -> int:
    if args.emulate and args.link != "can":
        raise UsageError("--emulate hosts CAN motor controllers; run `scmbridge learner` for the other links")
    if args.drift is not None:
        if not args.emulate:
            raise UsageError("--drift changes the emulated controllers: give --emulate")
        from sim_learner.can_ecu import Drift

        try:
            Drift.parse(args.drift)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    cfg = load_driver(args.config)  # a mistake ends here, before any link or session opens
    robot = M.check_robot(args.robot or cfg.robot)
    link_cfg = getattr(cfg.link, args.link)
    if args.emulate:
        link_cfg = msgspec.structs.replace(link_cfg, interface="virtual", channel=f"scm-{robot}",
                                           initial_pose=args.x0)
    if args.insecure:  # a person's opt-in, on the command line where it is seen (and on status, and in the log)
        if not hasattr(link_cfg, "insecure"):
            raise UsageError(f"--insecure is for --link udp (the {args.link} link has no such setting)")
        link_cfg = msgspec.structs.replace(link_cfg, insecure=True)
    for name in ("key_file", "signing_key_file"):  # a missing or unsafe key is one line now, not a retry loop later
        if getattr(link_cfg, name, ""):
            load_key(getattr(link_cfg, name), args.link)
    host = DriverHost(cfg, args.link, open_driver(args.link, link_cfg), robot, args.rate or cfg.driver.rate_hz,
                      dry_run=args.dry_run, latch_path=latch_file(robot))
    host.engage_on_start = host.engage_on_start or args.engage
    stop = stop_on_signals()
    ecus = _emulated_ecus(link_cfg, args.model, args.x0, args.drift) if args.emulate else None
    if ecus is not None:
        host.co_located.append(ecus)
    try:
        with open_session(zenoh_config(args), wait=stop, what="driver host") as session:
            host.serve(session, stop, args.duration)
    finally:
        host.close()
        if ecus is not None:
            ecus.stop()
    return 0
