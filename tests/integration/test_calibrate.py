"""The calibration stage: the pure plan on the paper's learner, and `scmbridge calibrate` end to end over Zenoh
through a driver host and the emulated CAN controllers, into the station's store."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.nodes.station_tags import read_store
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children
from sim_learner.dynamics import mpc_learner
from tests.collect import Collector
from transfer.calibration import CalibrationPlan
from transfer.domain import Bounds
from transfer.pairs import teacher_equivalent
from transfer.paper import MPC_TEACHER_V, MPC_TEACHER_W
from transfer.store import PairStore

LEARNER = mpc_learner()
LB = Bounds(LEARNER.v_range, LEARNER.w_range)


def _simulate(plan: CalibrationPlan, dt: float = 0.1) -> tuple[list, float, PairStore]:
    store = PairStore(LB, Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=1)
    x, t, far = np.zeros(3), 0.0, 0.0
    while True:
        s = plan.step(t, x)
        if s.done:
            return s, far, store
        x1 = LEARNER.step(x, s.u_L, dt)
        store.add(teacher_equivalent(x, x1, dt), s.u_L)
        x, t = x1, t + dt
        far = max(far, float(np.hypot(*x[:2])))


def test_the_plan_drives_every_command_stays_near_the_start_and_measures_the_limits() -> None:
    done, far, store = _simulate(CalibrationPlan(LB, (5, 5), hold_s=1.0, max_distance=1.5))
    assert done.reason == "all 25 commands driven"
    assert far < 1.5
    true = [float(LEARNER.response(LB.lo)[0]), float(LEARNER.response(LB.hi)[0])]
    assert np.allclose(store.limits.box.v, true, atol=1e-6)  # the extremes were driven: measured, not guessed


def test_the_plan_stops_at_the_distance_and_time_bounds() -> None:
    done, far, _ = _simulate(CalibrationPlan(LB, (5, 5), hold_s=3.0, max_distance=0.5, return_radius=0.45))
    assert done.done and "distance bound" in done.reason and far < 0.5 + 0.3 * 0.1 + 1e-9
    done, _, _ = _simulate(CalibrationPlan(LB, (5, 5), hold_s=1.0, max_distance=5.0, max_time_s=4.0))
    assert "time bound" in done.reason and done.index < 24


@pytest.mark.slow
@pytest.mark.timeout(150)
def test_scmbridge_calibrate_drives_the_robot_through_its_driver_host_into_the_store(tmp_path) -> None:
    port, robot = free_port(), f"cal{os.getpid()}"
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    store = tmp_path / "pairs.bin"
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        states, lock = col.listen(M.key(robot, "state"), M.LearnerState), col.lock
        kids.spawn(["driver", "--engage", "--link", "can", "--emulate", *client, "--duration", "140"])
        res = subprocess.run([sys.executable, "-m", "bridge", "calibrate", *client, "--store", str(store),
                              "--grid", "3x3", "--hold", "0.6", "--max-distance", "1.2", "--duration", "90"],
                             capture_output=True, text=True, timeout=130)
        host_said = kids.said()  # the driver host's own account of a pause (a stall, a rejected estimate)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:] + host_said
    assert "all 9 commands driven" in res.stdout
    assert "calibration 9/9" in res.stderr  # progress, command by command
    learned = read_store(store)
    assert learned.raw_count > 20 and len(learned.refined()) >= 3
    with lock:
        far = max(np.hypot(s.x - states[0].x, s.y - states[0].y) for s in states)
    assert far < 1.2 + 0.1
    true_v = [float(LEARNER.response(LB.lo)[0]), float(LEARNER.response(LB.hi)[0])]
    assert np.allclose(learned.limits.box.v, true_v, atol=0.02)  # measured through CAN odometry


@pytest.mark.slow
@pytest.mark.timeout(150)
def test_the_motion_primitive_teacher_drives_from_calibrated_pairs(tmp_path) -> None:
    """The paper's Section 5.1 on the bridge: calibrate, then the station's motion-primitive teacher plans with
    the primitives inside the calibrated limits and drives the emulated learner along the S-path."""
    from bridge.core.config import load_mission

    mission = load_mission()
    port, robot = free_port(), f"prim{os.getpid()}"
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    store, cfg = tmp_path / "pairs.bin", tmp_path / "station.toml"
    # the calibration may leave the robot up to --max-distance from where it started, so off the path: the corridor
    # (docs/OPERATING.md) is as wide as that, or the teacher's first steps back would leave it
    cfg.write_text('[station]\ncorridor_m = 3.0\n\n[teacher]\nkind = "primitives"\n')
    x0 = ",".join(f"{a:.6f}" for a in mission.start)
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        states, lock = col.listen(M.key(robot, "state"), M.LearnerState), col.lock
        kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", x0, *client, "--duration", "140"])
        res = subprocess.run([sys.executable, "-m", "bridge", "calibrate", *client, "--store", str(store),
                              "--grid", "3x3", "--hold", "0.5", "--max-distance", "2.0", "--duration", "60"],
                             capture_output=True, text=True, timeout=90)
        assert res.returncode == 0, res.stderr[-2000:]
        kids.spawn(["station", "--start", "--config", str(cfg), *client, "--store", str(store), "--duration", "80"])
        t_end, progress = time.monotonic() + 70, 0.0
        while time.monotonic() < t_end and progress < 0.15:
            time.sleep(0.5)  # the poll step: until the robot is far enough along (the loop's deadline is the test)
            with lock:
                last = states[-1]
            progress = max(progress, mission.progress([last.x, last.y]))
        assert progress >= 0.15, f"the primitive teacher covered only {progress:.0%} of the path" + kids.said()
