"""The station's command sources (:mod:`bridge.nodes.sources`), each asked directly with a pose, a time and a
:class:`SourceContext`: the external teacher's every answer at its edges, the motion primitives refusing to plan
without learned limits, the calibration stage's learner commands and its end, :func:`make_source`'s choice, and
what bounds the teacher (:meth:`SourceContext.box`, :meth:`SourceContext.allows`: the learned limits, or the
teacher's own range for the paper's baseline).
Times are arguments; nothing sleeps. (The MPC source needs its solver: it is tested through the station core in
tests/unit/bridge/nodes/test_station_core.py, which also drives an external teacher through the core.)"""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission
from bridge.nodes.sources import (
    CalibrationSource,
    ExternalSource,
    PrimitivesSource,
    Proposal,
    SourceContext,
    Why,
    make_source,
)
from bridge.nodes.station_status import StationCounters
from transfer.calibration import CalibrationPlan
from transfer.domain import Bounds
from transfer.store import PairStore

LEARNER = Bounds(v=(-0.4, 0.4), w=(-1.0, 1.0))
TEACHER = Bounds(v=(-1.0, 1.0), w=(-2.0, 2.0))
POSE = M.LearnerState(stamp=1.0, seq=1, x=0.5, y=-0.25, theta=0.1)


def _ctx(**kw) -> SourceContext:
    return SourceContext(mission=load_mission(), store=PairStore(LEARNER, TEACHER), counters=StationCounters(), **kw)


def _teacher(v: float = 0.3, omega: float = 0.1, ok: bool = True) -> M.TeacherCommand:
    return M.TeacherCommand(stamp=1.0, seq=1, v=v, omega=omega, solver="lab", ok=ok)


def test_a_why_is_the_teachers_unless_it_says_otherwise() -> None:
    assert Why("x") == Why("x", "teacher") and Why("x", "calibration_done").reason == "calibration_done"
    p = Proposal(np.zeros(2))
    assert (p.method, p.solver, p.ok, p.pose, p.predicted, p.solve_ms) == (None, None, True, None, None, None)


def test_the_external_teacher_waits_until_it_has_spoken() -> None:
    src = ExternalSource(0.5)
    assert (src.what, src.follows_mission, src.external) == ("external teacher", False, True)
    assert src.propose(10.0, POSE, _ctx()) == Why("waiting for the external teacher")


def test_a_new_teacher_command_is_proposed_once_for_mapping_with_the_pose() -> None:
    src = ExternalSource(0.5)
    p = src.propose(10.0, POSE, _ctx(teacher=_teacher(0.3, -0.2), teacher_at=9.9, teacher_new=True))
    assert isinstance(p, Proposal) and p.method is None and p.solver is None  # a teacher command: mapped
    np.testing.assert_array_equal(p.u, [0.3, -0.2])
    np.testing.assert_array_equal(p.pose, [0.5, -0.25])
    assert src.propose(10.0, POSE, _ctx(teacher=_teacher(), teacher_at=9.9, teacher_new=False)) is None


def test_a_silent_teacher_stops_the_robot_after_its_timeout_not_before() -> None:
    src = ExternalSource(0.5)
    assert isinstance(src.propose(10.5, POSE, _ctx(teacher=_teacher(), teacher_at=10.0, teacher_new=True)), Proposal)
    why = src.propose(10.75, POSE, _ctx(teacher=_teacher(), teacher_at=10.0, teacher_new=True))
    assert why == Why("no teacher command for 0.8 s")  # stale even if never mapped


@pytest.mark.parametrize("cmd", [_teacher(ok=False), _teacher(0.0, 0.0), _teacher(0.0, -0.0)])
def test_a_teacher_that_says_stop_stops_the_robot(cmd: M.TeacherCommand) -> None:
    assert ExternalSource(1.0).propose(10.0, POSE, _ctx(teacher=cmd, teacher_at=10.0, teacher_new=True)) == Why(
        "the teacher says stop")


