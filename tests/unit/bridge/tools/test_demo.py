"""bridge/tools/demo.py: the demo's pure figures, :func:`driving_time`, :func:`method_counts`, and
:class:`Monitor` (its live line and its run summary) fed recorded messages through
:class:`bridge.tools.report.FeedSession`, the very callbacks that handle them live. Other tests of them:
tests/integration/test_operator_truths.py (a run with an estop, every method counted), tests/integration/test_fleet.py
(the goal distance) and tests/integration/test_record.py (the Monitor live beside a recorder)."""

from __future__ import annotations

import pytest

from bridge.core import wire as M
from bridge.core.config import mission_from_spec
from bridge.tools.demo import ECHO_GAP_S, LINE_METHODS, Monitor, driving_time, method_counts, touched_an_obstacle
from bridge.tools.report import FeedSession

LINE = mission_from_spec(M.MissionSpec(name="line", path=[[0.0, 0.0], [1.0, 0.0]], goal_tolerance=0.05))


# ------------------------------------------------------------------------------------------------ driving_time
def test_no_echo_or_a_single_one_is_no_driving() -> None:
    assert driving_time([], 0.0, 10.0) == 0.0
    assert driving_time([(1.0, "cmd", 1)], 0.0, 10.0) == 0.0


def test_driving_runs_from_each_driving_echo_to_the_next_echo() -> None:
    applied = [(0.0, "cmd", 1), (0.1, "clamped", 2), (0.2, "stop", 3), (0.3, "estop", None), (0.4, "cmd", 4),
               (0.5, "stop", 5)]
    # cmd 0->0.1, clamped 0.1->0.2 and cmd 0.4->0.5 drive; the stop and the estop do not
    assert driving_time(applied, 0.0, 1.0) == pytest.approx(0.3)
    assert driving_time(list(reversed(applied)), 0.0, 1.0) == pytest.approx(0.3)  # any order


def test_a_gap_between_echoes_counts_at_most_echo_gap() -> None:
    applied = [(0.0, "cmd", 1), (10.0, "cmd", 2), (10.02, "stop", 3)]
    assert driving_time(applied, 0.0, 20.0) == pytest.approx(ECHO_GAP_S + 0.02)


def test_only_the_echoes_inside_the_window_count() -> None:
    applied = [(float(t), "cmd", t) for t in range(10)]  # 1 s apart: each counts ECHO_GAP_S
    assert driving_time(applied, 2.0, 5.0) == pytest.approx(3 * ECHO_GAP_S)  # 2-3, 3-4, 4-5
    assert driving_time(applied, 20.0, 30.0) == 0.0


# ----------------------------------------------------------------------------------------------- method_counts
def test_every_line_method_is_shown_even_at_zero_with_stop_last() -> None:
    assert method_counts({}) == "scm=0 barycentric=0 direct=0 perturb=0 stop=0"
    assert LINE_METHODS[-1] == "stop"


def test_other_methods_are_shown_sorted_before_stop_and_other_counters_ignored() -> None:
    line = method_counts({"method_zeta": 1, "method_affine": 2, "method_scm": 7, "method_stop": 3, "pairs": 99})
    assert line == "scm=7 barycentric=0 direct=0 perturb=0 affine=2 zeta=1 stop=3"


# ----------------------------------------------------------------------------------------------------- Monitor
class Run:
    """A monitor on robot ``r1`` and the feed that delivers its messages."""

    def __init__(self) -> None:
        self.feed, self.keys = FeedSession(), M.Keys("r1")
        self.mon = Monitor(self.feed, "r1")
        self.seq = 0

    def state(self, t: float, x: float, y: float = 0.0) -> None:
        self.seq += 1
        self.feed.put(self.keys.state, M.encode(M.LearnerState(stamp=t, seq=self.seq, x=x, y=y, theta=0.0)))

    def applied(self, t: float, reason: str, cmd_seq: int | None) -> None:
        self.seq += 1
        self.feed.put(self.keys.applied, M.encode(M.Applied(stamp=t, seq=self.seq, v=0.0, omega=0.0, reason=reason,
                                                            cmd_seq=cmd_seq)))

    def cmd(self, seq: int, method: str) -> None:
        self.feed.put(self.keys.cmd, M.encode(M.Command(stamp=1.0, seq=seq, v=0.1, omega=0.0, method=method)))

    def station(self, **counters: int) -> None:
        self.seq += 1
        self.feed.put(M.status_key("r1", "station"), M.encode(M.Status(
            stamp=1.0, seq=self.seq, node="station", counters=counters, text="driving",
            rates_hz={"loop": 20.0}, latencies_ms={"solve_median": 4.5})))


