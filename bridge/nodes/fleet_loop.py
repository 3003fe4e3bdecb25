"""Many robots in one station process: one thread ticks them all (``station --robots``, ``--shard``; docs/FLEET.md).

:class:`FleetLoop` ticks every robot's :class:`~bridge.nodes.station.Station` on its own deadlines
(:class:`Deadlines`), woken robots handled between two ticks (:class:`FleetWake`); :func:`run_fleet` builds the
stations of a process, shares one build of the MPC's compiled code among them, and serves them over one Zenoh
session. A robot whose station cannot be built or whose tick fails stops alone (its driver host's deadman stops the
vehicle); the others drive on.
"""

from __future__ import annotations

import logging
import math
import operator
import threading
from typing import Any, Protocol

from bridge.core import wire as M
from bridge.core.clock import SYSTEM, Clock


class Ticked(Protocol):
    """What :class:`FleetLoop` ticks: a robot's station (:class:`bridge.nodes.station.Station`)."""

    robot: str
    period: float
    ticker: Any
    wake: Any
    core: Any
    pubs: dict

    def tick(self, now: float, periodic: bool = True) -> Any: ...

    def between_ticks(self) -> bool: ...

    def background(self) -> bool: ...

    def begin(self) -> None: ...

    def end(self) -> None: ...

    def undeclare(self) -> int: ...


log = logging.getLogger("scmbridge.station")

#: the loop does its robots' work left for later (a hole search's step: a few ms on a slow machine) only while the
#: next deadline is at least this far, s; nearer, each robot's next tick does its own first
BACKGROUND_LEAD_S = 0.004
#: how often a many-robot station hands the GIL over, s (Python's default is 5 ms; see run_fleet)
FLEET_SWITCH_INTERVAL_S = 0.0005
#: threads that tick a many-robot process's robots (:class:`FleetLoop`; ``station --loop-threads``)
DEFAULT_LOOP_THREADS = 1
#: instants of the period at which a many-robot process's robots are due (:func:`phases`): with more
#: robots than this, the robots sharing an instant are ticked back to back on one wake-up of the loop
FLEET_SLOTS = 10


class Deadlines:
    """One robot's periodic deadlines in a many-robot process (:class:`FleetLoop`): the rules of
    :class:`~bridge.nodes.node.FixedRate` for what counts as missed (no send budget, no rephase), without its waiting,
    which the one scheduler thread does for every robot. ``t_next`` is the next periodic tick's deadline. A periodic
    tick that ends at or past the next deadline is counted in ``missed``; a tick woken between two deadlines keeps the
    schedule, and is counted only when it ended a whole period past the deadline. Missed deadlines are counted per
    robot exactly as a loop of its own counts them. After a miss the schedule keeps its phase: the next tick is due at
    the first of the robot's own deadlines after the late one ended (a loop of its own restarts at once instead). The
    robots of a process are spread over the period so that they do not queue for the one thread; restarting each at
    the end of a stall would bunch every robot the stall delayed at one instant, and the queue behind them would make
    the next ticks late too."""

    def __init__(self, period: float, first: float) -> None:
        self.period = float(period)
        self.t_next = float(first)
        self.missed = 0
        self.late = 0.0  # s the last periodic tick started after its deadline

    def ticked(self, end: float, periodic: bool) -> None:
        """A tick (``periodic``, or woken by an input) ended at ``end``."""
        if periodic:
            self.t_next += self.period
            if end >= self.t_next:
                self._missed(end)
        elif end - self.t_next >= self.period:
            self._missed(end)

    def _missed(self, end: float) -> None:
        """Count a miss; the next deadline is the first of this robot's own after ``end``."""
        self.missed += 1
        self.t_next += self.period * (math.floor((end - self.t_next) / self.period) + 1)