def test_a_teacher_command_with_one_axis_zero_is_still_a_command() -> None:
    p = ExternalSource(1.0).propose(10.0, POSE, _ctx(teacher=_teacher(0.0, 0.5), teacher_at=10.0, teacher_new=True))
    assert isinstance(p, Proposal)


def _primitives() -> PrimitivesSource:
    src = make_source(msgspec.convert({"teacher": {"kind": "primitives"}}, StationConfig), 0.1)
    assert isinstance(src, PrimitivesSource) and src.follows_mission and not src.external
    return src


def test_the_primitives_plan_only_with_those_inside_the_learned_limits() -> None:
    """A fresh store's limits are the teacher's full range (transfer.limits: online adaptation starts there), so
    every primitive of the station's teacher range is allowed and counted, and the command is one of them."""
    src, cfg = _primitives(), StationConfig()
    ctx = SourceContext(mission=load_mission(), store=PairStore(cfg.learner_bounds.bounds(),
                                                                cfg.teacher_bounds.bounds()),
                        counters=StationCounters())
    p = src.propose(0.0, POSE, ctx)
    lib = src.follower.planner.lib.commands
    assert isinstance(p, Proposal) and p.method is None  # a teacher command: mapped by the transfer step
    assert any(np.allclose(p.u, c) for c in lib)
    assert ctx.counters.primitives_allowed == len(lib) and ctx.counters.primitive_replans == src.follower.replans


def test_the_primitives_refuse_to_plan_when_no_primitive_is_within_the_learned_limits() -> None:
    src = _primitives()
    slow = PairStore(LEARNER, Bounds(v=(-1.0, 0.01), w=(-2.0, 2.0)))  # limits below every primitive's speed
    ctx = SourceContext(mission=load_mission(), store=slow, counters=StationCounters())
    assert src.propose(0.0, POSE, ctx) == Why("no primitive within the learned limits: calibrate first (scmbridge "
                                              "calibrate)")
    assert ctx.counters.primitives_allowed is None  # nothing counted for a refusal
    assert not src.done()


def test_calibration_sends_the_plans_learner_commands_as_they_are_and_counts_its_progress() -> None:
    plan = CalibrationPlan(LEARNER, (2, 2), hold_s=1.0, max_distance=5.0)
    src = make_source(StationConfig(), 0.1, calibration=plan)
    assert isinstance(src, CalibrationSource) and not src.follows_mission and not src.external
    ctx = _ctx()
    first = src.propose(0.0, POSE, ctx)
    assert isinstance(first, Proposal) and first.method == "calibrate" and first.pose is None
    np.testing.assert_array_equal(first.u, plan.commands[0])
    assert (ctx.counters.calibration_index, ctx.counters.calibration_total) == (0, 4)
    assert src.progress == (0, 4, "drive")
    second = src.propose(1.05, POSE, ctx)  # held for hold_s: the next command (the pose has not moved)
    np.testing.assert_array_equal(second.u, plan.commands[1])
    assert ctx.counters.calibration_index == 1 and not src.done()


def test_calibration_ends_with_its_reason_and_stays_done() -> None:
    plan = CalibrationPlan(LEARNER, (2, 2), hold_s=1.0, max_distance=1.0)
    src = CalibrationSource(plan)
    ctx = _ctx()
    src.propose(0.0, POSE, ctx)
    far = msgspec.structs.replace(POSE, x=POSE.x + 2.0)
    why = src.propose(0.5, far, ctx)
    assert isinstance(why, Why) and why.reason == "calibration_done"
    assert why.text.startswith("calibration: stopped at the distance bound")
    assert src.done() and src.propose(0.6, POSE, ctx) == why  # finished for good