def test_nothing_to_sum_up_without_telemetry_or_a_station() -> None:
    run = Run()
    assert run.mon.summary(LINE) is None
    run.state(1.0, 0.0)
    assert run.mon.summary(LINE) is None  # no station status yet
    assert "waiting for station and driver" in run.mon.line(LINE, 0.5)
    run.station()
    assert run.mon.summary(LINE) is not None


def test_the_summary_covers_the_driving_time_and_reports_the_parked_time_apart() -> None:
    run = Run()
    for i in range(10):  # parked 1 s before the first command
        run.state(100.0 + 0.1 * i, 0.0)
    t, x = 101.0, 0.0
    for k in range(20):  # 2 s driving at 0.6 m/s, commands 1..20, each pose 40 ms after its command's echo
        run.cmd(k + 1, "scm" if k < 5 else "barycentric")
        run.applied(t, "cmd", k + 1)
        x = min(1.0, x + 0.06)
        run.state(t + 0.04, x)
        t += 0.1
    for k in range(10):  # parked at the goal 1 s, the station stopping it
        run.cmd(100 + k, "stop")
        run.applied(t, "stop", 100 + k)
        run.state(t + 0.04, 1.0)
        t += 0.1
    run.station(goal_reached=1, refined_pairs=12, raw_pairs=30, missed_deadlines=2, method_scm=5,
                method_barycentric=15, method_stop=10)
    s = run.mon.summary(LINE)
    assert s["reached_goal"] is True
    assert s["parked_before_s"] == pytest.approx(1.0)
    # the goal (within 5 cm of x = 1) is first reached by the 16th pose (x = 0.96, 1.54 s after the first command):
    # the run ends there, and the time at the goal after it is apart
    assert s["time_s"] == pytest.approx(1.5) and s["parked_after_s"] == pytest.approx(1.4)
    assert s["driving_s"] == pytest.approx(1.5) and s["paused_s"] == 0.0
    assert s["methods"] == {"scm": 5, "barycentric": 11}  # the commands of the driving time, not those after
    assert s["mean_dev_m"] == 0.0 and s["max_dev_m"] == 0.0 and s["goal_dist_m"] <= 0.05
    assert (s["refined_pairs"], s["raw_pairs"], s["missed_deadlines"], s["solve_ms_median"]) == (12, 30, 2, 4.5)
    assert s["_traj"].shape == (len(run.mon.states), 3)


def test_without_commands_the_methods_are_the_stations_counters() -> None:
    run = Run()
    for i in range(5):
        run.state(10.0 + i, 0.2 * i, 0.1)  # 10 cm beside the line, never at the goal
    run.station(method_scm=3, method_direct=1, refined_pairs=0)
    s = run.mon.summary(LINE)
    assert s["reached_goal"] is False and s["methods"] == {"scm": 3, "direct": 1}
    assert s["driving_s"] == 0.0 and s["time_s"] == pytest.approx(4.0)  # no command: the whole telemetry
    assert s["mean_dev_m"] == pytest.approx(0.1)


def test_the_live_line_shows_rate_methods_pairs_and_progress() -> None:
    run = Run()
    run.state(1.0, 0.5, 0.02)
    run.station(method_scm=2, refined_pairs=7)
    line = run.mon.line(LINE, 3.0)
    assert line.startswith("t=  3.0s rate=20Hz scm=2 barycentric=0")
    assert "pairs=7" in line and "dev=  2.0cm" in line and "progress= 50.0%" in line and line.endswith("[driving]")


