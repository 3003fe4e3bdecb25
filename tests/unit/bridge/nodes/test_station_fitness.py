"""Whether the station may drive (bridge.nodes.station_fitness): pure, every time passed in, no Zenoh."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.nodes.sources import Why
from bridge.nodes.station_fitness import DRIVER_STATUS_MAX_AGE, assess_fitness, driver_estop, why_not_drive

AGE = 0.5  # the pose's largest age, s (the configuration's default)
POSE = M.LearnerState(stamp=1.0, seq=1, x=0.0, y=0.0, theta=0.0)


def _driver(ok: bool = True, state: str = "driving", reason: str | None = "ok", text: str = "") -> M.Status:
    return M.Status(stamp=1.0, seq=1, node="driver", ok=ok, state=state, reason=reason, text=text)


def test_a_fit_robot_has_no_reason_and_nothing_for_mission_control_to_pause_on() -> None:
    why, fitness = assess_fitness(10.0, POSE, 9.9, _driver(), 9.5, AGE)
    assert why is None
    assert (fitness.why, fitness.estop, fitness.immediate) == ("", False, False)


def test_each_reason_not_to_drive_in_order_of_what_is_checked_first() -> None:
    assert why_not_drive(10.0, POSE, 9.9, None, -np.inf, AGE) == Why("robot not ready: no driver host status",
                                                                      "robot_not_ready")
    assert why_not_drive(10.0, POSE, 9.9, _driver(False, text="link can: fault"), 9.5, AGE) == \
        Why("robot not ready: link can: fault", "robot_not_ready")
    assert why_not_drive(10.0, None, -np.inf, _driver(), 9.5, AGE) == Why("no pose yet", "no_telemetry")
    assert why_not_drive(10.0, POSE, 9.2, _driver(), 9.5, AGE) == Why("no pose for 0.8 s", "no_telemetry")
    assert why_not_drive(10.0, POSE, 10.0 - AGE, _driver(), 9.5, AGE) is None  # exactly the largest age: fresh


def test_a_driver_status_is_fresh_up_to_its_largest_age_and_stale_after_it() -> None:
    now = 100.0
    assert why_not_drive(now, POSE, now, _driver(), now - DRIVER_STATUS_MAX_AGE, AGE) is None
    late = why_not_drive(now, POSE, now, _driver(), now - DRIVER_STATUS_MAX_AGE - 0.01, AGE)
    assert late is not None and late.reason == "robot_not_ready" and "no driver host status" in late.text


@pytest.mark.parametrize(("driver", "driver_at", "immediate"), [
    (_driver(False, "estop", "estop", "estop latched by operator"), 9.9, True),  # the host refuses: pause at once
    (_driver(False, "fault", "fault", "link can: fault"), 9.9, True),
    (None, -np.inf, False),  # no host heard: late, not a refusal
    (_driver(False, "fault", "fault", "old news"), 10.0 - DRIVER_STATUS_MAX_AGE - 1.0, False),  # a stale refusal
    (_driver(), 9.9, False),  # the host is fine, the pose is late (below)
])
def test_only_a_fresh_refusal_by_the_driver_host_pauses_at_once(driver, driver_at, immediate) -> None:
    """The old code named this ``late`` and folded ``driver.ok`` into it: what it means is "the host refuses now".
    A status or a pose that is late pauses only after mission control's grace (PAUSE_AFTER_S)."""
    why, fitness = assess_fitness(10.0, POSE, 8.0, driver, driver_at, AGE)
    assert why is not None and fitness.why == why.text
    assert fitness.immediate is immediate


def test_an_estop_is_seen_by_the_typed_reason_or_an_old_hosts_state_never_the_words() -> None:
    assert driver_estop(_driver(False, "dry_run", "estop", "all fine"))
    assert driver_estop(_driver(False, "estop", "latch_unsaved"))
    assert not driver_estop(_driver(False, "fault", "fault", "estop latched"))
    assert driver_estop(_driver(False, "estop", None))  # a host older than the reason field
    assert not driver_estop(_driver(False, "fault", None, "estop"))
    _, fitness = assess_fitness(10.0, POSE, 9.9, _driver(False, "estop", "estop", "estop latched"), 9.9, AGE)
    assert fitness.estop and fitness.immediate
