"""Settled pairs only (``[station] pair_settle_s``, bridge/nodes/pairing.py): a vehicle whose body lags its command
(ArduPilot Rover SITL's skid body, about 0.3 s) is paired only where the command had been steady, and the probe of
the learner's top command is then held until the speed has settled, so the learned limit is the vehicle's steady
top speed (docs/BENCHMARKS.md, "The transfer on SITL"). Off by default: the paper's pairing is unchanged."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.core.config import StationConfig, load_mission, load_station
from bridge.nodes.pairing import IntervalPairer
from bridge.nodes.station_core import StationCore
from transfer.domain import Bounds
from transfer.policy import make_policy
from transfer.store import PairStore

#: the weak SITL rover's command range (WP_SPEED 0.6, ATC_STR_RAT_MAX 30) and the paper's MPC teacher's
LB = Bounds((0.05, 0.6), (-math.radians(30), math.radians(30)))
TB = Bounds((0.05, 0.6), (-math.pi / 4, math.pi / 4))
#: the lagging learner: steady speed GAIN x command, reached with time constant TAU (SITL's skid body: ~0.3 s)
GAIN, TAU = 0.58, 0.3


class LaggingRover:
    """A unicycle whose forward speed follows GAIN * command through a first-order lag; its turn rate is exact."""

    def __init__(self, v0: float = 0.0) -> None:
        self.x = np.zeros(3)
        self.v = v0

    def step(self, u: np.ndarray, dt: float) -> None:
        self.v += (GAIN * u[0] - self.v) * (1.0 - math.exp(-dt / TAU))
        th = self.x[2]
        self.x = self.x + np.array([self.v * math.cos(th) * dt, self.v * math.sin(th) * dt, u[1] * dt])


def drive(pairer: IntervalPairer, commands, rover: LaggingRover, t0: float = 0.0, telemetry_dt: float = 0.05):
    """Each command held 0.1 s (a 10 Hz station), echoed once, poses every ``telemetry_dt``; the pairs formed."""
    pairs, t = [], t0
    for u in commands:
        u = np.asarray(u, dtype=float)
        out = pairer.applied(t, float(u[0]), float(u[1]), "cmd")
        if out is not None:
            pairs.append(out)
        for _ in range(round(0.1 / telemetry_dt)):
            rover.step(u, telemetry_dt)
            t += telemetry_dt
            out = pairer.state(t, tuple(rover.x.tolist()))
            if out is not None:
                pairs.append(out)
    return pairs, t


def mpc_like(v: float, n: int, w: float = 0.0) -> list[tuple[float, float]]:
    """``n`` ticks of about (v, w), each a hair different from the last, as an MPC's commands are: one segment (and
    one pair) per tick."""
    return [(v + (0.0005 if k % 2 else 0.0), w) for k in range(n)]


def test_by_default_every_pair_is_kept_and_a_step_reads_the_speed_part_way_up() -> None:
    p = IntervalPairer(0.1, command_bounds=LB)
    pairs, _ = drive(p, mpc_like(0.6, 20), LaggingRover(v0=0.1))
    assert p.unsettled == 0 and p.formed == len(pairs) == 19  # the 20th is closed by the next command
    assert pairs[0][0][0] < 0.6 * GAIN * 0.6  # the first pair: far below the steady 0.348 m/s


def test_settled_pairs_only_drop_the_step_and_keep_the_steady_speed() -> None:
    p = IntervalPairer(0.1, command_bounds=LB, settle_s=0.5)
    pairs, _ = drive(p, mpc_like(0.6, 20), LaggingRover(v0=0.1))
    # a pair's interval starts 0.05 s into its tick: ticks 0..4 began less than 0.5 s after the step
    assert p.unsettled == 5 and len(pairs) == 14
    assert min(u_T[0] for u_T, _ in pairs) > 0.8 * GAIN * 0.6
    assert all(u_T[0] < 1.01 * GAIN * 0.6 and u_L[0] >= 0.6 for u_T, u_L in pairs)
    # the same hold as one unchanging command (a segment paired every dt): its first 0.5 s dropped too
    q = IntervalPairer(0.1, command_bounds=LB, settle_s=0.5)
    pairs, _ = drive(q, [(0.6, 0.0)] * 20, LaggingRover(v0=0.1))
    assert q.unsettled >= 3 and pairs and min(u_T[0] for u_T, _ in pairs) > 0.8 * GAIN * 0.6


def test_commands_within_the_tolerance_are_steady_a_larger_change_or_a_stop_is_not() -> None:
    tol = 0.05 * LB.span[0]  # 0.0275 m/s
    p = IntervalPairer(0.1, command_bounds=LB, settle_s=0.3, settle_tol=0.05)
    rover = LaggingRover()
    # a slow drift (0.004 m/s a tick): the commands of the last 0.3 s stay within the tolerance of each
    drift = [(0.3 + 0.004 * k, 0.0) for k in range(10)]
    assert 0.004 * 6 < tol < 0.004 * 7
    pairs, t = drive(p, drift, rover)
    assert p.unsettled == 3 and len(pairs) == 6  # ticks 0-2 began less than 0.3 s after the start
    # a step of 0.1 m/s (18 % of the range) is a new start: its first three ticks' pairs dropped
    pairs, t = drive(p, mpc_like(0.45, 6), rover, t)
    assert len(pairs) == 1 + 2 and p.unsettled == 3 + 3  # the drift's last pair, then ticks 3 and 4 of the step
    # a faster drift (0.03 m/s a tick, beyond the tolerance every tick) never settles
    pairs, t = drive(p, [(0.48 + 0.03 * k, 0.0) for k in range(5)], rover, t)
    assert len(pairs) == 1 and p.unsettled == 6 + 4  # the step's last pair only
    # a stop between two equal commands breaks the run
    assert p.applied(t, 0.0, 0.0, "deadman") is None and p.unsettled == 11  # the drift's last tick, dropped
    pairs, t = drive(p, mpc_like(0.5, 5), rover, t + 0.1)
    assert len(pairs) == 1 and p.unsettled == 11 + 3  # ticks 0-2 after the stop dropped, tick 3 kept
    assert p.formed == 6 + 3 + 1 + 1


def test_the_probe_of_the_top_speed_is_held_until_it_settles_and_fixes_the_limit_there() -> None:
    """The transfer's probe of a never-driven limit repeats until a boundary pair is learned; with settled pairs
    only, that boundary pair is the steady top speed; with every pair, the first step's part-way speed."""
    learned = {}
    for settle in (0.0, 0.5):
        store = PairStore(LB, TB, k_min=5)
        policy = make_policy(store, "scm", seed=0)
        pairer = IntervalPairer(0.1, command_bounds=LB, settle_s=settle)
        rover, t = LaggingRover(v0=0.1), 0.0
        probes = 0
        for _ in range(30):  # a teacher that asks for the learned top speed, straight on
            u_T = np.array([store.limits.box.v[1], 0.0])
            m = policy.map(u_T)
            probes += m.method == "perturb" and m.u_L[0] == LB.v[1]
            pairs, t = drive(pairer, [m.u_L], rover, t)
            for pair in pairs:
                store.add(*pair)
        learned[settle] = (store.limits.box.v[1], probes)
    steady = GAIN * LB.v[1]
    # every pair: the probe's first pair (learned a tick later, so sent twice) fixes the limit part-way up
    assert learned[0.0][1] <= 2 and learned[0.0][0] < 0.75 * steady
    # settled pairs only: the probe held (0.5 s, 1.7 time constants) until its pair is 0.92 of the steady speed
    assert learned[0.5][1] >= 5 and 0.9 * steady < learned[0.5][0] <= steady


