"""The pieces of a station's state, one job each, beside :class:`bridge.nodes.station_core.StationCore`
(docs/ARCHITECTURE.md, "bridge/nodes"): what the core keeps between ticks, grouped by what it is for, so the core
holds its collaborators and its tick, not a long list of loose values.

- :class:`Latest`: the latest inputs and when they arrived (the pose, the driver host's status, an external
  teacher's command) and whether anyone hears the teacher topic; whether the robot is fit is judged from them
  (:func:`bridge.nodes.station_fitness.assess_fitness`).
- :class:`TickTime`: the tick's timing and dates: the clock, the period, the wall clock's offset (a tick's date is
  its ``now`` plus it), when the next periodic status is due, the ticks' and the solves' durations.
- :class:`Outbox`: the commands this station sends: this run's epoch, their sequence, their validity (three
  periods) and the bytes the wire's decoder checked for the last one.
- :class:`Verdict`: what the station says and why: the one reason it does (not) drive (typed and in words), why
  the robot was not fit, where a paused robot stands on its path, and the log of the reason (once, then how long it
  held).
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from bridge.core import wire as M
from bridge.core.clock import Clock, wall_offset
from bridge.core.logs import ReasonLog
from bridge.nodes.mission_control import Fitness
from bridge.nodes.sources import Why
from bridge.nodes.station_fitness import assess_fitness
from bridge.nodes.station_status import STATUS_EVERY_S


class Latest:
    """The latest of each input, kept across ticks, with its receipt time (``-inf`` before the first): the learner
    state, the driver host's status (and its seq: a lower one means the host restarted), an external teacher's
    command (``teacher_new`` until the source has been given it) and whether anyone subscribes to the teacher topic
    (the teacher message is built only then). ``max_pose_age``: how old a pose may be for the robot to be fit."""

    def __init__(self, max_pose_age: float) -> None:
        self.max_pose_age = max_pose_age
        self.state: M.LearnerState | None = None
        self.state_at = -np.inf
        self.driver: M.Status | None = None
        self.driver_at = -np.inf
        self.driver_seq = -1
        self.teacher: M.TeacherCommand | None = None
        self.teacher_at = -np.inf
        self.teacher_new = False
        #: whether anyone subscribes to the teacher topic (the station follows Zenoh's matching status)
        self.teacher_heard = True

    def driver_status(self, st: M.Status, at: float) -> bool:
        """Keep the driver host's latest status; True when its seq went down (a new driver host process)."""
        restarted = st.seq < self.driver_seq
        self.driver_seq = st.seq
        self.driver, self.driver_at = st, at
        return restarted

    def teacher_command(self, cmd: M.TeacherCommand, at: float) -> None:
        """An external teacher's command, new until :meth:`take_teacher`."""
        self.teacher, self.teacher_at = cmd, at
        self.teacher_new = True

    def take_teacher(self) -> bool:
        """Whether the teacher's command is new to the source (it is not any more)."""
        new, self.teacher_new = self.teacher_new, False
        return new

    def fresh_pose(self, now: float) -> bool:
        """The latest pose is younger than ``max_pose_age``."""
        return now - self.state_at <= self.max_pose_age

    def fitness(self, now: float) -> tuple[Why | None, Fitness]:
        """Why the robot may not be driven now (None: it may), and the :class:`Fitness` mission control decides on
        (:func:`bridge.nodes.station_fitness.assess_fitness`)."""
        return assess_fitness(now, self.state, self.state_at, self.driver, self.driver_at, self.max_pose_age)


class TickTime:
    """The tick's timing and dates. ``clock`` is read here once for the wall clock's offset from the monotonic one
    (a tick's date is its ``now`` plus it: one time per tick) and for the ticks' durations (:meth:`Clock.perf`)."""

    def __init__(self, clock: Clock, period: float) -> None:
        self.clock = clock
        self.period = period
        #: wall clock minus monotonic clock at start: a tick's date is its ``now`` plus it (:meth:`wall`)
        self.wall_offset = wall_offset(clock, clock.wall)[0]  # read in a bracket: a preemption does not move it
        self.t_status: float | None = None  # the next status is due then (None: at the first periodic tick)
        self.tick_ms: deque[float] = deque(maxlen=600)  # the last minute of periodic ticks' durations
        self.solve_ms: deque[float] = deque(maxlen=100)

    def wall(self, t: float) -> float:
        """The date (wall clock, s since the epoch) of monotonic time ``t`` on this station's clock."""
        return t + self.wall_offset

    def status_due(self, now: float) -> bool:
        """The periodic status is due at ``now`` (the next one is then :data:`STATUS_EVERY_S` later)."""
        if self.t_status is None or now >= self.t_status:
            self.t_status = now + STATUS_EVERY_S
            return True
        return False


class Outbox:
    """The commands this station sends: stamped with this run's ``epoch`` and sender name, numbered, valid three
    periods, each checked on the wire's decoder once (:func:`bridge.core.wire.validated_bytes`), its bytes kept to
    be sent as they are."""

    def __init__(self, epoch: int, period: float) -> None:
        self.epoch = epoch
        self.valid_ms = int(3000 * period)
        self.seq = 0  # the next command's
        self.last: tuple[M.Command, bytes] | None = None  # the last command and its checked bytes

    def command(self, now: float, v: float, omega: float, method: str, region: list[int] | None = None) -> M.Command:
        cmd = M.Command(stamp=now, seq=self.seq, v=v, omega=omega, method=method, valid_ms=self.valid_ms,
                        region=region or [], sender="station", epoch=self.epoch)
        self.seq += 1
        cmd, data = M.validated_bytes(cmd)
        self.last = (cmd, data)
        return cmd

    def bytes_of(self, command: M.Command | None) -> bytes | None:
        """The bytes :meth:`command` checked for ``command`` (None for any other)."""
        last = self.last
        return last[1] if command is not None and last is not None and last[0] is command else None


class Verdict:
    """What the station says and why: the one reason it does (not) drive, in words (``why``: status text, log) and
    typed (``reason``: what its status's ok and reason are decided on); why the robot was not fit at the last tick
    (``unfit_reason``, None: fit, and the :class:`Fitness` mission control decided on); the latest pose's distance
    from the path (``off_path``, m) and, paused, where a fresh pose stands on it (``standing``, 0..1, what the status
    shows); ``said``: the reason in the log, once, then how long it held."""

    def __init__(self, log: logging.Logger) -> None:
        self.why = "starting"
        self.reason: M.Reason = "starting"
        self.unfit_reason: M.Reason | None = None
        self.fitness = Fitness()
        self.off_path: float | None = None
        self.standing: float | None = None
        self.said = ReasonLog(log)

    def judged(self, unfit: Why | None, fitness: Fitness) -> Why | None:
        """Keep the robot's fitness at this tick; returns ``unfit``."""
        self.fitness = fitness
        self.unfit_reason = unfit.reason if unfit is not None else None
        return unfit

    def decided(self, stop: Why | None) -> None:
        """The tick's decision: driving, or the stop's reason."""
        self.why, self.reason = (stop.text, stop.reason) if stop is not None else ("driving", "ok")


__all__ = ["Latest", "Outbox", "TickTime", "Verdict"]
