"""A vehicle nobody tuned for, end to end on ArduPilot's Rover SITL (marked ``sitl``, ``make test-sitl``): one
profile per frame drawn as the held-out half of ``scmbridge bench sitl`` is (sim_learner/sitl_profiles.py, from
the next seed: a vehicle of the same family that no benchmark figure was made on), run as a person runs the demo
(``--baseline``, the automatic reference, ``--identify``): the learner's range measured before the transfer, the
paper's baseline and the teacher on SITL itself, each on a freshly booted SITL, and the run's verdict
(docs/BENCHMARKS.md "A family of vehicles")."""

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
    assert [ln.split()[1] for ln in verdicts] == ["goal:", "time:", "deviation:", "baseline:"], verdicts
    assert set(summary["verdicts"]) == {"goal", "time", "deviation", "baseline"}, summary
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
    # the car of the next seed did not reach its goal in the one run made (nor did most of the held-out cars:
    # docs/BENCHMARKS.md, "A family of vehicles"): the goal of the issue is not met there, and this test does not
    # claim it
