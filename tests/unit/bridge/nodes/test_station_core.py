"""The station core without Zenoh: typed ticks in, messages out, one counters object, one command source per
teacher, several cores in one process."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission
from bridge.nodes.sources import ExternalSource, MpcSource, PrimitivesSource, Proposal, Why, make_source
from bridge.nodes.station_core import StationCore, TickInputs, robot_phase
from bridge.nodes.station_status import StationCounters
from sim_learner.dynamics import mpc_learner

#: the status counter keys of a station that has driven with the MPC (the keys tools and tests read)
MPC_KEYS = {"method_scm", "method_direct", "method_perturb", "method_barycentric", "method_stop",
            "obstacles_dropped", "persist_failures", "missions", "explore_vetoed", "missed_deadlines",
            "refined_pairs", "raw_pairs", "pairs_rejected", "pairs_formed", "pairs_out_of_order",
            "implausible_stamps", "implausible_poses", "implausible_pairs", "pairer_resyncs", "goal_reached",
            "cells_relearned", "ticks"}


def _driver(seq: int = 1, ok: bool = True) -> M.Status:
    return M.Status(stamp=0.0, seq=seq, node="driver", ok=ok, text="link can: driving (cmd)")


def _start(core: StationCore) -> None:
    core.request(M.MissionRequest(stamp=0.0, action="start", source="test"), 0.0)


class _Robot:
    """The paper's learner, fed each command and answering with its echo and its pose, as a driver host would."""

    def __init__(self, start) -> None:
        self.learner = mpc_learner()
        self.x = np.array(start, dtype=float)
        self.seq = 0

    def state(self, now: float) -> M.LearnerState:
        self.seq += 1
        return M.LearnerState(stamp=now, seq=self.seq, x=float(self.x[0]), y=float(self.x[1]),
                              theta=float(self.x[2]))

    def apply(self, cmd: M.Command, now: float, dt: float) -> M.Applied:
        u = np.array([cmd.v, cmd.omega])
        self.x = self.learner.step(self.x, u, dt)
        return M.Applied(stamp=now + 1e-3, seq=cmd.seq, v=cmd.v, omega=cmd.omega,
                         reason="stop" if cmd.method == "stop" else "cmd", cmd_seq=cmd.seq)


def test_a_core_drives_a_robot_by_ticks_alone_and_reports_todays_counters(tmp_path) -> None:
    mission = load_mission()
    core = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", mission)
    assert isinstance(core.source, MpcSource)
    robot = _Robot(mission.start)
    out = core.tick(TickInputs(telemetry=((robot.state(0.0), 0.0),), driver=(_driver(), 0.0)), 0.0)
    # idle: a stop, and the status says who has to act
    assert out.command.method == "stop" and out.teacher is None
    assert out.status.text.startswith("idle: waiting for a person") and out.limits is not None
    assert (tmp_path / "p.bin").exists()  # the first periodic tick saves the store
    _start(core)
    methods, dt = [], 0.1
    pending: list = []
    for k in range(1, 40):
        now = k * dt
        out = core.tick(TickInputs(telemetry=((robot.state(now), now), *pending), driver=(_driver(k), now),
                                   input_counts={"malformed_state": 2}), now)
        methods.append(out.command.method)
        pending = [(robot.apply(out.command, now, dt), now + 2e-3)]
        if out.command.method != "stop":
            assert out.teacher is not None and out.teacher.seq == out.command.seq
            assert out.teacher.epoch == out.command.epoch == core.outbox.epoch
    assert "stop" not in methods and core.verdict.why == "driving"
    # nobody subscribes to the teacher topic (the station follows Zenoh's matching status): no teacher message is
    # built, and the command is the same as ever
    core.latest.teacher_heard = False
    for k in range(40, 43):
        now = k * 0.1
        out = core.tick(TickInputs(telemetry=((robot.state(now), now), *pending), driver=(_driver(k), now),
                                   input_counts={"malformed_state": 2}), now)
        pending = [(robot.apply(out.command, now, dt), now + 2e-3)]
        assert out.command.method != "stop" and out.teacher is None
    core.latest.teacher_heard = True
    status = core.status(4.0)
    assert status.ok and status.state == "driving"
    assert set(status.counters) == MPC_KEYS | {"malformed_state"}
    c = status.counters
    assert c["ticks"] == 43 and c["method_stop"] == 1 and c["malformed_state"] == 2
    assert sum(c[f"method_{m}"] for m in ("scm", "direct", "perturb", "barycentric")) == 42  # affine: only if used
    assert c["pairs_formed"] > 0 and c["raw_pairs"] == c["pairs_formed"]


