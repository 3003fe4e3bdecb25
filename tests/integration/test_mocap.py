"""Poses from motion capture: a simulated mocap bridge with its own clock (offset by 1000 s) and jittery delivery
publishes `scm/<robot>/mocap`; the driver host (pose_source = "mocap") puts each sample on its own clock and
publishes it as the state the station pairs with the applied commands."""

from __future__ import annotations

import heapq
import os
import random
import threading
import time

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.clock import ClockOffset
from bridge.nodes.pairing import IntervalPairer
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children, free_udp_port
from sim_learner.dynamics import mpc_learner
from sim_learner.udp_robot import UdpRobot
from sim_learner.vehicle import SimVehicle
from tests.collect import Collector
from tests.wait import Pace

MOCAP_CLOCK = 1000.0  # the mocap system's clock runs this far ahead of ours
JITTER = 0.02  # s of random delivery delay on top of the network's


def test_clock_offset_removes_delivery_jitter_and_follows_the_minimum() -> None:
    rng = random.Random(1)
    c = ClockOffset(window_s=2.0)
    errs = []
    for k in range(500):
        t_true = k * 0.01
        receipt = t_true + 0.002 + rng.uniform(0.0, JITTER)
        errs.append(c.restamp(t_true + MOCAP_CLOCK, receipt) - t_true)
    late = np.abs(np.array(errs[100:]) - 0.002)
    assert late.max() < 0.0015  # restamped to the sample's own time (+ the minimum latency), jitter gone
    assert abs(c.offset - (0.002 - MOCAP_CLOCK)) < 0.0015


def test_one_stamp_forged_ahead_is_dropped_and_shifts_nothing() -> None:
    """Finding: one forged sample 0.4 s ahead shifted every pose for the next 5 s, undetected (the default max_age
    0.5 s let it through). It pulls the window's minimum no more: it is dropped, the next samples keep their time."""
    c = ClockOffset(window_s=5.0)
    for k in range(50):
        t, verdict = c.judge(k * 0.02 + MOCAP_CLOCK, k * 0.02 + 0.001)
        assert verdict == "ok" and t == pytest.approx(k * 0.02 + 0.001)
    assert c.judge(50 * 0.02 + MOCAP_CLOCK + 0.4, 50 * 0.02 + 0.001) == (None, "dropped")
    for k in range(51, 60):
        t, verdict = c.judge(k * 0.02 + MOCAP_CLOCK, k * 0.02 + 0.003)
        assert verdict == "ok" and t == pytest.approx(k * 0.02 + 0.001)


@pytest.mark.parametrize("step", [-0.45, 0.45])
def test_a_clock_step_is_detected_within_a_few_samples(step: float) -> None:
    """Finding: a real clock step back of 0.45 s shifted every pose for the next 5 s. A step either way restarts the
    estimate once a few samples agree on it; at most those few samples are not placed exactly."""
    c = ClockOffset(window_s=5.0)
    for k in range(50):
        c.judge(k * 0.02 + MOCAP_CLOCK, k * 0.02 + 0.001)
    verdicts = []
    for k in range(50, 70):
        t, verdict = c.judge(k * 0.02 + MOCAP_CLOCK + step, k * 0.02 + 0.001)
        verdicts.append(verdict)
        if k >= 53:
            assert verdict == "ok" and t == pytest.approx(k * 0.02 + 0.001)
    assert verdicts[:3].count("restarted") == 1


def test_late_deliveries_keep_their_own_time() -> None:
    c = ClockOffset(window_s=5.0)
    for k in range(50):
        c.judge(k * 0.02 + MOCAP_CLOCK, k * 0.02 + 0.001)
    t, verdict = c.judge(50 * 0.02 + MOCAP_CLOCK, 50 * 0.02 + 0.2)  # one sample 0.2 s late
    assert verdict == "ok" and t == pytest.approx(50 * 0.02 + 0.001)


class MocapBridge:
    """Samples the vehicle's true pose at 100 Hz, stamps it with the mocap clock and delivers it late by a random
    delay (out of order at times), like a motion-capture bridge on a busy network."""

    def __init__(self, session, robot: str, vehicle: SimVehicle) -> None:
        self.pub = session.declare_publisher(M.key(robot, "mocap"))
        self.vehicle = vehicle
        self.truth: list[tuple[float, float, float]] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        rng = random.Random(7)
        queue: list[tuple[float, int, bytes]] = []
        seq, t_next = 0, time.monotonic()
        while not self.stop.is_set():
            now = time.monotonic()
            if now >= t_next:
                x, y, th = self.vehicle.measured_pose(now)  # SimVehicle locks: the robot's thread drives it
                self.truth.append((now, x, y))
                msg = M.LearnerState(stamp=now + MOCAP_CLOCK, seq=seq, x=x, y=y, theta=th, source="mocap")
                heapq.heappush(queue, (now + rng.uniform(0.0, JITTER), seq, M.encode(msg)))
                seq += 1
                t_next += 0.01
            while queue and queue[0][0] <= now:
                self.pub.put(heapq.heappop(queue)[2])
            time.sleep(0.001)  # pacing: samples on their 100 Hz grid (t_next), delivered when their delay is up


