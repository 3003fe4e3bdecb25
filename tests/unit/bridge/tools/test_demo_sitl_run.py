"""bridge/tools/demo_sitl_run.py: the automatic reference's parameter file (``scmbridge demo --sitl --reference
auto``). Its runs on SITL: tests/integration/test_demo_sitl.py (marked ``sitl``)."""

from __future__ import annotations

import math

import pytest

from bridge.tools.demo_sitl_run import reference_parm


def test_the_automatic_reference_is_the_stock_rover_bounded_by_what_the_run_learned_never_more() -> None:
    params = {"WP_SPEED": 0.0, "CRUISE_SPEED": 3.0, "ATC_STR_RAT_MAX": 30.0}
    text = reference_parm("rover-skid", {"v": [0.05, 0.35], "w": [-0.31, 0.29]}, params)
    got = dict(line.split() for line in text.splitlines() if not line.startswith("#"))
    assert float(got["WP_SPEED"]) == pytest.approx(0.35) and float(got["ATC_STR_RAT_MAX"]) == pytest.approx(
        math.degrees(0.29), abs=0.1)
    # nothing learned: the learner's own caps, never past the teacher's range (0.6 m/s, 45 deg/s)
    got = dict(line.split() for line in reference_parm("rover-skid", None, {**params, "ATC_STR_RAT_MAX": 120.0})
               .splitlines() if not line.startswith("#"))
    assert float(got["WP_SPEED"]) == pytest.approx(0.6) and float(got["ATC_STR_RAT_MAX"]) == pytest.approx(45.0)
    ack = reference_parm("rover", {"v": [0.05, 0.36], "w": [-0.2, 0.2]}, {**params, "WP_SPEED": 0.6})
    assert "ATC_STR_RAT_FF 1.5" in ack and "ATC_STR_RAT_MAX 30.0" in ack  # its command range, the loop raised


def test_the_runs_duration_waits_for_its_first_command_or_a_guards_stop_not_for_the_start_up() -> None:
    """A first start compiles the MPC's kernels: the run's --duration begins at its first command driven (the
    station and the driver host are given STARTUP_S more), and a mission a guard stopped before any command (outside
    the method's assumption) is not waited for."""
    import threading
    import time
    from types import SimpleNamespace

    from bridge.core import wire as M
    from bridge.tools.demo_sitl_run import STARTUP_S, started
    from bridge.tools.guard_log import GuardLog
    from bridge.tools.procs import Children

    assert STARTUP_S >= 60
    with Children() as kids:
        mon = SimpleNamespace(driving=threading.Event(), guards=GuardLog())
        threading.Timer(0.3, mon.driving.set).start()  # the first command, once the station is up
        assert started(mon, kids, 10.0) is True
        mon = SimpleNamespace(driving=threading.Event(), guards=GuardLog())
        mon.guards.note(M.Status(stamp=0.0, seq=1, node="station", ok=False, state="paused",
                                 reason="outside_assumption", text="paused: outside"), None)
        t0 = time.monotonic()
        assert started(mon, kids, 10.0) is False and time.monotonic() - t0 < 2.0
        t0 = time.monotonic()
        assert started(SimpleNamespace(driving=threading.Event(), guards=GuardLog()), kids, 0.5) is False
        assert 0.4 < time.monotonic() - t0 < 5.0