def test_counters_name_the_optional_keys_only_once_they_mean_something() -> None:
    c = StationCounters()
    assert "method_calibrate" not in c.as_dict() and "primitive_replans" not in c.as_dict()
    c.count_method("calibrate")
    c.primitive_replans, c.calibration_index, c.calibration_total = 3, 1, 9
    c.foreign_commands = 1
    d = c.as_dict()
    assert d["method_calibrate"] == 1 and d["primitive_replans"] == 3 and d["foreign_commands"] == 1
    assert (d["calibration_index"], d["calibration_total"]) == (1, 9)
    assert all(isinstance(v, int) for v in d.values())


def test_the_configured_teacher_picks_its_source() -> None:
    import msgspec

    def cfg(kind: str) -> StationConfig:
        return msgspec.convert({"teacher": {"kind": kind}}, StationConfig)

    assert isinstance(make_source(cfg("primitives"), 0.1), PrimitivesSource)
    ext = make_source(cfg("external"), 0.1)
    assert isinstance(ext, ExternalSource) and ext.external and not ext.follows_mission


def test_an_external_teachers_command_is_mapped_once_and_a_silent_teacher_stops_the_robot(tmp_path) -> None:
    import msgspec

    cfg = msgspec.convert({"teacher": {"kind": "external", "timeout_s": 0.5}}, StationConfig)
    core = StationCore(cfg, "r1", 10.0, tmp_path / "p.bin", load_mission())
    _start(core)
    pose = M.LearnerState(stamp=1.0, seq=1, x=0.0, y=-1.0, theta=0.0)
    first = core.tick(TickInputs(telemetry=((pose, 1.0),), driver=(_driver(), 1.0)), 1.0)
    assert first.command.method == "stop" and core.verdict.why == "waiting for the external teacher"
    t = M.TeacherCommand(stamp=1.0, seq=1, v=0.3, omega=0.1, solver="lab", ok=True)
    woken = core.tick(TickInputs(teacher=(t, 1.05), periodic=False), 1.05)
    assert woken.command is not None and woken.command.method != "stop"
    assert woken.status is None and woken.limits is None  # a woken tick only maps
    again = core.tick(TickInputs(telemetry=((pose, 1.1),)), 1.1)
    assert again.command is None  # mapped once: nothing new to send
    silent = core.tick(TickInputs(telemetry=((pose, 1.7),), driver=(_driver(2), 1.7)), 1.7)
    assert silent.command.method == "stop" and core.verdict.why.startswith("no teacher command for")


def test_a_new_teacher_is_one_class_and_cores_share_nothing(tmp_path) -> None:
    class Constant:
        """A teacher that always asks for the same command."""

        what, follows_mission, external = "constant", False, False

        def __init__(self) -> None:
            self.resets = 0

        def propose(self, now, pose, ctx):
            if pose.x > 1.0:
                return Why("far enough")
            return Proposal(np.array([0.2, 0.0]), np.array([pose.x, pose.y]))

        def reset(self) -> None:
            self.resets += 1

        def done(self) -> bool:
            return False

    mission = load_mission()
    a = StationCore(StationConfig(), "a", 10.0, tmp_path / "a.bin", mission, source=Constant())
    b = StationCore(StationConfig(), "b", 10.0, tmp_path / "b.bin", mission, source=Constant())
    assert a.outbox.epoch != b.outbox.epoch and a.store is not b.store and a.counters is not b.counters
    _start(a)
    near = M.LearnerState(stamp=1.0, seq=1, x=0.9, y=-1.0, theta=0.0)
    far = M.LearnerState(stamp=1.1, seq=2, x=1.05, y=-1.0, theta=0.0)
    out_a = a.tick(TickInputs(telemetry=((near, 1.0),), driver=(_driver(), 1.0)), 1.0)
    out_b = b.tick(TickInputs(telemetry=((near, 1.0),), driver=(_driver(), 1.0)), 1.0)
    assert out_a.command.method != "stop" and out_a.teacher is None  # not the station's own solver: no teacher
    assert out_b.command.method == "stop" and b.counters.method_stop == 1 and a.counters.method_stop == 0
    assert a.tick(TickInputs(telemetry=((far, 1.1),)), 1.1).command.method == "stop" and a.verdict.why == "far enough"
    spec = M.MissionSpec(name="other", path=[[0.0, 0.0], [1.0, 0.0]])
    from bridge.core.config import mission_from_spec

    a.tick(TickInputs(mission=(spec, mission_from_spec(spec))), 1.2)
    assert a.source.resets == 1 and b.source.resets == 0 and a.mission.name == "other" != b.mission.name


