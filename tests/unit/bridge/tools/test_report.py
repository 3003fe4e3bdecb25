"""``scmbridge report``'s pure parts (:mod:`bridge.tools.report`) on synthetic recordings: which robots a recording
has, which mission it followed, the command-to-applied pairing and its clocks, the run's refusals, and report.json
of a recording without a station (no figures drawn here). Entries are built in memory or written by the recorder's
own sink; receive times are passed in.

A recorded demo giving the live demo's figures, with figures, is tested in tests/integration/test_record.py; the
clocks told from the nodes' machines in tests/integration/test_operator_truths.py."""

from __future__ import annotations

import argparse
import json

import pytest

from bridge.core import wire as M
from bridge.core.errors import UsageError
from bridge.tools import report as R
from bridge.tools.mcap_format import Entry, classify, to_json
from bridge.tools.mcap_sink import McapSink

K = M.Keys("r1")
MS = 1_000_000  # ns


def _e(topic: str, t_ns: int, msg) -> Entry:
    return Entry(topic, "", t_ns, to_json(msg))


def _cmd(seq: int, stamp: float, t_ns: int) -> Entry:
    return _e(K.cmd, t_ns, M.Command(stamp=stamp, seq=seq, v=0.1, omega=0.0, method="scm"))


def _applied(seq: int, stamp: float, t_ns: int, reason: str = "cmd", cmd_seq: int | None = None) -> Entry:
    return _e(K.applied, t_ns, M.Applied(stamp=stamp, seq=seq, v=0.1, omega=0.0, reason=reason,
                                         cmd_seq=seq if cmd_seq is None else cmd_seq))


def _state(robot: str, t_ns: int) -> Entry:
    return _e(M.key(robot, "state"), t_ns, M.LearnerState(stamp=t_ns / 1e9, seq=1, x=0.0, y=0.0, theta=0.0))


def test_the_robots_are_those_with_state() -> None:
    entries = [_state("b", 1), _state("a", 2), _state("a", 3), _cmd(1, 0.0, 4),
               _e(M.key("c", "cmd"), 5, M.Command(stamp=0.0, seq=1, v=0.0, omega=0.0, method="stop"))]
    assert R.robots(entries) == ["a", "b"]


def test_the_mission_is_the_last_recorded_else_the_file_else_the_shipped_one(tmp_path) -> None:
    one = M.MissionSpec(name="one", path=[[0.0, 0.0], [1.0, 0.0]])
    two = M.MissionSpec(name="two", path=[[0.0, 0.0], [0.0, 1.0]])
    m, where = R.pick_mission([_e(K.mission, 1, one), _e(K.mission, 2, two)], "r1", None)
    assert m.name == "two" and where == f"recorded on {K.mission} (the last of 2)"
    m, where = R.pick_mission([_e(K.mission, 1, one)], "r1", "ignored.toml")
    assert m.name == "one" and where == f"recorded on {K.mission}"
    f = tmp_path / "m.toml"
    f.write_text('name = "from-file"\npath = [[0.0, 0.0], [2.0, 0.0]]\n')
    m, where = R.pick_mission([_e(M.key("other", "mission"), 1, one)], "r1", str(f))
    assert m.name == "from-file" and where == f"file {f}"
    m, where = R.pick_mission([], "r1", None)
    assert m.name == "paper-s-path" and "no mission recorded" in where


