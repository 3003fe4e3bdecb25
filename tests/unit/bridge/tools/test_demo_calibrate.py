"""bridge/tools/demo_calibrate.py: ``scmbridge demo --calibrate``'s argument and checks, its bound on time and the
method shares and deviations of a summary (the calibrated start end to end:
tests/integration/test_demo_calibrate.py)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from bridge.core.errors import UsageError
from bridge.tools.demo_calibrate import calibration_budget, deviations, method_shares
from transfer.teacher.path import Polyline


def test_method_shares_leave_stop_out_and_sum_to_one() -> None:
    shares = method_shares({"scm": 30, "barycentric": 10, "stop": 50})
    assert shares == {"scm": 0.75, "barycentric": 0.25} and list(shares) == ["scm", "barycentric"]
    assert method_shares({"stop": 3}) == {}
    assert calibration_budget(None) == 0.0 < calibration_budget((3, 3)) < calibration_budget((5, 5))


@pytest.mark.parametrize("argv", [["--calibrate", "5x5", "--count", "2"], ["--calibrate", "5x5", "--inprocess"],
                                  ["--calibrate", "3x3", "--robots", "a,b"]])
def test_calibrate_is_for_one_robot(argv: list[str]) -> None:
    from bridge.tools.demo import arguments, run

    ap = argparse.ArgumentParser()
    arguments(ap)
    with pytest.raises(UsageError, match="calibrates one robot"):
        run(ap.parse_args(argv))


def test_calibrate_takes_the_calibration_grids_form() -> None:
    from bridge.tools.demo import arguments

    ap = argparse.ArgumentParser()
    arguments(ap)
    assert ap.parse_args(["--calibrate", "5x5"]).calibrate == (5, 5)
    with pytest.raises(SystemExit):
        ap.parse_args(["--calibrate", "1x5"])


def test_on_sitl_each_calibration_command_is_held_past_the_pairs_settling(tmp_path) -> None:
    # a real firmware's pairs count only after the station's pair_settle_s: the default hold of 1 s would leave a
    # command one settled pair or none, and a cell needs k_min of them
    from bridge.core.config import load_station
    from bridge.tools.demo import transfer_table
    from bridge.tools.demo_calibrate import SITL_HOLD_AFTER_SETTLE_S, sitl_calibration_table

    path = tmp_path / "station.toml"
    path.write_text('robot = "r1"\n\n[station]\npair_settle_s = 0.9\n\n' + transfer_table("on", None)
                    + 'at_limit = "region"\n' + sitl_calibration_table(0.9))
    cfg = load_station(path)
    assert cfg.calibration.hold_s == pytest.approx(0.9 + SITL_HOLD_AFTER_SETTLE_S)
    assert cfg.calibration.hold_s - cfg.station.pair_settle_s >= 5 * 0.1  # k_min control intervals after settling
    assert cfg.transfer.at_limit == "region"
    assert calibration_budget((5, 5), cfg.calibration.hold_s) > calibration_budget((5, 5))


def test_the_deviations_of_a_run_and_of_its_last_half() -> None:
    # a straight 10 m path; the robot starts 0.3 m beside it and drives 0.1 m beside it from 2 m on: the mean over
    # the run counts the start, the last half's does not (the paper's reading), the maximum is the start's
    path = Polyline(np.array([[0.0, 0.0], [10.0, 0.0]]))
    x = np.linspace(0.0, 10.0, 101)
    y = np.where(x < 2.0, 0.3, 0.1)
    got = deviations(path, np.column_stack([x, y, np.zeros_like(x)]))
    assert got["max_dev_m"] == 0.3 and got["dev_last_half_m"] == 0.1
    assert got["mean_dev_m"] == round(float(np.mean(y)), 4) and got["mean_dev_m"] > 0.1
    assert deviations(path, np.array([[1.0, 0.2, 0.0]]))["dev_last_half_m"] is None  # not half-way yet