@pytest.mark.parametrize("restart_seq", [0, 3])
def test_a_driver_host_restart_pauses_a_running_mission(tmp_path, restart_seq: int) -> None:
    core = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", load_mission(),
                       source=make_source(StationConfig(), 0.1))
    _start(core)
    core.tick(TickInputs(driver=(_driver(10), 1.0)), 1.0)
    core.tick(TickInputs(driver=(_driver(restart_seq), 2.0)), 2.0)
    assert core.control.phase == "paused"


def test_a_store_learned_on_another_day_is_checked_against_todays_pairs_by_default(tmp_path) -> None:
    """``[transfer] adapt = true`` (the default): the station loads yesterday's store, saved without change
    detection, and the cells whose learner answers otherwise today (a dragging wheel: 15 % of the yaw-rate range) are
    re-learned from today's pairs and counted on the status; ``adapt = false`` keeps the paper's store; a station
    learning from no pairs adapts too, unless ``adapt = "reloaded"``."""
    import msgspec

    from transfer.store import PairStore

    learner = mpc_learner()
    cfg = StationConfig()
    lb, tb = cfg.learner_bounds.bounds(), cfg.teacher_bounds.bounds()
    yesterday = PairStore(lb, tb)
    rng = np.random.default_rng(4)
    for i in range(11):
        for j in range(11):
            for _ in range(8):
                u = lb.denormalise((np.array([i, j]) + rng.uniform(0.1, 0.9, 2)) / 11)
                yesterday.add(learner.response(u), u)
    (tmp_path / "p.bin").write_bytes(yesterday.to_bytes())
    core = StationCore(cfg, "r1", 10.0, tmp_path / "p.bin", load_mission())
    assert core.store.adapt and core.store.change.change_tol == cfg.transfer.change_tol
    assert core.store.limits.memory == PairStore(lb, tb, adapt=True).limits.memory > 0  # its limits follow too
    assert core.store.n_configured() == 121 and core.store.relearned == 0  # loaded as it was
    bias = np.array([0.0, 0.15 * (lb.w[1] - lb.w[0])])
    for _ in range(8):  # today: the top-speed row driven, as the mission does
        for j in range(11):
            u = lb.denormalise(np.array([(10 + rng.uniform(0.1, 0.9)) / 11, (j + rng.uniform(0.1, 0.9)) / 11]))
            core.store.add(learner.response(u) + bias, u, stamp=5.0)
    assert core.store.relearned == 11 and np.all(core.store.change.changed_at[10] == 5.0)
    assert np.all(np.isnan(core.store.change.changed_at[:10]))  # the cells not driven today are not touched
    out = core.tick(TickInputs(), 6.0)
    assert out.status is not None and out.status.counters["cells_relearned"] == 11
    # the cells not driven moved provisionally by the change the top row agreed on: counted on the status
    assert core.store.shifts.shared > 0 and out.status.counters["shared_changes"] == core.store.shifts.shared
    assert out.status.changed_cells == list(range(110, 121))  # named on the status (scmbridge status prints them)
    assert [c.id for c in core.pairs(6.0).changed] == list(range(110, 121))  # and in the pairs reply, with when
    never = msgspec.convert({"transfer": {"adapt": False}}, StationConfig)
    off = StationCore(never, "r2", 10.0, tmp_path / "p.bin", load_mission())
    assert not off.store.adapt and off.store.limits.memory == 0  # the paper's never-forgetting store
    fresh = StationCore(cfg, "r3", 10.0, tmp_path / "new.bin", load_mission())
    assert fresh.store.adapt and fresh.store.limits.memory > 0  # from no pairs too: a first run's change is followed
    reloaded = msgspec.convert({"transfer": {"adapt": "reloaded"}}, StationConfig)
    assert not StationCore(reloaded, "r4", 10.0, tmp_path / "new2.bin", load_mission()).store.adapt
    assert StationCore(reloaded, "r5", 10.0, tmp_path / "p.bin", load_mission()).store.adapt


