"""A robot moves only when a person asked: the station starts idle, drives after ``mission start``, pauses on
anything that stops the robot without a person (estop, lost link, a driver-host restart) and stays paused until a
person resumes; a resume is refused while the estop is latched. The phase machine alone (pure), then end to end over
real Zenoh with a driver host process on the emulated CAN link.

Findings this answers: the robot drove as soon as both services were up; after ``estop --release`` it drove off at
once while the station's log still read ``not driving: estop latched by operator``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from bridge.core import wire as M
from bridge.core.config import load_mission, load_mission_spec
from bridge.nodes.mission_control import Fitness, MissionControl, spec_of
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children
from tests.collect import Collector

FIT = Fitness("")
ESTOP = Fitness("robot not ready: link can: estop latched by operator", estop=True)
NO_POSE = Fitness("no pose for 0.8 s")
LATE = Fitness("no pose for 0.6 s", immediate=False)


def _req(action: str, **kw) -> M.MissionRequest:
    return M.MissionRequest(stamp=0.0, action=action, source="tester", **kw)


def test_only_a_persons_start_or_resume_drives_and_every_stop_without_one_pauses() -> None:
    c = MissionControl("r1", load_mission_spec())
    assert c.phase == "idle" and not c.may_drive(FIT)
    assert not c.request(_req("resume"), FIT, 0.0).accepted  # nothing to resume
    ans = c.request(_req("start"), NO_POSE, 0.0)  # start while the robot is not yet fit: it waits
    assert ans.accepted and c.phase == "running" and "waiting for the robot" in ans.text
    assert not c.may_drive(NO_POSE) and c.phase == "running"  # not driven yet: waiting is not a stop
    assert c.may_drive(FIT)
    assert not c.may_drive(ESTOP) and c.phase == "paused" and "estop latched" in c.reason
    assert not c.may_drive(FIT) and c.phase == "paused"  # released: still paused
    ans = c.request(_req("resume"), ESTOP, 0.0)
    assert not ans.accepted and "estop latched by operator" in ans.text and c.phase == "paused"
    assert not c.request(_req("resume"), NO_POSE, 0.0).accepted  # not fit: refused with the reason
    assert c.request(_req("resume"), FIT, 0.0).accepted and c.may_drive(FIT)
    c.driver_restarted()
    assert c.phase == "paused" and "driver host restarted" in c.reason
    assert c.request(_req("start"), FIT, 0.0).accepted and c.phase == "running"  # start on paused: resumes
    assert c.request(_req("pause"), FIT, 0.0).accepted and c.phase == "paused"
    assert c.request(_req("abort"), FIT, 0.0).accepted and c.phase == "aborted"
    assert not c.request(_req("resume"), FIT, 0.0).accepted and not c.may_drive(FIT)
    assert not c.request(_req("start"), ESTOP, 0.0).accepted  # never started into a latched estop


def test_a_pose_late_for_a_moment_is_not_a_lost_link_but_a_lasting_one_pauses() -> None:
    c = MissionControl("r1", load_mission_spec())
    c.request(_req("start"), FIT, 0.0)
    assert c.may_drive(FIT, 0.0)
    assert not c.may_drive(LATE, 0.1) and not c.may_drive(LATE, 1.5) and c.phase == "running"  # a loaded moment
    assert c.may_drive(FIT, 1.6)
    assert not c.may_drive(LATE, 2.0) and not c.may_drive(LATE, 4.1) and c.phase == "paused"  # lasted 2 s: lost
    assert not c.may_drive(FIT, 4.2) and "no pose" in c.reason


def test_send_loads_a_mission_idle_and_a_restart_never_comes_back_running() -> None:
    c = MissionControl("r1", load_mission_spec())
    c.request(_req("start"), FIT, 0.0)
    short = M.MissionSpec(name="short", path=[[0.0, 0.0], [1.0, 0.0]])
    ans = c.request(_req("send", spec=short), FIT, 0.0)
    assert ans.accepted and c.phase == "idle" and ans.mission == "short" and c.version == 1
    bad = c.request(_req("send"), FIT, 0.0)
    assert not bad.accepted and c.mission.name == "short"
    c.request(_req("start"), FIT, 0.0)
    back = MissionControl.restored("r1", M.decode(M.encode(c.saved()), type(c.saved())))
    assert back.phase == "paused" and "restarted" in back.reason and back.spec == short
    c.reached()
    assert MissionControl.restored("r1", c.saved()).phase == "finished"
    assert spec_of(load_mission()).path == load_mission_spec().path


def test_a_published_mission_never_starts_the_robot_and_is_named_until_a_person_starts_it() -> None:
    """Finding (issue 31): a MissionSpec published on scm/<robot>/mission after the goal restarted the robot with no
    person's act (x 1.5 -> 2.85 m). While running it replaces the path in place; in every other phase it loads idle;
    either way the answers say where it came from and when, until a person starts or sends one."""
    from bridge.core.config import mission_from_spec

    new = M.MissionSpec(name="program", path=[[0.0, 0.0], [1.0, 0.0]])
    for phase in ("idle", "paused", "finished", "aborted"):
        c = MissionControl("r1", load_mission_spec(), phase)
        c.replace(new, mission_from_spec(new), by="a publisher on scm/r1/mission", at=1.7e9)
        ans = c.request(_req("status"), FIT, 0.0)
        assert c.phase == "idle" and not c.may_drive(FIT), phase
        assert ans.replaced_by == "a publisher on scm/r1/mission" and ans.replaced_at == 1.7e9
        assert "not a person's request" in c.reason and "mission start" in c.reason
    c = MissionControl("r1", load_mission_spec())
    c.request(_req("start"), FIT, 0.0)
    c.replace(new, mission_from_spec(new), by="a publisher on scm/r1/mission", at=1.7e9)
    assert c.phase == "running" and c.may_drive(FIT) and c.mission.name == "program"  # in place
    assert c.request(_req("status"), FIT, 0.0).replaced_by
    c.reached()
    c.replace(new, mission_from_spec(new))
    assert c.phase == "idle" and "scm/r1/mission" in c.replaced_by  # after the goal: idle
    ans = c.request(_req("start"), FIT, 0.0)  # the person's start is told where it came from, once
    assert ans.accepted and ans.replaced_by and c.phase == "running"
    assert not c.request(_req("status"), FIT, 0.0).replaced_by
    c.replace(new, mission_from_spec(new))
    c.request(_req("send", spec=new), FIT, 0.0)  # a person's own send
    assert not c.request(_req("status"), FIT, 0.0).replaced_by


def _mission(client: list[str], *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", "mission", *args, *client], capture_output=True,
                          text=True, timeout=60)


def _estop(client: list[str], *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", "estop", *args, *client], capture_output=True, text=True,
                          timeout=60)


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_a_station_drives_only_after_a_person_and_an_estop_release_or_a_driver_restart_leaves_it_paused(
        tmp_path) -> None:
    port, robot = free_port(), f"mc{os.getpid()}"
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    driver = ["driver", "--link", "can", "--emulate", "--x0", x0, *client, "--duration", "150"]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        cmds = col.listen(M.key(robot, "cmd"), M.Command)
        status = col.listen(M.status_key(robot, "station"), M.Status)
        drv_status = col.listen(M.status_key(robot, "driver"), M.Status)
        host = kids.spawn([*driver, "--engage"], out=subprocess.DEVNULL)
        kids.spawn(["station", *client, "--store", str(tmp_path / "p.bin"), "--duration", "150"],
                   out=subprocess.DEVNULL)

        def last_state() -> str:
            return status[-1].state if status else ""

        # idle: the robot is fit, yet only stops go out
        assert col.wait(lambda: drv_status and drv_status[-1].ok and last_state() == "idle", 60), \
            [s.text for s in status[-2:]]
        n0 = len(cmds)
        assert col.wait(lambda: len(cmds) > n0 + 15, 10)
        with col.lock:
            assert cmds and all(c.method == "stop" for c in cmds)
            assert "mission start" in status[-1].text
        ans = _mission(client, "status")
        assert ans.returncode == 0 and "idle" in ans.stdout, ans.stdout + ans.stderr

        # a person starts it: it drives
        ans = _mission(client, "start")
        assert ans.returncode == 0 and "started" in ans.stdout, ans.stdout + ans.stderr
        assert col.wait(lambda: any(c.method != "stop" for c in cmds), 30)
        assert col.wait(lambda: last_state() == "driving", 5)

        # an estop pauses it; a resume is refused while latched; the release leaves it paused
        assert _estop(client, "--reason", "test").returncode == 0
        assert col.wait(lambda: last_state() == "paused" and "estop latched" in status[-1].text, 10), \
            [s.text for s in status[-2:]]
        ans = _mission(client, "resume")
        assert ans.returncode == 1 and "estop latched by operator" in ans.stderr, ans.stdout + ans.stderr
        assert _estop(client, "--release").returncode == 0
        assert col.wait(lambda: drv_status and drv_status[-1].ok, 10)
        t_rel = time.monotonic()
        assert col.wait(lambda: len(cmds) > n0 + 200 and time.monotonic() > t_rel + 2.0, 20)
        with col.lock:
            after = [c for c, t in zip(cmds, col.times[M.key(robot, "cmd")]) if t > t_rel]
            assert after and all(c.method == "stop" for c in after), "it drove after the release by itself"
            assert last_state() == "paused"

        # a person resumes: it drives again
        ans = _mission(client, "resume")
        assert ans.returncode == 0 and "resumed" in ans.stdout, ans.stdout + ans.stderr
        assert col.wait(lambda: cmds[-1].method != "stop", 10)

        # the driver host is killed and restarted: it waits for a new engage, and the mission stays paused after it
        os.killpg(host.pid, signal.SIGKILL)
        host.wait(timeout=5)
        assert col.wait(lambda: last_state() == "paused", 10), [s.text for s in status[-2:]]
        kids.spawn(driver, out=subprocess.DEVNULL)
        n1 = len(drv_status)
        assert col.wait(lambda: len(drv_status) > n1 and drv_status[-1].state == "waiting", 60)
        assert "waiting for engage" in drv_status[-1].text and not drv_status[-1].ok
        eng = subprocess.run([sys.executable, "-m", "bridge", "engage", *client], capture_output=True, text=True,
                             timeout=60)
        assert eng.returncode == 0 and "engaged" in eng.stdout, eng.stdout + eng.stderr
        assert col.wait(lambda: drv_status[-1].ok, 10)
        t_back = time.monotonic()
        assert col.wait(lambda: time.monotonic() > t_back + 1.5, 5)
        with col.lock:
            after = [c for c, t in zip(cmds, col.times[M.key(robot, "cmd")]) if t > t_back]
            assert after and all(c.method == "stop" for c in after) and last_state() == "paused"
        ans = _mission(client, "abort")
        assert ans.returncode == 0 and "aborted" in ans.stdout
        assert _mission(client, "resume").returncode == 1
