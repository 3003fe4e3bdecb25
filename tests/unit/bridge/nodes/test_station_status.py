"""What the station says about itself (bridge.nodes.station_status): the reasons not to drive in words, the
integrity window, the status message and when it goes out, the limits; pure, every time passed in, no Zenoh."""

from __future__ import annotations

import numpy as np

from bridge.core import wire as M
from bridge.nodes.mission_control import Fitness, MissionControl
from bridge.nodes.pairing import IntervalPairer
from bridge.nodes.sources import Why
from bridge.nodes.station_status import (
    INTEGRITY_WINDOW_S,
    STATUS_MAX_HZ,
    Integrity,
    LimitsReport,
    StationCounters,
    StatusFacts,
    StatusReport,
    not_driving,
    paused_text,
    status_key,
    verdict,
)
from sim_learner.dynamics import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W
from transfer.domain import Bounds
from transfer.store import PairStore

SPEC = M.MissionSpec(name="line", path=[[0.0, 0.0], [2.0, 0.0]])
UNFIT = Why("no pose for 0.8 s", "no_telemetry")


def _control(phase: M.MissionPhase, reason: str = "") -> MissionControl:
    return MissionControl("r1", SPEC, phase, reason)


def _facts(**kw) -> StatusFacts:
    base = dict(reason="ok", why="driving", phase="running", progress=0.25, persist_error="", problems=[],
                counters={"ticks": 3}, tick_ms=[1.0, 2.0, 3.0], solve_ms=[], rate_hz=10.0,
                key=status_key("ok", "running", None, "ok", False))
    return StatusFacts(**{**base, **kw})


def test_the_one_reason_not_to_drive_is_typed_from_the_missions_phase() -> None:
    assert not_driving(_control("idle"), "r1", None) == Why(
        "idle: waiting for a person (scmbridge mission start --robot r1)", "idle")
    replaced = _control("idle")
    replaced.replace(SPEC, replaced.mission, by="a publisher on scm/r1/mission", at=0.0)
    assert not_driving(replaced, "r1", None).text.startswith("idle: new mission 'line' from a publisher")
    assert not_driving(_control("finished"), "r1", UNFIT) == Why("goal reached", "goal_reached")
    assert not_driving(_control("running"), "r1", UNFIT) == Why("waiting for the robot: no pose for 0.8 s",
                                                                 "no_telemetry")
    assert not_driving(_control("running"), "r1", None) == Why("waiting for the robot: not fit", "robot_not_ready")
    assert not_driving(_control("aborted", "aborted by test"), "r1", None) == Why("aborted by test", "aborted")
    assert not_driving(_control("paused", ""), "r1", None).reason == "paused"  # an empty reason still stops


def test_a_pause_says_the_robots_reason_now_or_a_persons_and_the_next_step() -> None:
    by_person = _control("paused", "paused by alice")
    assert paused_text(by_person, "r1", UNFIT) == "paused by alice; waiting for the robot: no pose for 0.8 s"
    assert paused_text(by_person, "r1", None) == ("paused by alice; the robot is ready: scmbridge mission resume "
                                                   "--robot r1 to drive on")
    by_robot = _control("running")
    by_robot.drove = True
    by_robot.may_drive(Fitness("estop latched", True), 1.0)  # the robot stopped after it drove: paused by it
    assert by_robot.phase == "paused" and by_robot.paused_by_robot
    assert paused_text(by_robot, "r1", Why("estop latched")) == "paused: estop latched"
    assert paused_text(by_robot, "r1", None).startswith("paused; the robot is ready")  # released: not "estop" now


def test_the_verdict_is_ok_only_for_good_reasons_and_untrustworthy_work_says_why() -> None:
    assert verdict("ok", "running", "", []) == (True, "ok", "driving")
    assert verdict("goal_reached", "finished", "", []) == (True, "goal_reached", "parked")
    assert verdict("ok", "running", "pair store not saved: full", ["x"]) == (False, "persist_failed", "driving")
    assert verdict("ok", "running", "", ["another sender"]) == (False, "integrity", "driving")
    assert verdict("no_telemetry", "running", "disk", []) == (False, "no_telemetry", "waiting")
    assert verdict("idle", "idle", "", []) == (False, "idle", "idle")
    assert verdict("paused", "paused", "", []) == (False, "paused", "paused")


