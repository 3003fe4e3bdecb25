"""``scmbridge station``: the base-station service, the teacher and the transfer policy in a fixed-rate loop.

Each tick (10 Hz default; absolute deadlines, missed ones counted) it takes the learner states and applied-command
echoes that arrived, forms the command pairs they really bracket (:mod:`bridge.nodes.pairing`), updates the pair store
(and so the learned limits), and then either drives or says why not:

- it drives only while a person has started the mission (:mod:`bridge.nodes.mission_control`: it starts idle;
  ``scmbridge mission start``, or ``--start``; requests are answered on ``scm/<robot>/control``) and the robot is
  fit: the driver host's status is fresh and ``ok`` (link up, engaged, no fault, no estop), and the latest pose
  arrived less than ``max_pose_age_s`` ago; a robot that stops being fit while driving pauses the mission until a
  person resumes it;
- otherwise, and at the goal, it publishes stops and its status says why (``idle: ...``, ``paused: estop latched by
  operator``, ``waiting for the robot: ...``, ``goal reached``).

Driving: the teacher MPC, bounded by the learned limits and given the obstacles that matter, proposes a command;
the transfer policy maps it; ``cmd`` carries it (with the method, a validity of three periods, this run's sender
name and epoch) and ``teacher`` the teacher's own command and plan. ``limits`` is published when the learned
limits change and each second; ``pairs`` answers queries; ``mission`` takes a program's new mission (the goal state
resets): in place while running, else loaded idle until a person's ``mission start`` (never a start by itself), and
the status and the answers say where it came from and when. Mission requests other than ``status`` are taken only
addressed to this run, fresh and once (``bridge.core.acts``: its epoch, an echo of its clock within 10 s and a nonce
not seen; one without them is refused). Without TLS it says at start that anyone who can reach its Zenoh session
may command the robot.
The pair store is persisted atomically every ``persist_every_s`` and at exit, and reloaded at start; a failed save
(a full disk) is logged, reported on status and retried, and never stops the loop; the saves are written by a writer
thread from the bytes the tick encoded, so a slow disk never delays a tick. Callbacks only decode and store, under a
lock the loop holds only to take what they left; all work is in the loop, which also answers the queries
(docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from pathlib import Path

import msgspec
import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg, robots_arg
from bridge.core.clock import SYSTEM, Clock
from bridge.core.config import RATE_HZ_RANGE, StationConfig, load_mission_spec, load_station
from bridge.core.errors import UsageError
from bridge.core.paths import TEXT_FILE, quarantine, read_bounded, save_atomic, state_dir
from bridge.nodes import systemd
from bridge.nodes.fleet_loop import DEFAULT_LOOP_THREADS, FLEET_SWITCH_INTERVAL_S, Deadlines, FleetLoop
from bridge.nodes.mission_control import Fitness, MissionControl, Saved
from bridge.nodes.node import (
    FixedRate,
    Inputs,
    OffThread,
    Queued,
    StatusOut,
    add_zenoh_args,
    freeze_startup_heap,
    on_zenoh,
    stop_on_signals,
    stopped_because,
    zenoh_config,
)
from bridge.nodes.sources import MpcSource
from bridge.nodes.station_core import StationCore, TickOutputs
from bridge.nodes.station_inbox import Asked, Receiver
from bridge.nodes.station_journal import Journal
from bridge.nodes.station_tags import FileTags
from bridge.nodes.writer import Save, SaveWriter
from bridge.nodes.zsession import open_session
from transfer.calibration import CalibrationPlan
from transfer.mission import Mission

log = logging.getLogger("scmbridge.station")


#: a mission request that waited this long for the loop is dropped unanswered, s: its asker (``scmbridge mission``
#: waits at most 1 s for one reply) has given up and asks again; acting on it now would act on a stale request
CONTROL_MAX_WAIT_S = 0.9
#: the process's one thread for what a station's callbacks (run on Zenoh's thread) must not do there: a mission
#: built from its message, a query answered while no loop runs (docs/ARCHITECTURE.md, "Threads and clocks")
OFF_ZENOH = OffThread("station-off-zenoh")
#: a start or resume that the robot's fitness alone would refuse waits up to this long for a driver host status that
#: arrives after it, s: one sent on an engage or an estop release confirmed just before the request may still be on
#: its way (the host publishes it within a tick or two of the change; its answer to the person can come first)
SETTLE_S = 0.3


class KernelBuild:
    """The MPC's compiled code, built in a background thread (:mod:`bridge.teacher.codegen`: once per machine, then
    loaded from the cache in milliseconds) while the stations already run the same functions interpreted; each loop
    switches its teacher to it between two ticks (:meth:`adopt`). Never a build inside a tick. One build serves
    every robot of a process whose MPC solves the same problem."""

    def __init__(self, teacher) -> None:
        self.result: list | None = None
        self.done = threading.Event()
        kernels = teacher.kernels() if teacher is not None else []
        if kernels:
            threading.Thread(target=self._build, args=(kernels,), name="mpc-build", daemon=True).start()
        else:
            self.done.set()

    def _build(self, kernels: list) -> None:
        from bridge.teacher.codegen import compile_functions

        try:
            self.result = compile_functions(kernels)
        finally:
            self.done.set()

    def adopt(self, teacher) -> bool:
        """Switch ``teacher`` to the compiled code when ready (from its station's loop, between ticks): True once."""
        if not self.done.is_set() or self.result is None or teacher is None or teacher.compiled:
            return False
        teacher.use_compiled(self.result)
        log.info("MPC: compiled code in use")
        return True


class Station:
    """One robot's station on Zenoh: the Zenoh adapter of a :class:`~bridge.nodes.station_core.StationCore`.

    The core does the work of each tick (pairing, the command source, the transfer step, mission control, the status
    and persistence). Here subscribers decode, count and put what arrives into a typed inbox under the lock of
    :attr:`rx` (:class:`~bridge.nodes.station_inbox.Receiver`, the callbacks), which the loop holds only to swap
    the inbox out: the tick itself runs without it, so no callback
    ever waits for a tick (an MPC solve) or a save. The fixed-rate loop hands the inbox to ``core.tick`` and publishes
    what it returns; the core is only ever called from the loop's thread. The queryables (``control``, ``pairs``)
    put their query in the inbox and wake the loop, which answers it at once between two ticks (or, when it
    arrived during one, right after it): a mission request acts on the state the ticks leave and the driver host's
    latest status (one sent on an engage or a release a moment before is heard), as one tick's decision is never
    split by it, and ``pairs`` reads a store no tick is updating. Before the loop starts and
    after it ends a query is answered in its callback. An external teacher's command also wakes the loop, so it is
    mapped as it arrives. The tick's saves go to a :class:`~bridge.nodes.writer.SaveWriter` (a snapshot taken in
    the tick, encoded and written by its thread; a failure comes back to the core at the next tick, as before)."""

    def __init__(self, cfg: StationConfig, robot: str, rate_hz: float, store_path: Path, mission: Mission,
                 control: MissionControl | None = None, control_path: Path | None = None,
                 calibration: CalibrationPlan | None = None, save: Save = save_atomic, clock: Clock = SYSTEM) -> None:
        """``control``: the mission's phase machine (default: ``mission``, idle); ``control_path``: where it is
        kept across restarts (None: not kept); ``calibration``: run this plan instead of a teacher; ``save``: how
        the writer thread saves a file (a test slows it down; the final save at exit is always
        :func:`~bridge.core.paths.save_atomic`); ``clock``: the time and the waits of the station, its loop and its
        core (a test's fake clock)."""
        self.clock = clock
        self.core = StationCore(cfg, robot, rate_hz, store_path, mission, control, control_path, calibration,
                                clock=clock, defer=True)
        self.robot, self.keys = robot, M.Keys(robot)
        self.period = self.core.time.period
        self.inputs = Inputs(clock)
        self.wake = threading.Event()  # a query, or an external teacher's command: the loop handles it now
        #: the callbacks: what arrives waits in its inbox, under its lock, for the loop (bridge.nodes.station_inbox)
        self.rx = Receiver(self.core.outbox.epoch, self.inputs, clock, lambda: self.wake.set(), self._answer,
                           off=OFF_ZENOH)
        self.writer = SaveWriter(save, name=f"station-save-{robot}")
        self.core.saves.writer = self.writer
        self.telemetry: list[Queued] = []  # the echoes' and the poses' queues, read at each tick (serve declares them)
        self.pubs: dict[str, zenoh.Publisher] = {}
        self.teacher_listener: zenoh.MatchingListener | None = None  # whether anyone subscribes to the teacher
        self.ticker: FixedRate | Deadlines | None = None  # its deadlines (and missed ones)
        self.build: KernelBuild | None = None
        self.teacher = self.core.source.teacher if isinstance(self.core.source, MpcSource) else None
        self.journal = Journal(self.core, cfg, Path(store_path))  # what the core is given, for a replay

    @property
    def store(self):
        return self.core.store

    @property
    def control(self) -> MissionControl:
        return self.core.control

    @property
    def calibration(self) -> CalibrationPlan | None:
        return self.core.calibration

    # ------------------------------------------------------------------------------------------------ queries
    def _answer(self, queries: list[Asked], now: float, settle: bool = False) -> None:
        """Do and answer the queries taken from the inbox (on the loop's thread, between two ticks): a mission
        request from the robot's fitness now, ``pairs`` from the store as the last tick left it. A mission request
        that waited more than :data:`CONTROL_MAX_WAIT_S` (a stalled loop) is dropped unanswered: its asker has
        given up and asks again. With ``settle`` (the loop's thread, the lock not held), a start or resume that only
        the robot's fitness refuses goes back to the inbox until a driver host status arrives after it, at most
        :data:`SETTLE_S` (else `engage` then `mission resume` at once is refused "waiting for
        engage": the host's answer to the engage can reach the person before its status reaches the station)."""
        later = [q for q in queries if settle and self._settling(q, now)]
        if later:
            self.rx.requeue(later)
            queries = [q for q in queries if q not in later]
        for q in queries:
            try:
                if q.kind == "pairs":
                    q.query.reply(self.keys.pairs, M.encode(self.core.pairs(now)))
                elif now - q.at > CONTROL_MAX_WAIT_S:
                    what = q.request.action if isinstance(q.request, M.MissionRequest) else "malformed"
                    log.warning("mission %s dropped unanswered: it waited %.1f s for the station's loop", what,
                                now - q.at)
                else:
                    if isinstance(q.request, M.MissionRequest):
                        self.journal.request(q.request, now)
                    ans = (self.core.request(q.request, now) if isinstance(q.request, M.MissionRequest)
                           else self.core.control.answer(now, False, str(q.request)))
                    # stamped on this station's clock, with its epoch: the address of the person's next act
                    ans = msgspec.structs.replace(ans, stamp=self.clock(), epoch=self.rx.acts.epoch)
                    q.query.reply(self.keys.control, M.encode(ans))
            except Exception:  # a query must never stop the loop (it did not when it failed in its callback)
                log.exception("%s query not answered", q.kind)
            finally:
                q.query.drop()  # the reply is final: the asker stops waiting for more

    def _settling(self, q: Asked, now: float) -> bool:
        """A start or resume the robot's fitness alone would refuse, younger than :data:`SETTLE_S`, with no driver
        host status heard since it arrived."""
        return (q.kind == "control" and isinstance(q.request, M.MissionRequest) and now - q.at < SETTLE_S
                and self.core.latest.driver_at <= q.at and self.core.refused_for_the_robot(q.request, now))

    # ------------------------------------------------------------------------------------------------ tick
    def tick(self, now: float, periodic: bool = True) -> TickOutputs:
        """Take the inbox (the lock held only for that), answer the queries that waited, hand the rest to the core
        and publish what it returns."""
        inbox = self.rx.take()
        if inbox.queries:
            if inbox.driver is not None:  # a request is judged on the robot as it is now
                self.journal.driver(*inbox.driver, now)
                self.core.note_driver(*inbox.driver)
            self._answer(inbox.queries, now, settle=True)  # a pause that came before this tick stops the robot in it
        for cmd, at in inbox.foreign:
            self.core.heard_command(cmd, at)
        for what, error in self.writer.results():
            self.core.saves.saved(what, error)
        if self.build is not None and self.build.done.is_set():
            self.build.adopt(self.teacher)
            self.build = None
        for q in self.telemetry:
            inbox.telemetry += q.drain(now)
        inputs = inbox.take(periodic, self.inputs.snapshot(), self.ticker.missed if self.ticker else 0)
        self.journal.tick(inputs, now, self.teacher is not None and self.teacher.compiled)
        out = self.core.tick(inputs, now)
        self._publish(out)
        return out

    def between_ticks(self) -> bool:
        """Woken before the next deadline: answer the queries that came; True when an external teacher's command
        waits to be mapped now."""
        queries, teacher, driver = self.rx.take_queries()
        if queries:
            now = self.clock()
            if driver is not None:  # the driver host's status that came since the tick: an engage, a release
                self.journal.driver(*driver, now)
                self.core.note_driver(*driver)
            self._answer(queries, now, settle=True)
        return teacher and self.core.source.external

    def background(self) -> bool:
        """The work the last tick's command left for later, done now: the loop calls it once the tick's outputs are
        out (:meth:`bridge.nodes.station_core.StationCore.background`); True when there was some."""
        return self.core.background()

    def _publish(self, out: TickOutputs) -> None:
        for topic, msg in (("cmd", out.command), ("teacher", out.teacher), ("limits", out.limits),
                           ("status", out.status)):
            if msg is not None:  # the command as the core checked it: encoded once
                self.pubs[topic].put(out.command_bytes if topic == "cmd" and out.command_bytes else M.encode(msg))

    def persist(self) -> bool:
        """The final save of the pair store (at exit, once the loop has ended): the writer's last saves first, then
        this one at once; False (reported on the status and logged by the caller) when it failed."""
        self._close_writer()
        with self.rx.lock:
            return self.core.saves.persist()

    def save_control(self) -> None:
        """The final save of the mission state (at exit), at once."""
        self._close_writer()
        with self.rx.lock:
            self.core.saves.save_control()

    def _close_writer(self) -> None:
        self.writer.close()
        with self.rx.lock:
            self.core.saves.writer = None
            for what, error in self.writer.results():
                self.core.saves.saved(what, error)

    # ------------------------------------------------------------------------------------------------- run
    def serve(self, session: zenoh.Session, stop: threading.Event, duration: float | None,
              exit_at_goal: bool, announce: bool = True, phase: float = 0.0) -> None:
        """Declare this robot's keys on ``session`` and run its fixed-rate loop until ``stop`` (or ``duration``, or
        the goal with ``exit_at_goal``). ``announce``: tell systemd the service is ready (one robot per process).
        ``phase``: seconds to wait before the first tick. (A many-robot process declares each robot's keys with
        :meth:`declare` and ticks them all from one thread: :class:`~bridge.nodes.fleet_loop.FleetLoop`.)"""
        self.declare(session, announce)
        if phase > 0 and stop.wait(phase):
            return
        self.begin()
        try:
            self._loop(stop, duration, exit_at_goal)
        finally:
            self.end()

    def _on_teacher_matching(self, status: zenoh.MatchingStatus) -> None:
        """A subscriber of the teacher topic came or the last one went (Zenoh's callback thread)."""
        self.core.latest.teacher_heard = bool(status.matching)

    def declare(self, session: zenoh.Session, announce: bool = False) -> None:
        """Declare this robot's inputs, queryables and publishers on ``session`` (nothing is ticked yet)."""
        k = self.keys
        external = self.core.source.external
        # poses (100 Hz) and echoes (50 Hz) wait in Zenoh's ring until the tick reads them: no callback per sample
        self.telemetry = [self.inputs.queue(session, k.applied, M.Applied, "applied"),
                          self.inputs.queue(session, k.state, M.LearnerState, "state")]
        # every callback runs on Zenoh's own thread (on_zenoh), none on a thread per declaration: each decodes,
        # counts and hands over under the inbox's lock; a mission is built, and a query answered while no loop runs,
        # on the process's OFF_ZENOH thread
        rx = self.rx
        self.inputs.subscribe(session, M.status_key(self.robot, "driver"), M.Status, "driver_status",
                              rx.on_driver_status, direct=True)
        self.inputs.subscribe(session, k.mission, M.MissionSpec, "mission",
                              lambda spec, now: OFF_ZENOH(rx.on_mission, spec, now), direct=True)
        # another sender's commands on this robot's key; this session's own (every command it publishes) never
        # reach the callback: Zenoh drops them at the source (a decode and a GIL handover per command saved)
        self.inputs.subscribe(session, k.cmd, M.Command, "own_cmd", rx.on_own_cmd, remote_only=True,
                              direct=True)
        if external:
            self.inputs.subscribe(session, k.teacher, M.TeacherCommand, "teacher", rx.on_teacher, direct=True)
        keep = self.inputs.declared.keep  # all undeclared by undeclare(): a fleet's failed robot lets go of its keys
        keep(session.declare_queryable(k.pairs, on_zenoh(rx.on_pairs_query)))
        keep(session.declare_queryable(k.control, on_zenoh(rx.on_control_query)))
        self.pubs = {t: keep(session.declare_publisher(getattr(k, t))) for t in ("cmd", "limits")}
        if not external:
            # the teacher message (the MPC's command and plan, for a person's viewer or a recorder) is built and
            # sent only while someone subscribes to it: a fleet's robots mostly have no viewer
            pub = self.pubs["teacher"] = keep(session.declare_publisher(k.teacher))
            self.teacher_listener = keep(pub.declare_matching_listener(on_zenoh(self._on_teacher_matching)))
            self.core.latest.teacher_heard = bool(pub.matching_status.matching)
        self.pubs["status"] = keep(StatusOut(session, M.status_key(self.robot, "station")))  # asked by status
        self.journal.declare(session, keep)
        if self.build is None:
            self.build = KernelBuild(self.teacher)
        what = self.core.what()
        log.info("station for %s at %.0f Hz, %s, %s (epoch %x)", self.robot, 1 / self.period, what,
                 self.core.control.phase, self.core.outbox.epoch)
        if announce:
            systemd.ready(f"{self.robot}: {what}, mission {self.core.control.phase}")

    def undeclare(self) -> int:
        """Undeclare every key :meth:`declare` declared (the session stays open for the process's other robots)."""
        return self.inputs.declared.undeclare()

    def begin(self) -> None:
        """From here on only the loop's thread calls the core (queries wait in the inbox for it)."""
        self.rx.begin()

    def end(self) -> None:
        """The loop has ended: queries left waiting are answered now; later ones in their callbacks."""
        self.rx.end(self.clock())

    def _loop(self, stop: threading.Event, duration: float | None, exit_at_goal: bool) -> None:
        clock = self.clock
        self.ticker = FixedRate(1 / self.period, stop, clock=clock)
        t_start = clock()
        periodic = True
        while not stop.is_set():
            now = clock()
            if duration is not None and now - t_start >= duration:
                break
            self.tick(now, periodic)
            self.background()  # its command is out: what it left for later, before the wait
            if periodic and exit_at_goal and self.core.finished:
                self.pubs["status"].put(M.encode(self.core.status(now)))
                clock.wait(stop, 3 * self.period)  # the status reaches its subscribers
                break
            # until the next deadline, or an external teacher's command to map at once; queries answered meanwhile
            while not (periodic := self.ticker.wait(self.wake)) and not stop.is_set():
                if self.between_ticks():
                    break


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--config", help="station TOML (scmbridge config show --kind station)")
    ap.add_argument("--robot", type=robot_arg, default=None, help="robot name (overrides the config)")
    ap.add_argument("--robots", type=robots_arg, default=None,
                    help="serve several robots from this one process (comma-separated names; each its own loop, "
                         "deadlines, pair store and mission; one Zenoh session and one compiled MPC for all)")
    ap.add_argument("--shard", default=None, help="serve the robots the config's [fleet] shards give this station "
                    "host (one process, as --robots)")
    ap.add_argument("--loop-threads", type=int, default=DEFAULT_LOOP_THREADS, metavar="N",
                    help="threads that tick the robots of --robots / --shard, each robot always by the same one "
                         f"(default {DEFAULT_LOOP_THREADS}; docs/FLEET.md)")
    ap.add_argument("--mission", default=None, help="mission file (TOML; overrides the config)")
    add_zenoh_args(ap)
    ap.add_argument("--rate", type=positive_float, default=None, help="control tick rate, Hz (overrides the config)")
    ap.add_argument("--store", default=None, help="pair store file (persisted atomically, reloaded at start)")
    ap.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    ap.add_argument("--exit-at-goal", action="store_true", help="stop the service once the goal is reached")
    ap.add_argument("--start", action="store_true",
                    help="start the mission at once (a person's act: never in a service unit that restarts)")


def control_file(robot: str) -> Path:
    """Where a station keeps its mission and phase across restarts."""
    return state_dir() / f"mission-{robot}.bin"


def restore_control(robot: str, mission_arg: str | None, default_mission: str | None) -> MissionControl:
    """The mission a station starts with: ``--mission`` (a new one: idle), else the saved one (never running),
    else the configured or shipped one (idle). An unreadable saved file is kept aside, not lost."""
    path = control_file(robot)
    if mission_arg:
        return MissionControl(robot, load_mission_spec(mission_arg))
    refused = ""
    if path.exists():
        try:
            data, why = FileTags().open("control", path, read_bounded(path, TEXT_FILE))
            if data is None:
                raise ValueError(why)
            return MissionControl.restored(robot, M.decode(data, Saved))
        except (OSError, M.MessageError, ValueError) as exc:
            aside = quarantine(path)
            log.error("mission state %s unusable (%s); moved to %s, starting idle", path, exc, aside)
            refused = f"the saved mission {path.name} was refused ({exc}; kept as {aside.name}): look at it"
    control = MissionControl(robot, load_mission_spec(default_mission))
    if refused:  # said to the person on every answer and status until a person starts or sends one
        control.reason = f"{refused}; this is the configured mission, idle"[:1024]
    return control


def _station(cfg: StationConfig, robot: str, rate: float, args: argparse.Namespace) -> Station:
    """One robot's station as the command line asks for it (its store, its saved or given mission)."""
    store_path = Path(args.store) if args.store else cfg.store_file(robot)
    if store_path.is_dir():
        raise UsageError(f"pair store {store_path} is a directory; name a file")
    control = restore_control(robot, args.mission, cfg.station.mission or None)
    if args.start:
        control.request(M.MissionRequest(stamp=0.0, action="start", source="command line"),
                        Fitness("not checked yet"), 0.0)
    return Station(cfg, robot, rate, store_path, control.mission, control, control_file(robot))


def _save(station: Station) -> bool:
    saved = station.persist()
    station.save_control()
    path, n = station.core.saves.store_path, len(station.store.refined())
    if saved:
        log.info("%s: pair store saved to %s (%d refined pairs)", station.robot, path, n)
    else:
        log.error("%s: pair store NOT saved to %s: %s (%d refined pairs lost at this exit)", station.robot, path,
                  station.core.saves.error, n)
    return saved


def run(args: argparse.Namespace) -> int:
    cfg = load_station(args.config)  # mistakes end here, before any session opens
    rate = cfg.station.rate_hz if args.rate is None else args.rate
    if not RATE_HZ_RANGE[0] <= rate <= RATE_HZ_RANGE[1]:
        raise UsageError(f"--rate {rate:g}: must be within {RATE_HZ_RANGE[0]:g}..{RATE_HZ_RANGE[1]:g} Hz")
    if args.shard is not None:
        if args.robots is not None:
            raise UsageError("--shard takes its robots from the config's [fleet] shards: drop --robots")
        if args.shard not in cfg.fleet.shards:
            known = ", ".join(sorted(cfg.fleet.shards)) or "none: the config has no [fleet] shards"
            raise UsageError(f"--shard {args.shard!r}: not in the config's [fleet] shards (known: {known})")
        args.robots = cfg.fleet.shards[args.shard]
    if args.robots is not None:
        if args.robot is not None or args.store is not None:
            raise UsageError("--robots names every robot and keeps each one's pair store in the state directory: "
                             "drop --robot and --store")
        return run_fleet(cfg, args.robots, rate, args)
    robot = M.check_robot(args.robot or cfg.robot)
    station = _station(cfg, robot, rate, args)
    from transfer.scm import warmup

    warmup()  # compile / load the SC kernels before the first tick
    freeze_startup_heap()
    stop = stop_on_signals()
    try:
        with open_session(zenoh_config(args), wait=stop, what="station") as session:
            station.serve(session, stop, args.duration, args.exit_at_goal)
    finally:
        saved = _save(station)
        station.core.verdict.said.flush(station.clock())
        log.info("station for %s stopped %s (mission %s)", robot, stopped_because(stop), station.core.control.phase)
    return 0 if saved else 1


def run_fleet(cfg: StationConfig, robots: list[str], rate: float, args: argparse.Namespace) -> int:
    """Every robot's station in this one process over one Zenoh session, all ticked by one thread
    (:class:`FleetLoop`): each robot on its own deadlines (missed ones its own), with its own store, mission and
    status; the SC kernels and the MPC's compiled code are built once and shared. A robot whose station cannot be
    built (an unreadable mission) or whose tick fails is logged and left stopped (its driver host's deadman stops
    the vehicle); the others drive on."""
    from transfer.scm import warmup

    # Zenoh's callbacks and the writer threads still take the GIL from the one loop thread: hand it over every
    # 0.5 ms (Python's default is 5 ms), so a callback (which only fills an inbox) never waits long behind a tick
    sys.setswitchinterval(FLEET_SWITCH_INTERVAL_S)
    stations: dict[str, Station] = {}
    for robot in robots:
        try:
            stations[robot] = _station(cfg, robot, rate, args)
        except (UsageError, ValueError, OSError) as exc:
            log.error("%s: not served: %s", robot, exc)
    if not stations:
        raise UsageError(f"none of the {len(robots)} robots could be served (see the log)")
    warmup()
    # one build of the MPC's compiled code for every robot: the first station's, adopted by all
    teachers = [st.core.source.teacher for st in stations.values() if isinstance(st.core.source, MpcSource)]
    build = KernelBuild(teachers[0] if teachers else None)
    for st in stations.values():
        st.build = build
    stop = stop_on_signals()
    failed: list[str] = []
    try:
        with open_session(zenoh_config(args), wait=stop, what="station") as session:
            declared = []
            for st in stations.values():
                try:
                    st.declare(session)
                    declared.append(st)
                except Exception as exc:  # one robot's failure stops that robot only
                    failed.append(st.robot)
                    log.exception("%s: station not started (%s); its robot stops by its deadman, the others drive on",
                                  st.robot, exc)
            fleet = FleetLoop(declared, stop, args.duration, args.exit_at_goal,
                              threads=getattr(args, "loop_threads", DEFAULT_LOOP_THREADS))
            systemd.ready(f"{len(stations)} robots: {', '.join(stations)}")
            log.info("serving %d robots from one process: %s", len(declared), ", ".join(s.robot for s in declared))
            freeze_startup_heap()
            fleet.run()
            failed += fleet.failed
    finally:
        saved = [_save(st) for st in stations.values()]
        for st in stations.values():
            st.core.verdict.said.flush(st.clock())
        log.info("station for %s stopped %s", ", ".join(stations), stopped_because(stop))
    return 0 if all(saved) and not failed and len(stations) == len(robots) else 1