def test_make_source_builds_the_external_teacher_with_its_timeout_and_refuses_an_unknown_kind() -> None:
    src = make_source(msgspec.convert({"teacher": {"kind": "external", "timeout_s": 0.7}}, StationConfig), 0.1)
    assert isinstance(src, ExternalSource) and src.timeout_s == 0.7
    cfg = StationConfig()
    bogus = msgspec.structs.replace(cfg, teacher=msgspec.structs.replace(cfg.teacher, kind="oracle"))
    with pytest.raises(ValueError, match="unknown teacher kind 'oracle'"):
        make_source(bogus, 0.1)


def _learned(limits: str) -> SourceContext:
    """A context whose store has learned the learner's top speed at 0.5 of the teacher's 1.0 (a boundary pair)."""
    store = PairStore(LEARNER, TEACHER)
    store.add([0.5, 0.0], [0.4, 0.0])  # the learner's top command gives half the teacher's top speed
    assert store.limits.box.v[1] == pytest.approx(0.5)
    return SourceContext(mission=load_mission(), store=store, counters=StationCounters(), limits=limits)


def test_the_teacher_is_bounded_by_the_learned_limits_unless_limits_say_its_own_range() -> None:
    """``[transfer] limits``: learned (the default, the paper's method) bounds the teacher by the box and hull
    learned from the pairs; teacher (the paper's baseline learner) by the teacher's own range, whatever was learned.
    The store learns the same in both."""
    learned, own = _learned("learned"), _learned("teacher")
    assert _ctx().limits == "learned"
    assert learned.box() == learned.store.limits.box and learned.box().v[1] == pytest.approx(0.5)
    assert own.box() == TEACHER and own.store.limits.box == learned.store.limits.box
    fast = np.array([[0.8, 0.0], [0.3, 0.0], [1.5, 0.0]])  # beyond the learned limit, inside it, beyond the teacher
    assert learned.allows(fast).tolist() == [False, True, False]
    assert own.allows(fast).tolist() == [True, True, False]


def test_the_primitives_of_the_baseline_plan_with_the_teachers_whole_library() -> None:
    src, cfg = _primitives(), StationConfig()
    lib = src.follower.planner.lib.commands
    counts = {}
    for limits in ("learned", "teacher"):
        store = PairStore(cfg.learner_bounds.bounds(), cfg.teacher_bounds.bounds())
        store.add([0.3, 0.0], [cfg.learner_bounds.v[1], 0.0])  # the learner's top speed: half the teacher's
        ctx = SourceContext(mission=load_mission(), store=store, counters=StationCounters(), limits=limits)
        assert isinstance(src.propose(0.0, POSE, ctx), Proposal)
        counts[limits] = ctx.counters.primitives_allowed
    assert counts["learned"] < len(lib) and counts["teacher"] == len(lib)


def test_learned_limits_under_commands_sent_as_they_are_end_at_the_learners_range() -> None:
    """``[transfer] mapper = "identity"`` with learned limits (``--transfer off --limits learned``, a reference run):
    the teacher's commands are clipped to the learner's range on the way, so a learned limit beyond it (one noisy
    pair read 0.40 m/s of a rover's 0.36 on SITL) must not let the plan run ahead of the vehicle; an axis the learner's
    range does not cut keeps the learned edge, and the mapped transfer keeps the learned box as it is."""
    store = PairStore(LEARNER, TEACHER)
    store.add([0.5, 0.0], [LEARNER.v[1], 0.0])  # its top command read faster than the learner's range
    assert store.limits.box.v[1] > LEARNER.v[1]
    direct = SourceContext(mission=load_mission(), store=store, counters=StationCounters(), direct_within=LEARNER)
    box = direct.box()
    lb = store.limits.box
    assert box.v == (max(lb.v[0], LEARNER.v[0]), LEARNER.v[1])
    assert box.w == (max(lb.w[0], LEARNER.w[0]), min(lb.w[1], LEARNER.w[1]))
    assert direct.box() is box  # built once for the same pair of boxes
    mapped = SourceContext(mission=load_mission(), store=store, counters=StationCounters())
    assert mapped.box() == store.limits.box
    own = SourceContext(mission=load_mission(), store=store, counters=StationCounters(), limits="teacher",
                        direct_within=LEARNER)
    assert own.box() == TEACHER  # the paper's baseline: the teacher's own range, as before


