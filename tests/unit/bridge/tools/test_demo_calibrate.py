"""bridge/tools/demo_calibrate.py: ``scmbridge demo --calibrate``'s argument and checks, its bound on time and the
method shares of a summary (the calibrated start end to end: tests/integration/test_demo_calibrate.py)."""

from __future__ import annotations

import argparse

import pytest

from bridge.core.errors import UsageError
from bridge.tools.demo_calibrate import calibration_budget, method_shares


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