def test_each_command_pairs_with_the_first_applied_echo_that_executed_it() -> None:
    entries = [_cmd(1, 10.000, 1000 * MS), _applied(1, 10.004, 1005 * MS), _applied(1, 10.050, 1050 * MS),
               _cmd(2, 10.100, 1100 * MS), _applied(2, 10.103, 1103 * MS, "refused"),  # refused: not executed
               _cmd(3, 10.200, 1200 * MS), _applied(3, 10.206, 1207 * MS, "clamped"),
               _cmd(4, 10.300, 1300 * MS), _applied(4, 10.302, 1302 * MS, "stop"),
               _applied(9, 10.4, 1400 * MS)]  # its command is not in the recording
    out, rows = R.command_latency(entries, "r1", same_machine=True)
    assert (out["commands"], out["paired"], out["stamps_one_clock"]) == (4, 3, True)
    assert [r[0] for r in rows] == [1000 * MS, 1200 * MS, 1300 * MS]
    assert [round(r[1], 6) for r in rows] == [0.004, 0.006, 0.002]  # by stamps
    assert [round(r[2], 6) for r in rows] == [0.005, 0.007, 0.002]  # by the recorder's receipt
    assert out["by_stamps_ms"] == {"median": 4.0, "p99": pytest.approx(5.96, abs=1e-3), "max": 6.0, "min": 2.0}
    assert out["by_receipt_ms"]["median"] == 5.0


def test_a_restarted_station_reusing_seqs_pairs_with_the_nearest_command_and_far_ones_are_dropped() -> None:
    entries = [_cmd(1, 5.0, 1_000 * MS), _cmd(1, 50.0, 9_000 * MS), _applied(1, 50.003, 9_004 * MS),
               _cmd(2, 6.0, 2_000 * MS), _applied(2, 12.0, 8_000 * MS)]  # 6 s after its command: not its echo
    out, rows = R.command_latency(entries, "r1", True)
    assert out["paired"] == 1 and rows[0][0] == 9_000 * MS and rows[0][1] == pytest.approx(0.003)


def test_stamps_of_two_clocks_are_discarded_and_unknown_machines_are_judged_from_the_numbers() -> None:
    two_clocks = [_cmd(1, 100.0, 1000 * MS), _applied(1, 7.0, 1004 * MS)]  # applied "before" the command
    out, _ = R.command_latency(two_clocks, "r1", None)
    assert not out["stamps_one_clock"] and out["by_stamps_ms"] is None and out["by_receipt_ms"]["median"] == 4.0
    one = [_cmd(1, 10.0, 1000 * MS), _applied(1, 10.004, 1004 * MS)]
    assert R.command_latency(one, "r1", None)[0]["stamps_one_clock"]
    assert not R.command_latency(one, "r1", False)[0]["stamps_one_clock"]  # the statuses say two machines
    out, rows = R.command_latency([], "r1", True)
    assert (out["paired"], out["by_stamps_ms"], out["by_receipt_ms"], rows) == (0, None, None, [])


def test_stats_are_in_milliseconds_rounded() -> None:
    assert R._stats_ms([]) is None
    assert R._stats_ms([0.001, 0.003, 0.002]) == {"median": 2.0, "p99": 2.98, "max": 3.0, "min": 1.0}


def test_feed_session_hands_each_message_to_the_subscribers_whose_key_matches() -> None:
    feed, got = R.FeedSession(), []
    feed.declare_subscriber("scm/r1/*", lambda s: got.append(("one", s.key_expr, s.payload.to_bytes())))
    feed.declare_subscriber("scm/*/status/**", lambda s: got.append(("status", s.key_expr, s.payload.to_bytes())))
    feed.put("scm/r1/state", b"a")
    feed.put("scm/r2/status/driver", b"b")
    feed.put("scm/r2/state", b"c")
    assert got == [("one", "scm/r1/state", b"a"), ("status", "scm/r2/status/driver", b"b")]


def _record(path, entries: list[tuple[str, object]]) -> None:
    sink = McapSink(path)
    for i, (key, msg) in enumerate(entries):
        for spec, data, _ in classify(key, M.encode(msg)):
            sink.write(spec, data, log_time_ns=(i + 1) * 50 * MS)
    sink.close("test done")


