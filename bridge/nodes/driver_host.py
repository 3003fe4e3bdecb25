"""The driver host (:class:`DriverHost`): between Zenoh and one vehicle link; what it does for a person and the
vehicle is the ``scmbridge driver`` command's to say (:mod:`bridge.nodes.driver_cmd`, docs/ARCHITECTURE.md).

The host is the wiring (one job per class): Zenoh callbacks -> the pure pieces -> the link, in its loop.
The pieces are :mod:`bridge.core.gate` (the command gate), :mod:`bridge.nodes.engagement` (a person's consent and the
last word on each decision), :mod:`bridge.nodes.pose_feed` (the poses published, motion capture restamped),
:mod:`bridge.nodes.host_status` (the status) and :mod:`bridge.nodes.latch_store` (the estop latch on disk).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from bridge.core import wire as M
from bridge.core.acts import ActGuard, Refusal
from bridge.core.backoff import Backoff
from bridge.core.clock import SYSTEM, Clock
from bridge.core.errors import UsageError
from bridge.core.gate import CommandGate, Decision
from bridge.core.paths import save_atomic
from bridge.core.stalls import BlockedLoop, Usage
from bridge.nodes import systemd
from bridge.nodes.driver_config import DriverConfig
from bridge.nodes.engagement import Engagement, OperatorEvent, Outcome, overrule
from bridge.nodes.host_loop import Echo, HostOptions, HostTiming
from bridge.nodes.host_status import Assessment, HostFacts, HostStatus, host_counters, node_state
from bridge.nodes.latch_store import LatchStore, SaveResult
from bridge.nodes.node import FixedRate, Inputs, StatusOut
from bridge.nodes.pose_feed import PoseFeed
from drivers.base import Driver, DriverError, LinkHealth, close_link, link_unauthenticated

log = logging.getLogger("scmbridge.driver")


#: the first and the longest wait between attempts to open a link that is not there yet, s
OPEN_BACKOFF = (0.5, 10.0)
#: ticks the link may get back to back (the send budget, a token bucket of ``max_send_hz``): a command that arrives
#: just after a periodic tick is sent at once; over any T seconds the link gets at most SEND_BURST + max_send_hz * T
SEND_BURST = 2
#: s ``close()`` waits for a latch save still under way before the process ends
LATCH_FLUSH_S = 2.0
#: s an estop query's answer says why the last release was refused
RELEASE_REFUSED_SHOWN_S = 10.0


class DriverHost:
    """One robot's driver host: the wiring between Zenoh, its pieces and the link (see the module docstring).

    The pieces, each with one job: the gate (:class:`bridge.core.gate.CommandGate`: which command the vehicle may
    get), the engagement (:class:`bridge.nodes.engagement.Engagement`: whether a person let it drive, and the last
    word on each decision), the pose feed (:class:`bridge.nodes.pose_feed.PoseFeed`: the poses published, motion
    capture put on this host's clock), the status (:class:`bridge.nodes.host_status.HostStatus`) and the estop latch
    on disk (:class:`bridge.nodes.latch_store.LatchStore`). The host owns the Zenoh callbacks, the loop and the link.

    Threads and locks (docs/ARCHITECTURE.md section 4): ``lock`` guards what Zenoh's callback threads and the loop
    share: the gate, the act guard, the engage queries waiting for the loop, the pose feed's motion-capture inbox,
    ``latch_unsaved``, ``release_refused`` and ``clear_requested``. The engagement, the status, the link and the
    pose feed's stream are the loop thread's alone. The latch store's writer has its own lock and calls back
    (:meth:`_latch_saved`) from its own thread, taking ``lock`` only to apply what a save came to; nothing does file
    I/O under ``lock``."""

    def __init__(self, cfg: DriverConfig, link: str, driver: Driver, robot: str, rate_hz: float, *,
                 dry_run: bool = False, latch_path: Path | None = None,
                 latch_saver: Callable[[Path, bytes], None] = save_atomic, clock: Clock = SYSTEM) -> None:
        """``dry_run``: run the whole loop and publish what would be applied, sending nothing to the vehicle;
        ``latch_path``: where the estop latch is kept (None: in memory only; its install marker beside it,
        :func:`bridge.nodes.latch_store.latch_marker`; both kept in :attr:`options`); ``latch_saver``: how the writer
        saves it (atomically; a test slows it down or has it fail as a full disk does). The first start's marker and
        released latch are written with :func:`save_atomic` (:meth:`LatchStore.open`). ``clock``: the host's time, the
        station's kind of clock (:class:`bridge.core.clock.Clock`, kept in :attr:`timing`; the link is built on the
        same one): the loop reads it once a tick and hands that ``now`` to the link and the pieces; every wait (the
        loop's, the link's open retries) is its ``wait``, so a test drives the loop on a fake clock."""
        d = cfg.driver
        self.link, self.driver, self.robot = link, driver, robot
        self.keys = M.Keys(robot)
        self.settings = d  # the [driver] section: telemetry age, stop speed and timeout, max_drive_on_s
        self.timing = HostTiming(rate_hz, d.max_send_hz, clock)
        self.options = HostOptions(dry_run=dry_run, engage_on_start=d.engage_on_start, latch_path=latch_path)
        self.gate = CommandGate(d.hard_limits.bounds(), d.cmd_timeout, tuple(d.estop_release_sources))
        #: acceleration and jerk limits on what the vehicle gets (the loop thread's; bridge.core.limiter): a stalled
        #: loop's step is bounded by two periods' worth
        self.limiter = d.hard_limits.limiter(self.timing.period)
        self.inputs = Inputs()
        self.lock = threading.Lock()  # see the class docstring: what Zenoh's callback threads and the loop share
        self.wake = threading.Event()
        self.clear_requested = False
        self.echo = Echo()
        self.health = LinkHealth()
        self.pubs: dict[str, zenoh.Publisher] = {}
        self.poses = PoseFeed("mocap" if d.pose_source == "mocap" else link, M.new_epoch(), d.mocap_window_s)
        operator_engages = bool(getattr(driver, "operator_engages", False))
        self.engagement = Engagement(follows_operator=operator_engages and not dry_run)
        self.engage_queries: list[tuple[zenoh.Query, M.EngageRequest]] = []  # answered by the loop thread
        #: engage requests and estop releases are taken fresh and once (bridge.core.acts); under the lock
        self.acts = ActGuard(self.poses.epoch, persons=tuple(d.estop_release_sources) or ("operator",))
        self.release_refused: tuple[str, float] = ("", -math.inf)  # why the last release was refused, and when
        #: the status; it also keeps why anyone on the network can drive this robot through its link ("" when the
        #: link authenticates) and the link's failsafe report once read
        self.reporter = HostStatus(robot, link, period=self.timing.period, max_telemetry_age=d.max_telemetry_age_s,
                                   operator_engages=operator_engages,
                                   unauthenticated=link_unauthenticated(getattr(driver, "config", None)),
                                   max_drive_on=d.max_drive_on_s)
        #: why the latch on disk is not the gate's (its save failed): while set the host stops and refuses to engage;
        #: cleared by the next save that succeeds (a person's release, on a disk that takes it)
        self.latch_unsaved = ""
        self.latch = LatchStore(latch_path, self._latch_saved, latch_saver)
        saved = self.latch.open()
        if saved.latched:
            self.gate.estop(M.Estop(stamp=0.0, engaged=True, source=saved.source, reason=saved.reason))
            log.warning("estop latched by %s (kept from before this start): %s", saved.source or "unknown",
                        saved.reason or "no reason given")

    @property
    def engaged(self) -> bool:
        """A person (or the operator, on MAVLink) engaged the vehicle since this host started."""
        return self.engagement.engaged

    @engaged.setter
    def engaged(self, value: bool) -> None:  # (tests and benchmarks start from an engaged host)
        self.engagement.engaged = value

    # ---------------------------------------------------------------------------------------------- inputs
    def on_mocap(self, st: M.LearnerState, now: float) -> None:
        """A motion-capture sample: its own stamp put on this host's clock (:class:`PoseFeed`). A sample stamped
        ahead of any possible delivery is dropped (``mocap_dropped``: forged, or a clock step not yet confirmed); a
        confirmed step of the bridge's clock restarts the estimate (``mocap_clock_restarts``)."""
        with self.lock:
            verdict = self.poses.offer_mocap(st, now)
            if verdict != "ok":
                self.inputs.count("mocap_clock_restarts" if verdict == "restarted" else "mocap_dropped")

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
            why = (self.acts.check(e.target, e.echo, e.nonce, e.source, now)
                   if not e.engaged and self.gate.estopped else None)
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
            if changed:  # under the lock, at each change: the last latch handed over is the gate's latest
                self.latch.submit(self.gate.estopped, self.gate.estop_source, self.gate.estop_reason)
        self.wake.set()
        if changed:
            log.warning("estop %s by %r: %s", "engaged" if e.engaged else "released", e.source, e.reason)
        elif why is not None and why.kind != "source":
            log.warning("estop release by %r %s", e.source, why.text)

    def _latch_saved(self, result: SaveResult) -> None:
        """A save's result (the writer's thread). Fail safe: a latch that could not be saved must not come back
        released after a restart (the store has removed the old file), nor be released in memory while the disk
        cannot say so: a failed release latches the gate again; either way the host stops, refuses to engage and
        says why on status (reason ``latch_unsaved``) until a save succeeds: a person's release on a disk that
        takes it."""
        if result.saved:
            with self.lock:
                was, self.latch_unsaved = self.latch_unsaved, ""
            if was:
                log.warning("estop latch saved to %s (%s)", self.options.latch_path,
                            "latched" if result.latch.latched else "released: the host may be engaged again")
            return
        self.inputs.count("latch_save_failures")
        with self.lock:
            self.latch_unsaved = result.text
            if result.relatch and not self.gate.estopped:  # (a newer estop may have latched it meanwhile)
                self.gate.estop(M.Estop(stamp=0.0, engaged=True, source="unsaved release", reason=result.text[:200]))

    def on_engage_query(self, query: zenoh.Query) -> None:
        """A person's ``scmbridge engage``: handed to the loop (which owns the link) and answered from there."""
        now = self.timing.clock()
        try:
            payload = query.payload
            req = M.decode(payload.to_bytes() if payload is not None else b"", M.EngageRequest)
        except M.MessageError as exc:
            self.inputs.count("malformed_engage")
            query.reply(self.keys.engage, M.encode(M.EngageState(
                stamp=now, node=f"driver-{self.link}", engaged=self.engaged, accepted=False,
                text=f"malformed request: {exc}"[:1024], epoch=self.acts.epoch)))
            return
        with self.lock:  # engaging is taken fresh and once (bridge.core.acts); handing the vehicle back always
            why = (self.acts.check(req.target, req.echo, req.nonce, req.source, now)
                   if req.engaged else None)
            if why is None:
                self.engage_queries.append((query, req))
        if why is not None:
            n = self.inputs.count(f"engage_refused_{why.kind}")
            if n & (n - 1) == 0:  # the 1st, 2nd, 4th, 8th... of a kind: a flood of acts logs a dozen lines, not 4000
                (log.debug if why.kind == "unaddressed" else log.warning)(
                    "engage by %r %s (%d refused so; counter engage_refused_%s)", req.source, why.text, n, why.kind)
            query.reply(self.keys.engage, M.encode(M.EngageState(
                stamp=now, node=f"driver-{self.link}", engaged=self.engaged, accepted=False,
                text=why.text[:1024], epoch=self.acts.epoch)))
            return
        self.wake.set()

    def handle_engage(self, req: M.EngageRequest, now: float, clear: bool = False) -> M.EngageState:
        """Engage (or hand back) the vehicle, in the loop thread; the answer says what was done or why not (the
        engagement rules, :meth:`Engagement.request`; the link's own refusal)."""
        node = f"driver-{self.link}"

        def answer(**kw: Any) -> M.EngageState:  # stamped on this host's clock, with its epoch: the next act's address
            # (read when answered: the link's engage may have taken seconds, and the next act echoes this stamp)
            return M.EngageState(stamp=self.timing.clock(), node=node, epoch=self.acts.epoch, **kw)

        who = f" by {req.source}" if req.source else ""
        with self.lock:
            latched, source, unsaved = self.gate.estopped, self.gate.estop_source, self.latch_unsaved
        ruling = self.engagement.request(req.engaged, now, estopped=latched, estop_source=source, unsaved=unsaved)
        outcome = ruling.outcome
        if outcome in (Outcome.DISENGAGED, Outcome.NOT_ENGAGED):
            log.warning("disengaged%s: the vehicle gets stops only", who)
            return answer(engaged=False, text=outcome.value)
        if outcome is Outcome.ALREADY_ENGAGED:
            return answer(engaged=True, text=outcome.value)
        if not outcome.accepted:
            return answer(engaged=False, accepted=False, text=ruling.text[:1024])
        if not self.options.dry_run:
            try:
                self.driver.engage(now, clear_faults=clear)
            except DriverError as exc:
                log.warning("engage%s refused: %s", who, exc)
                return answer(engaged=False, accepted=False, text=str(exc)[:1024])
        self.engagement.confirm(now)
        log.warning("engaged%s: the vehicle follows the station's commands", who)
        return answer(engaged=True, text="engaged" + (" (dry run)" if self.options.dry_run else ""))

    def _answer_engage_queries(self, now: float) -> None:
        with self.lock:
            pending, self.engage_queries = self.engage_queries, []
        for query, req in pending:
            ans = self.handle_engage(req, now, req.clear_faults)
            try:
                query.reply(self.keys.engage, M.encode(ans))
            finally:
                query.drop()

    def on_estop_query(self, query: zenoh.Query) -> None:
        """Answered with the latch state; while a change of it is being saved, from the writer's thread once saved
        (a confirmed latch survives a restart, as when the save ran in the estop's callback)."""
        if self.latch.defer(lambda: self._answer_estop_query(query, True)):
            return
        self._answer_estop_query(query)

    def _answer_estop_query(self, query: zenoh.Query, deferred: bool = False) -> None:
        with self.lock:  # an unsaved latch is latched, and says so (estop prints it beside LATCHED)
            now = self.timing.clock()
            why, at = self.release_refused
            st = M.EstopState(stamp=now, node=f"driver-{self.link}",
                              latched=self.gate.estopped or bool(self.latch_unsaved), source=self.gate.estop_source,
                              reason=(self.latch_unsaved or self.gate.estop_reason)[:1024],
                              release_refused=why[:1024] if now - at < RELEASE_REFUSED_SHOWN_S else "",
                              epoch=self.acts.epoch)
        try:
            query.reply(self.keys.estop, M.encode(st))
        finally:
            if deferred:
                query.drop()

    # ------------------------------------------------------------------------------------------------ tick
    def decide(self, now: float) -> Decision:
        """The gate's decision, overruled by engagement, the link's health and the telemetry's age
        (:func:`bridge.nodes.engagement.overrule`). MAVLink: the operator taking the vehicle (leaving GUIDED)
        disengages; the operator putting it in GUIDED and arming it while the host runs engages
        (:meth:`Engagement.follow`)."""
        self.health = h = self.driver.health(now)
        event = self.engagement.follow(h, now)
        if event is OperatorEvent.TOOK:
            log.warning("disengaged: %s", h.text)
        elif event is OperatorEvent.GAVE:
            log.warning("engaged by the operator: %s", h.text)
        with self.lock:
            d = self.gate.decide(now)
            clear, self.clear_requested = self.clear_requested, False
            unsaved = self.latch_unsaved
        if clear:
            log.warning("operator released the estop: clearing the link's latched faults")
            self.driver.clear_faults(now)
        d = overrule(d, now, engaged=self.engaged, unsaved=bool(unsaved), health=h, dry_run=self.options.dry_run,
                     last_pose=self.poses.last_pose, max_telemetry_age=self.settings.max_telemetry_age_s)
        return self.limited(d, now)

    def limited(self, d: Decision, now: float) -> Decision:
        """The last word: a driving decision within the acceleration and jerk limits (a command the limiter
        changed is ``clamped``), any other exactly zero, at once (:class:`bridge.core.limiter.SpeedLimiter`)."""
        if not d.driving:
            self.limiter.stop(now)
            return d
        v, w = self.limiter.limit(d.v, d.omega, now)
        return d if (v, w) == (d.v, d.omega) else Decision(v, w, "clamped", d.cmd_seq)

    def tick(self, now: float) -> None:
        """Read the link, then decide and send. The link is read before its health and the telemetry's age are
        judged, so that after a stall of the host's own the Heartbeats waiting unread on the bus count as heard, not
        as lost (a link that really went silent still fails). Each pose is checked and encoded once: the bytes the
        check decoded are the bytes published."""
        if self.engage_queries:
            self._answer_engage_queries(now)
        for st in self._read_link(now):
            try:
                self.pubs["state"].put(M.validated_bytes(st)[1])
            except M.MessageError:
                self.inputs.count("telemetry_out_of_range")
                log.warning("telemetry out of range, not published: %s", st)
                continue
            self.poses.published(now, st)
        d = self.decide(now)
        if self.options.dry_run:
            pass  # what would be sent is published on applied; the vehicle gets nothing
        elif d.driving:
            self.driver.send(d.v, d.omega, now)
        else:
            self.driver.stop(now)
        if d.reason != self.echo.last.reason:
            if not d.driving:
                log.info("vehicle stopped: %s", d.reason)
            elif not self.echo.last.driving:
                log.info("vehicle driving (%s)", d.reason)
        self.echo.last = d
        self._put("applied", M.Applied(stamp=now, seq=self.echo.seq, v=d.v, omega=d.omega, reason=d.reason,
                                       cmd_seq=d.cmd_seq))
        self.echo.seq += 1

    def _read_link(self, now: float) -> list[M.LearnerState]:
        """Let the co-located emulated devices send what is due, read the link, and return this tick's poses: the
        link's telemetry, or the motion-capture samples (the link is read either way: its frames carry the vehicle's
        health)."""
        for device in self.options.co_located:
            device.emit_due()
        link = self.driver.poll(now)
        samples: list[M.LearnerState] = []
        if self.poses.mocap_source:
            with self.lock:
                samples = self.poses.take_mocap()
        return self.poses.states(link, samples)

    # ---------------------------------------------------------------------------------------------- status
    def _assess(self, now: float) -> Assessment:
        """This instant's facts (the shared ones read under the lock) and what they come to
        (:meth:`HostStatus.assess`)."""
        with self.lock:
            estopped, source = self.gate.estopped, self.gate.estop_source
            unsaved = self.latch_unsaved
            conflict = self.gate.conflict(now)
        facts = HostFacts(health=self.health, engaged=self.engaged, last_pose=self.poses.last_pose,
                          measured=self.poses.measured,
                          estopped=estopped, estop_source=source, unsaved=unsaved, conflict=conflict,
                          dry_run=self.options.dry_run)
        return self.reporter.assess(facts, now)

    def status(self, now: float, assessed: Assessment | None = None) -> M.Status:
        """Health as it is: ok only if the link is fit, the telemetry fresh and no estop is latched."""
        with self.lock:
            gate_counters = dict(self.gate.counters)
        counters = host_counters(gate_counters, self.inputs.snapshot(), self.health,
                                 unauthenticated=bool(self.reporter.unauthenticated),
                                 missed=self.timing.missed,
                                 stalls=self.timing.stall_watch.stalls, ticks=len(self.timing.ticks))
        if not self.limiter.unlimited:
            counters["rate_limited"] = self.limiter.limited
        a = assessed if assessed is not None else self._assess(now)
        if a.state != self.reporter.logged_state:
            log.info("%s: %s", a.state, "; ".join(a.problems) or "engaged and fit")
            self.reporter.logged_state = a.state
        return self.reporter.build(now, a, counters=counters, late=self.timing.late,
                                   failsafe=self.reporter.failsafe,
                                   driving_reason=self.echo.last.reason)

    def node_state(self, estop: bool, h: LinkHealth, pose_age: float, problems: list[str],
                   unsaved: bool = False) -> tuple[M.NodeState, M.Reason]:
        """The one word ``scmbridge status`` shows for this host, and its typed reason
        (:func:`bridge.nodes.host_status.node_state` with this host's engagement and dry run)."""
        return node_state(estop, h, pose_age, problems, unsaved, engaged=self.engaged, dry_run=self.options.dry_run,
                          max_telemetry_age=self.settings.max_telemetry_age_s)

    def _status_due(self, now: float) -> Assessment | None:
        """This tick's assessment when a status should go out now (:meth:`HostStatus.due`: each second, and at
        once on a change of ok, state or reason)."""
        assessed = self._assess(now)
        return assessed if self.reporter.due(assessed, now) else None

    # ------------------------------------------------------------------------------------------------ run
    def _put(self, topic: str, msg: msgspec.Struct) -> None:
        self.pubs[topic].put(M.encode(msg))

    def serve(self, session: zenoh.Session, stop: threading.Event, duration: float | None) -> None:
        """Declare the host's keys, open the link and run the loop until ``stop`` or ``duration``."""
        try:
            self._serve(session, stop, duration)
        finally:  # what it declared goes when it stops serving, not when the session closes (it may be shared)
            self.inputs.declared.undeclare()

    def _serve(self, session: zenoh.Session, stop: threading.Event, duration: float | None) -> None:
        k, keep = self.keys, self.inputs.declared.keep
        self.inputs.subscribe(session, k.cmd, M.Command, "cmd", self.on_cmd)
        self.inputs.subscribe(session, k.estop, M.Estop, "estop", self.on_estop)
        self.inputs.answer(session, k.estop, "estop", self.on_estop_query)  # a flood of queries delays no sample
        self.inputs.answer(session, k.engage, "engage", self.on_engage_query)
        keep(session.liveliness().declare_token(M.alive_key(self.robot, "driver")))
        if self.poses.mocap_source:
            self.inputs.subscribe(session, k.mocap, M.LearnerState, "mocap", self.on_mocap)
        self.pubs = {"applied": keep(session.declare_publisher(k.applied)),
                     "state": keep(session.declare_publisher(k.state)),
                     "status": keep(StatusOut(session, M.status_key(self.robot, "driver")))}
        self._put("status", self.reporter.starting(self.timing.clock(), "starting",
                                                   f"link {self.link}: opening (vehicle not yet ready)"))
        if not self._open_link(stop):
            return
        self.reporter.failsafe = failsafe = self.driver.failsafe()
        too_long = failsafe.drive_on_s is None or failsafe.drive_on_s > self.settings.max_drive_on_s
        (log.warning if too_long else log.info)("vehicle failsafe: %s%s", failsafe.text,
                                                f" (more than max_drive_on_s = {self.settings.max_drive_on_s:g} s)"
                                                if too_long else "")
        log.info("driver host for %s on link %s at %.0f Hz (epoch %x)%s", self.robot, self.link, 1 / self.timing.period,
                 self.poses.epoch, ": DRY RUN, nothing is sent to the vehicle" if self.options.dry_run else "")
        if self.reporter.unauthenticated:
            log.warning("link %s unauthenticated: %s: anyone on the network can drive it (status counter "
                        "unauthenticated_link = 1)", self.link, self.reporter.unauthenticated)
        if self.options.fence:  # a person's request: the vehicle holds this fence itself (drivers.mavlink.fence)
            try:
                log.warning("%s", self.driver.upload_fence(self.options.fence))  # type: ignore[attr-defined]
            except DriverError as exc:
                raise UsageError(f"--fence: the vehicle did not take the fence: {exc}") from None
        systemd.ready(f"{self.robot}: link {self.link} open, "
                      + ("engaging (engage_on_start)" if self.options.engage_on_start else "waiting for engage"))
        self.loop(stop, duration)

    def _engage_on_start(self) -> None:
        """``engage_on_start`` (a person's act at start-up), done by the running loop right before its first tick, as
        an engage request is: the controllers it arms are fed by that tick at once, and a stall after the arming is
        watched and reported like any other. Armed before the loop runs, the controllers would go unfed while the
        loop is set up (its watcher thread started), where no stall is watched."""
        ans = self.handle_engage(M.EngageRequest(stamp=0.0, source="engage_on_start"), self.timing.clock())
        if not ans.engaged:
            log.error("engage_on_start: %s", ans.text)

    def _open_link(self, stop: threading.Event) -> bool:
        """Open the link, retrying with a backoff while the vehicle (or the CAN interface) is not there, saying what
        it waits for on status, in the log (once per reason) and to systemd; False if stopped meanwhile."""
        backoff, said = Backoff(*OPEN_BACKOFF), ""
        while not stop.is_set():
            try:
                self.driver.open(self.timing.clock())  # bounded by the link's open_timeout
                return True
            except DriverError as exc:
                text = f"link {self.link}: waiting for the vehicle: {exc}"
                if text != said:
                    log.warning("%s; trying again (every %.0f s at most)", text, backoff.maximum)
                    said = text
                systemd.status(text[:200])
                self._put("status", self.reporter.starting(self.timing.clock(), "link_down", text))
                close_link(self.driver, self.timing.clock(), disarm=False, stop_timeout=0.0)  # let go before the retry
                self.timing.wait(stop, backoff.delay)
                backoff.grow()
        return False

    def close(self) -> None:
        """Stop, wait until the vehicle has stopped, then disarm / idle (only what this host engaged); then let a
        latch save still under way finish (bounded: ``LATCH_FLUSH_S``)."""
        systemd.stopping()
        try:
            if self.options.dry_run:
                close_link(self.driver, self.timing.clock(), disarm=False, stop_speed=self.settings.stop_speed,
                           stop_timeout=0.0)
                return
            cfg = self.settings
            close_link(self.driver, self.timing.clock(), disarm=self.engaged, stop_speed=cfg.stop_speed,
                       stop_timeout=cfg.stop_timeout)
        finally:
            if not self.latch.close(LATCH_FLUSH_S):
                log.error("estop latch: the save to %s did not finish within %.0f s of closing",
                          self.options.latch_path, LATCH_FLUSH_S)

    def loop(self, stop: threading.Event, duration: float | None) -> None:
        """Periodic ticks, plus an immediate tick for each accepted command, estop or engage query (the wake); the
        scheduler is the station's (:class:`FixedRate`). A woken tick re-phases the period (the link got a command:
        the periodic re-send is due a period later) and the link's send budget (``max_send_hz``, a burst of
        ``SEND_BURST``) bounds the send rate whatever arrives. Why both: with ticks never closer than
        1 / max_send_hz on a fixed schedule, a command published within that gap after a periodic tick waits out the
        rest of it, and a periodic tick after a command tick is pushed back the same way; a token bucket alone on the
        fixed schedule sends as many ticks as its budget and queues (``scmbridge bench bridge`` measures the latency
        and jitter: docs/BENCHMARKS.md, "The bridge")."""
        t_start = self.timing.clock()
        timing = self.timing
        timing.ticker = ticker = FixedRate(1.0 / timing.period, stop, wake=self.wake, max_hz=timing.max_send_hz,
                                           burst=SEND_BURST, rephase=True, clock=timing.clock, wait=timing.wait)
        periodic = True
        blocked = BlockedLoop(self.timing.stall_report_s, stop, log).start()
        try:
            if self.options.engage_on_start and not stop.is_set():
                self._engage_on_start()
            while not stop.is_set():
                blocked.beat()
                now = self.timing.clock()
                if duration is not None and now - t_start >= duration:
                    return
                if periodic:
                    self.timing.ticks.append(now)
                self.tick(now)
                # after the tick, off a woken command's way (reading the process's and the machine's usage costs
                # tens of microseconds); the gap is still the one between this iteration's now and the last's
                stalled = self.timing.stall_watch.check(now, Usage.now())
                if stalled:
                    log.warning("%s", stalled)
                assessed = self._status_due(now)
                if assessed is not None:
                    self._put("status", self.status(now, assessed))
                periodic = ticker.wait()
                if periodic:
                    self.timing.late.append(ticker.late)
        finally:
            blocked.done()
