"""bench/sitl.py: a profile's row from its demo summary, and the table. Its runs on SITL:
tests/integration/test_sitl_profiles.py (marked ``sitl``)."""

from __future__ import annotations

import json

import pytest

from bench import sitl as B
from sim_learner.sitl_profiles import family


def test_a_profile_meets_the_goal_only_if_every_claim_was_judged_and_held() -> None:
    """The row is read from the demo's output, its last summary line, with the verdicts the demo judged."""
    def log(verdicts: dict, worked: bool) -> str:
        return ("run learner: {}\nverdict goal: PASS x\nsummary: "
                + json.dumps({"verdicts": verdicts, "worked": worked, "learner_time_ratio": 1.1}) + "\nfigures: x\n")

    ok = B.judge(log({"goal": True, "time": True, "deviation": True, "baseline": True}, True))
    assert ok["worked"] is True and ok["why"] is None and ok["learner_time_ratio"] == 1.1
    slow = B.judge(log({"goal": True, "time": False, "deviation": True, "baseline": True}, False))
    assert slow["worked"] is False and slow["why"] == "time failed"
    unjudged = B.judge(log({"goal": True, "time": None, "deviation": None, "baseline": True}, True))
    assert unjudged["worked"] is False and "time not judged" in unjudged["why"]
    silent = B.judge("SITL did not boot\n")
    assert silent["worked"] is False and "no summary" in silent["why"]
    table = B.table([{"profile": "skid-00", "split": "heldout", **ok}, {"profile": "skid-01", **slow}]).splitlines()
    assert table[0].startswith("| profile | split |") and len(table) == 4 and "time failed" in table[3]


def test_a_profile_outside_the_methods_assumption_is_counted_apart_from_the_failures() -> None:
    s = {"verdicts": {"assumption": False, "goal": False, "time": False, "deviation": False, "baseline": True},
         "worked": False, "outside_assumption": "paused: outside the method's assumption: ..."}
    row = B.judge("summary: " + json.dumps(s) + "\n")
    assert row["worked"] is False and row["outside"] is True and "outside the method" in row["outside_assumption"]
    inside = B.judge("summary: " + json.dumps({"verdicts": {"assumption": True, "goal": True}, "worked": True}))
    assert inside["outside"] is False and inside["worked"] is True
    assert "| outside |" in B.table([row])


def test_the_demo_command_runs_the_profile_with_its_baseline_and_the_automatic_reference(tmp_path) -> None:
    p = family("ackermann")[2]
    cmd = B.demo_command(p, "/x/ardurover", tmp_path / "p.parm", tmp_path / "run", 120.0, None)
    assert cmd[cmd.index("--sitl-model") + 1] == "rover" and "--baseline" in cmd
    assert "--reference" not in cmd and "--teacher-ref" not in cmd  # the demo's default: auto
    assert "--identify" not in cmd and "--no-identify" not in cmd  # the demo's default: the range measured
    assert "--no-identify" in B.demo_command(p, "/x/ardurover", tmp_path / "p.parm", tmp_path / "run", 120.0, None,
                                             identify=False)
    with pytest.raises(ValueError):
        cmd.index("--transfer")  # the transfer, as a person runs it