def test_a_status_goes_out_at_once_on_a_change_but_at_most_status_max_hz() -> None:
    r = StatusReport()
    key = status_key("ok", "running", None, "ok", False)
    assert not r.changed(0.0, key)  # before the first: the periodic one goes first
    first = r.message(1.0, _facts(key=key))
    other = status_key("paused", "paused", "robot_not_ready", "estop", False)
    assert not r.changed(1.0 + 0.5 / STATUS_MAX_HZ, other)  # too soon after the last
    assert r.changed(1.0 + 1.0 / STATUS_MAX_HZ, other)
    assert not r.changed(5.0, key)  # nothing a person reads it for changed
    second = r.message(1.2, _facts(key=other))
    assert (first.seq, second.seq) == (0, 1) and not r.changed(9.0, other)


def test_the_status_message_says_the_reason_the_failures_and_the_latencies() -> None:
    msg = StatusReport().message(2.0, _facts(persist_error="pair store not saved: full", problems=["implausible"],
                                             progress=1.7, tick_ms=[1.0] * 98 + [50.0, 60.0], solve_ms=[4.0, 8.0]))
    assert (msg.ok, msg.reason, msg.state) == (False, "persist_failed", "driving")
    assert msg.text == "driving; pair store not saved: full; implausible" and msg.progress == 1.0
    assert msg.latencies_ms["tick_max"] == 60.0 and msg.latencies_ms["tick_p50"] == 1.0
    assert msg.latencies_ms["solve_median"] == 6.0 and msg.latencies_ms["solve_max"] == 8.0
    assert msg.counters == {"ticks": 3} and msg.rates_hz == {"loop": 10.0} and msg.node == "station"
    empty = StatusReport().message(0.0, _facts(tick_ms=[], why="x" * 2000))
    assert empty.latencies_ms["tick_max"] == 0.0 and len(empty.text) == 1024
    M.validated(empty)


def test_integrity_problems_last_the_window_after_they_were_last_seen() -> None:
    integrity, pairer = Integrity(), IntervalPairer(dt=0.1)
    assert integrity.problems(0.0, pairer) == []
    integrity.foreign_command(0xAB, 1.0)
    assert "another sender publishes commands for this robot (epoch ab)" in integrity.problems(1.1, pairer)[0]
    assert integrity.problems(1.0 + INTEGRITY_WINDOW_S, pairer) == []
    pairer.state(0.0, np.zeros(3), received=100.0)
    pairer.state(1e11, np.zeros(3), received=100.01)  # a forged stamp: dropped and counted
    (problem,) = integrity.problems(100.1, pairer)
    assert problem.startswith("implausible telemetry dropped before pairing (1 stamps")
    assert integrity.problems(100.1 + INTEGRITY_WINDOW_S - 0.01, pairer) != []
    assert integrity.problems(100.1 + INTEGRITY_WINDOW_S, pairer) == []  # the count did not grow since


def test_a_dropped_pose_is_named_by_what_it_moved_and_in_how_long() -> None:
    """A person (or a failed test) reading "implausible poses" learns whether it was a jump or two stamps too close."""
    integrity, pairer = Integrity(), IntervalPairer(dt=0.1, max_speed=1.0, max_turn=2.0)
    pairer.state(10.0, np.zeros(3), received=10.0)
    pairer.state(10.02, np.array([0.5, 0.0, 0.0]), received=10.02)  # 0.5 m in 20 ms at most 1 m/s: dropped
    (problem,) = integrity.problems(10.1, pairer)
    assert "1 poses" in problem and "the last pose dropped: 0.500 m and 0.000 rad in 0.020 s" in problem, problem
    assert "(at most 1.00 m/s, 2.00 rad/s)" in problem, problem
    pairer.state(10.03, np.array([0.0, 0.0, np.nan]), received=10.03)
    assert integrity.problems(10.1, pairer)[0].endswith("the last pose dropped: not finite)")


