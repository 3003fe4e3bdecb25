"""The corridor on a real loop: a station process running the paper's baseline (the teacher's MPC commands applied as
they are: ``mapper = "identity"``, no exploration, the teacher's own range), a driver host process on the UDP link,
and an emulated robot that cannot follow (``scmbridge learner --model miswired``, a process of its own on loopback as
a lab's robot is: its yaw rate answers the opposite way, a miswired motor), so the MPC's every correction drives it
farther off the path. The station stops the robot and pauses the mission (typed reason ``left_corridor``, the distance
on its status), the robot stays within 1.5 m of the path, and only a person's resume drives on (here into the same
runaway, stopped again; a resume with the robot still out is refused without ``--override``:
tests/unit/bridge/nodes/test_station_guards.py)."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import load_mission
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children, free_udp_port
from tests.collect import Collector

BASELINE = ('[transfer]\nmapper = "identity"\nexploration = "off"\nlimits = "teacher"\n\n'
            '[station]\ncorridor_m = 1.0\n')


def _ask(session, robot: str, action: str, override: bool = False) -> M.MissionState:
    from bridge.tools.mission import ask

    req = M.MissionRequest(stamp=time.monotonic(), action=action, source="test", override=override,
                           wall_time=time.time(), nonce=os.urandom(8).hex())
    st = ask(session, robot, req, 5.0)
    assert st is not None, f"no answer to {action}"
    return st


@pytest.mark.timeout(150)
def test_a_robot_that_runs_away_stops_within_the_corridor_and_waits_for_a_person(tmp_path) -> None:
    port, robot = free_port(), f"cor{os.getpid()}"
    mission = load_mission(None)  # the paper's S-path, its start 0.3 m beside the path facing 45 degrees away
    robot_port, bind = free_udp_port(), free_udp_port()
    cfg, scfg = tmp_path / "driver.toml", tmp_path / "station.toml"
    scfg.write_text(BASELINE)
    cfg.write_text(f"[link.udp]\ninsecure = true\nrobot_port = {robot_port}\nbind_port = {bind}\n")
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        k, col = M.Keys(robot), Collector(session)
        states = col.listen(k.state, M.LearnerState)
        status = col.listen(M.status_key(robot, "station"), M.Status)
        kids.spawn(["learner", "--link", "udp", "--model", "miswired", "--port", str(robot_port),
                    "--peer", f"127.0.0.1:{bind}", "--x0=" + ",".join(repr(float(a)) for a in mission.start),
                    "--duration", "130"])
        kids.spawn(["driver", "--engage", "--link", "udp", "--config", str(cfg), *client, "--duration", "120"])
        kids.spawn(["station", "--start", "--config", str(scfg), *client, "--store", str(tmp_path / "p.bin"),
                    "--duration", "110"])
        if not col.wait(lambda: bool(status) and status[-1].reason == "left_corridor", 60.0):
            said = [s.text for s in col.snapshot(M.status_key(robot, "station"))]
            said = [t for i, t in enumerate(said) if i == 0 or t != said[i - 1]]  # what it said, each change once
            pytest.fail(f"never left the corridor: {status[-1] if status else None}; the station said {said[-8:]}"
                        + kids.said())
        paused = col.snapshot(M.status_key(robot, "station"))[-1]
        # the robot stops and stays stopped: a second of poses that do not move, well after the pause
        t_pause = time.monotonic()
        assert col.wait(lambda: time.monotonic() > t_pause + 2.0 and len(states) > 50, 10.0)
        tail = [s for s in col.snapshot(k.state) if s.stamp > states[-1].stamp - 1.0]
        # a person resumes (the robot stopped inside): it runs away again, and is stopped again
        resumed = _ask(session, robot, "resume")
        assert col.wait(lambda: status[-1].counters.get("corridor_trips") == 2 and status[-1].state == "paused", 30.0)
        again = col.snapshot(M.status_key(robot, "station"))[-1]
        t_again = time.monotonic()
        assert col.wait(lambda: time.monotonic() > t_again + 2.0, 5.0)
        poses = np.array([(s.x, s.y) for s in col.snapshot(k.state)])
    devs = np.array([mission.path.project(p)[1] for p in poses])
    assert paused.state == "paused" and not paused.ok and paused.counters.get("corridor_trips") == 1, paused
    # stopped at the corridor's edge: the stop given as it reached 1 m, or ahead of it at the speed it ran away
    assert paused.off_path_m is not None and 0.6 < paused.off_path_m < 1.5, paused
    assert "the corridor" in paused.text and "mission resume" in paused.text, paused.text
    assert 0.6 < devs.max() < 1.5, f"the robot went {devs.max():.2f} m from the path"
    assert float(np.hypot(tail[-1].x - tail[0].x, tail[-1].y - tail[0].y)) < 0.01, "still moving after the pause"
    assert resumed.accepted and resumed.phase == "running", resumed
    assert again.reason == "left_corridor" and again.off_path_m is not None and again.off_path_m < 1.5, again
