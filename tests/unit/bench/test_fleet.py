"""``scmbridge bench fleet`` reports the tick alone beside the fleet: ``bench tick`` of as many robots as one station
process serves, and the fleet's CPU per robot-tick over it."""

from __future__ import annotations

import os

from bench.fleet import tick_alone


def test_the_tick_alone_is_measured_and_the_fleets_cost_put_over_it() -> None:
    level = {"station_cpu_ms_per_tick": 3.0}
    got = tick_alone(2, 10, level, dict(os.environ), ("--no-compile", "--tiles", "1"))
    alone = got["tick_alone"]
    assert "failed" not in alone, alone
    assert alone["robots"] == 2 and alone["ticks"] == 2 * 10
    assert alone["process_ms_per_tick"] > 0 and alone["tick_mean_ms"] > 0 and alone["tick_p99_ms"] > 0
    assert len(alone["reference_ratio"]) == 2 and min(alone["reference_ratio"]) > 0  # the load it was measured at
    assert got["fleet_over_tick"] == round(3.0 / alone["process_ms_per_tick"], 2)
    paced = got["tick_alone_paced"]  # the same ticks at a station's pace (cold between periods)
    assert "failed" not in paced, paced
    assert paced["robots"] == 2 and paced["ticks"] == 2 * 10 and paced["process_ms_per_tick"] > 0
    assert got["fleet_over_paced_tick"] == round(3.0 / paced["process_ms_per_tick"], 2)
    none = tick_alone(2, 10, {}, dict(os.environ), ("--no-compile", "--tiles", "1"))
    assert none["fleet_over_tick"] is None and none["fleet_over_paced_tick"] is None


def test_a_tick_alone_that_cannot_run_says_why() -> None:
    got = tick_alone(2, 10, {"station_cpu_ms_per_tick": 3.0}, dict(os.environ), ("--no-such-option",))
    assert "failed" in got["tick_alone"] and got.get("fleet_over_tick") is None and "tick_alone_paced" not in got