def test_the_station_takes_the_setting_from_its_configuration(tmp_path) -> None:
    assert StationConfig().station.pair_settle_s == 0.0  # the paper's pairing by default
    f = tmp_path / "station.toml"
    f.write_text("[station]\npair_settle_s = 0.5\npair_settle_tol = 0.1\n")
    cfg = load_station(f)
    core = StationCore(cfg, "r1", 10.0, tmp_path / "p.bin", load_mission())
    assert core.pairer.settle_s == 0.5
    assert core.pairer._settle_tol == pytest.approx((0.1 * cfg.learner_bounds.bounds().span[0],
                                                     0.1 * cfg.learner_bounds.bounds().span[1]))
    with pytest.raises(ValueError):
        IntervalPairer(0.1, settle_s=-1.0)
    # a learner that cannot turn in place, slow to its top: the edge's hold, curvatures, the MPC's rows, the probe
    g = tmp_path / "ackermann.toml"
    g.write_text('[station]\npair_settle_s = 1.0\npair_settle_edge_s = 2.5\n[transfer]\nturn = "needs-speed"\n')
    core = StationCore(load_station(g), "r1", 10.0, tmp_path / "q.bin", load_mission())
    assert core.pairer.settle_s == 1.0 and core.pairer.settle_edge_s == 2.5
    assert core.store.limits.needs_speed and core.transfer.policy.turn_probe == "at-top-speed"
    assert core.source.teacher.cfg.turn_needs_speed


def test_a_command_on_an_edge_of_the_range_is_held_longer_with_settle_edge_s() -> None:
    """``settle_edge_s``: a body slower to reach its top from rest than to follow small steps (SITL's Ackermann
    rover, about 2 s) has its probe of a limit (a command on an edge of the learner's range) held that long, while
    the mission's commands inside the range keep ``settle_s``; without the bounds whose edges it names, or without
    ``settle_s``, it is refused."""
    global TAU
    slow = 0.8  # a body four times slower than the skid's
    old, TAU = TAU, slow
    try:
        plain = IntervalPairer(0.1, command_bounds=LB, settle_s=0.5)
        pairs, _ = drive(plain, mpc_like(0.6, 40), LaggingRover(v0=0.0))
        first_plain = pairs[0][0][0]
        edge = IntervalPairer(0.1, command_bounds=LB, settle_s=0.5, settle_edge_s=2.0)
        pairs, _ = drive(edge, mpc_like(0.6, 40), LaggingRover(v0=0.0))
        # 0.6 is the learner's top: held 2 s, the first pair reads the body at 92 % of its steady speed, not 53 %
        assert first_plain < 0.6 * GAIN * 0.6 < 0.9 * GAIN * 0.6 < pairs[0][0][0]
        assert edge.unsettled == 20 and plain.unsettled == 5
        inside = IntervalPairer(0.1, command_bounds=LB, settle_s=0.5, settle_edge_s=2.0)
        drive(inside, mpc_like(0.4, 40), LaggingRover(v0=0.0))
        assert inside.unsettled == 5  # inside the range: settle_s
    finally:
        TAU = old
    with pytest.raises(ValueError, match="settle_edge_s needs"):
        IntervalPairer(0.1, settle_s=0.5, settle_edge_s=2.0)
    with pytest.raises(ValueError, match="settle_edge_s needs"):
        IntervalPairer(0.1, command_bounds=LB, settle_edge_s=2.0)
