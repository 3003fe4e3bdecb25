"""bridge/tools/live.py: the live view's routing of ``scm/...`` samples to a robot's Foxglove channels
(:class:`LiveView`, :class:`RobotView`) and its helpers, written through the Foxglove SDK's own MCAP writer
(``foxglove.open_mcap``, what ``scmbridge view --mcap`` uses) in a temporary directory and read back with the mcap
library. A real Foxglove WebSocket client against ``scmbridge view`` is in tests/integration/test_live_view.py."""

from __future__ import annotations

import json
import math
import struct
import time
import warnings
from pathlib import Path

import pytest

from bridge.core import wire as M
from bridge.core.config import load_mission
from bridge.tools import live
from bridge.tools.live import JSON_TOPICS, NODES, TRAIL, LiveView, RobotView, json_schema
from bridge.tools.report import _Sample

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    import foxglove

MISSION = load_mission(None)


def _recorded(path: Path) -> list[tuple[str, str, str, bytes]]:
    """(topic, encoding, schema name, data) of every message in ``path``, in order."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(ch.topic, ch.message_encoding, sch.name if sch else "", msg.data)
                for sch, ch, msg in make_reader(f).iter_messages()]


@pytest.fixture
def shown(tmp_path: Path):
    """A live view whose channels are written into an MCAP file; call ``shown.read()`` to close and read it."""
    path = tmp_path / "view.mcap"
    writer = foxglove.open_mcap(str(path), allow_overwrite=True)

    class Shown:
        view = LiveView(MISSION)

        @staticmethod
        def put(key: str, msg) -> None:
            Shown.view.on_sample(_Sample(key, msg if isinstance(msg, bytes) else M.encode(msg)))

        @staticmethod
        def read() -> list[tuple[str, str, str, bytes]]:
            writer.close()
            return _recorded(path)

    yield Shown
    writer.close()


def test_json_schemas_are_objects_at_the_top_with_their_definitions() -> None:
    s = json_schema(M.Command)
    assert s["type"] == "object" and {"stamp", "seq", "v", "omega", "method"} <= set(s["properties"])
    assert "$ref" not in s
    pairs = json_schema(M.Pairs)  # a message with a nested Struct keeps the definitions it refers to
    assert "PairRecord" in pairs["$defs"] and pairs["title"] == "Pairs"


def test_timestamps_and_headings() -> None:
    t = live._ts(12.25)
    assert (t.sec, t.nsec) == (12, 250_000_000)
    q = live._quat(math.pi / 2)
    for value in (math.sin(math.pi / 4), math.cos(math.pi / 4)):  # z = sin(theta / 2), w = cos(theta / 2)
        assert struct.pack("<d", value) in q.encode()


def test_a_robot_has_its_json_and_status_channels_from_the_start() -> None:
    v = RobotView("rv1", MISSION)
    assert set(v.json) == {*JSON_TOPICS, *(f"status/{n}" for n in NODES)}
    assert v.json["cmd"].topic() == "/rv1/cmd" and v.pose.topic() == "/rv1/pose"
    assert v.channel("status/mocap", M.Status) is v.channel("status/mocap", M.Status)  # made once, on first use
    assert v.trail.maxlen == TRAIL


def test_samples_are_routed_to_their_robots_channels_as_json(shown) -> None:
    shown.put("scm/r1/cmd", M.Command(stamp=1.0, seq=3, v=0.25, omega=-0.1, method="scm"))
    shown.put("scm/r1/status/driver", M.Status(stamp=1.0, seq=1, node="driver", ok=False, text="operator"))
    shown.put("scm/r2/applied", M.Applied(stamp=1.0, seq=1, v=0.0, omega=0.0, reason="stop"))
    got = {(topic, enc, schema): json.loads(data) for topic, enc, schema, data in shown.read()}
    assert got[("/r1/cmd", "json", "Command")] == {"stamp": 1.0, "seq": 3, "v": 0.25, "omega": -0.1, "method": "scm"}
    assert got[("/r1/status/driver", "json", "Status")]["text"] == "operator"
    assert got[("/r2/applied", "json", "Applied")]["reason"] == "stop"
    assert set(shown.view.robots) == {"r1", "r2"} and shown.view.counts == {"messages": 3, "malformed": 0}


def test_a_pose_is_logged_in_the_world_frame_and_the_scene_with_it(shown) -> None:
    shown.put("scm/r1/state", M.LearnerState(stamp=1.0, seq=1, x=1.5, y=-2.0, theta=0.5))
    rec = shown.read()
    (pose,) = [d for t, enc, s, d in rec if t == "/r1/pose"]
    assert [s for t, enc, s, d in rec if t == "/r1/pose"] == ["foxglove.PoseInFrame"]
    for value in (1.5, -2.0, math.sin(0.25), math.cos(0.25)):  # position and heading, as protobuf doubles
        assert struct.pack("<d", value) in pose
    assert b"world" in pose
    (scene,) = [d for t, enc, s, d in rec if t == "/r1/scene"]
    assert b"r1-mission" in scene
    assert shown.view.robots["r1"].trail[-1] == (1.5, -2.0)


def test_the_scene_is_redrawn_only_when_the_last_is_a_fifth_of_a_second_old(shown) -> None:
    view = shown.view.robot("r1")
    view.t_scene = time.time() + 3600.0  # as if just drawn (the view reads the wall clock: no waiting here)
    for i in range(20):
        shown.put("scm/r1/state", M.LearnerState(stamp=1.0, seq=i, x=0.01 * i, y=0.0, theta=0.0))
    view.t_scene = 0.0  # long ago
    shown.put("scm/r1/state", M.LearnerState(stamp=1.0, seq=20, x=0.2, y=0.0, theta=0.0))
    rec = shown.read()
    assert sum(t == "/r1/pose" for t, *_ in rec) == 21 and len(view.trail) == 21
    assert sum(t == "/r1/scene" for t, *_ in rec) == 1 and view.t_scene > 0.0


def test_a_teacher_command_gives_the_plan_and_a_published_mission_replaces_the_drawn_one(shown) -> None:
    shown.put("scm/r1/teacher", M.TeacherCommand(stamp=1.0, seq=1, v=0.2, omega=0.0, predicted_x=[0.0, 1.0, 2.0],
                                                 predicted_y=[0.0, 0.5, 1.0]))
    view = shown.view.robots["r1"]
    assert view.plan == [(0.0, 0.0), (1.0, 0.5), (2.0, 1.0)] and view.mission is MISSION
    shown.put("scm/r1/mission", M.MissionSpec(name="line", path=[[0.0, 0.0], [3.0, 0.0]]))
    assert view.mission.path.length == pytest.approx(3.0)
    assert shown.view.robot("r9").mission is MISSION  # other robots keep the default


def test_what_fails_to_decode_is_counted_and_what_is_not_ours_ignored(shown) -> None:
    shown.put("scm/r1/cmd", b"not a message")
    shown.put("scm/r1/state", M.encode(M.Command(stamp=1.0, seq=1, v=0.0, omega=0.0, method="stop")))  # wrong type
    shown.put("other/r1/cmd", M.Command(stamp=1.0, seq=1, v=0.0, omega=0.0, method="stop"))
    shown.put("scm/r1", b"")
    assert shown.view.counts == {"messages": 0, "malformed": 2}
    assert set(shown.view.robots) == {"r1"}
    assert [t for t, *_ in shown.read()] == []


def test_a_mission_that_does_not_decode_is_malformed_and_the_drawn_one_stays(shown) -> None:
    shown.put("scm/r1/mission", M.MissionSpec(name="ok", path=[[0.0, 0.0], [1.0, 0.0]]))
    view = shown.view.robots["r1"]
    drawn = view.mission
    shown.put("scm/r1/mission", b"\x80")  # an empty map: no path
    shown.put("scm/r1/mission", M.encode(M.MissionSpec(name="x", path=[[0.0, 0.0], [1.0, 0.0]]))[:-3])  # torn
    assert view.mission is drawn and shown.view.counts == {"messages": 1, "malformed": 2}