def test_counters_take_the_pairers_counts_under_their_status_names() -> None:
    pairer, store = IntervalPairer(dt=0.1), PairStore(Bounds(MPC_LEARNER_V, MPC_LEARNER_W),
                                                      Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=1)
    pairer.state(0.0, np.zeros(3), received=0.0)
    pairer.state(1e11, np.zeros(3), received=0.01)
    pairer.state(-5.0, np.zeros(3), received=0.02)
    c = StationCounters()
    c.observe(pairer, store, _control("finished"))
    d = c.as_dict()
    assert d["implausible_stamps"] == pairer.implausible_stamp == 1
    assert d["pairs_out_of_order"] == pairer.out_of_order and d["pairer_resyncs"] == pairer.resyncs
    assert d["goal_reached"] == 1 and d["raw_pairs"] == 0 and d["refined_pairs"] == 0


def test_limits_go_out_when_their_box_moved_or_forced_with_a_new_version_only_when_they_changed() -> None:
    store = PairStore(Bounds(MPC_LEARNER_V, MPC_LEARNER_W), Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=1)
    report = LimitsReport(store, "r1")
    first = report.message(0.0, force=False)
    assert first is not None and first.version == 1 and first.robot == "r1"
    assert report.message(0.1, force=False) is None  # nothing moved
    again = report.message(1.0, force=True)
    assert again is not None and again.version == 1 and again.box == first.box  # each second, as they are
    for u in ([0.05, 0.0], [0.25, 0.3], [0.3, -0.3], [0.1, 0.2]):
        store.add(u, u)
    moved = report.message(1.1, force=False)
    assert moved is not None and moved.version == 2 and moved.box != first.box
    M.validated(moved)


def test_the_limits_of_a_learner_that_cannot_turn_in_place_carry_its_curvatures_and_a_config_needs_a_forward_teacher(
        tmp_path) -> None:
    """``[transfer] turn = "needs-speed"``: the ``limits`` message carries [k_lo, k_hi] (null for a side not learned
    yet; absent for a learner that turns in place), and a teacher that may drive backwards is refused, since
    omega <= k v does not hold there."""
    import pytest

    from bridge.core.config import ConfigError, load_station

    lb, tb = Bounds(MPC_LEARNER_V, MPC_LEARNER_W), Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
    store = PairStore(lb, tb, k_min=1)
    assert LimitsReport(store, "r1").message(0.0, force=True).curvature is None
    store.limits.set_needs_speed(True)
    assert LimitsReport(store, "r1").message(0.0, force=True).curvature == [None, None]
    store.add([0.3, 0.15], [lb.v[1], lb.w[1]])  # a full-lock pair: 0.5 rad/s per m/s to the left
    report = LimitsReport(store, "r1")
    msg = report.message(0.0, force=True)
    assert msg.curvature == [None, 0.5] and msg.box[3] == pytest.approx(0.5 * msg.box[1])
    M.validated(msg)
    assert report.message(0.1, force=False) is None  # nothing moved
    store.limits.turn_vw[1] *= 1.2  # the curvature moves (as a full-lock pair would move it), the box not yet
    moved = report.message(0.2, force=False)
    assert moved is not None and moved.curvature == [None, 0.6] and moved.version == msg.version + 1
    assert load_station(None).transfer.turn == "in-place"
    ok = tmp_path / "ok.toml"
    ok.write_text('[transfer]\nturn = "needs-speed"\n')
    assert load_station(ok).transfer.turn == "needs-speed"
    bad = tmp_path / "bad.toml"
    bad.write_text('[transfer]\nturn = "needs-speed"\n[teacher_bounds]\nv = [-0.5, 0.5]\nw = [-1.0, 1.0]\n')
    with pytest.raises(ConfigError, match="forward-only teacher"):
        load_station(bad)


def test_the_status_quantiles_are_numpys_default_percentiles() -> None:
    from bridge.nodes.station_status import quantiles

    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 600):
        x = rng.exponential(1.0, n)
        got = quantiles(sorted(x.tolist()), (0.0, 0.5, 0.99, 1.0))
        np.testing.assert_allclose(got, np.percentile(x, (0, 50, 99, 100)), rtol=1e-12, atol=1e-12)
