"""Station pieces: pairing from stamps, atomic persistence, restart with reload over a real Zenoh query, a station
killed and restarted. The whole HIL demo (three processes, bounded, nothing left behind) runs in
tests/integration/test_record.py, recorded, so one demo run checks both."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.paths import save_atomic
from bridge.core.wire import Keys
from bridge.nodes.pairing import IntervalPairer
from bridge.nodes.station_core import load_store
from bridge.nodes.station_tags import read_store
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import spawn, stop_group
from sim_learner.dynamics import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W
from tests.collect import Collector
from transfer.domain import Bounds
from transfer.store import PairStore
from transfer.teacher.unicycle import step

TB = Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
LB = Bounds(MPC_LEARNER_V, MPC_LEARNER_W)


def test_pairs_come_only_from_intervals_with_one_command_in_force() -> None:
    p = IntervalPairer(dt=0.1)
    x = np.zeros(3)
    pairs = []
    t = 0.0
    u = np.array([0.2, 0.1])
    p.applied(t, *u, "cmd")
    for _ in range(27):  # poses every 10 ms under one command: a pair every dt
        t += 0.01
        x = step(x, u, 0.01)
        out = p.state(t, x)
        if out:
            pairs.append(out)
    assert len(pairs) == 2
    for ut, ul in pairs:
        np.testing.assert_allclose(ut, u, atol=1e-4)  # one Euler step over 0.1 s vs ten of 0.01 s: the chord
        np.testing.assert_allclose(ul, u)
    # a command change closes the open interval (0.07 s >= dt / 2): one more pair, of the old command
    out = p.applied(t + 0.001, 0.3, 0.0, "cmd")
    assert out is not None and np.allclose(out[1], u)
    # deadman and telemetry gaps never pair
    p.applied(t + 0.01, 0.0, 0.0, "deadman")
    assert p.state(t + 0.05, x) is None and p.state(t + 0.2, x) is None
    q = IntervalPairer(dt=0.1)
    q.applied(0.0, 0.2, 0.0, "cmd")
    q.state(0.01, np.zeros(3))
    assert q.state(0.5, np.array([0.1, 0, 0])) is None and q.rejected == 1
    assert q.applied(0.52, 0.1, 0.0, "cmd") is None  # only one pose since the gap: nothing to pair


def test_atomic_save_and_corrupt_store_is_set_aside(tmp_path) -> None:
    s = PairStore(LB, TB, k_min=1)
    s.add([0.2, 0.0], [0.2, 0.0])
    f = tmp_path / "pairs.bin"
    save_atomic(f, s.to_bytes())
    loaded, how = load_store(f, LB, TB, (11, 11), 1)
    assert "reloaded 1" in how and len(loaded.refined()) == 1
    f.write_bytes(f.read_bytes()[:-5])  # a torn write from some other tool
    fresh, how = load_store(f, LB, TB, (11, 11), 1)
    assert how == "new pair store" and fresh.raw_count == 0
    assert any(p.name.startswith("pairs.bin.corrupt-") for p in tmp_path.iterdir())  # nothing is lost
    assert not list(tmp_path.glob(".pairs.bin.*.tmp"))


_spawn = spawn


def _query_pairs(session, robot: str, timeout: float = 15.0) -> M.Pairs | None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        for reply in session.get(Keys(robot).pairs, timeout=1.0):
            if reply.ok is not None:
                return M.decode(reply.ok.payload.to_bytes(), M.Pairs)
        time.sleep(0.2)  # the poll step: the station is not up yet (no queryable, no reply)
    return None


def test_station_restarts_and_reloads_its_pairs(tmp_path) -> None:
    store = tmp_path / "pairs.bin"
    seeded = PairStore(LB, TB, k_min=1)
    for uL in ([0.1, 0.0], [0.2, 0.1], [0.25, -0.1]):
        seeded.add(uL, uL)
    save_atomic(store, seeded.to_bytes())
    port = free_port()
    robot = f"st{os.getpid()}"
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session:
        for _round in range(2):  # start, query, kill; start again: the pairs are still there
            proc = _spawn(["station", "--robot", robot, "--mode", "client", "--connect", tcp(port), "--store",
                           str(store), "--duration", "30"])
            try:
                reply = _query_pairs(session, robot)
            finally:
                stop_group(proc)
            assert reply is not None, "the station did not answer the pairs query"
            assert sorted(p.id for p in reply.pairs) == sorted(p.id for p in seeded.refined())
            assert reply.limits_box is not None and len(reply.limits_box) == 4
        assert read_store(store).raw_count == 3


@pytest.mark.slow
@pytest.mark.timeout(200)
def test_a_station_killed_and_restarted_comes_back_paused_and_drives_at_once_when_resumed(tmp_path) -> None:
    """Finding: after a kill -9 and restart the vehicle did not move for 19.9 s (the gate dropped every
    seq <= last and the new station counted from 0). Now the new run's epoch is followed on its first command.
    And a restart never takes the robot back by itself: the restarted station comes back paused with its mission,
    and drives once a person resumes it."""
    from bridge.core.config import load_mission
    from bridge.tools.procs import Children

    port, robot = free_port(), f"rs{os.getpid()}"
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    station = ["station", *client, "--store", str(tmp_path / "pairs.bin"), "--duration", "90"]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        keys, col = Keys(robot), Collector(session)
        applied, commands = col.listen(keys.applied, M.Applied), col.listen(keys.cmd, M.Command)
        cmd_times, wait = col.times[keys.cmd], col.wait
        kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", x0, *client, "--duration", "120"])
        first = kids.spawn([*station, "--start"])
        assert wait(lambda: any(a.reason == "cmd" for a in applied), 90), "the first station never drove"
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(timeout=5)
        with col.lock:
            old_epoch = commands[-1].epoch
        assert wait(lambda: applied[-1].reason == "deadman", 2.0)
        status = col.listen(M.status_key(robot, "station"), M.Status)
        kids.spawn(station)
        assert wait(lambda: status and status[-1].state == "paused" and "restarted" in status[-1].text, 60), \
            [s.text for s in status[-3:]]
        with col.lock:
            assert all(c.method == "stop" for c in commands if c.epoch != old_epoch)  # paused: stops only
        t_end = time.monotonic() + 30
        while True:  # refused until the new station has heard the driver host (its status comes each second)
            res = subprocess.run([sys.executable, "-m", "bridge", "mission", "resume", *client], capture_output=True,
                                 text=True, timeout=60)
            if res.returncode != 1 or "no driver host status" not in res.stderr or time.monotonic() > t_end:
                break
            time.sleep(0.2)  # the poll step: until the new station has heard the driver host
        assert res.returncode == 0 and "resumed" in res.stdout, res.stdout + res.stderr
        assert wait(lambda: any(c.epoch != old_epoch and c.method != "stop" for c in commands), 30)
        with col.lock:
            t_first = next(t for t, c in zip(cmd_times, commands) if c.epoch != old_epoch and c.method != "stop")
        assert wait(lambda: any(a.reason in ("cmd", "clamped") and a.stamp >= t_first for a in applied), 1.0), \
            "the restarted station's commands were not applied within 1 s"


def test_exploration_is_a_setting_and_never_happens_near_an_obstacle(tmp_path) -> None:
    """Finding: exploration ran mid-mission next to obstacles with no way to bound or stop it."""
    import msgspec

    from bridge.core.config import StationConfig, load_mission
    from bridge.nodes.sources import Proposal
    from bridge.nodes.station_core import StationCore

    mission = load_mission()
    ox, oy, r = mission.obstacles[0]
    near, far = np.array([ox + r + 0.1, oy]), np.array([0.0, -1.0])
    for exploration, vetoed in (("guided", 1), ("paper", 1), ("off", 2)):
        cfg = msgspec.convert({"transfer": {"exploration": exploration, "explore_clearance_m": 0.3}}, StationConfig)
        core = StationCore(cfg, "r1", 10.0, tmp_path / f"{exploration}.bin", mission)
        cmds = [core.send(1.0, Proposal(np.array([0.3, 0.1]), near)),
                core.send(1.1, Proposal(np.array([0.3, 0.1]), far))]
        assert core.counters.explore_vetoed == vetoed, exploration
        assert cmds[0].method != "perturb" and [c.seq for c in cmds] == [0, 1]


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_a_running_station_takes_a_new_mission_over_zenoh_and_its_goal_state_resets(tmp_path) -> None:
    """Finding: the mission was hard-wired and `reached` stayed set after the goal. A new MissionSpec on
    scm/<robot>/mission replaces it (goal state reset) and the station drives to the new goal. Finding (issue 31):
    one published after the goal restarted the robot with no person's act; now it loads idle, says where it came
    from, and drives only after a person's start."""
    import math

    from bridge.core.config import load_mission
    from bridge.tools.procs import Children

    port, robot = free_port(), f"mi{os.getpid()}"
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        keys, col = Keys(robot), Collector(session)
        states = col.listen(keys.state, M.LearnerState)
        status = col.listen(M.status_key(robot, "station"), M.Status)
        commands = col.listen(keys.cmd, M.Command)
        kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", x0, *client, "--duration", "100"])
        kids.spawn(["station", *client, "--start", "--store", str(tmp_path / "p.bin"), "--duration", "90"])
        assert col.wait(lambda: status and status[-1].text == "driving", 60)
        for goal_no in (1, 2):  # two short missions ahead of the robot: each reached, then the next resets it
            with col.lock:
                s = states[-1]
            ahead = [[s.x + d * math.cos(s.theta), s.y + d * math.sin(s.theta)] for d in (0.0, 0.2, 0.4, 0.6)]
            session.put(keys.mission, M.encode(M.MissionSpec(name=f"ahead{goal_no}", path=ahead,
                                                             goal_tolerance=0.2)))
            assert col.wait(lambda n=goal_no: status and status[-1].counters.get("missions") == n
                            and status[-1].counters.get("goal_reached") == 0, 10), f"mission {goal_no} not taken"
            if goal_no == 2:  # after the goal: loaded idle, the robot stays where it is until a person starts it
                with col.lock:
                    x_goal = (states[-1].x, states[-1].y)
                assert col.wait(lambda: status[-1].state == "idle" and "not a person's request" in status[-1].text,
                                5), status[-1].text
                with col.lock:
                    n_cmd = len(commands)
                # a second of the station's ticks (a command each): counted, not slept
                assert col.wait(lambda n=n_cmd: len(commands) >= n + 10, 30)
                with col.lock:
                    assert all(c.method == "stop" for c in commands[n_cmd:]), [c.method for c in commands[n_cmd:]]
                    assert math.dist(x_goal, (states[-1].x, states[-1].y)) < 0.02, "it drove without a person"
                    assert status[-1].state == "idle"
                started = subprocess.run([sys.executable, "-m", "bridge", "mission", "start", *client],
                                         capture_output=True, text=True, timeout=60)
                assert started.returncode == 0, started.stdout + started.stderr
            assert col.wait(lambda: status[-1].counters.get("goal_reached") == 1 and status[-1].text ==
                            "goal reached", 30), f"goal {goal_no} not reached"
        import msgspec

        bad = msgspec.msgpack.encode({"name": "bad", "path": [[0.0, 0.0], [0.0, 0.0]]})  # no length: refused
        session.put(keys.mission, bad)
        assert col.wait(lambda: status[-1].counters.get("malformed_mission", 0) == 1, 5)


