"""The pieces of a station core's state (:mod:`bridge.nodes.station_parts`), each alone: the latest inputs, the
tick's time, the commands it sends, what it says and why."""

from __future__ import annotations

import logging

import numpy as np

from bridge.core import wire as M
from bridge.nodes.sources import Why
from bridge.nodes.station_parts import Latest, Outbox, TickTime, Verdict
from bridge.nodes.station_status import STATUS_EVERY_S
from tests.fakeclock import FakeClock


def _status(seq: int, ok: bool = True) -> M.Status:
    return M.Status(stamp=0.0, seq=seq, node="driver", ok=ok, text="link can: driving (cmd)")


def test_latest_keeps_each_input_with_its_time_and_sees_a_restarted_driver_host() -> None:
    latest = Latest(max_pose_age=0.5)
    assert latest.state is None and latest.state_at == -np.inf and latest.teacher_heard
    assert not latest.driver_status(_status(3), 1.0)
    assert not latest.driver_status(_status(3), 1.1)  # the same status twice is harmless
    assert latest.driver_status(_status(0), 1.2)  # a lower seq: a new driver host process
    assert (latest.driver.seq, latest.driver_at, latest.driver_seq) == (0, 1.2, 0)


def test_latest_gives_a_teacher_command_to_the_source_as_new_once() -> None:
    latest = Latest(max_pose_age=0.5)
    assert not latest.take_teacher()
    latest.teacher_command(M.TeacherCommand(stamp=1.0, seq=1, v=0.2, omega=0.0), 1.05)
    assert latest.teacher_at == 1.05 and latest.take_teacher() and not latest.take_teacher()


def test_latest_judges_the_robot_fit_from_a_fresh_pose_and_an_ok_driver_host() -> None:
    latest = Latest(max_pose_age=0.5)
    why, fitness = latest.fitness(1.0)
    assert why is not None and fitness.why  # nothing heard yet
    latest.driver_status(_status(1), 1.0)
    latest.state, latest.state_at = M.LearnerState(stamp=1.0, seq=1, x=0.0, y=0.0, theta=0.0), 1.0
    assert latest.fresh_pose(1.5) and not latest.fresh_pose(1.51)
    assert latest.fitness(1.1)[0] is None
    assert latest.fitness(1.6)[0] is not None  # the pose is too old


def test_tick_time_dates_a_tick_by_its_now_and_makes_the_status_due_each_period_of_it() -> None:
    clock = FakeClock(t=50.0, wall_offset=1.7e9)
    time = TickTime(clock, 0.1)
    clock.advance(10.0)  # the offset is read once, at start
    assert time.wall(2.0) == 2.0 + 1.7e9 and time.period == 0.1
    assert time.status_due(1.0)  # the first periodic tick
    assert not time.status_due(1.0 + STATUS_EVERY_S - 0.01)
    assert time.status_due(1.0 + STATUS_EVERY_S) and time.t_status == 1.0 + 2 * STATUS_EVERY_S


def test_the_outbox_numbers_its_commands_and_keeps_the_bytes_it_checked_for_the_last() -> None:
    out = Outbox(epoch=77, period=0.1)
    first = out.command(1.0, 0.2, 0.1, "scm", [1, 2])
    second = out.command(1.1, 0.0, 0.0, "stop")
    assert (first.seq, second.seq) == (0, 1) and first.epoch == second.epoch == 77 and second.valid_ms == 300
    assert first.sender == "station" and first.region == [1, 2] and second.region == []
    assert out.bytes_of(first) is None  # not the last one
    assert M.decode(out.bytes_of(second), M.Command) == second and out.bytes_of(None) is None


def test_the_verdict_says_driving_or_the_stops_reason_and_keeps_why_the_robot_was_unfit() -> None:
    v = Verdict(logging.getLogger("test"))
    assert (v.why, v.reason, v.unfit_reason) == ("starting", "starting", None)
    unfit = Why("robot not ready: no driver host status", "robot_not_ready")
    latest = Latest(max_pose_age=0.5)
    assert v.judged(unfit, latest.fitness(1.0)[1]) is unfit and v.unfit_reason == "robot_not_ready"
    v.decided(unfit)
    assert (v.why, v.reason) == (unfit.text, "robot_not_ready")
    v.decided(None)
    assert (v.why, v.reason) == ("driving", "ok")
