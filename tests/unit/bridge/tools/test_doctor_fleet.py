"""doctor's lines about the robots (bridge/tools/doctor_fleet.py): where each driver host runs and its latch as it
holds it. Asking real driver hosts over Zenoh: tests/integration/test_doctor_fleet.py."""

from __future__ import annotations

from bridge.core import wire as M
from bridge.core.clock import machine
from bridge.tools.doctor_fleet import local_robots, robot_checks, where


def test_a_robot_on_another_machine_is_named_by_its_host() -> None:
    away = M.Status(stamp=0.0, seq=0, node="driver", state="waiting", text="link can: waiting for engage",
                    host="rover-pi/0123abcd")
    here = M.Status(stamp=0.0, seq=0, node="driver", state="estop", text="link can: estop latched", host=machine())
    assert where(away) == "host rover-pi" and where(here) == "this machine" and "did not say" in where(None)
    lines = robot_checks({"r1": [M.EstopState(stamp=0.0, node="driver-can", latched=False)]}, {"r1": away})
    assert lines == [("ok", "r1 (driver host on host rover-pi): estop released, as its driver host holds it; "
                            "state waiting: link can: waiting for engage")]


def test_a_latched_robot_and_one_that_did_not_answer_are_warnings_and_only_this_machines_are_local() -> None:
    here = M.Status(stamp=0.0, seq=0, node="driver", state="estop", text="link can: estop latched", host=machine())
    lines = dict((t.split(" ", 1)[0], lvl) for lvl, t in robot_checks(
        {"r1": [M.EstopState(stamp=0.0, node="driver-can", latched=True, source="alice")]}, {"r1": here, "r2": here}))
    assert lines == {"r1": "warn", "r2": "warn"}
    away = M.Status(stamp=0.0, seq=0, node="driver", host="elsewhere/1")
    assert local_robots({"r1": here, "r2": away, "r3": M.Status(stamp=0.0, seq=0, node="driver")}) == ["r1"]
