"""bridge/tools/sitl_verdict.py: a run's corridor from its own poses, its figures named by role, one verdict per claim
(docs/BENCHMARKS.md "The transfer on SITL")."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.tools import sitl_verdict as V

PATH = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0]])


def test_the_distance_to_the_path_is_to_its_nearest_segment_endpoints_included() -> None:
    d = V.path_distances(PATH, np.array([[2.0, 0.5], [5.0, 2.0], [-3.0, 4.0], [4.0, 4.0], [6.0, 7.0]]))
    assert d == pytest.approx([0.5, 1.0, 5.0, 0.0, math.hypot(2.0, 3.0)])
    assert V.corridor(PATH, np.array([[1.0, 0.2], [4.9, 3.0]])) == {
        "corridor_m": 1.0, "max_path_dist_m": 0.9, "left_corridor": False}
    assert V.corridor(PATH, np.array([[1.0, 0.2], [5.1, 3.0]]))["left_corridor"] is True


def test_a_run_has_its_role_by_what_drove_the_vehicle() -> None:
    assert V.role_of("on", None) == V.role_of("on", "teacher") == "learner"
    assert V.role_of("off", None) == V.role_of("off", "teacher") == "baseline"
    assert V.role_of("off", "learned") == "reference"
    f = V.role_fields("baseline", {"reached_goal": True, "time_s": 40.0, "dev_last_half_m": 0.02, "collided": False,
                                   "max_dev_m": 0.3, "left_corridor": False})
    assert f["baseline_time_s"] == 40.0 and f["baseline_dev_last_half_m"] == 0.02 and not any(
        k.startswith(("scm_", "learner_")) for k in f)


def fields(**kw: object) -> dict:
    base = {**V.role_fields("learner", {"reached_goal": True, "time_s": 45.0, "dev_last_half_m": 0.006,
                                        "collided": False, "max_dev_m": 0.3, "left_corridor": False}),
            "reference_time_s": 40.0, "reference_dev_last_half_m": 0.005, "corridor_m": 1.0}
    return {**base, **kw}


def by_claim(f: dict) -> dict:
    return {v["claim"]: v for v in V.verdicts(f)}


def test_each_claim_has_its_verdict_line_and_a_missing_run_is_not_judged() -> None:
    vs = by_claim(fields())
    assert vs["goal"]["ok"] and vs["time"]["ok"] and vs["deviation"]["ok"]
    assert vs["baseline"]["ok"] is None and "no baseline run" in vs["baseline"]["line"]
    assert "1.12x the reference's 40.0 s" in vs["time"]["line"] and "1.20x" in vs["deviation"]["line"]
    assert V.worked(list(vs.values())) is True
    assert V.verdict_text(vs["time"]).startswith("verdict time: PASS ")
    slow = by_claim(fields(learner_time_s=61.0, learner_dev_last_half_m=0.008))
    assert slow["time"]["ok"] is False and slow["deviation"]["ok"] is False
    assert V.worked(list(slow.values())) is False
    alone = by_claim(fields(reference_time_s=None, reference_dev_last_half_m=None))
    assert alone["time"]["ok"] is None and alone["deviation"]["ok"] is None
    assert V.verdict_text(alone["time"]).startswith("verdict time: n/a ")


def test_a_run_out_of_its_corridor_or_into_an_obstacle_fails_every_claim() -> None:
    out = by_claim(fields(learner_left_corridor=True, learner_max_dev_m=18.4))
    assert out["goal"]["ok"] is False and "left its 1 m corridor" in out["goal"]["line"]
    assert out["time"]["ok"] is False and out["deviation"]["ok"] is False
    hit = by_claim(fields(learner_collided=True))
    assert hit["goal"]["ok"] is False and "collided" in hit["goal"]["line"]


def test_against_the_baseline_half_its_deviation_or_a_baseline_that_failed() -> None:
    b = V.role_fields("baseline", {"reached_goal": True, "time_s": 40.0, "dev_last_half_m": 0.02,
                                   "collided": False, "max_dev_m": 0.3, "left_corridor": False})
    assert by_claim(fields(**b))["baseline"]["ok"] is True  # 6 mm against 20 mm: 0.30x
    assert by_claim(fields(**{**b, "baseline_dev_last_half_m": 0.01}))["baseline"]["ok"] is False  # 0.60x
    crashed = by_claim(fields(**{**b, "baseline_collided": True, "baseline_dev_last_half_m": 0.001}))
    assert crashed["baseline"]["ok"] is True and "the baseline collided" in crashed["baseline"]["line"]
    # a baseline run alone is judged as the subject, against the reference
    alone = by_claim({**b, "reference_time_s": 30.0, "reference_dev_last_half_m": 0.005})
    assert set(alone) == {"goal", "time", "deviation"} and alone["deviation"]["ok"] is False


def test_a_trajectory_moves_rigidly_into_another_runs_frame() -> None:
    traj = np.array([[1.0, 2.0, 0.3], [2.0, 2.0, 0.3]])
    np.testing.assert_allclose(V.into_frame(traj, (1.0, 2.0, 0.5), (1.0, 2.0, 0.5)), traj)
    moved = V.into_frame(traj, (1.0, 2.0, 0.0), (0.0, 0.0, math.pi / 2))
    np.testing.assert_allclose(moved[:, :2], [[0.0, 0.0], [0.0, 1.0]], atol=1e-12)


def test_a_run_stopped_outside_the_methods_assumption_says_so_and_a_checked_one_passes() -> None:
    text = "paused: outside the method's assumption: the path bends left at 0.73 rad/m (7.2 m along it); ..."
    out = by_claim(fields(learner_reached_goal=False, learner_time_s=None, outside_assumption=text,
                          assumption_checked=True))
    assert out["assumption"]["ok"] is False and "stopped inside its corridor" in out["assumption"]["line"]
    assert "0.73 rad/m" in out["assumption"]["line"]
    assert V.verdict_text(out["assumption"]).startswith("verdict assumption: OUTSIDE ")
    assert V.worked(list(out.values())) is False
    inside = by_claim(fields(assumption_checked=True))
    assert inside["assumption"]["ok"] is True and V.worked(list(inside.values())) is True
    assert "assumption" not in by_claim(fields())  # nothing measured of the turn: nothing said
