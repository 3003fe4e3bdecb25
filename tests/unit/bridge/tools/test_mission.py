"""``scmbridge mission`` (:mod:`bridge.tools.mission`): the one line it prints for an answer, the reversed mission of
``send --reverse``, the arguments, a mission file checked before anything is sent, and :func:`ask` on one real
Zenoh session whose own queryable answers as a station would. The commands end to end against a real station are
in tests/integration/test_mission_control.py and tests/integration/test_acts.py; a reversed mission driven back from
the goal in tests/integration/test_operator_truths.py."""

from __future__ import annotations

import argparse
import math
import time

import pytest
import zenoh

from bridge.core import wire as M
from bridge.core.config import ConfigError, load_mission_spec
from bridge.nodes.zsession import free_port, make_config, tcp
from bridge.tools import mission as T


def _state(**kw) -> M.MissionState:
    base = {"stamp": 1.0, "robot": "r1", "phase": "paused", "mission": "s-path", "accepted": True, "text": "paused",
            "reason": "paused by alice", "progress": 0.426}
    return M.MissionState(**{**base, **kw})


def test_the_line_says_what_was_done_where_the_mission_is_and_how_far() -> None:
    assert T.line(_state()) == "r1: paused | mission 's-path' paused (paused by alice), 43% done"
    assert T.line(_state(accepted=False, text="refused: estop latched")).startswith("r1: REFUSED: refused: estop")
    running = T.line(_state(phase="running", reason="started by alice", text="started", progress=0.0))
    assert running == "r1: started | mission 's-path' running, 0% done"  # running: no reason repeated
    assert T.line(_state(reason="")) == "r1: paused | mission 's-path' paused, 43% done"


def test_a_mission_a_program_published_is_named_with_its_time() -> None:
    at = time.mktime((2026, 5, 4, 13, 2, 3, 0, 0, -1))
    text = T.line(_state(replaced_by="a publisher on scm/r1/mission", replaced_at=at))
    assert text.endswith("| WARNING: this mission came from a publisher on scm/r1/mission at 13:02:03, not from a "
                         "person's send: check it")
    assert "at ?," in T.line(_state(replaced_by="someone"))  # an unknown time


def test_the_reversed_mission_starts_at_the_goal_facing_back_along_the_path() -> None:
    spec = M.MissionSpec(name="L", path=[[0.0, 0.0], [2.0, 0.0], [2.0, 3.0], [2.0, 3.0]],
                         obstacles=[[1.0, 1.0, 0.2]], goal_tolerance=0.3, start=[0.0, 0.0, 0.0])
    back = T.reversed_spec(spec)
    assert back.path == [[2.0, 3.0], [2.0, 3.0], [2.0, 0.0], [0.0, 0.0]]
    assert back.start == [2.0, 3.0, pytest.approx(-math.pi / 2)]  # along the first segment of length (a repeat)
    assert (back.name, back.obstacles, back.goal_tolerance, back.frame) == ("L-reversed", spec.obstacles, 0.3,
                                                                             spec.frame)
    assert T.reversed_spec(back).path == spec.path
    long = M.MissionSpec(name="n" * 64, path=[[0.0, 0.0], [1.0, 1.0]])
    name = T.reversed_spec(long).name
    assert name == "n" * 55 + "-reversed" and len(name) <= 64  # still a valid name on the wire
    assert M.decode(M.encode(T.reversed_spec(load_mission_spec())), M.MissionSpec).path[0] == load_mission_spec(
        ).path[-1]


@pytest.mark.parametrize("action", ["start", "pause", "resume", "abort", "status"])
def test_every_action_takes_the_same_arguments(action: str) -> None:
    ap = argparse.ArgumentParser()
    getattr(T, f"arguments_{action}")(ap)
    a = ap.parse_args(["--robot", "r1"])
    assert (a.robot, a.source, a.timeout) == ("r1", "operator", 3.0)
    with pytest.raises(SystemExit):
        ap.parse_args([])


def test_send_checks_its_file_before_anything_is_sent(tmp_path) -> None:
    ap = argparse.ArgumentParser()
    T.arguments_send(ap)
    nobody = ["--robot", "r1", "--mode", "client", "--connect", tcp(free_port())]  # no router: opening would fail
    with pytest.raises(ConfigError, match="no such file"):
        T.run_send(ap.parse_args([str(tmp_path / "absent.toml"), *nobody]))
    bad = tmp_path / "bad.toml"
    bad.write_text('path = [[0.0, 0.0], [0.0, 0.0]]\n')
    with pytest.raises(ConfigError, match="no length"):
        T.run_send(ap.parse_args([str(bad), "--reverse", *nobody]))
    assert ap.parse_args(["paper-s-path", "--robot", "r1", "--reverse"]).reverse


def test_a_slow_stations_answer_to_an_act_is_awaited_not_asked_for_again() -> None:
    """A station that takes longer than a second to answer an act (a machine that stalls it) gets the act once: a
    second try would be answered too ("already running") while the first one did the work."""
    acts: list[str] = []

    def station(q: zenoh.Query) -> None:
        req = M.decode(q.payload.to_bytes(), M.MissionRequest)
        if req.action == "status":
            q.reply("scm/r1/control", M.encode(_state(epoch=7, stamp=4.5)))
            return
        acts.append(req.action)
        time.sleep(1.5)  # a simulated stall: the station's tick
        q.reply("scm/r1/control", M.encode(_state(text="resumed", phase="running", epoch=7, stamp=6.0)))

    with zenoh.open(make_config()) as s:
        s.declare_queryable("scm/r1/control", station)
        got = T.ask(s, "r1", M.MissionRequest(stamp=0.0, action="resume", source="alice"), timeout=20.0)
    assert got is not None and got.text == "resumed" and acts == ["resume"]


def test_ask_stamps_each_try_and_returns_the_stations_answer() -> None:
    asked: list[M.MissionRequest] = []

    def station(q: zenoh.Query) -> None:  # a station of epoch 7 whose clock reads 4.5
        asked.append(M.decode(q.payload.to_bytes(), M.MissionRequest))
        q.reply("scm/r1/control", M.encode(_state(text="started", phase="running", epoch=7, stamp=4.5)))

    req = M.MissionRequest(stamp=0.0, action="start", source="alice")
    with zenoh.open(make_config()) as s:
        s.declare_queryable("scm/r1/control", station)
        s.declare_queryable("scm/r2/control", lambda q: q.reply("scm/r2/control", b"\xc1"))
        assert T.ask(s, "r2", req, timeout=0.5) is None  # an answer that does not decode is skipped
        got = T.ask(s, "r1", req, timeout=20.0)
        got2 = T.ask(s, "r1", req, timeout=20.0)
        t0 = time.monotonic()
        assert T.ask(s, "nobody", req, timeout=0.5) is None  # no station: None once the timeout passes
        assert time.monotonic() - t0 < 5.0
    assert got == got2 == _state(text="started", phase="running", epoch=7, stamp=4.5)
    # each act is addressed: its status asked first, then the act with that station's epoch and clock
    assert [a.action for a in asked] == ["status", "start", "status", "start"]
    acts = asked[1::2]
    assert acts[0].nonce != acts[1].nonce and all((a.target, a.echo) == (7, 4.5) for a in acts)
    assert all(a.wall_time > 0 and a.source == "alice" for a in acts)