class _RecordingMpc:
    """An MPC teacher's stand-in that records whether each solve was asked to slow for bends, and the closest point
    of the path it was given."""

    def __init__(self) -> None:
        self.slow: list[bool] = []
        self.closest: list[tuple[float, int] | None] = []

    def solve(self, x, path, box, obstacles, curvature=None, slow_for_bends=True, closest=None):
        from types import SimpleNamespace

        self.slow.append(slow_for_bends)
        self.closest.append(closest)
        return SimpleNamespace(u=[0.1, 0.0], predicted=None, solver="fake", ok=True, obstacles_dropped=0)


def test_the_mpc_slows_for_bends_once_the_learner_changed_or_always_where_the_station_says_so() -> None:
    """``[teacher] slow_for_bends``: "changed" (the default) asks the MPC to slow only once the store says its
    learner changed (an unchanged store: the paper's MPC); "always" from the first tick, for a learner that turns
    too little from the start (the SITL weak-turn rover: docs/BENCHMARKS.md, "The transfer on SITL")."""
    from bridge.nodes.sources import MpcSource

    changed, always = _RecordingMpc(), _RecordingMpc()
    ctx = _ctx()
    assert not ctx.store.slows_for_bends()
    MpcSource(changed).propose(1.0, POSE, ctx)
    MpcSource(always, slow_always=True).propose(1.0, POSE, ctx)
    assert changed.slow == [False] and always.slow == [True]
    cfg = msgspec.convert({"teacher": {"slow_for_bends": "always"}}, StationConfig)
    assert make_source(cfg, 0.1).slow_always and not make_source(StationConfig(), 0.1).slow_always


def test_the_mpc_is_given_the_closest_point_the_station_found_for_the_same_pose() -> None:
    """The station finds the path's point closest to the pose for its off-path verdict; the MPC's solve is handed
    it (``SourceContext.closest``) instead of searching the path again, and searches only where none was found."""
    from bridge.nodes.sources import MpcSource

    mpc = _RecordingMpc()
    MpcSource(mpc).propose(1.0, POSE, _ctx(closest=(1.25, 3)))
    MpcSource(mpc).propose(1.1, POSE, _ctx())
    assert mpc.closest == [(1.25, 3), None]


def test_the_install_warms_the_kernels_a_default_station_builds_for_both_kinds_of_turn(tmp_path) -> None:
    """`make install` said it filled the services' cache with the MPC's code, but it built none (its warm-up made an
    IPOPT teacher, which has no kernels), so each service built them at its first start, and a station stopped before
    its build ended never cached them. ``warm_kernels`` (which `make install` runs) asks for exactly the code a
    station on the default configuration builds, for a learner that turns in place and one that needs speed."""
    import casadi as ca
    from msgspec.structs import replace

    from bridge.nodes.sources import warm_kernels
    from bridge.nodes.station_core import StationCore

    def code(functions: list) -> str:
        gen = ca.CodeGenerator("k.c", {"with_header": False})
        for fn in functions:
            gen.add(fn)
        return gen.dump()

    asked: list[str] = []
    assert warm_kernels(lambda fns: asked.append(code(fns)) or fns) == 2
    base = StationConfig()
    built = []
    for turn in ("in-place", "needs-speed"):
        cfg = replace(base, transfer=replace(base.transfer, turn=turn))
        core = StationCore(cfg, "r1", cfg.station.rate_hz, tmp_path / f"{turn}.bin", load_mission())
        built.append(code(core.source.teacher.kernels()))
    assert asked == built and built[0] != built[1] and all("mpc_rti" in c for c in built)

