"""A person starts the robot: the station's mission phases and the requests that move between them (pure: times
and the robot's fitness are arguments; docs/ARCHITECTURE.md, "Mission control").

Phases: ``idle`` (a mission is loaded, nothing is driven), ``running`` (driving, or waiting for the robot to become
fit right after a person's start or resume), ``paused``, ``finished`` (goal reached), ``aborted``. Only a person's
request starts or resumes (``scmbridge mission start|resume``, or ``--start`` on the station's command line).
Anything that stops the robot without a person (an estop, the operator taking the vehicle, a lost link or pose, a
fault, the driver host restarting) moves ``running`` to ``paused`` with that reason, and it stays paused until a
person resumes it; a resume is refused, with the reason, while an estop is latched or the robot is not fit.
``send`` replaces the mission and goes to ``idle``; ``abort`` stops for good until a new ``start``. A restarted
station comes back with its saved mission, never running (a running mission comes back paused).

A mission published on ``scm/<robot>/mission`` (a program feeding goals, not a person's request) never starts a robot
by itself: while running it replaces the path in place (a started robot follows the new goal); in every other phase
(after the goal, idle, paused, aborted) it loads ``idle`` and waits for a person's ``start``. Either way the answers
and the station's status say where it came from and when, so the operator is warned before starting it. (Found by a
hostile test: a mission published after the goal restarted the robot with no person's act.) Under the lab's access
control only the operator's certificate may publish it (``scmbridge deploy``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime

import msgspec
import numpy as np

from bridge.core import wire as M
from bridge.core.config import mission_from_spec
from transfer.mission import Mission

log = logging.getLogger("scmbridge.station")


#: a pose or a driver status late for this long after driving pauses the mission (a lost link), s
PAUSE_AFTER_S = 2.0
#: the mission state is saved again when its progress grew by this much (a restart shows where it was)
SAVE_PROGRESS_STEP = 0.01


class Saved(msgspec.Struct, kw_only=True):
    """What a station keeps on its disk so a restart knows its mission and where it was."""

    phase: M.MissionPhase
    reason: str = ""
    spec: M.MissionSpec
    progress: float = 0.0  # the share of the path done (a file older than this field: 0, or 1 when finished)
    guard: M.Reason | None = None  # paused by this guard of the station's (a restart still says which)


@dataclass
class Fitness:
    """The robot's fitness as the station sees it this tick: ``why`` empty when it may be driven, else the one
    reason; ``estop`` when that reason is a latched estop (a resume is refused until it is released);
    ``immediate`` when it stops the mission at once (the driver host says the robot cannot drive), else (a pose or
    a status late) only once it has lasted ``PAUSE_AFTER_S`` (a loaded moment is not a lost link)."""

    why: str = "no driver host status"
    estop: bool = False
    immediate: bool = True


class MissionControl:
    """The phase machine (see the module docstring). ``request`` answers a person; ``tick`` follows the robot."""

    def __init__(self, robot: str, spec: M.MissionSpec, phase: M.MissionPhase = "idle", reason: str = "") -> None:
        self.robot = robot
        self.spec = spec
        self.mission: Mission = mission_from_spec(spec)
        self.phase: M.MissionPhase = phase
        self.reason = reason or ("waiting for a person: scmbridge mission start" if phase == "idle" else "")
        self.drove = False  # running and driven since the last start/resume (a stop after that pauses)
        self.progress = 0.0
        self.saved_progress = 0.0  # the progress last saved: a restart comes back to it (within SAVE_PROGRESS_STEP)
        self.changed = True  # the phase or mission changed since the last save
        self.version = 0  # counts mission replacements (the station resets its teacher on a new one)
        self.unfit_since: float | None = None  # since when the robot has not been fit while running
        #: the mission came from a publisher on the mission key, not a person's send: from where, when (wall clock)
        self.replaced_by = ""
        self.replaced_at = 0.0
        #: paused because the robot stopped being fit (its reason now is the station's to say), not by a person or a
        #: restart (that reason stays true)
        self.paused_by_robot = False
        #: paused by one of the station's guards (bridge.nodes.station_guards): its typed reason (None: not)
        self.guard: M.Reason | None = None

    # ------------------------------------------------------------------------------------------- restarts
    @classmethod
    def restored(cls, robot: str, saved: Saved) -> MissionControl:
        """A restarted station: its saved mission, never running."""
        if saved.phase == "running":
            c = cls(robot, saved.spec, "paused", "paused: the station restarted")
        else:
            c = cls(robot, saved.spec, saved.phase, saved.reason)
            c.guard = saved.guard if saved.phase == "paused" else None
        c.progress = 1.0 if saved.phase == "finished" else min(1.0, max(0.0, saved.progress))
        return c

    def saved(self) -> Saved:
        self.changed = False
        self.saved_progress = self.progress
        return Saved(phase=self.phase, reason=self.reason, spec=self.spec,
                     progress=min(1.0, max(0.0, float(self.progress))), guard=self.guard)

    # ------------------------------------------------------------------------------------------- requests
    def request(self, req: M.MissionRequest, fit: Fitness, now: float) -> M.MissionState:
        """Do what a person asked, if it may be done now; the answer says what was done or why not."""
        who = f" by {req.source}" if req.source else ""
        act = req.action
        if act == "status":
            return self.answer(now, True, f"mission {self.spec.name!r} is {self.phase}")
        if act == "send":
            if req.spec is None:
                return self.answer(now, False, "send needs a mission")
            try:
                mission = mission_from_spec(req.spec)
            except ValueError as exc:
                return self.answer(now, False, f"mission refused: {exc}")
            self.spec, self.mission, self.progress = req.spec, mission, 0.0
            self.version += 1
            self.replaced_by, self.replaced_at = "", 0.0  # a person's own mission
            self._go("idle", f"new mission{who}: scmbridge mission start to drive it")
            return self.answer(now, True, f"mission {req.spec.name!r} loaded; idle until started")
        if act in ("start", "resume"):
            if self.phase == "running":
                return self.answer(now, True, "already running")
            if act == "resume" and self.phase != "paused":
                return self.answer(now, False, f"nothing to resume: the mission is {self.phase}"
                                   + ("; use start" if self.phase in ("idle", "finished", "aborted") else ""))
            if fit.estop or (act == "resume" and fit.why):
                return self.answer(now, False, f"refused: {fit.why}")
            if act == "start" and self.phase in ("finished", "aborted"):
                self.progress = 0.0  # start again from the beginning
            done = "started" if act == "start" else "resumed"
            self._go("running", f"{done}{who}")
            ans = self.answer(now, True, f"mission {self.spec.name!r} {done}" + (
                f"; waiting for the robot: {fit.why}" if fit.why else ""))
            self.replaced_by, self.replaced_at = "", 0.0  # a person started it, told where it came from
            return ans
        if act == "pause":
            if self.phase != "running":
                return self.answer(now, False, f"nothing to pause: the mission is {self.phase}")
            self._go("paused", f"paused{who}")
            return self.answer(now, True, "paused")
        if act == "abort":
            if self.phase in ("aborted", "finished"):
                return self.answer(now, True, f"the mission is already {self.phase}")
            self._go("aborted", f"aborted{who}")
            return self.answer(now, True, "aborted: stopped until a new start")
        return self.answer(now, False, f"unknown action {act!r}")

    def replace(self, spec: M.MissionSpec, mission: Mission, by: str = "", at: float = 0.0) -> None:
        """A program's new mission on ``scm/<robot>/mission`` (``by``: where it came from; ``at``: when, wall
        clock): while running it replaces the path in place; in any other phase it loads idle, and only a person's
        start drives it (never the mission message itself)."""
        self.spec, self.mission, self.progress = spec, mission, 0.0
        self.version += 1
        by = by or f"a publisher on scm/{self.robot}/mission"
        self.replaced_by, self.replaced_at = by, at
        when = datetime.fromtimestamp(at).strftime("%H:%M:%S") if at > 0 else "an unknown time"
        if self.phase == "running":
            log.warning("mission %r: path replaced in place while running, from %s at %s", spec.name, by, when)
        else:
            self._go("idle", f"new mission {spec.name!r} from {by} at {when}, not a person's request: check it, "
                     f"then scmbridge mission start --robot {self.robot}")
        self.changed = True

    # ------------------------------------------------------------------------------------------------ tick
    def may_drive(self, fit: Fitness, now: float = 0.0) -> bool:
        """Whether this tick drives; pauses a running mission the robot stopped following without a person."""
        if self.phase != "running":
            self.unfit_since = None
            return False
        if fit.why:
            self.unfit_since = now if self.unfit_since is None else self.unfit_since
            if self.drove and (fit.immediate or now - self.unfit_since >= PAUSE_AFTER_S):
                self._go("paused", f"paused: {fit.why}")
                self.paused_by_robot = True
            return False
        self.unfit_since = None
        self.drove = True
        return True

    @property
    def unsaved(self) -> bool:
        """Something a restart should come back to changed since the last save: the phase, the mission, or the
        progress by ``SAVE_PROGRESS_STEP``."""
        return self.changed or abs(self.progress - self.saved_progress) >= SAVE_PROGRESS_STEP

    def reached(self) -> None:
        self.progress = 1.0
        self._go("finished", "goal reached")

    def guard_pause(self, reason: M.Reason, text: str) -> None:
        """One of the station's guards (the corridor, the fence, a pose jump) stops a running mission: paused with
        its typed ``reason`` until a person resumes it."""
        if self.phase == "running":
            self._go("paused", f"paused: {text}")
            self.guard = reason

    def driver_restarted(self) -> None:
        if self.phase == "running":
            self._go("paused", "paused: the driver host restarted")

    # ------------------------------------------------------------------------------------------- helpers
    def _go(self, phase: M.MissionPhase, reason: str) -> None:
        if phase != self.phase or reason != self.reason:
            log.info("mission %r: %s -> %s (%s)", self.spec.name, self.phase, phase, reason)
        self.phase, self.reason, self.changed = phase, reason, True
        self.paused_by_robot = False
        self.guard = None
        if phase == "running":
            self.drove = False

    def answer(self, now: float, accepted: bool, text: str) -> M.MissionState:
        return M.MissionState(stamp=now, robot=self.robot, phase=self.phase, mission=self.spec.name,
                              accepted=accepted, text=text[:1024], reason=self.reason[:1024],
                              progress=min(1.0, max(0.0, self.progress)), replaced_by=self.replaced_by[:1024],
                              replaced_at=max(0.0, self.replaced_at))


def spec_of(mission: Mission) -> M.MissionSpec:
    """The wire form of a mission (to keep it on disk and answer with its name)."""
    obstacles = [[float(x), float(y), float(r)] for x, y, r in np.asarray(mission.obstacles).reshape(-1, 3)]
    start = None if mission.start is None else [float(a) for a in mission.start]
    return M.MissionSpec(name=mission.name, frame=mission.frame, path=[[float(x), float(y)] for x, y in
                                                                       mission.path.points],
                         goal_tolerance=float(mission.goal_tolerance), obstacles=obstacles, start=start)


__all__ = ["Fitness", "MissionControl", "Saved", "spec_of"]
