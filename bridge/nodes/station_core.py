"""One robot's station without Zenoh: ``StationCore.tick(inputs, now) -> outputs`` over typed messages.

Each tick takes what arrived (:class:`TickInputs`: learner states and applied echoes in arrival order, the latest
driver host status, a new mission, an external teacher's command), forms the command pairs they really bracket
(:mod:`bridge.nodes.pairing`), updates the pair store (and so the learned limits), and then either drives or says
why not:

- it drives only while a person has started the mission (:mod:`bridge.nodes.mission_control`) and the robot is
  fit: the driver host's status is fresh and ``ok`` (link up, engaged, no fault, no estop), and the latest pose
  arrived less than ``max_pose_age_s`` ago; a robot that stops being fit while driving pauses the mission until a
  person resumes it;
- otherwise, and at the goal, it publishes stops and its status says why (``idle: ...``, ``paused: estop latched by
  operator``, ``waiting for the robot: ...``, ``goal reached``).

Driving: the command source (:mod:`bridge.nodes.sources`: the MPC, the motion primitives, an external teacher or
the calibration stage, chosen once from the configuration) proposes a command at the latest pose, bounded by the
learned limits (or, ``[transfer] limits = "teacher"``, by the teacher's own range: the paper's baseline); a teacher
command is mapped by the one transfer step (:class:`transfer.step.TransferStep`) and goes out as ``cmd`` (with the
method, a validity of three periods, this run's sender name and epoch), the station's own teacher's command and
plan as ``teacher``. A periodic tick also gives ``limits`` when the learned limits change and each second, the
status each second, and saves the pair store every ``persist_every_s`` (atomically; a failed save is logged,
reported on status and retried, and never stops the loop).

:class:`TickOutputs` is what to publish; the Zenoh adapter (:mod:`bridge.nodes.station`) puts it on the wire. The
core has no threads, no module-level state and no session: a process may run many, one per robot. It is not
thread-safe: the adapter calls it (ticks and the control and pairs queries) from its loop's thread only. Its saves are
snapshots taken in the tick, encoded, tagged and written by the writer the adapter gives :attr:`StationCore.saves`
(:class:`bridge.nodes.station_saves.StationSaves`: off the tick, on the writer's thread; the outcome comes back
through its ``saved``), else at once.

The core's jobs off the tick's path live beside it, one each: whether the robot is fit to drive
(:mod:`bridge.nodes.station_fitness`, pure), what the station says about itself (its status, its limits, why it does
not drive; :mod:`bridge.nodes.station_status`) and its saves (:mod:`bridge.nodes.station_saves`); what it keeps
between ticks is in pieces of one job each (:mod:`bridge.nodes.station_parts`).
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np

from bridge.core import wire as M
from bridge.core.clock import SYSTEM, Clock
from bridge.core.config import StationConfig
from bridge.core.paths import STORE_FILE, quarantine, read_bounded
from bridge.nodes.mission_control import MissionControl, spec_of
from bridge.nodes.pairing import IntervalPairer, Reorder
from bridge.nodes.sources import CalibrationSource, CommandSource, Proposal, SourceContext, Why, make_source
from bridge.nodes.station_assumption import AssumptionCheck
from bridge.nodes.station_guards import Guards, Trip
from bridge.nodes.station_parts import Latest, Outbox, TickTime, Verdict
from bridge.nodes.station_saves import StationSaves
from bridge.nodes.station_status import (
    Integrity,
    LimitsReport,
    StationCounters,
    StatusFacts,
    StatusReport,
    not_driving,
    status_key,
)
from bridge.nodes.station_tags import FileTags
from transfer.calibration import CalibrationPlan
from transfer.domain import Bounds
from transfer.mission import Mission
from transfer.policy import make_policy
from transfer.step import TransferStep
from transfer.store import PairStore
from transfer.teacher._refs import closest, closest_near

log = logging.getLogger("scmbridge.station")

#: what the learner can really do is its box (or the teacher's) times this; beyond it a pose or pair is implausible
PLAUSIBLE = 1.5


def command_extent(learner: Bounds, teacher: Bounds) -> tuple[float, float]:
    """The largest speed and yaw rate (absolute) either command box holds: what a plausible pair stays within (times
    ``PLAUSIBLE``) and what the pairer's teacher box spans."""
    return (float(max(abs(x) for x in (*learner.v, *teacher.v))),
            float(max(abs(x) for x in (*learner.w, *teacher.w))))