def test_a_recording_without_a_station_reports_no_summary_and_says_why(tmp_path) -> None:
    f = tmp_path / "run.mcap"
    states = [(K.state, M.LearnerState(stamp=0.05 * i, seq=i, x=0.01 * i, y=0.0, theta=0.0)) for i in range(20)]
    _record(f, [*states, (K.cmd, M.Command(stamp=1.0, seq=1, v=0.1, omega=0.0, method="scm")),
                (K.applied, M.Applied(stamp=1.002, seq=1, v=0.1, omega=0.0, reason="cmd", cmd_seq=1))])
    out = tmp_path / "out"
    result = R.report([str(f)], out, figures=False)
    assert result["robot"] == "r1" and result["summary"] is None and "no station status" in result["note"]
    assert result["messages"] == {K.applied: 1, K.cmd: 1, K.state: 20}
    assert result["duration_s"] == pytest.approx(1.05) and result["truncated"] == []
    assert result["cmd_to_applied"]["paired"] == 1 and "figures" not in result
    assert json.loads((out / "report.json").read_text()) == result


def test_a_recording_with_no_robot_or_several_asks_for_one(tmp_path) -> None:
    empty = tmp_path / "empty.mcap"
    _record(empty, [])
    with pytest.raises(ValueError, match="the recording has no state message"):
        R.report([str(empty)], tmp_path / "o", figures=False)
    two = tmp_path / "two.mcap"
    _record(two, [(M.key(r, "state"), M.LearnerState(stamp=0.0, seq=1, x=0.0, y=0.0, theta=0.0)) for r in "ab"])
    with pytest.raises(ValueError, match=r"state for 2 robots \(a, b\): choose one with --robot"):
        R.report([str(two)], tmp_path / "o", figures=False)
    with pytest.raises(ValueError, match=r"no state of robot 'c' in the recording \(robots: a, b\)"):
        R.report([str(two)], tmp_path / "o", robot="c", figures=False)


def test_run_refuses_a_missing_file_and_exits_1_for_a_recording_without_a_run(tmp_path, capsys) -> None:
    ap = argparse.ArgumentParser()
    R.arguments(ap)
    with pytest.raises(UsageError, match="no such file"):
        R.run(ap.parse_args([str(tmp_path / "absent.mcap"), "--out", str(tmp_path / "o")]))
    empty = tmp_path / "empty.mcap"
    _record(empty, [])
    assert R.run(ap.parse_args([str(empty), "--out", str(tmp_path / "o"), "--no-figures"])) == 1
    assert "scmbridge report: error: the recording has no state message" in capsys.readouterr().err


def test_the_timeline_marks_when_the_mission_was_paused_and_an_estop_latched(tmp_path) -> None:
    """Finding: the report's timeline marked no pause or estop. The episodes come from the statuses (typed reasons),
    one still on at the end is closed there, and the timeline shades them."""
    from bridge.tools.report import _figures, episodes

    def status(node: str, t_s: float, state: str, reason: str) -> Entry:
        return _e(M.status_key("r1", node), int(t_s * 1e3) * MS,
                  M.Status(stamp=t_s, seq=int(t_s * 10), node=node, state=state, reason=reason))

    entries = sorted([status("station", 1.0, "driving", "ok"), status("driver", 1.0, "driving", "ok"),
                      status("driver", 2.0, "estop", "estop"), status("station", 2.1, "paused", "paused"),
                      status("driver", 4.0, "driving", "ok"), status("station", 5.0, "driving", "ok"),
                      status("station", 7.0, "paused", "paused"), _state("r1", 8_000 * MS)],
                     key=lambda e: e.log_time)
    marks = episodes(entries, "r1")
    assert marks == {"estop": [(2_000 * MS, 4_000 * MS)], "paused": [(2_100 * MS, 5_000 * MS),
                                                                      (7_000 * MS, 8_000 * MS)]}, marks
    import numpy as np

    from bridge.core.config import load_mission

    files = _figures(tmp_path, entries, "r1", load_mission(), np.zeros((0, 3)), [], True)
    assert (tmp_path / "timeline.png") in files and (tmp_path / "timeline.png").stat().st_size > 0
