"""``scmbridge demo --calibrate``: the paper's calibrated start on a link (docs/OPERATING.md, "The calibrated start
in the demo"): ``scmbridge calibrate`` drives its grid on the emulated learner through the demo's driver host, then
the station's mission starts from that store. Every process started here is stopped; every wait is bounded."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from bridge.nodes.station_tags import read_store
from bridge.tools.procs import Children


@pytest.mark.slow
@pytest.mark.timeout(420)
def test_the_demo_calibrates_then_drives_its_mission_from_the_calibrated_store(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    with Children() as kids:
        demo = kids.spawn(["demo", "--link", "can", "--calibrate", "3x3", "--duration", "120", "--out", str(out)],
                          subprocess.PIPE)
        try:
            stdout, _ = demo.communicate(timeout=380)
        except subprocess.TimeoutExpired:
            pytest.fail("the demo did not end within 380 s")
    text = stdout.decode()
    lines = [ln for ln in text.splitlines() if ln.startswith("summary: ")]
    assert demo.returncode == 0 and lines, text[-3000:]
    summary = json.loads(lines[0][len("summary: "):])
    assert summary["reached_goal"] and not summary["collided"], summary
    cal = summary["calibration"]
    assert cal["ok"] and "all 9 commands driven" in cal["line"], cal
    # the mission's figures count from after the calibration: no calibrate command among its methods
    assert "calibrate" not in summary["methods"] and summary["method_shares"], summary
    assert abs(sum(summary["method_shares"].values()) - 1.0) < 0.01
    # the paper's calibrated start: most driving commands SC-mapped (at_limit = "region": the calibrated
    # quadrilaterals map the commands at the learned limits, where the MPC drives)
    assert summary["method_shares"].get("scm", 0.0) >= 0.5, summary["method_shares"]
    store = read_store(out / "pairs.bin")  # the station's file, tagged as its own (bridge.nodes.station_tags)
    assert store.limits.bcnt_hi[0] > 0 and store.limits.bcnt_lo[1] > 0  # the calibration measured the limits
    assert (out / "demo_trajectory.png").stat().st_size > 10_000 and (out / "calibrate.log").exists()
    # the mission starts where the calibration left the robot (placed there, as `scmbridge mission place` does), so
    # its deviation is measured from the same start pose as an uncalibrated run's
    assert "@calibrated" in (out / "mission.toml").read_text() and summary["max_dev_m"] < 0.6, summary
