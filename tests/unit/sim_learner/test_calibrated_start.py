"""The paper's calibrated start in-process (its Jackal MPC run; docs/PAPER.md, "The calibrated start"): the MPC
case's learner calibrated on ``scmbridge calibrate``'s 5 x 5 grid first, then the mission, commands at a driven limit
mapped by the region just inside it. Most of the mission's driving commands are then SC-mapped, as the paper says,
where the uncalibrated run maps almost none by SC; the goal is reached either way. ``scmbridge demo --calibrate``
runs the same over a link (tests/integration/test_demo_calibrate.py)."""

from __future__ import annotations

from sim_learner.experiments import run_scm


def _scm_share(counts: dict[str, int]) -> float:
    driving = {m: n for m, n in counts.items() if m != "stop"}
    return driving.get("scm", 0) / max(1, sum(driving.values()))


def test_a_calibrated_start_maps_most_driving_commands_by_sc() -> None:
    calibrated, store = run_scm(0, True, calibrated=True)
    fresh, _ = run_scm(0, True)
    assert calibrated.reached and fresh.reached
    assert store.n_configured() >= 25  # the calibration's grid, each command a refined pair
    assert _scm_share(calibrated.method_counts()) >= 0.5 > _scm_share(fresh.method_counts())
