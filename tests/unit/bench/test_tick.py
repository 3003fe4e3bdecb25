"""The station tick's cost harness (``scmbridge bench tick``) runs and drives, and what the tick's cuts keep: the
command goes out as the very bytes the core checked, and the pairer pairs a pose given as three floats exactly as
the same pose given as an array."""

from __future__ import annotations

import gc
import json

import numpy as np

from bench import tick
from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission
from bridge.nodes.pairing import IntervalPairer
from bridge.nodes.station_core import StationCore, TickInputs
from transfer.domain import Bounds


def test_the_harness_drives_a_robot_and_splits_its_ticks_by_phase(capsys) -> None:
    frozen = gc.get_freeze_count()
    try:
        assert tick.main(["--ticks", "25", "--skip", "5", "--count", "2", "--no-compile", "--tiles", "1"]) == 0
        # its start-up heap frozen before the first tick, as the station's (no full collection scans it in a tick)
        assert gc.get_freeze_count() > frozen
    finally:
        gc.unfreeze()  # this test process's heap back as it was
    text = capsys.readouterr().out
    out = json.loads(text[text.index("{\n"):])  # past qpOASES's banner (CasADi prints it on Python's stdout)
    assert out["robots"] == 2 and out["ticks"] == 2 * 20 and out["why"] == "driving"
    assert {"decode", "pairing", "mpc", "transfer", "encode", "core_rest"} <= set(out["phases_ms"])
    assert out["cpu_ms_per_tick"]["median"] > 0 and out["methods"].get("stop", 0) <= 2
    # the phases come from a second pass over the same robots, which drove alike; its totals hold the timers' cost
    assert out["passes_agree"] is True and out["timed_cpu_ms_per_tick"]["median"] > 0
    assert "timers_ms_per_tick" in out
    assert sum(out["methods"].values()) == 2 * 26 and out["raw_pairs"] > 0
    # the saves are written by each robot's writer thread, off the tick, as the station's are
    assert out["saves_written"] >= 2


def test_without_phases_the_robots_drive_once_and_no_phase_is_given(capsys) -> None:
    try:
        assert tick.main(["--ticks", "15", "--skip", "5", "--no-phases", "--no-compile", "--tiles", "1"]) == 0
    finally:
        gc.unfreeze()
    text = capsys.readouterr().out
    out = json.loads(text[text.index("{\n"):])
    assert out["ticks"] == 10 and out["cpu_ms_per_tick"]["mean"] > 0 and out["process_ms_per_tick"] > 0
    assert "phases_ms" not in out and "passes_agree" not in out


def test_the_command_goes_out_as_the_bytes_the_core_checked(tmp_path) -> None:
    mission = load_mission()
    core = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", mission)
    state = M.LearnerState(stamp=0.0, seq=1, x=float(mission.start[0]), y=float(mission.start[1]), theta=0.0)
    out = core.tick(TickInputs(telemetry=((state, 0.0),)), 0.0)
    assert out.command is not None and out.command_bytes == M.encode(out.command)
    assert M.decode(out.command_bytes, M.Command) == out.command
    assert M.validated_bytes(out.command) == (out.command, out.command_bytes)


def test_a_pose_as_three_floats_pairs_as_the_same_pose_as_an_array() -> None:
    lb, tb = Bounds((0.0, 0.5), (-0.7, 0.7)), Bounds((-0.6, 0.6), (-1.0, 1.0))
    a, b = (IntervalPairer(0.1, max_speed=1.0, max_turn=2.0, command_bounds=lb, teacher_bounds=tb) for _ in "ab")
    rng = np.random.default_rng(7)
    x, t, got = np.zeros(3), 0.0, 0
    for k in range(300):
        t += 0.01
        if k % 5 == 0:
            u = (0.3, float(rng.uniform(-0.5, 0.5))) if k % 20 else (0.9, 0.0)  # 0.9: beyond the plausible box
            pa, pb = a.applied(t, *u, "cmd", t), b.applied(t, *u, "cmd", t)
            assert (pa is None) == (pb is None)
            if pa is not None:
                got += 1
                assert np.array_equal(pa[0], pb[0]) and np.array_equal(pa[1], pb[1])
        x = x + np.array([0.003 * np.cos(x[2]), 0.003 * np.sin(x[2]), 0.002]) + rng.normal(0.0, 1e-3, 3)
        pa, pb = a.state(t, x.copy(), t), b.state(t, tuple(x.tolist()), t)
        assert (pa is None) == (pb is None)
        if pa is not None:
            got += 1
            assert np.array_equal(pa[0], pb[0]) and np.array_equal(pa[1], pb[1])
    assert got > 20 and a.implausible_pair > 0
    assert (a.formed, a.rejected, a.implausible_pair) == (b.formed, b.rejected, b.implausible_pair)


def test_a_robots_commands_are_the_same_whether_its_left_over_work_ran_between_ticks_or_in_the_next(tmp_path) -> None:
    """The station's core with ``defer``: the hole search's step a command leaves is done by the loop after the
    command went out (``StationCore.background``) or, if the loop had no time, first thing in the next tick; the
    commands are the same either way (so replay through the station needs no record of when it ran)."""
    from bench.fleet import write_mission

    cfg = StationConfig()
    mission = load_mission(str(write_mission(tmp_path / "mission.toml", 1)))
    rigs = []
    for side in ("loop", "tick"):
        (tmp_path / side).mkdir()
        rigs.append(tick._Rig("r1", cfg, mission, tmp_path / side, tick._Clock(phases=False), None, None, 1000.0))
    period = rigs[0].core.time.period
    sent: dict[str, list] = {"loop": [], "tick": []}
    done = 0
    try:
        for k in range(400):
            now = 1000.0 + k * period
            for side, rig in zip(("loop", "tick"), rigs):
                rig.robot_side(now, period, k == 0)
                out = rig.tick(now, tick._Clock(phases=False), M.decode, M.encode)
                c = out.command
                sent[side].append(None if c is None else (c.seq, c.v, c.omega, c.method))
                rig.take(c, now)
                if side == "loop":
                    done += rig.core.background()
    finally:
        for rig in rigs:
            rig.writer.close()
    assert done >= 3 and rigs[0].core.transfer.policy.searches >= 1  # the loop did steps of hole searches
    assert sum(c is not None and c[3] == "perturb" for c in sent["loop"]) > 0
    assert sent["loop"] == sent["tick"]