def load_store(path: Path, learner: Bounds, teacher: Bounds, grid, k_min: int,
               tags: FileTags | None = None) -> tuple[PairStore, str]:
    """The persisted store if there is a valid one, else a new one. A file that is corrupt, made for other bounds,
    holds a pair no vehicle could have produced, or would break the wire contract when served (``pairs``) is
    quarantined: kept aside, not lost, and not served."""
    path = Path(path)
    if path.exists():
        try:
            data, why = (read_bounded(path, STORE_FILE), "")
            if tags is not None:
                data, why = tags.open("store", path, data)
            if data is None:
                raise ValueError(why)
            store = PairStore.from_bytes(data)
            if store.learner_bounds != learner or store.teacher_bounds != teacher:
                raise ValueError(f"its command bounds (learner {store.learner_bounds}, teacher {store.teacher_bounds})"
                                 f" differ from this configuration's (learner {learner}, teacher {teacher})")
            if tuple(store.grid) != tuple(int(g) for g in grid):
                raise ValueError(f"its grid {store.grid[0]} x {store.grid[1]} is not this configuration's "
                                 f"{grid[0]} x {grid[1]}")
            top_v, top_w = (PLAUSIBLE * x for x in command_extent(learner, teacher))
            for p in store.refined():
                if not all(abs(float(u[0])) <= top_v and abs(float(u[1])) <= top_w for u in (p.u_T, p.u_L)):
                    raise ValueError(f"pair {p.id} (teacher {p.u_T[0]:.3g}, {p.u_T[1]:.3g}; learner "
                                     f"{p.u_L[0]:.3g}, {p.u_L[1]:.3g}) is beyond what the vehicle can do")
            M.validated(pairs_message(store, "learner", 0.0))  # what the pairs queryable would serve
            return store, f"reloaded {len(store.refined())} refined pairs from {path}"
        except (ValueError, OSError) as exc:
            aside = quarantine(path)
            log.error("pair store %s unusable (%s); quarantined as %s, starting empty", path, exc, aside)
    return PairStore(learner, teacher, tuple(grid), k_min), "new pair store"


def pairs_message(store: PairStore, robot: str, now: float) -> M.Pairs:
    """The ``pairs`` reply: the refined pairs, the learned limits and the cells re-learned (``[transfer] adapt``)."""
    recs = [M.PairRecord(id=p.id, version=p.version, count=p.count, teacher_v=float(p.u_T[0]),
                         teacher_omega=float(p.u_T[1]), learner_v=float(p.u_L[0]), learner_omega=float(p.u_L[1]))
            for p in store.refined()]
    return M.Pairs(stamp=now, robot=robot, pairs=recs, limits_box=store.limits.box.as_list(),
                   limits_hull=[[float(a), float(b)] for a, b in store.limits.hull],
                   teacher_bounds=store.teacher_bounds.as_list(), learner_bounds=store.learner_bounds.as_list(),
                   grid=[int(store.grid[0]), int(store.grid[1])],
                   changed=[M.CellChange(id=c.id, count=c.count, at=c.at if c.at is not None and 0 <= c.at <= 1e11
                                         else None) for c in store.changed_cells()])


@dataclass(frozen=True)
class TickInputs:
    """What arrived since the last tick. ``telemetry``: applied echoes and learner states with their receipt
    times, each kind in arrival order (the pairer takes them in stamp order); ``driver``: the latest driver host
    status and its receipt time; ``mission``: a new mission (its spec and the decoded mission); ``teacher``: an
    external teacher's latest command and its receipt time. ``periodic`` False: a tick woken by an external
    teacher's command (map it, nothing else). ``input_counts``: the transport's counts of dropped inputs;
    ``missed_deadlines``: the loop's, for the status."""

    telemetry: tuple[tuple[M.LearnerState | M.Applied, float], ...] = ()
    driver: tuple[M.Status, float] | None = None
    mission: tuple[M.MissionSpec, Mission] | None = None
    teacher: tuple[M.TeacherCommand, float] | None = None
    periodic: bool = True
    input_counts: Mapping[str, int] = field(default_factory=dict)
    missed_deadlines: int = 0


