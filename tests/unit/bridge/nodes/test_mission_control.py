"""The station's mission phases (:mod:`bridge.nodes.mission_control`), pure: every request's answer in each phase,
the refusals and their words, what a save keeps and a restart restores, when a save is due, and the wire form of a
mission. Times and the robot's fitness are arguments.

The phase machine's main stories (only a person starts, every stop without one pauses, a late pose against a lost
link, a published mission never starting a robot) are in tests/integration/test_mission_control.py, beside the same
rules end to end over Zenoh."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import load_mission_spec, mission_from_spec
from bridge.nodes.mission_control import (
    PAUSE_AFTER_S,
    SAVE_PROGRESS_STEP,
    Fitness,
    MissionControl,
    Saved,
    spec_of,
)
from transfer.mission import Mission

FIT = Fitness("")
NOT_FIT = Fitness("no pose for 0.8 s")
ESTOP = Fitness("estop latched by operator", estop=True)
SHORT = M.MissionSpec(name="short", path=[[0.0, 0.0], [1.0, 0.0]])


def _req(action: str, source: str = "alice", **kw) -> M.MissionRequest:
    return M.MissionRequest(stamp=0.0, action=action, source=source, **kw)


def _in(phase: str) -> MissionControl:
    c = MissionControl("r1", SHORT, phase)  # type: ignore[arg-type]
    c.changed = False
    return c


def test_a_new_control_is_idle_waiting_for_a_person_and_unsaved() -> None:
    c = MissionControl("r1", SHORT)
    assert (c.phase, c.reason, c.version, c.progress) == ("idle", "waiting for a person: scmbridge mission start", 0,
                                                          0.0)
    assert c.unsaved and c.mission.name == "short"
    assert MissionControl("r1", SHORT, "paused", "paused by bob").reason == "paused by bob"
    assert MissionControl("r1", SHORT, "paused").reason == ""  # only idle gets the default words
    assert Fitness() == Fitness("no driver host status", estop=False, immediate=True)  # not fit until heard


@pytest.mark.parametrize(("phase", "accepted", "says"), [
    ("idle", False, "nothing to resume: the mission is idle; use start"),
    ("finished", False, "nothing to resume: the mission is finished; use start"),
    ("aborted", False, "nothing to resume: the mission is aborted; use start"),
    ("running", True, "already running"),
])
def test_resume_is_only_for_a_paused_mission(phase: str, accepted: bool, says: str) -> None:
    c = _in(phase)
    ans = c.request(_req("resume"), FIT, 1.0)
    assert (ans.accepted, ans.text, c.phase) == (accepted, says, phase)
    assert not c.changed  # nothing happened


@pytest.mark.parametrize("phase", ["idle", "paused", "finished", "aborted"])
def test_pause_is_only_for_a_running_mission(phase: str) -> None:
    ans = _in(phase).request(_req("pause"), FIT, 1.0)
    assert not ans.accepted and ans.text == f"nothing to pause: the mission is {phase}"


@pytest.mark.parametrize("phase", ["finished", "aborted"])
def test_abort_of_a_mission_that_is_over_says_so_and_changes_nothing(phase: str) -> None:
    c = _in(phase)
    ans = c.request(_req("abort"), FIT, 1.0)
    assert ans.accepted and ans.text == f"the mission is already {phase}" and c.phase == phase and not c.changed


def test_the_answers_name_who_asked_in_the_reason_and_the_mission() -> None:
    c = MissionControl("r1", SHORT)
    ans = c.request(_req("start", source="alice"), FIT, 12.5)
    assert (ans.stamp, ans.robot, ans.mission, ans.phase, ans.reason) == (12.5, "r1", "short", "running",
                                                                          "started by alice")
    assert ans.text == "mission 'short' started"
    assert c.request(_req("pause", source=""), FIT, 13.0).reason == "paused"  # no source: no "by"
    assert c.request(_req("resume", source="bob"), FIT, 14.0).reason == "resumed by bob"
    assert c.request(_req("abort", source="carol"), FIT, 15.0).reason == "aborted by carol"
    ans = c.request(_req("status"), FIT, 16.0)
    assert ans.accepted and ans.text == "mission 'short' is aborted"


def test_a_start_after_the_goal_or_an_abort_starts_from_the_beginning() -> None:
    c = MissionControl("r1", SHORT)
    c.request(_req("start"), FIT, 0.0)
    c.progress = 0.4
    c.reached()
    assert c.phase == "finished" and c.progress == 1.0 and c.reason == "goal reached"
    assert c.request(_req("start"), FIT, 1.0).accepted and c.progress == 0.0 and c.phase == "running"
    c.progress = 0.6
    c.request(_req("pause"), FIT, 2.0)
    c.request(_req("start"), FIT, 3.0)  # a start on a paused mission resumes where it was
    assert c.progress == 0.6


def test_a_start_is_refused_only_by_a_latched_estop_and_waits_for_a_robot_that_is_not_fit() -> None:
    c = MissionControl("r1", SHORT)
    ans = c.request(_req("start"), ESTOP, 0.0)
    assert not ans.accepted and ans.text == "refused: estop latched by operator" and c.phase == "idle"
    ans = c.request(_req("start"), NOT_FIT, 0.0)
    assert ans.accepted and ans.text == "mission 'short' started; waiting for the robot: no pose for 0.8 s"
    assert not c.may_drive(NOT_FIT, 100.0) and c.phase == "running"  # never driven since the start: no pause


def test_send_checks_the_mission_and_counts_the_replacements() -> None:
    c = MissionControl("r1", SHORT)
    bad = M.MissionSpec(name="bad", path=[[0.0, 0.0], [1.0, 0.0]], goal_tolerance=-1.0)  # built unvalidated
    ans = c.request(_req("send", spec=bad), FIT, 0.0)
    assert not ans.accepted and ans.text.startswith("mission refused: goal tolerance must be a positive number")
    assert c.spec == SHORT and c.version == 0
    assert c.request(_req("send"), FIT, 0.0).text == "send needs a mission"
    other = M.MissionSpec(name="other", path=[[0.0, 0.0], [0.0, 2.0]])
    c.request(_req("start"), FIT, 0.0)
    c.progress = 0.5
    ans = c.request(_req("send", spec=other, source="bob"), FIT, 1.0)
    assert ans.accepted and ans.text == "mission 'other' loaded; idle until started"
    assert (c.phase, c.version, c.progress, c.mission.name) == ("idle", 1, 0.0, "other")
    assert c.reason == "new mission by bob: scmbridge mission start to drive it"


def test_an_unknown_action_is_refused_naming_it() -> None:
    c = MissionControl("r1", SHORT)
    ans = c.request(M.MissionRequest(stamp=0.0, action="jump"), FIT, 0.0)  # type: ignore[arg-type]
    assert not ans.accepted and ans.text == "unknown action 'jump'" and c.phase == "idle"


def test_a_pause_by_the_robot_is_marked_and_a_persons_act_clears_it() -> None:
    c = MissionControl("r1", SHORT)
    c.request(_req("start"), FIT, 0.0)
    assert c.may_drive(FIT, 0.0) and c.drove
    late = Fitness("no pose for 0.6 s", immediate=False)
    assert not c.may_drive(late, 1.0) and c.phase == "running"
    assert not c.may_drive(late, 1.0 + PAUSE_AFTER_S) and c.phase == "paused" and c.paused_by_robot
    assert c.reason == "paused: no pose for 0.6 s"
    c.request(_req("resume"), FIT, 5.0)
    assert not c.paused_by_robot and not c.drove  # driven again only once a tick drives
    c.request(_req("pause"), FIT, 6.0)
    assert not c.paused_by_robot  # a person's pause


def test_the_unfit_time_is_forgotten_whenever_the_robot_is_fit_or_the_mission_is_not_running() -> None:
    c = MissionControl("r1", SHORT)
    c.request(_req("start"), FIT, 0.0)
    c.may_drive(FIT, 0.0)
    late = Fitness("late", immediate=False)
    c.may_drive(late, 1.0)
    assert c.unfit_since == 1.0
    c.may_drive(FIT, 1.5)
    assert c.unfit_since is None
    c.may_drive(late, 2.0)
    c.request(_req("pause"), FIT, 2.1)
    assert not c.may_drive(late, 2.2) and c.unfit_since is None


def test_a_driver_restart_pauses_only_a_running_mission() -> None:
    for phase in ("idle", "paused", "finished", "aborted"):
        c = _in(phase)
        c.driver_restarted()
        assert c.phase == phase and not c.changed
    c = _in("running")
    c.driver_restarted()
    assert c.phase == "paused" and c.reason == "paused: the driver host restarted" and c.changed


def test_a_save_is_due_on_a_change_or_on_progress_by_the_step() -> None:
    c = MissionControl("r1", SHORT)
    assert c.unsaved
    s = c.saved()
    assert not c.unsaved and s == Saved(phase="idle", reason=c.reason, spec=SHORT, progress=0.0)
    c.progress = SAVE_PROGRESS_STEP * 0.9
    assert not c.unsaved
    c.progress = SAVE_PROGRESS_STEP * 1.01
    assert c.unsaved
    c.saved()
    c.request(_req("status"), FIT, 0.0)
    assert not c.unsaved  # a status changes nothing
    c.request(_req("start"), FIT, 0.0)
    assert c.unsaved


def test_what_is_saved_round_trips_and_a_restart_restores_it_never_running() -> None:
    c = MissionControl("r1", SHORT)
    c.request(_req("start"), FIT, 0.0)
    c.progress = 0.37
    saved = msgspec.msgpack.decode(msgspec.msgpack.encode(c.saved()), type=Saved)
    back = MissionControl.restored("r1", saved)
    assert (back.phase, back.reason, back.progress, back.spec) == ("paused", "paused: the station restarted", 0.37,
                                                                   SHORT)
    for phase in ("idle", "paused", "aborted"):
        back = MissionControl.restored("r1", Saved(phase=phase, reason=f"why {phase}", spec=SHORT, progress=0.2))
        assert (back.phase, back.reason, back.progress) == (phase, f"why {phase}", 0.2)
    old = msgspec.msgpack.decode(msgspec.msgpack.encode({"phase": "finished", "reason": "goal reached",
                                                         "spec": msgspec.to_builtins(SHORT)}), type=Saved)
    assert old.progress == 0.0 and MissionControl.restored("r1", old).progress == 1.0  # a file older than progress
    assert MissionControl.restored("r1", Saved(phase="idle", spec=SHORT, progress=7.0)).progress == 1.0  # clamped


def test_the_answer_is_clamped_to_what_the_wire_takes() -> None:
    c = MissionControl("r1", SHORT)
    c.reason = "x" * 5000
    c.progress = 1.5
    ans = c.answer(1.0, True, "y" * 5000)
    assert len(ans.text) == len(ans.reason) == 1024 and ans.progress == 1.0
    assert M.decode(M.encode(ans), M.MissionState) == ans  # it validates on the receiving side
    c.progress = -0.1
    assert c.answer(1.0, True, "").progress == 0.0


def test_spec_of_is_the_wire_form_of_a_mission_and_round_trips() -> None:
    m = Mission("with-obstacles", mission_from_spec(SHORT).path, np.array([[0.5, 0.3, 0.1], [0.8, -0.2, 0.05]]),
                0.2, np.array([0.0, 0.1, 0.2]), "lab")
    spec = spec_of(m)
    assert spec == M.MissionSpec(name="with-obstacles", frame="lab", path=[[0.0, 0.0], [1.0, 0.0]],
                                 goal_tolerance=0.2, obstacles=[[0.5, 0.3, 0.1], [0.8, -0.2, 0.05]],
                                 start=[0.0, 0.1, 0.2])
    assert M.decode(M.encode(spec), M.MissionSpec) == spec
    shipped = load_mission_spec()
    assert spec_of(mission_from_spec(shipped)).path == shipped.path
    assert spec_of(mission_from_spec(SHORT)).start is None and spec_of(mission_from_spec(SHORT)).obstacles == []