def pairs_of(states: list, applied: list) -> list:
    """The pairs the station's IntervalPairer forms from these applied commands and poses."""
    pairer = IntervalPairer(0.1)
    pairs = []
    for _, kind, e in sorted([(a.stamp, 0, a) for a in applied] + [(s.stamp, 1, s) for s in states],
                             key=lambda t: t[:2]):
        out = (pairer.applied(e.stamp, e.v, e.omega, e.reason) if kind == 0
               else pairer.state(e.stamp, np.array([e.x, e.y, e.theta])))
        if out is not None:
            pairs.append(out)
    return pairs


def enough(col: Collector, states: list, applied: list) -> bool:
    """Whether what came so far is what the test judges: over 200 poses (past the 50 it skips) and 20 pairs."""
    with col.lock:
        st, ap = list(states), list(applied)
    return len(st) > 200 and len(pairs_of(st, ap)) > 20


@pytest.mark.slow
@pytest.mark.timeout(90)
def test_the_driver_host_publishes_mocap_poses_on_its_clock_and_they_pair_with_the_commands(tmp_path) -> None:
    port, robot = free_port(), f"mc{os.getpid()}"
    learner = mpc_learner()
    vehicle = SimVehicle(learner, (0.0, 0.0, 0.0), now=time.monotonic())
    bind = free_udp_port()
    cfg = tmp_path / "driver.toml"
    with UdpRobot(vehicle, peer=("127.0.0.1", bind)) as robot_dev, \
            open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        cfg.write_text(f'[driver]\npose_source = "mocap"\n[link.udp]\ninsecure = true\nrobot_port = {robot_dev.port}\n'
                       f"bind_port = {bind}\n")
        k, col = M.Keys(robot), Collector(session)
        states, applied = col.listen(k.state, M.LearnerState), col.listen(k.applied, M.Applied)
        lock = col.lock
        mocap = MocapBridge(session, robot, vehicle)
        mocap.thread.start()
        kids.spawn(["driver", "--engage", "--link", "udp", "--config", str(cfg), "--robot", robot, "--mode", "client",
                    "--connect", tcp(port), "--duration", "60"])
        try:
            col.wait(lambda: bool(states), 30)
            pub = session.declare_publisher(k.cmd)
            epoch = M.new_epoch()
            cmds = [(0.2, 0.1), (0.3, -0.15), (0.12, 0.2)]
            seq, pace = 0, Pace(0.05)
            for i, (v, w) in enumerate(cmds):  # each command held 1.5 s, sent at 20 Hz; the last one on until the
                t_hold = time.monotonic() + 1.5  # poses and pairs judged below have come (a stalled host takes
                t_end = t_hold + 30.0  # longer, it does not fail the test)
                while time.monotonic() < t_hold or (i == len(cmds) - 1 and time.monotonic() < t_end
                                                    and not enough(col, states, applied)):
                    pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=v, omega=w, method="scm",
                                               sender="test", epoch=epoch)))
                    seq += 1
                    pace.wait()  # pacing: the station's 20 Hz
        finally:
            mocap.stop.set()
            mocap.thread.join(timeout=2)
    with lock:
        st, ap = list(states), list(applied)
    assert len(st) > 200 and all(s.source == "mocap" for s in st)
    truth = np.array(mocap.truth)
    # every published pose sits at its true sample time on our clock (+ the small minimum latency), not at its
    # (jittered) arrival time
    idx = np.searchsorted(truth[:, 0], [s.stamp for s in st])
    errs = []
    for s, i in zip(st, idx):
        j = int(np.argmin([np.hypot(truth[m, 1] - s.x, truth[m, 2] - s.y) + abs(truth[m, 0] - s.stamp)
                           for m in range(max(0, i - 3), min(len(truth), i + 3))])) + max(0, i - 3)
        errs.append(s.stamp - truth[j, 0])
    errs = np.array(errs[50:])
    assert np.percentile(np.abs(errs), 95) < 0.006, np.percentile(np.abs(errs), [50, 95, 100])
    # and pairs formed from applied + mocap state recover the learner's real response
    pairs = pairs_of(st, ap)
    assert len(pairs) > 20
    err = [np.abs(uT - learner.response(uL)) for uT, uL in pairs]
    assert np.median([e[0] for e in err]) < 0.01 and np.median([e[1] for e in err]) < 0.03
