"""Where a station's commands come from: one :class:`CommandSource` per teacher, chosen once by :func:`make_source`.

Each tick the station core (:mod:`bridge.nodes.station_core`) asks its source for a :class:`Proposal` at the
latest pose; the source answers with a teacher command to map (the built-in MPC, the paper's motion primitives, an
external teacher's command), a learner command to send as it is (the calibration stage), ``None`` (nothing new:
an external teacher that has not spoken since the last command) or a :class:`Why` (the one reason it does not
drive; the core then publishes a stop). Sources keep their own state (warm starts, the current primitive, the
calibration plan) and nothing else: the core owns the store, the transfer step, the counters and the wire.

A new teacher is one new class implementing :class:`CommandSource` and one line in :func:`make_source`.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from bridge.core import wire as M
from bridge.core.clock import SYSTEM, Clock
from bridge.core.config import StationConfig
from transfer.calibration import CalibrationPlan
from transfer.domain import Bounds
from transfer.mission import Mission
from transfer.store import PairStore
from transfer.teacher.primitives import PrimitiveFollower, PrimitiveLibrary, PrimitivePlanner

log = logging.getLogger("scmbridge.station")


@dataclass(frozen=True)
class Why:
    """The one reason the source (or the station) does not drive this tick: the station publishes a stop and says
    it, ``text`` in words for people, ``reason`` typed for what the station decides on (its status's ``ok`` and
    ``reason``): a source's own stop is ``teacher`` unless it says otherwise."""

    text: str
    reason: M.Reason = "teacher"


@dataclass(frozen=True)
class Proposal:
    """A command to send. ``method`` None: ``u`` is a teacher command, mapped by the transfer step with
    ``predicted`` (the teacher's plan, if any) as its hint; else ``u`` is a learner command sent as it is with that
    method. ``solver`` set: the source is the station's own teacher and its command goes out on ``teacher``
    (``ok``: whether it solved). ``solve_ms``: how long it took to compute, for the status."""

    u: NDArray[np.float64]
    pose: NDArray[np.float64] | None = None
    predicted: NDArray[np.float64] | None = None
    method: str | None = None
    solver: str | None = None
    ok: bool = True
    solve_ms: float | None = None