@dataclass(frozen=True)
class TickOutputs:
    """What to publish after a tick: each is None when there is nothing to send on that key. ``command_bytes``:
    the command as the core checked it on the wire's decoder (:func:`bridge.core.wire.validated_bytes`), to send as
    it is."""

    command: M.Command | None = None
    teacher: M.TeacherCommand | None = None
    limits: M.Limits | None = None
    status: M.Status | None = None
    command_bytes: bytes | None = None


def robot_phase(robot: str) -> float:
    """A robot's phase in [0, 1), the same in every process and on every run (a hash of its name): where its
    periodic work (the hole searches' budget, the store's saves) falls, so that a fleet started together spreads
    it instead of doing it all in one tick of its process's loop."""
    return zlib.crc32(robot.encode()) / 2**32


class StationCore:
    """One robot's station: its tick (pairing, the command source, the transfer step, mission control) and the
    mission requests between ticks (module docstring). Beside it, each with one job: whether the robot is fit
    (:mod:`bridge.nodes.station_fitness`), what the station says about itself (:mod:`bridge.nodes.station_status`:
    :attr:`report`, :attr:`limits_report`, :attr:`integrity`) and its saves (:attr:`saves`,
    :mod:`bridge.nodes.station_saves`). What it keeps between ticks is in pieces by what it is for
    (:mod:`bridge.nodes.station_parts`): the latest inputs (:attr:`latest`), the tick's timing and dates
    (:attr:`time`), the commands it sends (:attr:`outbox`: the run's epoch) and what it says and why
    (:attr:`verdict`)."""

    def __init__(self, cfg: StationConfig, robot: str, rate_hz: float, store_path: Path, mission: Mission,
                 control: MissionControl | None = None, control_path: Path | None = None,
                 calibration: CalibrationPlan | None = None, source: CommandSource | None = None,
                 clock: Clock = SYSTEM, defer: bool = False) -> None:
        """``control``: the mission's phase machine (default: ``mission``, idle); ``control_path``: where it is
        kept across restarts (None: not kept); ``calibration``: run this calibration plan instead of a teacher;
        ``source``: a command source to use instead of the configured one; ``clock``: read here once for the wall
        clock's offset from the monotonic one (a tick's dates are its ``now`` plus it: one time per tick) and for
        the ticks' durations (:meth:`Clock.perf`); a tick's time is the ``now`` it is given. ``defer``: the work a
        command may leave for later is done by :meth:`background`, after the command went out (the station's
        loops), not in the tick."""
        scfg, tcfg = cfg.station, cfg.transfer
        #: the tick's timing and dates: the clock, the period, the wall clock's offset, the status's due time
        self.time = TickTime(clock, 1.0 / rate_hz)
        period = self.time.period
        self.robot = robot
        #: the latest pose, driver host status and teacher command, with their receipt times
        self.latest = Latest(scfg.max_pose_age_s)
        learner, teacher = cfg.learner_bounds.bounds(), cfg.teacher_bounds.bounds()
        tags = FileTags()  # the station's files are tagged as its own (bridge/nodes/station_tags.py)
        self.store, how = load_store(Path(store_path), learner, teacher, tcfg.grid, tcfg.k_min, tags)
        # this configuration decides whether cells are re-learned after a change, whatever the file was saved with:
        # a store learned on another day (or before a restart) is then checked against the run's pairs, cell by cell
        adapt = tcfg.adapts(reloaded=self.store.n_configured() > 0)
        self.store.set_adapt(adapt)
        self.store.change.change_tol = tcfg.change_tol
        log.info("%s%s", how, "; cells whose learner changed are re-learned" if adapt else "")
        # this robot's own phase of the periodic work (the hole searches' budget, the store's saves): the robots of
        # a fleet that start together each do it at their own tick, not all in one period of the process's loop
        phase = robot_phase(robot)
        # a learner that cannot turn in place: its yaw-rate limits are curvatures, probed where it turns most
        self.store.limits.set_needs_speed(tcfg.turn == "needs-speed")
        policy = make_policy(self.store, tcfg.mapper, np.random.default_rng(tcfg.seed), turn_probe=tcfg.probe_turns(),
                             choice=tcfg.map_choice, at_limit=tcfg.at_limit,
                             **({"exploration": "paper"} if tcfg.exploration == "paper"
                                else {"exploration": "guided", "fill_budget": tcfg.fill_budget, "fill_phase": phase}))
        self.transfer = TransferStep(policy, dt=period, explore=tcfg.exploration != "off",
                                     clearance=tcfg.explore_clearance_m, defer=defer)
        self.source: CommandSource = source or make_source(cfg, period, calibration)
        # what bounds the teacher: the learned limits, or the teacher's own range (the paper's baseline)
        self.teacher_limits = tcfg.limits
        self.direct_within = learner if tcfg.mapper == "identity" else None  # (SourceContext.box)
        if tcfg.limits == "teacher":
            log.info("the teacher is bounded by its own range, not by the learned limits ([transfer] limits = "
                     "\"teacher\"%s)", ": the paper's baseline" if tcfg.mapper == "identity"
                     and tcfg.exploration == "off" else "")
        top_v, top_w = command_extent(learner, teacher)
        self.pairer = IntervalPairer(scfg.pair_dt, max_speed=PLAUSIBLE * top_v + 0.1, max_turn=PLAUSIBLE * top_w + 0.2,
                                     command_bounds=learner, teacher_bounds=Bounds((-top_v, top_v), (-top_w, top_w)),
                                     margin=PLAUSIBLE, settle_s=scfg.pair_settle_s, settle_tol=scfg.pair_settle_tol,
                                     settle_edge_s=scfg.pair_settle_edge_s if scfg.pair_settle_s > 0 else 0.0)
        self.reorder = Reorder()
        self.control = control or MissionControl(robot, spec_of(mission))
        self.top_v = top_v  # the configured top speed: the pose-jump guard's bound until the limits are learned
        #: the corridor, the fence and the pose jump (bridge.nodes.station_guards)
        self.guards = Guards(scfg.corridor_m, [(float(a), float(b)) for a, b in scfg.fence])
        self.guards.configure(self.control.spec)
        self.guards.begin(self.control.progress * self.mission.path.length)  # a restored mission: where it was
        #: a path the measured vehicle cannot follow pauses the mission (bridge.nodes.station_assumption)
        self.assumption = AssumptionCheck.from_config(tcfg.turn_reach, tcfg.turn == "needs-speed")
        self.assumption.armed = self.control.phase != "paused"  # a restored paused mission was checked before
        self.counters = StationCounters()
        self.saves = StationSaves(self.store, Path(store_path), self.control, control_path, self.counters,
                                  scfg.persist_every_s, phase)
        self.saves.tags = tags
        self.report = StatusReport()
        self.limits_report = LimitsReport(self.store, robot)
        self.integrity = Integrity()
        #: the commands it sends: this run's epoch, their seq, their checked bytes
        self.outbox = Outbox(M.new_epoch(), period)
        self.mission_version = self.control.version
        self._near = 0  # the mission path's segment closest to the last pose (where the next search starts)
        self._closest: tuple[float, int] | None = None  # this tick's closest point of the path (arc length, segment)
        #: what it says and why: the one reason it does (not) drive, the robot's fitness, where it stands
        self.verdict = Verdict(log)

    # -------------------------------------------------------------------------------------------- queries
    @property
    def mission(self) -> Mission:
        return self.control.mission

    @property
    def calibration(self) -> CalibrationPlan | None:
        """The calibration plan this core runs, if it runs one."""
        return self.source.plan if isinstance(self.source, CalibrationSource) else None

    @property
    def finished(self) -> bool:
        """Nothing more to do: the mission finished or was aborted, or the source is through (calibration)."""
        return self.control.phase in ("finished", "aborted") or self.source.done()

    def what(self) -> str:
        """What this station does, for its start-up line."""
        return f"mission {self.mission.name}" if self.source.follows_mission else self.source.what

    def request(self, req: M.MissionRequest, now: float) -> M.MissionState:
        """A person's mission request, done or refused from the robot's fitness now: the latest driver host status
        and pose (the adapter hands over a status that came since the last tick first, :meth:`note_driver`), not the
        last tick's verdict. A start with the robot already at the goal is refused (it would finish at once), saying
        how to drive back. The answer's reason is the mission's as the status says it now."""
        unfit, self.verdict.fitness = self.latest.fitness(now)  # (the tick's unfit_reason stays the tick's)
        out = self._guard_refusal(req)
        if req.action == "start" and self.control.phase != "running" and self._at_goal():
            ans = self.control.answer(now, False, f"refused: the robot is at the goal of {self.mission.name!r} "
                                      "already (a start would end at once); to drive back, send the mission reversed: "
                                      f"scmbridge mission send FILE --reverse --robot {self.robot}, then start it")
        elif out:
            ans = self.control.answer(now, False, out)
        else:
            ans = self.control.request(req, self.verdict.fitness, now)
            if req.action == "start" and ans.accepted and self.source.follows_mission:
                self._begin_track()  # progress counts from where the robot starts, along its track
        if req.action != "status":
            log.info("mission %s%s: %s", req.action, f" by {req.source}" if req.source else "", ans.text)
        if self.control.phase in ("paused", "finished"):
            ans = msgspec.structs.replace(ans, reason=not_driving(self.control, self.robot, unfit).text[:1024])
        return ans

    def refused_for_the_robot(self, req: M.MissionRequest, now: float) -> bool:
        """Whether ``req`` would be refused now only because of the robot's fitness: a start while an estop is
        latched, a resume of a paused mission while the robot is not fit."""
        c = self.control
        if req.action not in ("start", "resume") or c.phase == "running":
            return False
        if req.action == "resume" and c.phase != "paused":
            return False
        _, fitness = self.latest.fitness(now)
        return fitness.estop or (req.action == "resume" and bool(fitness.why))

    def _guard_refusal(self, req: M.MissionRequest) -> str:
        """Why a start or resume is refused with the robot outside the corridor or the fence ("" when it is not; a
        person's ``override`` lets the station drive it back: :meth:`Guards.refusal`)."""
        state = self.latest.state
        if (req.action not in ("start", "resume") or self.control.phase == "running" or state is None
                or not self.source.follows_mission or (req.action == "resume" and self.control.phase != "paused")):
            return ""
        path = self.mission.path
        _, off = closest(path.points, path.s, path.seg_len, state.x, state.y)
        return self.guards.refusal(state.x, state.y, off, req.override, self.robot)

    def _begin_track(self) -> None:
        """A start: the mission's track begins at the latest pose's closest point (the next pose's, without one)."""
        state, path = self.latest.state, self.mission.path
        self.guards.begin(None if state is None else closest(path.points, path.s, path.seg_len, state.x, state.y)[0])
        self.assumption.arm()

    def _at_goal(self) -> bool:
        """The latest pose is at the mission's goal by the mission's own rule (a station that follows a mission)."""
        state = self.latest.state
        if state is None or not self.source.follows_mission:
            return False
        path = self.mission.path
        s, _ = closest(path.points, path.s, path.seg_len, state.x, state.y)
        return bool(self.mission.reached_at(s, [state.x, state.y]))

    def pairs(self, now: float) -> M.Pairs:
        """The ``pairs`` reply now: the refined pairs and the learned limits."""
        return pairs_message(self.store, self.robot, now)

    def heard_command(self, cmd: M.Command, now: float) -> None:
        """A command on this robot's key: one this station did not send is another station's (or a forger's)."""
        if cmd.epoch != self.outbox.epoch:
            self.integrity.foreign_command(cmd.epoch, now)
            self.counters.foreign_commands += 1

    # ----------------------------------------------------------------------------------------------- tick
    def tick(self, inputs: TickInputs, now: float) -> TickOutputs:
        """One tick at ``now`` (module docstring)."""
        time = self.time
        t0 = time.clock.perf()
        self.transfer.background()  # what the last command left for later, if the loop has not done it meanwhile
        self._ingest(inputs, now)
        command, teacher = self._control_step(now)
        if not inputs.periodic:
            return TickOutputs(command, teacher, command_bytes=self.outbox.bytes_of(command))
        time.tick_ms.append((time.clock.perf() - t0) * 1e3)
        self.counters.ticks += 1
        self.counters.inputs = dict(inputs.input_counts)
        self.counters.missed_deadlines = inputs.missed_deadlines
        status = limits = None
        if time.status_due(now):
            status = self.status(now)
            limits = self.limits_report.message(now, force=True)
        elif self.report.changed(now, self._status_key()):  # at once, between the periodic ones (their grid stays)
            status = self.status(now)
            limits = self.limits_report.message(now, force=False)
        else:
            limits = self.limits_report.message(now, force=False)
        self.saves.periodic(now)  # the pair store each persist_every_s
        return TickOutputs(command, teacher, limits, status, self.outbox.bytes_of(command))

    def background(self) -> bool:
        """With ``defer``: the work the last command left for later (a step of the transfer's hole search,
        :meth:`transfer.step.TransferStep.background`), done now; True when there was some. A loop calls it after it
        published the tick's outputs, when it has time before a deadline; a tick does it first if it is still left
        (so the commands are the same whenever it runs, and replay through the station needs no record of it)."""
        return self.transfer.background()

    def _ingest(self, inputs: TickInputs, now: float) -> None:
        """Pairs from the echoes and poses that arrived (put back in stamp order by :class:`Reorder`, so they reach
        the pairer ``REORDER_WINDOW`` after receipt), the latest pose and driver status, a new mission if one
        came."""
        push = self.reorder.push
        top = self._top_speed()
        for m, at in inputs.telemetry:  # one walk: into the reorder window, the latest pose, the pose-jump guard
            if isinstance(m, M.Applied):
                push(m.stamp, 0, at, (m, at))
            else:
                push(m.stamp, 1, at, (m, at))
                self.latest.state, self.latest.state_at = m, at
                jump = self.guards.pose(m, at, top)
                if jump is not None:
                    self._jumped(m, jump, top, at)
        for e, received in self.reorder.ready(now):
            if isinstance(e, M.Applied):
                pair = self.pairer.applied(e.stamp, e.v, e.omega, e.reason, received)
            else:
                pair = self.pairer.state(e.stamp, (e.x, e.y, e.theta), received)
            if pair is not None:
                self.add_pair(pair, self.time.wall(received))  # when a cell changed: wall clock
        if inputs.teacher is not None:
            self.latest.teacher_command(*inputs.teacher)
        if inputs.mission is not None:  # a program's, not a person's: named and timed for the operator
            self.control.replace(*inputs.mission, by=f"a publisher on {M.key(self.robot, 'mission')}",
                                 at=self.time.wall(now))
        if inputs.driver is not None:  # after a new mission: a finished mission that goes on is paused all the same
            self.note_driver(*inputs.driver)
        if self.control.version != self.mission_version:  # from the mission topic or a person's send
            self.mission_version = self.control.version
            mission = self.mission
            self.guards.configure(self.control.spec)
            self.guards.begin(None)  # (a path replaced while running: from where the robot is on it)
            self.assumption.arm()
            self.source.reset()
            self.counters.missions += 1
            log.info("new mission %r: %d waypoints, %.1f m, %d obstacles", mission.name, len(mission.path.points),
                     mission.path.length, len(mission.obstacles))

    def add_pair(self, pair: tuple[np.ndarray, np.ndarray], stamp: float) -> None:
        """One (teacher equivalent, learner command) pair into the store, ``stamp`` the wall-clock time it is given (a
        re-learned cell's); a warning for a cell or a learned limit it re-learned (``[transfer] adapt``)."""
        relearned, edges = self.store.relearned, self.store.limits.relearned
        res = self.store.add(*pair, stamp=stamp)
        if self.store.relearned > relearned:
            log.warning("cell %s re-learned: its learner no longer answers as its pairs said", res.cell)
        if self.store.limits.relearned > edges:
            log.warning("a learned limit re-learned from its recent boundary pairs: the learner's reach changed; "
                        "limits now %s", self.store.limits.box.as_list())

    def _top_speed(self) -> float:
        """The most the robot can move, m/s: its learned top speed (the learned limits' speed edge), the configured
        one (:func:`command_extent`) before any cell is learned."""
        if self.store.n_configured() == 0:
            return self.top_v
        v_lo, v_hi = self.store.limits.box.v
        return float(max(abs(v_lo), abs(v_hi)))

    def _jumped(self, st: M.LearnerState, jump: float, top: float, at: float) -> None:
        """A pose jumped ``jump`` m (received at ``at``): never progress; a running mission pauses (``pose_jump``)."""
        self.counters.pose_jumps += 1
        c = self.control
        log.warning("pose jump: %.2f m to (%.2f, %.2f) (top speed %.2f m/s)%s", jump, st.x, st.y, top,
                    ": mission paused" if c.phase == "running" else "")
        if c.phase == "running":
            self._tripped(self.guards.jump_trip(st.x, st.y, jump, c.progress, self.time.wall(at)))

    def _tripped(self, trip: Trip) -> None:
        """A guard paused the running mission (its typed reason, until a person resumes)."""
        if trip.reason == "left_corridor":
            self.counters.corridor_trips += 1
        elif trip.reason == "fence":
            self.counters.fence_trips += 1
        log.warning("mission %r paused: %s", self.mission.name, trip.text)
        self.control.guard_pause(trip.reason, trip.text)

    def note_driver(self, st: M.Status, at: float) -> None:
        """The driver host's latest status (at a tick, or before a mission request is answered between two ticks);
        the same status twice is harmless. A lower seq than the last one: a new driver host process (it counts
        from 0 again), which pauses a running mission."""
        if self.latest.driver_status(st, at):
            log.warning("the driver host restarted")
            self.control.driver_restarted()

    def _control_step(self, now: float) -> tuple[M.Command | None, M.TeacherCommand | None]:
        """Drive, or publish a stop and say why: the command and teacher message of this tick."""
        state = self.latest.state
        verdict = self.verdict
        unfit = verdict.judged(*self.latest.fitness(now))
        c = self.control
        self._closest = None
        if self.source.follows_mission and state is not None:
            path = self.mission.path  # the closest point in one compiled loop: a mission path has thousands of segments
            s, verdict.off_path, self._near = closest_near(path.points, path.s, path.seg_len, state.x, state.y,
                                                           self._near)  # = closest(...), from the last one's segment
            self._closest = (s, self._near)  # the MPC's closest point too (this pose, this path): not searched again
            if c.phase == "running" and self.guards.anchor_pending:
                self.guards.begin(s)
            if c.phase != "running" or unfit is not None:
                self.guards.pause()
            # a paused mission (a restarted station's) says where the robot stands now, from a fresh pose; that is
            # what the status shows, never the mission's progress (a pose that jumped while paused is no progress)
            fresh = self.latest.fresh_pose(now)
            verdict.standing = s / path.length if c.phase == "paused" and fresh else None
            if c.phase == "running" and unfit is None:
                trip = self.guards.check(state.x, state.y, verdict.off_path, c.progress, self.time.wall(now), now)
                outside = self.assumption.check(path.points, self.guards.corridor_m, s) if trip is None else None
                if outside is not None:
                    log.warning("mission %r paused: %s", self.mission.name, outside.text())
                    c.guard_pause("outside_assumption", outside.text())
                elif trip is not None:
                    self._tripped(trip)
                else:  # progress only along the continuous track: a pose that lands on the goal is not there
                    s = min(s, self.guards.progress_cap())
                    c.progress = max(c.progress, s / path.length)
                    if self.mission.reached_at(s, [state.x, state.y]):
                        c.reached()
        command = teacher = None
        stop = None if c.may_drive(verdict.fitness, now) else not_driving(c, self.robot, unfit)
        if stop is None:
            stop, command, teacher = self._drive(now, state)
        if stop is not None:  # logged once a reason (its type, not its words), then how long it held
            verdict.said.say((stop.reason, verdict.unfit_reason, c.phase, c.paused_by_robot),
                             f"not driving: {stop.text}", now)
            command = self.outbox.command(now, 0.0, 0.0, "stop")
            self.counters.method_stop += 1
        else:
            verdict.said.say("ok", f"driving (mission {self.mission.name!r})", now)
        verdict.decided(stop)
        self.counters.goal_reached = int(c.phase == "finished")
        if c.unsaved:
            self.saves.save("control")
        return command, teacher

    def _drive(self, now: float, state: M.LearnerState) -> tuple[Why | None, M.Command | None, M.TeacherCommand | None]:
        """The source's proposal, mapped and made a command; or why not."""
        latest = self.latest
        ctx = SourceContext(self.mission, self.store, self.counters, self.verdict.why, latest.teacher,
                            latest.teacher_at, latest.take_teacher(), self.teacher_limits, self.direct_within,
                            self._closest)
        prop = self.source.propose(now, state, ctx)
        if isinstance(prop, Why):
            return prop, None, None
        if prop is None:
            return None, None, None
        if prop.solve_ms is not None:
            self.time.solve_ms.append(prop.solve_ms)
        command = self.send(now, prop)
        teacher = None
        if prop.solver is not None and latest.teacher_heard:
            pred = np.asarray(prop.predicted, dtype=float) if prop.predicted is not None else np.zeros((0, 3))
            teacher = M.TeacherCommand(
                stamp=now, seq=command.seq, v=float(prop.u[0]), omega=float(prop.u[1]), solver=prop.solver,
                ok=prop.ok, predicted_x=pred[:, 0].tolist(), predicted_y=pred[:, 1].tolist(),
                sender="station", epoch=self.outbox.epoch)
        return None, command, teacher

    def send(self, now: float, prop: Proposal) -> M.Command:
        """The command for a proposal: a teacher command mapped by the transfer step (exploring only where it may),
        or a learner command as it is."""
        if prop.method is not None:
            self.counters.count_method(prop.method)
            return self.outbox.command(now, float(prop.u[0]), float(prop.u[1]), prop.method)
        m = self.transfer.map(prop.u, prop.pose, self.mission, prop.predicted, corridor_m=self.guards.corridor_m)
        if m.vetoed:
            self.counters.explore_vetoed += 1
        self.counters.count_method(m.method)
        return self.outbox.command(now, float(m.u_L[0]), float(m.u_L[1]), m.method, list(m.region)[:8])

    # ---------------------------------------------------------------------------------------- publications
    def status(self, now: float) -> M.Status:
        """The station's status now (:class:`bridge.nodes.station_status.StatusReport`): ok, state, the one reason,
        progress, latencies and every counter."""
        c = self.counters
        c.observe(self.pairer, self.store, self.control)
        verdict, time = self.verdict, self.time
        facts = StatusFacts(reason=verdict.reason, why=verdict.why, phase=self.control.phase,
                            progress=self._shown_progress(), persist_error=self.saves.error,
                            problems=self.integrity.problems(now, self.pairer), counters=c.as_dict(),
                            tick_ms=time.tick_ms, solve_ms=time.solve_ms, rate_hz=1 / time.period,
                            key=self._status_key(),
                            changed_cells=[k.id for k in self.store.changed_cells()[-M.STATUS_CHANGED_CELLS:]],
                            off_path_m=verdict.off_path)
        return self.report.message(now, facts)

    def _shown_progress(self) -> float:
        """The progress the status shows: a paused mission's is where the robot stands now (a restarted station's
        saved progress can be far behind it), any other the mission's own."""
        standing = self.verdict.standing
        return standing if standing is not None else self.control.progress

    def _status_key(self) -> tuple:
        """What a person reads the status for (:func:`bridge.nodes.station_status.status_key`)."""
        driver = self.latest.driver.reason if self.latest.driver is not None else None
        verdict = self.verdict
        return status_key(verdict.reason, self.control.phase, verdict.unfit_reason, driver, bool(self.saves.error))


__all__ = ["PLAUSIBLE", "StationCore", "TickInputs", "TickOutputs", "load_store", "pairs_message", "robot_phase"]