@pytest.mark.timeout(60)
def test_a_station_hears_another_senders_commands_and_is_not_handed_its_own_back(tmp_path) -> None:
    """Issue 34: the station's subscription to its robot's ``cmd`` key (to hear a second station or a forger)
    decoded each of the station's own commands again, only to find its own epoch. Its session now does not deliver
    them back; a command from another session is still heard and makes its status not ok."""
    import threading

    from bridge.core.config import StationConfig, load_mission
    from bridge.nodes.station import KernelBuild, Station

    robot, port, stop = f"echo{os.getpid()}", free_port(), threading.Event()
    st = Station(StationConfig(), robot, 10.0, tmp_path / "p.bin", load_mission())
    st.build = KernelBuild(None)  # no MPC code generation: this station never drives (its mission is idle)
    heard: list[int] = []
    real = st.rx.on_own_cmd

    def spy(cmd: M.Command, now: float) -> None:
        heard.append(cmd.epoch)
        real(cmd, now)

    st.rx.on_own_cmd = spy  # what serve() subscribes
    with open_session(make_config(mode="router", listen=[tcp(port)])) as server:
        loop = threading.Thread(target=st.serve, args=(server, stop, 30.0, False), kwargs={"announce": False},
                                name="test-station", daemon=True)
        loop.start()
        try:
            with open_session(make_config(mode="client", connect=[tcp(port)])) as client:
                col = Collector(client)
                cmds = col.listen(Keys(robot).cmd, M.Command)
                status = col.listen(M.status_key(robot, "station"), M.Status)
                assert col.wait(lambda: len(cmds) >= 5 and len(status) >= 1, 20), "the station never published"
                assert heard == []  # five of its own stops went out: none came back to it
                forged = M.Command(stamp=1.0, seq=1, v=0.0, omega=0.0, method="stop", epoch=st.core.outbox.epoch ^ 1)
                client.put(Keys(robot).cmd, M.encode(forged))
                assert col.wait(lambda: any("another sender publishes commands" in s.text and not s.ok
                                            for s in status), 10)
        finally:
            stop.set()
            loop.join(timeout=10)
            assert not loop.is_alive()
    assert heard == [st.core.outbox.epoch ^ 1]
    assert st.core.counters.foreign_commands == 1
