"""When and where the station's guards stopped a run: the demo's monitor keeps it from the station's status (so the
demo's summary and ``scmbridge report``, which replays a recording through that monitor, both say it)."""

from __future__ import annotations

from bridge.core import wire as M
from bridge.core.config import load_mission
from bridge.tools.demo import Monitor
from bridge.tools.report import FeedSession


def _status(seq: int, reason: M.Reason, text: str, off: float | None) -> bytes:
    return M.encode(M.Status(stamp=float(seq), seq=seq, node="station", ok=reason == "ok", state="paused",
                             reason=reason, text=text, off_path_m=off))


def test_the_summary_says_when_and_where_a_guard_stopped_the_run() -> None:
    feed, robot = FeedSession(), "r1"
    mon = Monitor(feed, robot)
    k = M.Keys(robot)
    status = M.status_key(robot, "station")
    feed.put(k.state, M.encode(M.LearnerState(stamp=10.0, seq=0, x=0.0, y=-0.3, theta=0.0)))
    feed.put(k.applied, M.encode(M.Applied(stamp=10.0, seq=0, v=0.2, omega=0.0, reason="cmd", cmd_seq=0)))
    feed.put(status, _status(1, "ok", "driving", 0.3))
    feed.put(k.state, M.encode(M.LearnerState(stamp=14.5, seq=1, x=0.9, y=-1.2, theta=0.0)))
    feed.put(k.applied, M.encode(M.Applied(stamp=14.5, seq=1, v=0.2, omega=0.0, reason="cmd", cmd_seq=1)))
    feed.put(status, _status(2, "left_corridor", "paused: left the corridor: 1.02 m from the path", 1.02))
    feed.put(status, _status(3, "left_corridor", "paused: left the corridor: 1.02 m from the path", 1.05))
    assert mon.guards.stopped
    summary = mon.summary(load_mission())
    assert summary is not None
    assert summary["guard_stops"] == [{"reason": "left_corridor", "x": 0.9, "y": -1.2, "off_path_m": 1.02,
                                       "text": "paused: left the corridor: 1.02 m from the path", "t_s": 4.5}]
    feed.put(status, _status(4, "ok", "driving", 0.2))  # resumed by a person: a later pause is a new entry
    assert not mon.guards.stopped
    feed.put(status, _status(5, "pose_jump", "paused: the pose jumped 3.00 m", 0.1))
    assert [g["reason"] for g in mon.summary(load_mission())["guard_stops"]] == ["left_corridor", "pose_jump"]