@dataclass
class SourceContext:
    """What a source may read (and count) when it proposes: the mission, the pair store (its learned limits), the
    station's counters, the last tick's reason, the external teacher's latest command, and what bounds the teacher
    (``limits``, the station's ``[transfer] limits``): a source asks :meth:`box` and :meth:`allows`, never the
    store's limits directly."""

    mission: Mission
    store: PairStore
    counters: Any  # the station's counters (bridge.nodes.station_status.StationCounters: that module imports this)
    why: str = "starting"
    teacher: M.TeacherCommand | None = None
    teacher_at: float = -np.inf
    teacher_new: bool = False
    limits: Literal["learned", "teacher"] = "learned"
    #: the commands are sent as they are (``[transfer] mapper = "identity"``): the learner's own range, which they
    #: are clipped to on the way, also bounds the learned limits
    direct_within: Bounds | None = None
    #: the mission path's point closest to the pose proposed at, where the station found it already this tick
    #: (arc length, segment: :func:`transfer.teacher._refs.closest_near`, bit for bit); None: not found yet
    closest: tuple[float, int] | None = None

    def box(self) -> Bounds:
        """The box the teacher plans within: the learned limits' (the paper's method, Section 4.2), or with
        ``limits`` "teacher" the teacher's own range, as the paper's baseline learner, which knows nothing of the
        learner and applies the teacher's commands directly (Section 5.2; docs/PAPER.md). Learned limits under
        commands sent as they are end at the learner's range (``direct_within``): a plan beyond what is sent runs
        ahead of the vehicle (found on SITL: a reference rover's one settled pair at its top speed read 0.40 m/s of
        its 0.36, and its plan ran ahead, 18.7 mm of deviation against 5.0-5.6)."""
        if self.limits != "learned":
            return self.store.teacher_bounds
        box = self.store.limits.box
        return box if self.direct_within is None else _within(box, self.direct_within)

    def curvature(self) -> tuple[float, float] | None:
        """The learned curvatures ``(k_lo, k_hi)`` that bound the teacher's turn rate by its speed, for a learner
        that cannot turn in place (``[transfer] turn = "needs-speed"``; None otherwise, or with ``limits``
        "teacher")."""
        return self.store.limits.curvature if self.limits == "learned" else None

    def allows(self, commands: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which teacher ``commands`` (n x 2) the teacher may use: those inside the learned limits' hull, or with
        ``limits`` "teacher" those inside the teacher's own range."""
        if self.limits == "learned":
            return np.asarray(self.store.limits.contains(commands, use_hull=True, tol=1e-6))
        return np.asarray(self.store.teacher_bounds.contains(commands, 1e-6))


@functools.lru_cache(maxsize=64)
def _within(box: Bounds, outer: Bounds) -> Bounds:
    """``box`` cut to ``outer`` on each axis (an axis whose cut would be empty keeps ``box``'s; built once per pair of
    boxes: the learned box changes far less often than the ticks ask)."""
    axes = []
    for (lo, hi), (olo, ohi) in ((box.v, outer.v), (box.w, outer.w)):
        cut = (max(lo, olo), min(hi, ohi))
        axes.append(cut if cut[0] < cut[1] else (lo, hi))
    return Bounds(axes[0], axes[1])


class CommandSource(Protocol):
    """One teacher of the station (module docstring)."""

    #: what the station does, for its log line at start ("mission <name>" is added for sources that follow one)
    what: str
    #: the source follows the mission's path (its goal ends the mission); False: an external teacher, calibration
    follows_mission: bool
    #: the station listens to ``teacher`` for this source's commands and maps each as it arrives
    external: bool

    def propose(self, now: float, pose: M.LearnerState, ctx: SourceContext) -> Proposal | Why | None:
        """The command for ``pose`` now, a reason not to drive, or None (nothing new to send)."""
        ...

    def reset(self) -> None:
        """A new mission: forget what belonged to the old one."""
        ...

    def done(self) -> bool:
        """The source has finished its work for good (the calibration plan is through)."""
        ...


def _pose(state: M.LearnerState) -> NDArray[np.float64]:
    return np.array([state.x, state.y, state.theta])


class MpcSource:
    """The built-in MPC: follows the mission's path, bounded by the learned limits' box (or the teacher's own range:
    :meth:`SourceContext.box`), given its obstacles."""

    what = "mpc"
    follows_mission = True
    external = False

    def __init__(self, teacher, clock: Clock = SYSTEM, slow_always: bool = False) -> None:
        self.teacher = teacher  # transfer.teacher.mpc.MpcTeacher (imported lazily: casadi)
        self.clock = clock  # its perf counter measures the solve
        #: ``[teacher] slow_for_bends = "always"``: the MPC slows for bends from the first tick, not only once the
        #: store says its learner changed
        self.slow_always = slow_always

    def propose(self, now: float, pose: M.LearnerState, ctx: SourceContext) -> Proposal:
        x = _pose(pose)
        t0 = self.clock.perf()
        res = self.teacher.solve(x, ctx.mission.path, ctx.box(), ctx.mission.obstacles, curvature=ctx.curvature(),
                                 slow_for_bends=self.slow_always or ctx.store.slows_for_bends(), closest=ctx.closest)
        solve_ms = (self.clock.perf() - t0) * 1e3
        ctx.counters.obstacles_dropped += res.obstacles_dropped
        return Proposal(np.asarray(res.u, dtype=float), x, res.predicted, solver=res.solver, ok=res.ok,
                        solve_ms=solve_ms)

    def reset(self) -> None:
        self.teacher.reset()

    def done(self) -> bool:
        return False


class PrimitivesSource:
    """The paper's motion-primitive teacher: only the primitives inside the learned limits (hull) are planned with,
    so it needs calibrated pairs first; each tick's command is the current primitive's."""

    what = "primitives"
    follows_mission = True
    external = False

    def __init__(self, follower: PrimitiveFollower) -> None:
        self.follower = follower

    def propose(self, now: float, pose: M.LearnerState, ctx: SourceContext) -> Proposal | Why:
        lib = self.follower.planner.lib
        allowed = ctx.allows(lib.commands)
        if not allowed.any():
            return Why("no primitive within the learned limits: calibrate first (scmbridge calibrate)")
        x = _pose(pose)
        u_T = self.follower.step(x, ctx.mission.path, allowed, ctx.mission.obstacles)
        ctx.counters.primitive_replans = self.follower.replans
        ctx.counters.primitives_allowed = int(allowed.sum())
        return Proposal(np.asarray(u_T, dtype=float), x)

    def reset(self) -> None:
        self.follower.reset()

    def done(self) -> bool:
        return False


class ExternalSource:
    """Transfer only: a lab's own teacher publishes ``TeacherCommand``s; each is mapped once, as it arrives. A
    teacher that says stop (``ok`` false or an exact zero) or falls silent for ``timeout_s`` gets the robot
    stopped."""

    what = "external teacher"
    follows_mission = False
    external = True

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = float(timeout_s)

    def propose(self, now: float, pose: M.LearnerState, ctx: SourceContext) -> Proposal | Why | None:
        t, t_at = ctx.teacher, ctx.teacher_at
        if t is None:
            return Why("waiting for the external teacher")
        if now - t_at > self.timeout_s:
            return Why(f"no teacher command for {now - t_at:.1f} s")
        if not t.ok or (t.v == 0.0 and t.omega == 0.0):
            return Why("the teacher says stop")
        if not ctx.teacher_new:
            return None
        return Proposal(np.array([t.v, t.omega]), np.array([pose.x, pose.y]))

    def reset(self) -> None:
        pass

    def done(self) -> bool:
        return False


class CalibrationSource:
    """The calibration stage: the plan's learner commands go out as they are (method ``calibrate``)."""

    what = "calibration"
    follows_mission = False
    external = False

    def __init__(self, plan: CalibrationPlan) -> None:
        self.plan = plan
        self.progress: tuple[int, int, str] | None = None

    def propose(self, now: float, pose: M.LearnerState, ctx: SourceContext) -> Proposal | Why:
        step = self.plan.step(now, [pose.x, pose.y, pose.theta])
        if step.done:
            if ctx.why != f"calibration: {step.reason}":
                log.info("calibration finished: %s; %d refined pairs", step.reason, len(ctx.store.refined()))
            return Why(f"calibration: {step.reason}", "calibration_done")
        if self.progress is None or (self.progress[0], self.progress[2]) != (step.index, step.phase):
            dist = float(np.hypot(pose.x - self.plan.start[0], pose.y - self.plan.start[1]))
            log.info("calibration %d/%d %s (v %.3f, omega %.3f): %d raw / %d refined pairs, %.2f m from the start",
                     step.index + 1, step.total, step.phase, step.u_L[0], step.u_L[1], ctx.store.raw_count,
                     len(ctx.store.refined()), dist)
        self.progress = (step.index, step.total, step.phase)
        ctx.counters.calibration_index, ctx.counters.calibration_total = step.index, step.total
        return Proposal(np.asarray(step.u_L, dtype=float), method="calibrate")

    def reset(self) -> None:
        pass

    def done(self) -> bool:
        return self.plan.finished is not None


def make_source(cfg: StationConfig, period: float, calibration: CalibrationPlan | None = None) -> CommandSource:
    """The station's command source from its configuration (``[teacher] kind``), or the calibration stage when a
    plan is given. The one place each teacher is built."""
    if calibration is not None:
        return CalibrationSource(calibration)
    t = cfg.teacher
    if t.kind == "mpc":
        from bridge.teacher.codegen import build_mpc
        from transfer.teacher.mpc import MpcConfig

        # compiled in the background by the Zenoh side (station.KernelBuild), never here: a core is built at once
        return MpcSource(build_mpc(MpcConfig(N=cfg.station.horizon, dt=period, max_obstacles=t.obstacle_slots,
                                             solver=t.mpc_solver, curve_margin=t.curve_margin,
                                             turn_needs_speed=cfg.transfer.turn == "needs-speed")),
                         slow_always=t.slow_for_bends == "always")
    if t.kind == "primitives":
        lib = PrimitiveLibrary(cfg.teacher_bounds.bounds(), t.primitives_grid, duration=t.primitive_s, dt=period)
        return PrimitivesSource(PrimitiveFollower(PrimitivePlanner(lib, k_d=1.0, k_theta=2.0, horizon=2)))
    if t.kind == "external":
        return ExternalSource(t.timeout_s)
    raise ValueError(f"unknown teacher kind {t.kind!r}")


def station_kernels(cfg: StationConfig) -> list:
    """The functions a station on ``cfg`` at its configured rate compiles in the background
    (:class:`~bridge.nodes.station.KernelBuild`): its MPC's real-time iteration; none for another teacher or IPOPT."""
    source = make_source(cfg, 1.0 / cfg.station.rate_hz)
    return source.teacher.kernels() if isinstance(source, MpcSource) else []


def warm_kernels(compiler: Any = None) -> int:
    """The MPC's compiled code of a station on the default configuration built into the cache (or found there), for
    a learner that turns in place and for one that needs speed to turn (``[transfer] turn``: an Ackermann rover's
    MPC has rows of its own): ``make install`` runs it into the services' cache, so a service's first start loads
    the library instead of building it (a build takes about a minute of a core, and a station that stops before its
    build ends never caches it). ``compiler``: :func:`bridge.teacher.codegen.compile_functions` unless given.
    Returns how many of the two are in the cache."""
    from msgspec.structs import replace

    from bridge.core.config import load_station
    from bridge.teacher.codegen import compile_functions

    build = compiler or compile_functions
    base = load_station(None)
    cached = 0
    for turn in ("in-place", "needs-speed"):
        cfg = replace(base, transfer=replace(base.transfer, turn=turn))
        if build(station_kernels(cfg)) is not None:
            cached += 1
    return cached


__all__ = ["CalibrationSource", "CommandSource", "ExternalSource", "MpcSource", "PrimitivesSource", "Proposal",
           "SourceContext", "Why", "make_source", "station_kernels", "warm_kernels"]
