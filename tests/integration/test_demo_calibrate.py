"""``scmbridge demo --calibrate``: the paper's calibrated start on a link (docs/OPERATING.md, "The calibrated start
in the demo"): ``scmbridge calibrate`` drives its grid on the emulated learner through the demo's driver host, then
the station's mission starts from that store. Every process started here is stopped; every wait is bounded.

Kept quick for ``make test``: the smallest calibration grid (2 x 2, the learner's four extreme commands: the corners of
its range, which the calibrated start is about) and the paper's S-path up to its first bend (the start's turn on the
spot and one bend, past the first obstacle): the same stages, assertions and summary as the full mission."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import msgspec
import pytest

from bridge.core.config import load_mission_spec
from bridge.nodes.station_tags import read_store
from bridge.tools.demo_sitl import mission_toml
from bridge.tools.procs import Children


def _first_bend(path: Path) -> Path:
    """The shipped S-path up to its first bend (x <= 2.6 m) with the obstacles beside that part, as a mission file."""
    spec = load_mission_spec(None)
    short = msgspec.structs.replace(spec, name="paper-s-path-first-bend", path=[p for p in spec.path if p[0] <= 2.6],
                                    obstacles=[o for o in spec.obstacles if o[0] - o[2] < 2.8])
    path.write_text(mission_toml(short))
    return path


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_the_demo_calibrates_then_drives_its_mission_from_the_calibrated_store(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    mission = _first_bend(tmp_path / "first-bend.toml")
    with Children() as kids:
        demo = kids.spawn(["demo", "--link", "can", "--calibrate", "2x2", "--mission", str(mission), "--duration", "60",
                           "--out", str(out)], subprocess.PIPE)
        try:
            stdout, _ = demo.communicate(timeout=200)
        except subprocess.TimeoutExpired:
            pytest.fail("the demo did not end within 200 s")
    text = stdout.decode()
    lines = [ln for ln in text.splitlines() if ln.startswith("summary: ")]
    assert demo.returncode == 0 and lines, text[-3000:]
    summary = json.loads(lines[0][len("summary: "):])
    assert summary["reached_goal"] and not summary["collided"], summary
    cal = summary["calibration"]
    assert cal["ok"] and "all 4 commands driven" in cal["line"], cal
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
