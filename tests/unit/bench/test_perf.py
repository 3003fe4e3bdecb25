"""The regression guard (``scmbridge bench perf``) judges figures right, and ``scmbridge bench estop`` runs end to
end. The judging is pure (given figures, no timing); the estop bench starts a real router and a real driver host,
bounded by its own ``--duration`` and by the timeouts here."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys

import pytest

from bench.perf import LIMIT_FACTOR, MAX_RATIO, calibration_ratio, figure, skipped, summary, verdict


def test_verdict_is_ok_to_target_warn_to_limit_and_fail_beyond() -> None:
    assert verdict(40.0, 50.0, 150.0) == "ok"
    assert verdict(50.0, 50.0, 150.0) == "ok"  # at the target is within it
    assert verdict(50.01, 50.0, 150.0) == "warn"
    assert verdict(150.0, 50.0, 150.0) == "warn"  # at the limit still passes (printed)
    assert verdict(150.01, 50.0, 150.0) == "fail"
    for missing in (None, float("nan"), float("inf")):  # a figure that was not measured proves nothing
        assert verdict(missing, 50.0, 150.0) == "fail"


def test_calibration_ratio_excuses_a_slow_machine_only_so_far() -> None:
    assert calibration_ratio(0.02, reference_s=0.02) == 1.0
    assert calibration_ratio(0.05, reference_s=0.02) == pytest.approx(2.5)
    assert calibration_ratio(0.01, reference_s=0.02) == 1.0  # a faster machine meets the plain targets
    assert calibration_ratio(1.0, reference_s=0.02) == MAX_RATIO  # too slow to judge kindly
    assert calibration_ratio(0.05, reference_s=0.02, cap=2.0) == 2.0
    assert calibration_ratio(float("nan"), reference_s=0.02) == 1.0
    assert calibration_ratio(0.0, reference_s=0.02) == 1.0


def test_figure_scales_target_and_limit_by_the_ratio() -> None:
    # 120 us on a machine 2x slower than the reference: target 100, limit 300: a warning, not a failure
    f = figure("scm_point_median", 120.0, "us", 50.0, ratio=2.0, n=60)
    assert (f["target"], f["limit"], f["verdict"]) == (100.0, 300.0, "warn")
    assert f["nominal_target"] == 50.0 and f["ratio"] == 2.0 and f["n"] == 60
    assert set(f) >= {"name", "value", "unit", "target", "limit", "verdict"}
    # the same figure on the reference machine is over 3x its target: it fails
    g = figure("scm_point_median", 151.0, "us", 50.0)
    assert (g["target"], g["limit"], g["verdict"]) == (50.0, 50.0 * LIMIT_FACTOR, "fail")
    assert "ratio" not in g  # uncalibrated figures say nothing of a ratio
    assert figure("estop", None, "ms", 50.0)["verdict"] == "fail"
    assert json.loads(json.dumps(f)) == f  # one JSON line each


def test_summary_fails_only_on_a_failed_figure() -> None:
    ok = figure("a", 1.0, "ms", 1.0)
    warn = figure("b", 2.0, "ms", 1.0)
    skip = skipped("c", "ms", 50.0, "strace is not installed")
    s = summary([ok, warn, skip], 12.34)
    assert s["verdict"] == "pass" and s["counts"] == {"ok": 1, "warn": 1, "fail": 0, "skipped": 1}
    assert s["warned"] == ["b"] and s["failed"] == [] and s["wall_s"] == 12.3
    s = summary([ok, figure("d", 3.5, "ms", 1.0)], 1.0)
    assert s["verdict"] == "fail" and s["failed"] == ["d"]


def _bench_estop(*args: str) -> dict:
    res = subprocess.run([sys.executable, "-m", "bridge", "bench", "estop", *args], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout)


def _check_case(case: dict, repeat: int) -> None:
    assert case["n"] == repeat and len(case["samples_ms"]) == repeat
    assert all(math.isfinite(x) and x > 0 for x in case["samples_ms"])
    assert case["median_ms"] <= case["max_ms"]


def test_bench_estop_runs_end_to_end_without_fsync_delay() -> None:
    out = _bench_estop("--fsync-delay", "0", "--repeat", "2")
    assert list(out["cases"]) == ["0"] and out["target_ms"] == 50.0
    _check_case(out["cases"]["0"], 2)


def test_bench_estop_delays_the_hosts_fsyncs_with_strace() -> None:
    if shutil.which("strace") is None:
        pytest.skip("strace is not installed: the delayed-fsync case of bench estop cannot run here")
    out = _bench_estop("--fsync-delay", "0.1", "--repeat", "1")
    case = out["cases"]["0.1"]
    if "skipped" in case:
        pytest.skip(f"bench estop skipped the delayed case here: {case['skipped']}")
    _check_case(case, 1)
    # the release and the estop each saved the latch: strace delayed those fsyncs (whatever the host's latency is)
    assert case["fsyncs_delayed"] >= 2
