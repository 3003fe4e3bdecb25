"""The parts of ``scmbridge demo --sitl`` that need no SITL: the learner's range read from the vehicle's parameters,
and the mission placed where the vehicle stands (a file the station reads back); and one transfer run on SITL
(marked ``sitl``): the weak, distorted rover of deploy/examples/sitl-weak.parm on the first bend of the S-path; and
the paper's claims on the whole S-path with the rover of deploy/examples/sitl-weak-turn.parm, which cannot turn its
bends at its own top speed: the teacher's reference, the transfer and the paper's baseline; and the same on the
Ackermann rover of deploy/examples/sitl-weak-ackermann.parm, which cannot turn in place."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bridge.core.config import load_mission, load_mission_spec
from bridge.core.errors import UsageError
from bridge.core.wire import MissionSpec
from bridge.tools.demo_sitl import (
    ParamChanges,
    learner_range,
    mission_toml,
    param_change,
    place_mission,
    start_on_path,
    teacher_reference,
)
from sim_learner.sitl import Sitl, find_sitl, where_sitl_is_looked_for
from sim_learner.sitl_response import measure

ROOT = Path(__file__).resolve().parents[2]


def test_the_learner_range_is_the_vehicles_guided_speed_cap_and_turn_rate_limit() -> None:
    v, w = learner_range({"CRUISE_SPEED": 3.0, "WP_SPEED": 0.3, "ATC_STR_RAT_MAX": 15.0})
    assert v == (0.05, 0.3) and w == pytest.approx((-math.pi / 12, math.pi / 12))  # the Jackal's top speeds
    # WP_SPEED 0: CRUISE_SPEED, as Rover does; CRUISE_SPEED is never a cap on its own (it tunes the throttle)
    assert learner_range({"CRUISE_SPEED": 2.0, "WP_SPEED": 0.0, "ATC_STR_RAT_MAX": 15.0})[0] == (0.05, 2.0)
    assert learner_range({"CRUISE_SPEED": 0.3, "WP_SPEED": 3.0, "ATC_STR_RAT_MAX": 15.0})[0] == (0.05, 3.0)
    with pytest.raises(UsageError):
        learner_range({"CRUISE_SPEED": 0.0, "WP_SPEED": 0.0, "ATC_STR_RAT_MAX": 15.0})


def test_the_mission_moves_rigidly_onto_the_vehicles_pose_and_reads_back(tmp_path) -> None:
    spec = load_mission_spec(None)  # the paper's S-path, start 0.3 m beside it facing 45 degrees away
    pose = (1.5, -2.0, 2.6)
    placed = place_mission(spec, pose)
    assert placed.start == pytest.approx(list(pose))
    f = tmp_path / "mission.toml"
    f.write_text(mission_toml(placed))
    world, world0 = load_mission(str(f)), load_mission(None)
    assert world.path.length == pytest.approx(world0.path.length)
    # every distance is kept: start to goal, start to each obstacle, and the radii
    s0, s1 = np.asarray(spec.start[:2]), np.asarray(pose[:2])
    assert np.hypot(*(world.goal - s1)) == pytest.approx(np.hypot(*(world0.goal - s0)))
    for (x, y, r), (x0, y0, r0) in zip(world.obstacles, world0.obstacles):
        assert r == r0 and np.hypot(x - s1[0], y - s1[1]) == pytest.approx(np.hypot(x0 - s0[0], y0 - s0[1]))
    # and the start's heading relative to the path's first segment is the same
    def rel(path, start) -> float:
        d = np.asarray(path[1]) - np.asarray(path[0])
        return (math.atan2(d[1], d[0]) - start[2]) % (2 * math.pi)
    assert rel(placed.path, placed.start) == pytest.approx(rel(spec.path, spec.start))
    # a car-like vehicle starts on the path facing along it (--start on-path): placed, it stands on the path's start
    on = place_mission(start_on_path(spec), pose)
    assert on.path[0] == pytest.approx(list(pose[:2]))
    assert math.remainder(rel(on.path, on.start), 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    assert on.obstacles != placed.obstacles and spec.start is not None  # the spec itself is left as it was


def test_the_teacher_reference_is_a_finished_run_on_sitl_and_a_parameter_change_is_read_strictly(tmp_path) -> None:
    ref = {"model": "rover-skid", "transfer": "off", "reached_goal": True, "scm_time_s": 41.0,
           "scm_dev_last_half_m": 0.006, "collisions": {"scm": False},
           "vehicle_params": {"WP_SPEED": 0.6, "ATC_STR_RAT_MAX": 45.0}}
    f = tmp_path / "summary.json"
    f.write_text(json.dumps(ref))
    got = teacher_reference(f)
    assert (got["time_s"], got["dev_last_half_m"], got["collided"]) == (41.0, 0.006, False)
    assert "rover-skid" in got["source"] and "transfer off" in got["source"] and "45" in got["source"]
    log = tmp_path / "demo.log"  # the demo's own output: its last summary line
    log.write_text("SITL booted\nsummary: " + json.dumps({**ref, "scm_time_s": 40.0}) + "\nfigure: x\n")
    assert teacher_reference(log)["time_s"] == 40.0
    f.write_text(json.dumps({**ref, "reached_goal": False, "scm_time_s": None}))
    with pytest.raises(UsageError):
        teacher_reference(f)  # a run that did not finish is no teacher's reference
    # a summary whose fields are named by role (the reference run's own)
    f.write_text(json.dumps({"model": "rover", "transfer": "off", "limits": "learned", "role": "reference",
                             "reached_goal": True, "reference_time_s": 39.0, "reference_dev_last_half_m": 0.005,
                             "reference_collided": False, "vehicle_params": {"WP_SPEED": 0.36}}))
    got = teacher_reference(f)
    assert (got["time_s"], got["dev_last_half_m"], got["collided"]) == (39.0, 0.005, False)
    assert param_change("30:cruise_throttle=45") == (30.0, "CRUISE_THROTTLE", 45.0)
    for bad in ("30", "x:A=1", "-1:A=1", "5:=1", "5:A=nan"):
        with pytest.raises(UsageError):
            param_change(bad)


def half_s_path() -> MissionSpec:
    """The S-path's first bend (x <= 4 m: 4.8 m of arc, its start pose and the two obstacles beside that bend)."""
    spec = load_mission_spec(None)
    return MissionSpec(name="s-path-first-bend", frame=spec.frame, goal_tolerance=spec.goal_tolerance,
                       start=spec.start, path=[p for p in spec.path if p[0] <= 4.0],
                       obstacles=[o for o in spec.obstacles if o[0] <= 4.0])