def test_a_learned_limit_whose_boundary_pairs_changed_is_logged_and_counted_on_the_status(tmp_path, caplog) -> None:
    """With change detection a learned edge tests its boundary pairs (``transfer/limits.py``, "An edge that moved"): a
    turn-rate cap lowered mid-run shows in a few pairs at the learner's full lock, and the station says so (a warning
    with the limits it now holds, ``limits_relearned`` on the status, shown once there is one)."""
    import msgspec

    cfg = msgspec.convert({"transfer": {"adapt": True}}, StationConfig)
    core = StationCore(cfg, "r1", 10.0, tmp_path / "p.bin", load_mission())
    lb, tb = core.store.learner_bounds, core.store.teacher_bounds
    assert "limits_relearned" not in core.tick(TickInputs(), 0.5).status.counters  # none yet: not shown

    def lock(share: float) -> np.ndarray:  # the full left lock at a share of the top speed
        return np.array([lb.v[0] + share * (lb.v[1] - lb.v[0]), lb.w[1]])

    # the pairs at the lock came seldom and at several speeds (each cell too few to test: the edge's own test finds it)
    for k in range(12):
        core.store.add(np.array([0.3, 0.6 * tb.w[1] + 0.005 * (-1) ** k]), lock(0.15 + 0.2 * (k % 4)), stamp=1.0)
    with caplog.at_level("WARNING", logger="scmbridge.station"):
        for _ in range(3):
            core.add_pair((np.array([0.3, 0.35 * tb.w[1]]), lock(0.95)), 2.0)
    said = [r.message for r in caplog.records if r.message.startswith("a learned limit re-learned")]
    assert len(said) == 1
    assert json.loads(said[0].split("limits now ")[1]) == pytest.approx(core.store.limits.box.as_list())
    assert core.store.limits.relearned == 1
    assert core.store.limits.box.w[1] == pytest.approx(0.35 * tb.w[1])
    out = core.tick(TickInputs(), 3.0)
    assert out.status is not None and out.status.counters["limits_relearned"] == 1


def _drive(core: StationCore, ticks: int) -> list[tuple[np.ndarray, np.ndarray, str, np.ndarray]]:
    """``ticks`` ticks of ``core`` driving the paper's learner from the mission's start: (teacher command, command
    sent, method, learned box [v_lo, v_hi, w_lo, w_hi] the tick ended with) for each command the core sent."""
    robot, dt, pending, sent = _Robot(core.mission.start), 0.1, [], []
    for k in range(1, ticks + 1):
        now = k * dt
        out = core.tick(TickInputs(telemetry=((robot.state(now), now), *pending), driver=(_driver(k), now)), now)
        pending = [(robot.apply(out.command, now, dt), now + 2e-3)]
        if out.teacher is not None:
            sent.append((np.array([out.teacher.v, out.teacher.omega]), np.array([out.command.v, out.command.omega]),
                         out.command.method, np.array(core.store.limits.box.as_list())))
    return sent


@pytest.mark.parametrize("limits", ["teacher", "learned"])
def test_the_papers_baseline_applies_the_teachers_commands_unbounded_by_what_it_learns(tmp_path, limits) -> None:
    """``[transfer]`` mapper identity, exploration off and limits teacher (``scmbridge demo --transfer off``): the
    paper's baseline learner (Section 5.2). Its MPC plans within the teacher's own range, beyond what the learner was
    seen to reach, and each command goes out as the teacher's, clipped to the learner's range only; the pairs are
    still learned. With limits learned (the teacher's commands under the learned limits: how the teacher's reference
    is made on SITL) the MPC keeps within the learned box once it has learned one."""
    import msgspec

    cfg = msgspec.convert({"transfer": {"mapper": "identity", "exploration": "off", "limits": limits}},
                          StationConfig)
    core = StationCore(cfg, "r1", 10.0, tmp_path / "p.bin", load_mission())
    assert core.teacher_limits == limits
    core.tick(TickInputs(driver=(_driver(0), 0.0)), 0.0)
    _start(core)
    sent = _drive(core, 60)
    lb = cfg.learner_bounds.bounds()
    assert len(sent) >= 55 and {m for _, _, m, _ in sent} == {"direct"}  # never mapped, never explored
    for u_T, u, _, _ in sent:
        np.testing.assert_allclose(u, lb.clip(u_T), atol=1e-9)  # the teacher's command, clipped by the learner's
    assert core.store.raw_count > 0  # pairs are formed and stored all the same
    # how far each teacher command lies beyond the box learned before it (the box the MPC was bounded by, or not)
    beyond = [max(u_T[0] - box[1], box[2] - u_T[1], u_T[1] - box[3]) for (u_T, _, _, _), (_, _, _, box)
              in zip(sent[1:], sent[:-1])]
    if limits == "teacher":
        # the learner's top speed learned (about 0.3 of the teacher's 0.6), and the teacher asking beyond it
        assert core.store.limits.box.v[1] < 0.4 < cfg.teacher_bounds.v[1]
        assert max(beyond) > 0.05, max(beyond)
    else:
        assert max(beyond) < 1e-6, max(beyond)