# ------------------------------------------------------------------------------------------------ --transfer
@pytest.mark.parametrize(("transfer", "limits", "want"), [
    ("on", None, ("scm", "guided", "learned")),
    ("off", None, ("identity", "off", "teacher")),  # the paper's baseline: sim mpc's teacher_range baseline
    ("off", "learned", ("identity", "off", "learned")),  # the teacher's reference on SITL (and --transfer off before)
    ("on", "teacher", ("scm", "guided", "teacher")),
])
def test_transfer_and_limits_are_the_stations_transfer_table(transfer: str, limits: str | None, want) -> None:
    from bridge.core.config import StationConfig, decode_toml
    from bridge.tools.demo import TRANSFER, transfer_table

    t = decode_toml(transfer_table(transfer, limits) + "adapt = true\n", StationConfig).transfer
    assert (t.mapper, t.exploration, t.limits) == want and t.adapt
    assert TRANSFER["off"] == ("identity", "off", "teacher")


@pytest.mark.parametrize("argv", [["--transfer", "off", "--count", "2"], ["--limits", "teacher", "--inprocess"],
                                  ["--transfer", "off", "--robots", "a,b"]])
def test_transfer_and_limits_set_one_robots_station_only(argv: list[str]) -> None:
    import argparse

    from bridge.core.errors import UsageError
    from bridge.tools.demo import arguments, run

    ap = argparse.ArgumentParser()
    arguments(ap)
    with pytest.raises(UsageError, match="one robot"):
        run(ap.parse_args(argv))


def test_the_curve_margin_is_the_stations_teacher_table_and_sets_one_robots_station_only() -> None:
    import argparse

    from bridge.core.config import StationConfig, decode_toml
    from bridge.core.errors import UsageError
    from bridge.tools.demo import arguments, run, teacher_table, transfer_table

    ap = argparse.ArgumentParser()
    arguments(ap)
    cfg = decode_toml(transfer_table("on", None) + "adapt = true\n" + teacher_table(ap.parse_args(
        ["--curve-margin", "0.9"])), StationConfig)
    assert cfg.teacher.curve_margin == 0.9 and cfg.transfer.adapt
    assert cfg.teacher.slow_for_bends == "always" and StationConfig().teacher.slow_for_bends == "changed"
    assert teacher_table(ap.parse_args([])) == "" and StationConfig().teacher.curve_margin == 0.9
    assert decode_toml(teacher_table(ap.parse_args(["--curve-margin", "0"])), StationConfig).teacher.curve_margin == 0.0
    with pytest.raises(UsageError, match="one robot"):
        run(ap.parse_args(["--curve-margin", "0.9", "--count", "2"]))
    with pytest.raises(UsageError, match=r"\[0, 1\]"):
        run(ap.parse_args(["--curve-margin", "1.5"]))


def test_a_run_touched_an_obstacle_when_the_vehicles_disc_at_any_pose_reaches_one() -> None:
    from sim_learner.experiments import VEHICLE_RADIUS

    world = mission_from_spec(M.MissionSpec(name="o", path=[[0.0, 0.0], [4.0, 0.0]], obstacles=[[2.0, 1.0, 0.3]]))
    clear = [[0.0, 0.0], [2.0, 1.0 - 0.3 - VEHICLE_RADIUS - 0.01], [4.0, 0.0]]
    assert not touched_an_obstacle(world, clear)
    assert touched_an_obstacle(world, [*clear, [2.0, 1.0 - 0.3 - VEHICLE_RADIUS + 0.01]])
    assert not touched_an_obstacle(world, [])


def test_a_run_that_left_its_corridor_did_not_reach_its_goal_whatever_the_goal_rule_said() -> None:
    """A runaway that came back to the goal (a loop far past it, as an untuned Ackermann rover drove): the goal rule
    is met and the station counted the goal, yet the run left its corridor, so it did not reach its goal."""
    run = Run()
    t = 0.0
    loop = [(0.5, 0.0), (0.9, 0.5), (0.9, 2.0), (0.5, 3.0), (0.2, 1.5), (0.6, 0.2), (1.0, 0.0)]  # 3 m off the line
    for k, (x, y) in enumerate(loop):
        run.applied(t, "cmd", k + 1)
        run.state(t + 0.04, x, y)
        t += 1.0
    run.station(goal_reached=1)
    s = run.mon.summary(LINE)
    assert s["goal_rule_met"] is True and s["left_corridor"] is True and s["reached_goal"] is False
    assert s["corridor_m"] == 1.0 and s["max_path_dist_m"] == pytest.approx(3.0)
    wide = run.mon.summary(LINE, corridor_m=3.5)  # a corridor that holds the loop: the goal counts
    assert wide["reached_goal"] is True and wide["left_corridor"] is False