class FleetWake:
    """A robot's wake-up in a many-robot process: its own flag (what :class:`Ticked` sets: a query, an external
    teacher's command) and the scheduler's one event, set with it, so that the one thread waits on one event for
    every robot. The flag is set after what it announces is in the inbox, and taken (read and cleared) before the
    inbox is: nothing handed over is left unseen."""

    def __init__(self, shared: threading.Event) -> None:
        self.shared = shared
        self.flag = False

    def set(self) -> None:
        self.flag = True
        self.shared.set()

    def is_set(self) -> bool:
        return self.flag

    def clear(self) -> None:
        self.flag = False

    def take(self) -> bool:
        """Whether it was set (and it is cleared). Cleared only when it was read set: a set between the read and
        the clear is then covered by the inbox read after it, and a set after a read that found it clear is kept."""
        if self.flag:
            self.flag = False
            return True
        return False


def phases(n: int, slots: int = FLEET_SLOTS) -> list[float]:
    """When each of a process's ``n`` robots (in their order) is first due, as a share of the period after the loop
    starts: ``min(n, slots)`` instants spread evenly over the period, the robots dealt to them in order, as evenly
    as they go. Up to ``slots`` robots each have an instant of their own (their ticks a ``1 / n`` period apart);
    beyond, the robots of one instant are ticked back to back, so the loop wakes once for them instead of once
    each, and their ticks run one after another on code the first one brought into the caches (each wake-up is a
    switch of the thread and a cold start of the tick's code; docs/FLEET.md). The later robots of an instant start
    their tick later by the ticks before them (a few milliseconds of a 100 ms period), which :class:`Deadlines`
    does not count as missed unless the tick ends past the robot's next deadline."""
    k = max(1, min(int(n), int(slots)))
    return [(i * k // n) / k for i in range(n)]


#: the key of the robot due first (C-implemented: called for every robot at every turn of the loop)
_NEXT_DEADLINE = operator.attrgetter("ticker.t_next")


class FleetLoop:
    """Every robot of a process ticked by one thread (``station --robots``, ``--shard``), or by a few
    (``threads``, ``station --loop-threads``), each robot always by the same one: each robot on its own deadlines
    (:class:`Deadlines`, its first at its phase: the robots' ticks spread evenly over the period, at most ``slots``
    instants of it (:func:`phases`), and dealt to the threads in phase order, so one thread's robots are spread over
    the period too), the one due first ticked first, woken robots (a query, an external teacher's command) handled
    between two ticks as a robot's own loop handles them. One thread instead of a thread per robot: the robots' loops
    no longer queue for the interpreter lock against each other (and Zenoh's threads), which cost CPU on every
    hand-over and let a late tick progress slowly through many frames (docs/FLEET.md). Zenoh's callbacks are
    unchanged: they fill each robot's inbox. A robot whose tick raises is logged and left stopped (its driver host's
    deadman stops the vehicle); the others drive on. ``clock``: the time and the waits (every reading and wait of
    the loop is the clock's); ``slots``: the instants of the period the robots are due at (:data:`FLEET_SLOTS`)."""

    def __init__(self, stations: list[Ticked], stop: threading.Event, duration: float | None,
                 exit_at_goal: bool, threads: int = 1, clock: Clock = SYSTEM, slots: int = FLEET_SLOTS) -> None:
        self.stations, self.stop, self.clock, self.slots = stations, stop, clock, slots
        self.duration, self.exit_at_goal = duration, exit_at_goal
        k = max(1, min(int(threads), len(stations)))
        self.groups = [stations[i::k] for i in range(k)]
        self.wakes = [threading.Event() for _ in self.groups]
        self.failed: list[str] = []
        for group, wake in zip(self.groups, self.wakes):
            for st in group:
                st.wake = FleetWake(wake)

    def run(self) -> None:
        """Tick every robot until ``stop`` (or ``duration``, or, with ``exit_at_goal``, each robot's goal)."""
        t0 = self.clock()
        for st, phase in zip(self.stations, phases(len(self.stations), self.slots)):
            st.ticker = Deadlines(st.period, t0 + phase * st.period)
            st.begin()
        if len(self.groups) == 1:
            self._run(self.groups[0], self.wakes[0])
            return
        loops = [threading.Thread(target=self._run, args=(g, w), name=f"station-loop-{k}", daemon=True)
                 for k, (g, w) in enumerate(zip(self.groups, self.wakes))]
        for t in loops:
            t.start()
        for t in loops:
            t.join()

    def _run(self, group: list[Ticked], wake: threading.Event) -> None:
        """One thread's loop over its robots (``group``, woken by ``wake``)."""
        active = list(group)
        start = {st.robot: st.ticker.t_next for st in active}
        clock = self.clock
        linger = clock()
        try:
            while active and not self.stop.is_set():
                if wake.is_set():  # inputs to handle now; then whatever is due (a stream of wakes never starves
                    wake.clear()   # the deadlines)
                    for st in list(active):
                        if st.wake.take() and not self._woken(st):
                            active.remove(st)
                    if not active:
                        break
                st = min(active, key=_NEXT_DEADLINE)
                now = clock()
                delay = st.ticker.t_next - now
                if delay > 0:
                    if delay > BACKGROUND_LEAD_S and self._background(active, st.ticker.t_next):
                        continue  # time went by: what is due now
                    clock.wait(wake, delay)
                    continue
                if self.duration is not None and now - start[st.robot] >= self.duration:
                    self._finish(st, active)
                    continue
                st.wake.clear()  # the periodic tick reads every input handed over until now
                st.ticker.late = -delay
                if not self._tick(st, now, True):
                    self._finish(st, active, failed=True)
                    continue
                if self.exit_at_goal and st.core.finished:
                    try:
                        st.pubs["status"].put(M.encode(st.core.status(now)))
                    except Exception:  # the robot is done: its last status is a courtesy
                        log.exception("%s: final status not published", st.robot)
                    linger = clock() + 3 * st.period  # the status reaches its subscribers
                    self._finish(st, active)
            left = linger - clock()
            if not self.stop.is_set() and left > 0:
                clock.wait(self.stop, left)
        finally:
            for st in active:
                st.end()

    def _tick(self, st: Ticked, now: float, periodic: bool) -> bool:
        """One tick of ``st`` and its deadlines' bookkeeping; False when it failed."""
        try:
            st.tick(now, periodic)
        except Exception as exc:  # one robot's failure stops that robot only
            log.exception("%s: station loop failed (%s); its robot stops by its deadman, the others drive on",
                          st.robot, exc)
            return False
        st.ticker.ticked(self.clock(), periodic)
        return True

    def _background(self, active: list[Ticked], deadline: float) -> bool:
        """The work the robots' last commands left for later (``Station.background``), while no robot is due: one
        robot's at a time, while the next ``deadline`` is at least :data:`BACKGROUND_LEAD_S` away; what is left when
        time runs short is done by each robot's next tick. True when some was done. A robot whose work failed is
        finished as one whose tick failed."""
        done = False
        for st in list(active):
            if self.clock() > deadline - BACKGROUND_LEAD_S:
                break
            try:
                done = st.background() or done
            except Exception as exc:  # one robot's failure stops that robot only
                log.exception("%s: station loop failed (%s); its robot stops by its deadman, the others drive on",
                              st.robot, exc)
                self._finish(st, active, failed=True)
                done = True
        return done

    def _woken(self, st: Ticked) -> bool:
        """A robot woken before its deadline: its queries answered, an external teacher's command mapped now;
        False when that failed (the robot is then stopped)."""
        try:
            teacher = st.between_ticks()
        except Exception as exc:
            log.exception("%s: station loop failed (%s); its robot stops by its deadman, the others drive on",
                          st.robot, exc)
            teacher, ok = False, False
        else:
            ok = True
        if ok and teacher:
            ok = self._tick(st, self.clock(), False)
        if not ok:
            self.failed.append(st.robot)
            st.end()
            st.undeclare()
        return ok

    def _finish(self, st: Ticked, active: list[Ticked], failed: bool = False) -> None:
        active.remove(st)
        if failed:
            self.failed.append(st.robot)
        st.end()
        if failed:  # its keys go with it: no samples taken, no query answered, no status for a robot not served
            st.undeclare()


__all__ = ["BACKGROUND_LEAD_S", "DEFAULT_LOOP_THREADS", "FLEET_SLOTS", "FLEET_SWITCH_INTERVAL_S", "Deadlines",
           "FleetLoop", "FleetWake", "Ticked", "phases"]