def _binary() -> Path:
    binary = find_sitl()
    if binary is None:
        why = f"ArduPilot SITL not found at {where_sitl_is_looked_for()}: set SCMBRIDGE_SITL"
        if os.environ.get("SCMBRIDGE_SITL_REQUIRED"):
            pytest.fail(why)
        pytest.skip(why)
    return binary


@pytest.mark.sitl
@pytest.mark.timeout(60)
def test_the_weak_profile_makes_the_rover_fall_short_of_its_commands_as_its_table_says() -> None:
    """Two points of deploy/examples/sitl-weak.parm's table, measured again: speed and turn rate about half."""
    with Sitl(_binary(), model="rover-skid", parm_files=[ROOT / "deploy" / "examples" / "sitl-weak.parm"]) as sitl:
        pts = measure(sitl, [0.6], [0.0, 0.3], hold_s=4.0)
    straight, turning = pts
    assert 0.45 < straight.v_ratio < 0.65, straight  # table: 0.56
    assert 0.45 < turning.w_ratio < 0.65 and 0.45 < turning.v_ratio < 0.65, turning  # table: 0.58, 0.55


@pytest.mark.sitl
@pytest.mark.timeout(60)
def test_a_parameter_changed_mid_run_is_set_on_the_vehicle_at_its_time() -> None:
    """``--param-at``: the pilot's PARAM_SET, made at its time and confirmed by the vehicle's PARAM_VALUE."""
    with Sitl(_binary(), model="rover-skid", parm_files=[ROOT / "deploy" / "examples" / "sitl-weak.parm"]) as sitl:
        pilot = sitl.pilot
        assert pilot is not None and pilot.param("CRUISE_THROTTLE") == 65.0
        changes = ParamChanges(pilot, [param_change("0.5:CRUISE_THROTTLE=45")])
        t0 = time.monotonic()
        changes.start(t0)
        assert changes.finished.wait(15.0)
        changes.stop()
        (at, name, value, err), = changes.done
        assert (name, value, err) == ("CRUISE_THROTTLE", 45.0, "") and at >= t0 + 0.5
        assert pilot.param("CRUISE_THROTTLE") == 45.0