def test_a_robots_phase_is_its_own_the_same_on_every_run_and_spreads_a_fleet() -> None:
    """``robot_phase``: where a robot's periodic work falls (its hole searches' budget, its store's saves): a hash of
    its name, so the same in every process, and spread over [0, 1) across a fleet's names."""
    phases = [robot_phase(f"fleet{i}") for i in range(1, 101)]
    assert all(0.0 <= p < 1.0 for p in phases) and robot_phase("fleet1") == phases[0]
    assert len(set(phases)) == 100
    counts, _ = np.histogram(phases, bins=4, range=(0.0, 1.0))
    assert counts.min() >= 15  # no quarter of the period left empty, none holding most of the fleet


def test_a_restarted_stations_progress_is_where_the_robot_stands_now(tmp_path) -> None:
    """Finding: a restarted station said `mission 2%` while its robot stood at about 14 % of the path (the progress
    last saved). Paused, the station still reads the robot's fresh pose and says where it is on the path."""
    from bridge.nodes.mission_control import MissionControl, spec_of

    mission = load_mission()
    running = MissionControl("r1", spec_of(mission))
    running.request(M.MissionRequest(stamp=0.0, action="start"), _fitness_ok(), 0.0)
    running.progress = 0.02
    restarted = MissionControl.restored("r1", running.saved())
    assert restarted.phase == "paused"
    core = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", mission, control=restarted)
    path = mission.path
    k = int(np.searchsorted(path.s, 0.14 * path.length))
    x, y = path.points[k]
    for i in range(3):
        now = 1.0 + 0.1 * i
        core.tick(TickInputs(telemetry=((M.LearnerState(stamp=now, seq=i, x=float(x), y=float(y), theta=0.0), now),),
                             driver=(_driver(i + 1), now)), now)
    st = core.status(now)
    assert st.state == "paused" and abs(st.progress - 0.14) < 0.01, (st.progress, st.text)
    assert core.control.phase == "paused"  # where it stands is said; nothing is started by it


def _fitness_ok():
    from bridge.nodes.mission_control import Fitness

    return Fitness("")


def test_a_repeated_reason_is_logged_once_and_how_long_it_held_when_it_changes(tmp_path, caplog) -> None:
    """Finding: `not driving: waiting for the robot: no pose for 0.6 s`, `0.7 s`, ... every 100 ms (48 lines for two
    short outages). Logged once per typed reason, then, on the next change, how long it held and how often."""
    import logging

    mission = load_mission()
    core = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", mission)
    _start(core)
    x, y, th = (float(a) for a in mission.start)
    caplog.set_level(logging.INFO, logger="scmbridge")
    now = 1.0
    for i in range(40):  # poses for 1 s, none for 3 s: the words change each tick ("no pose for 0.6 s", ...)
        now += 0.1
        tel = ((M.LearnerState(stamp=now, seq=i, x=x, y=y, theta=th), now),) if i < 10 else ()
        core.tick(TickInputs(telemetry=tel, driver=(_driver(i + 1), now)), now)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("not driving")]
    assert 1 <= len(lines) <= 3, lines
    before = len(lines)
    now += 0.1  # the poses are back: the mission stays paused, the robot is ready: a new reason
    core.tick(TickInputs(telemetry=((M.LearnerState(stamp=now, seq=41, x=x, y=y, theta=th), now),),
                         driver=(_driver(41), now)), now)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("not driving")]
    assert len(lines) == before + 1 and "held" in lines[-1] and "decided" in lines[-1], lines
