"""``scmbridge bench figures`` (bench/figures.py): each job's figures are read from what its command really prints
(the outputs below have the commands' own formats), a job that printed nothing usable measured nothing, and
``--write`` replaces exactly the generated block of BENCHMARKS.md and one row of the changelog's table."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench import figures as F

PERF = "\n".join([
    json.dumps({"calibration": "scm", "reference_s": [0.02, 0.021], "reference_quiet_s": 0.0215, "ratio": 1.0}),
    json.dumps({"name": "scm_point_median", "value": 31.2, "unit": "us", "target": 50.0, "limit": 150.0,
                "verdict": "ok", "ratio": 1.0}),
    json.dumps({"name": "bridge_can_p99", "value": 1.5, "unit": "ms", "target": 5.0, "limit": 15.0, "verdict": "ok"}),
    json.dumps({"summary": True, "ok": 2}),
])


def test_perf_lines_become_rows_with_their_targets_and_verdicts() -> None:
    rows = F.read_perf(PERF)
    assert [r.name for r in rows] == ["scm_point_median", "bridge_can_p99"]
    assert rows[0].value == "31.2 us" and rows[0].claim.startswith("target 50 us, ok")
    with pytest.raises(ValueError, match="no figure"):
        F.read_perf("nothing here\n")


def test_the_demo_summary_line_gives_its_figures() -> None:
    s = {"reached_goal": True, "time_s": 41.2, "driving_s": 39.9, "methods": {"scm": 3, "direct": 9},
         "refined_pairs": 15, "raw_pairs": 380, "missed_deadlines": 0, "mean_dev_m": 0.0981}
    rows = {r.name: r.value for r in F.read_demo("driving...\nsummary: " + json.dumps(s) + "\n")}
    assert rows["demo_reached_goal"] == "True" and rows["demo_driving_s"] == "39.9"
    assert rows["demo_refined_pairs"] == "15" and rows["demo_methods"] == "scm=3 direct=9"
    with pytest.raises(ValueError, match="no summary"):
        F.read_demo("summary? none\n")


def _stats(med: float) -> dict:
    return {"median": med, "min": med * 0.9, "max": med * 1.1, "worst_seed": 3, "missing": []}


def test_a_sweeps_indented_summary_gives_medians_and_the_collided_or_missed_seeds() -> None:
    summary = {"seeds": [0, 1, 2], "policies": {"guided": {"stats": {
        "scm_time_ratio": _stats(1.05), "scm_dev_ratio": _stats(1.2), "collided_seeds": [], "no_goal_seeds": [2]}}}}
    out = "sweep 100%\n" + json.dumps(summary, indent=2) + "\n"
    rows = {r.name: r.value for r in F.read_mpc(out)}
    assert rows["mpc_guided_time_ratio"].startswith("1.05 [")
    assert rows["mpc_guided_collided_or_missed"] == "0 collided, 1 missed of 3"
    grid = {"stats": {"scm_to_baseline": _stats(0.106), "scm_region_fraction": _stats(0.76)}}
    rows = {r.name: r.value for r in F.read_grid(json.dumps(grid, indent=2))}
    assert rows["grid_scm_to_baseline"].startswith("0.106 [")


def test_the_fleets_levels_give_the_held_size_and_the_cpu_per_robot_tick() -> None:
    out = {"robots_held": 50, "levels": [{"robots": 50, "missed_fraction_worst": 0.004,
                                          "station_cpu_ms_per_tick": 0.93, "tick_p99_ms_worst": 41.0,
                                          "station_rss_mb_total": 560.0}]}
    rows = {r.name: r.value for r in F.read_fleet(json.dumps(out, indent=2))}
    assert rows["fleet_robots_held"] == "50" and rows["fleet_50_station_cpu_ms_per_tick"] == "0.93"
    out["robots_held"] = 100
    out["levels"].append({"robots": 100, "missed_fraction_worst": 0.0, "station_cpu_ms_per_tick": 0.97,
                          "tick_p99_ms_worst": 6.0, "station_rss_mb_total": 663.0})
    got = {r.name: r for r in F.read_fleet(json.dumps(out))}
    assert got["fleet_robots_held"].value == "100" and got["fleet_100_station_cpu_ms_per_tick"].value == "0.97"
    # the goal's target is the hundred robots' (at fifty a process's own cost is shared by half as many)
    assert got["fleet_100_station_cpu_ms_per_tick"].claim.startswith("<= 1 ms")
    assert not got["fleet_50_station_cpu_ms_per_tick"].claim


def test_a_failed_job_is_a_row_that_says_so_and_never_a_figure() -> None:
    job = F.Job("grid", ["sim", "grid"], F.read_grid, error="exit 2: boom")
    text = F.table([job], "2026-11-27 12:00", "0.3", "0.4")
    assert "| grid | not measured: exit 2: boom |" in text and "`scmbridge sim grid`" in text


def test_write_replaces_only_the_block_and_one_changelog_row(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    bench = tmp_path / "docs" / "BENCHMARKS.md"
    bench.write_text(f"# B\n\nbefore\n{F.BEGIN}\nold table\n{F.END}\nafter\n")
    log = tmp_path / "CHANGELOG.md"
    log.write_text("# C\n\n| figure (where it is now) | commit | when |\n|---|---|---|\n| other | abc | x |\n")
    F.write_docs("new table", "2026-11-27 12:00", root=tmp_path)
    F.write_docs("newer table", "2026-11-27 13:00", root=tmp_path)
    assert bench.read_text() == f"# B\n\nbefore\n{F.BEGIN}\nnewer table\n{F.END}\nafter\n"
    rows = [ln for ln in log.read_text().splitlines() if ln.startswith(f"| {F.CHANGELOG_ROW}")]
    assert len(rows) == 1 and rows[0].endswith("| 2026-11-27 13:00 UTC |")
    assert "| other | abc | x |" in log.read_text()


def test_an_unknown_job_is_refused_before_anything_runs() -> None:
    res = subprocess.run([sys.executable, "-m", "bridge", "bench", "figures", "--only", "nope"], capture_output=True,
                         text=True, timeout=60, cwd=F.ROOT)
    assert res.returncode == 2 and "unknown nope" in res.stderr