@pytest.mark.sitl
@pytest.mark.timeout(120)
def test_a_transfer_run_on_sitl_reaches_the_goal_of_the_first_bend_without_collision(tmp_path) -> None:
    """``scmbridge demo --sitl`` as a person runs it, with the weak profile, transfer on, from no pairs at all."""
    binary = _binary()
    mission = tmp_path / "mission.toml"
    mission.write_text(mission_toml(half_s_path()))
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "bridge", "demo", "--link", "mavlink", "--sitl", str(binary),
                           "--sitl-params", str(ROOT / "deploy" / "examples" / "sitl-weak.parm"), "--transfer", "on",
                           "--mission", str(mission), "--duration", "60", "--reference", "none", "--no-identify",
                           "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=100, cwd=ROOT)  # 45-47 s (3 runs)
    wall = time.monotonic() - t0
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("summary: ")]
    assert lines, f"no summary after {wall:.0f} s: {done.stdout[-1500:]}{done.stderr[-1500:]}"
    run = json.loads(lines[-1][len("summary: "):])
    assert run["role"] == "learner" and run["reached_goal"] and run["learner_collided"] is False, run
    assert not run["learner_left_corridor"] and run["learner_max_dev_m"] < run["corridor_m"], run
    # one verdict line per claim; without a reference the time and deviation are not judged, and say so
    verdicts = [ln for ln in done.stdout.splitlines() if ln.startswith("verdict ")]
    assert [ln.split()[1] for ln in verdicts] == ["goal:", "time:", "deviation:", "baseline:"], verdicts
    assert verdicts[0].startswith("verdict goal: PASS") and "n/a" in verdicts[1], verdicts
    assert run["verdicts"] == {"goal": True, "time": None, "deviation": None, "baseline": None}, run
    assert run["refined_pairs"] > 0 and run["method_counts"].get("perturb", 0) > 0, run  # it learned, as it drove
    # settled pairs only (the demo's pair_settle_s): the learned top speed is the profile's steady 0.34-0.35 m/s
    # (with every pair it was 0.17-0.32: the probe read SITL's speed lag part-way up)
    assert run["pair_settle_s"] > 0 and 0.3 < run["learned_limits"]["v"][1] < 0.4, run
    assert done.returncode == 0, done.stderr[-1500:]
    # what was learned, drawn as the other links' demo draws it (finding: a SITL run wrote no pairs figure)
    assert (tmp_path / "out" / "demo_pairs.png").stat().st_size > 0


def _demo(binary: Path, out: Path, *args: str) -> dict:
    """One ``scmbridge demo --sitl`` run as a person makes it (the paper's S-path), its summary; the learner's range
    read from the vehicle's parameters (``--no-identify``: these claims were measured so, the demo's hand-set
    settings of the Ackermann body with it; the identification, the default, is tests/integration/
    test_sitl_profiles.py's)."""
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "bridge", "demo", "--link", "mavlink", "--sitl", str(binary),
                           "--duration", "120", "--out", str(out), "--no-identify", *args],
                          capture_output=True, text=True, timeout=200, cwd=ROOT)  # 60-75 s each (quiet)
    wall = time.monotonic() - t0
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("summary: ")]
    assert lines, f"no summary after {wall:.0f} s: {done.stdout[-1500:]}{done.stderr[-1500:]}"
    return json.loads(lines[-1][len("summary: "):])


@pytest.mark.sitl
@pytest.mark.timeout(600)
def test_a_rover_that_cannot_turn_the_s_path_at_its_top_speed_follows_it_through_the_transfer_and_not_without(
        tmp_path) -> None:
    """The paper's claims on SITL (docs/BENCHMARKS.md, "The transfer on SITL", where the runs are): the teacher's
    reference (the stock rover given the weak rover's range), the transfer from no pairs, and the paper's baseline
    (the teacher's commands as they are), one after the other, the teacher's MPC slowing for the bends it learns the
    rover cannot turn at speed. Measured (3 runs): the transfer 0.77x the reference's last-half deviation (claim
    1.5x) in 1.22-1.23x its time (claim 1.25x; asserted here with room for a loaded machine: SITL runs in real
    time, and its first 10 s are the exploration from no pairs); the baseline 6.7-6.9x its deviation (claim: 2x, or
    a collision, or the goal missed)."""
    binary = _binary()
    ex = ROOT / "deploy" / "examples"
    ref = _demo(binary, tmp_path / "ref", "--sitl-params", str(ex / "sitl-teacher-weak-turn.parm"), "--transfer",
                "off", "--limits", "learned", "--curve-margin", "0.9")
    assert ref["role"] == "reference" and ref["reached_goal"] and ref["reference_collided"] is False, ref
    ref_json = str(tmp_path / "ref" / "summary.json")
    weak = ("--sitl-params", str(ex / "sitl-weak-turn.parm"), "--teacher-ref", ref_json)
    run = _demo(binary, tmp_path / "scm", *weak, "--curve-margin", "0.9")
    assert run["reference_time_s"] == ref["reference_time_s"] and run["curve_margin"] == 0.9, run
    assert run["reached_goal"] and run["learner_collided"] is False, run
    assert 0.15 < run["learned_limits"]["w"][1] < 0.22, run  # what the rover turns: 0.17-0.18 rad/s
    assert run["learner_dev_last_half_m"] <= 1.5 * run["reference_dev_last_half_m"], run
    assert run["learner_time_s"] <= 1.5 * run["reference_time_s"], run
    base = _demo(binary, tmp_path / "base", *weak, "--transfer", "off")
    assert base["transfer"] == "off" and base["role"] == "baseline", base
    assert (base["baseline_collided"] or not base["reached_goal"]
            or base["baseline_dev_last_half_m"] >= 2.0 * base["reference_dev_last_half_m"]), base


