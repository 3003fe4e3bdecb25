"""A vehicle nobody tuned for, end to end on ArduPilot's Rover SITL (marked ``sitl``, ``make test-sitl``): one
profile per frame drawn as the held-out half of ``scmbridge bench sitl`` is (sim_learner/sitl_profiles.py, from
the next seed: a vehicle of the same family that no benchmark figure was made on), run as a person runs the demo
(``--baseline``, the automatic reference, the identification): the learner's range measured before the transfer,
the paper's baseline and the teacher on SITL itself, each on a freshly booted SITL, and the run's verdict
(docs/BENCHMARKS.md "A family of vehicles"); and a car that cannot turn the path's bends, stopped inside its corridor
as outside the method's assumption."""

from __future__ import annotations

import json

import pytest

from bench.sitl import judge, run_profile
from sim_learner.sitl_profiles import SEED, family
from tests.integration.test_sitl import _sitl_binary

#: one profile per frame, from the family's next seed, with WP_SPEED set, and for the car a turn-rate loop with a cap
#: and a feed-forward like those of the held-out cars that reached their goal
PROFILES = {"skid": 1, "ackermann": 4}


@pytest.mark.sitl
@pytest.mark.timeout(1500)
@pytest.mark.parametrize("frame", list(PROFILES))
def test_an_unseen_rover_drives_its_mission_with_the_transfer_and_the_run_says_whether_it_worked(
        frame: str, tmp_path) -> None:
    profile = family(frame, seed=SEED + 1)[PROFILES[frame]]
    assert "WP_SPEED" in profile.params, profile
    row = run_profile(profile, str(_sitl_binary()), tmp_path, 120.0, None, identify=True)
    log = (tmp_path / "demo.log").read_text()
    assert "summary: " in log, log[-3000:]
    summary = json.loads([ln for ln in log.splitlines() if ln.startswith("summary: ")][-1][len("summary: "):])
    # all three ran, each on its own SITL, each summary named by its role
    for role in ("learner", "baseline", "reference"):
        sub = json.loads((tmp_path / "run" / {"learner": ".", "baseline": "baseline", "reference": "reference"}[role]
                          / "summary.json").read_text())
        assert sub["role"] == role if role != "learner" else sub["role"] == "learner", sub
    # one verdict line per claim, the same verdicts in the summary, and one figure of all three
    verdicts = [ln for ln in log.splitlines() if ln.startswith("verdict ")]
    claims = ["goal", "time", "deviation", "baseline"]
    if frame == "ackermann":  # a car's tightest turn was measured: whether the path is inside the assumption
        claims.insert(0, "assumption")
    assert [ln.split()[1] for ln in verdicts] == [f"{c}:" for c in claims], verdicts
    assert set(summary["verdicts"]) == set(claims), summary
    assert (tmp_path / "run" / "demo_compare.png").stat().st_size > 0
    # the range was measured, within what the vehicle accepts; a skid rover turns in place, a car does not
    ident = summary["identified"]
    assert summary["range"] == "measured" and ident["turns_in_place"] is (frame == "skid"), summary
    assert 0.1 <= summary["learner_bounds"][0][1] <= summary["accepted_bounds"][0][1] + 1e-6, summary
    assert summary["turn"] == ("in-place" if frame == "skid" else "needs-speed"), summary
    # every claim judged, and the goal's verdict is what the run did (a run out of its corridor did not reach it)
    assert summary["reference_reached_goal"], summary
    assert None not in summary["verdicts"].values(), summary
    reached = summary["learner_reached_goal"] and not summary["learner_collided"]
    assert summary["verdicts"]["goal"] is reached, summary
    assert not (summary["learner_left_corridor"] and summary["learner_reached_goal"]), summary
    assert row == {**row, **judge(log)}
    if frame == "skid":  # the transfer: the goal, without collision, inside its corridor
        assert reached and summary["learner_max_dev_m"] < summary["corridor_m"], summary
    else:  # inside the assumption, or stopped inside its corridor saying why
        assert summary["verdicts"]["assumption"] is (summary["outside_assumption"] is None), summary
        if summary["outside_assumption"]:
            assert not summary["learner_left_corridor"], summary
    # the car of the next seed did not reach its goal in the one run made (nor did most of the held-out cars:
    # docs/BENCHMARKS.md, "A family of vehicles"): the goal of the issue is not met there, and this test does not
    # claim it


#: a held-out car whose steering turns far less than the S-path's bends need (docs/BENCHMARKS.md, "A family of
#: vehicles": it drove out of its corridor before the station checked the method's assumption)
OUTSIDE = ("ackermann", 10)


@pytest.mark.sitl
@pytest.mark.timeout(600)
def test_a_car_that_cannot_turn_the_paths_bends_stops_inside_its_corridor_and_says_why(tmp_path) -> None:
    import subprocess
    import sys

    frame, index = OUTSIDE
    profile = family(frame)[index]
    parm = tmp_path / f"{profile.name}.parm"
    parm.write_text(profile.parm())
    done = subprocess.run([sys.executable, "-m", "bridge", "demo", "--link", "mavlink", "--sitl", str(_sitl_binary()),
                           "--sitl-model", profile.model, "--sitl-params", str(parm), "--reference", "none",
                           "--duration", "120", "--out", str(tmp_path / "run")],
                          capture_output=True, text=True, timeout=540)
    log = done.stdout
    assert "summary: " in log, (log + done.stderr)[-3000:]
    summary = json.loads([ln for ln in log.splitlines() if ln.startswith("summary: ")][-1][len("summary: "):])
    assert summary["range"] == "measured" and summary["assumption_checked"], summary  # measured by default
    outside = summary["outside_assumption"]
    assert outside and "outside the method's assumption" in outside and "rad/m" in outside, summary
    assert summary["verdicts"]["assumption"] is False and summary["worked"] is False, summary
    assert any(ln.startswith("verdict assumption: OUTSIDE ") for ln in log.splitlines()), log[-3000:]
    # stopped where it started, well inside its corridor, not driven into the bend it cannot turn
    assert not summary["learner_left_corridor"] and summary["learner_max_dev_m"] < 0.5, summary
    assert [g["reason"] for g in summary["guard_stops"]] == ["outside_assumption"], summary
    assert done.returncode == 1  # the goal was not reached
