"""Each link's health is typed and pure: ``health(now)`` returns a new snapshot with the link's own frozen detail,
reads no clock, and the driver host's status carries the detail's counts under the same ``link_<name>`` keys as
before the detail was typed (what ``scmbridge status --json`` prints)."""

from __future__ import annotations

import dataclasses
import time

import pytest

import drivers
from bridge.nodes.driver_config import DriverConfig
from bridge.nodes.driver_host import DriverHost

#: the link counts a driver host's status carries, per link (``link_<name>``); an unopened MAVLink link has no
#: ``custom_mode`` yet (it comes with the first HEARTBEAT)
STATUS_KEYS = {
    "can": {"error_frames", "bus_failures", "reopens", "send_failures", "faults", "heartbeat_losses",
            "rejected_estimates", "resyncs", "stamp_fallbacks"},
    "mavlink": {"armed", "bad_signatures", "foreign", "setpoints_sent", "setpoints_withheld", "setpoints_deferred",
                "stray_acks", "reconnects", "link_losses", "invalid_values", "clock_restarts"},
    "udp": {"foreign", "unauthenticated", "state_gaps", "robot_restarts", "dropped_by_kernel", "clock_restarts",
            "stamp_fallbacks", "state_out_of_order", "state_seq_jump", "state_old_epoch", "state_foreign_epoch"},
}


def test_every_registered_link_has_its_status_keys_here() -> None:
    assert set(STATUS_KEYS) == set(drivers.LINKS)


@pytest.mark.parametrize("link", sorted(STATUS_KEYS))
def test_health_is_a_new_snapshot_with_a_frozen_typed_detail_and_reads_no_clock(
        link: str, monkeypatch: pytest.MonkeyPatch) -> None:
    driver = drivers.open_driver(link)

    def no_clock() -> float:
        raise AssertionError("health() read the clock")

    with monkeypatch.context() as m:
        m.setattr(time, "monotonic", no_clock)
        m.setattr(time, "time", no_clock)
        first, second = driver.health(100.0), driver.health(100.0)
    assert first == second and first is not second and not first.ok
    detail = first.detail
    assert dataclasses.is_dataclass(detail) and type(detail).__dataclass_params__.frozen
    with pytest.raises(dataclasses.FrozenInstanceError):
        detail.__setattr__(dataclasses.fields(detail)[0].name, 1)
    assert set(detail.status_counters()) == STATUS_KEYS[link]
    assert all(isinstance(v, int) and v >= 0 for v in detail.status_counters().values())


@pytest.mark.parametrize("link", sorted(STATUS_KEYS))
def test_the_driver_hosts_status_carries_the_links_counts_under_the_same_keys(link: str) -> None:
    host = DriverHost(DriverConfig(), link, drivers.open_driver(link), "r1", 50.0)
    now = time.monotonic()
    host.decide(now)
    counters = host.status(now).counters
    own = {"link_malformed", "link_errors"}  # the host's own copies of LinkHealth's common counts
    assert {k for k in counters if k.startswith("link_")} == {f"link_{k}" for k in STATUS_KEYS[link]} | own


def test_a_mavlink_vehicle_that_has_spoken_adds_its_mode_number() -> None:
    driver = drivers.open_driver("mavlink")
    driver.vehicle.custom_mode, driver.vehicle.armed = 15, True  # as a GUIDED, armed HEARTBEAT leaves them
    detail = driver.health(0.0).detail
    assert detail.mode == "GUIDED" and detail.status_counters()["custom_mode"] == 15
    assert detail.status_counters()["armed"] == 1