@pytest.mark.sitl
@pytest.mark.timeout(600)
def test_an_ackermann_rover_learns_that_it_cannot_turn_in_place_and_follows_the_s_path_through_the_transfer(
        tmp_path) -> None:
    """The same claims on SITL's Ackermann body (``--sitl-model rover``, deploy/examples/sitl-weak-ackermann.parm:
    its turn rate falls with its speed, and it reaches its top from rest in about 2 s), started on the path as a car
    is (the paper's start needs a turn on the spot). Its learned limits show that it cannot turn in place: a
    curvature on each side (the rover's full lock turns 0.85-0.94 rad/s per m/s), which bounds the teacher's MPC.
    The reference is the stock rover bounded by the speed the weak one reaches, its turn left to the path (``--turn
    in-place``: its own turn-rate loop gives 0.68-0.72 of what it is asked at these speeds, so bounded by the
    curvature it reaches it fell behind in the bends, 23 mm). Measured (docs/BENCHMARKS.md, "The transfer on SITL"):
    the transfer 1.17-1.22x the reference's time and 0.72-0.84x its deviation, the baseline 3.5x; in this test's
    passing runs (one alone, three beside other SITL runs) 1.21-1.23x and 0.81-1.36x, the baseline 4.0-4.3x (the
    three whose summaries were kept; BENCHMARKS has the run that failed, and why); after the first pair's side was
    mended (CHANGELOG), two runs side by side: 1.19-1.24x and 0.90-0.94x, both curvatures learned (-0.90 and
    0.86-0.94 rad/m)."""
    binary = _binary()
    ex = ROOT / "deploy" / "examples"
    ref = _demo(binary, tmp_path / "ref", "--sitl-model", "rover", "--sitl-params",
                str(ex / "sitl-teacher-ackermann.parm"), "--transfer", "off", "--limits", "learned", "--turn",
                "in-place", "--start", "on-path")
    assert ref["reached_goal"] and ref["reference_collided"] is False, ref
    assert ref["turn"] == "in-place" and ref["start"] == "on-path", ref
    weak = ("--sitl-model", "rover", "--sitl-params", str(ex / "sitl-weak-ackermann.parm"), "--teacher-ref",
            str(tmp_path / "ref" / "summary.json"))
    run = _demo(binary, tmp_path / "scm", *weak)
    assert run["turn"] == "needs-speed" and run["start"] == "on-path" and run["pair_settle_edge_s"] > 2, run
    assert run["reached_goal"] and run["learner_collided"] is False, run
    # it cannot turn in place: omega <= k v on each side (its first settled pairs are a bend each way; a run whose
    # first pair was a right turn once learned no right curvature: tests/unit/transfer/test_limits.py)
    k_lo, k_hi = run["learned_limits"].get("curvature", (None, None))  # none learned: the assertion below says so
    assert k_lo is not None and k_hi is not None and -1.3 < k_lo < -0.6 and 0.6 < k_hi < 1.3, run
    assert 0.3 < run["learned_limits"]["v"][1] < 0.4, run  # the probe of its top speed read settled: 0.36 m/s
    assert run["learner_dev_last_half_m"] <= 1.5 * run["reference_dev_last_half_m"], run
    assert run["learner_time_s"] <= 1.5 * run["reference_time_s"], run
    base = _demo(binary, tmp_path / "base", *weak, "--transfer", "off")
    assert (base["baseline_collided"] or not base["reached_goal"]
            or base["baseline_dev_last_half_m"] >= 2.0 * base["reference_dev_last_half_m"]), base
