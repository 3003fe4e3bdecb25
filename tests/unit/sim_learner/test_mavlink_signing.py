"""The emulated rover's signing as ArduPilot keeps it (sim_learner/mavlink_signing.py): the GPS's time raises and
saves the timestamp while disarmed and not while armed; the C library's check order; the minute a new stream may
lag. The rover is built, not started (no socket): its scheduler's steps are called directly."""

from __future__ import annotations

import json
import time
from pathlib import Path

from sim_learner.dynamics import mpc_learner
from sim_learner.mavlink_rover import MavlinkRover
from sim_learner.mavlink_signing import GPS_PERIOD, SIGNING_BOOT_AHEAD, signing_wall_clock
from sim_learner.vehicle import SimVehicle

KEY = bytes(range(1, 33))


def _rover(store: Path) -> MavlinkRover:
    rover = MavlinkRover(SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic()), init_s=0.0,
                         ekf_position_s=0.0, signing_key=KEY, signing_store=store)
    rover._initialised = True  # booted (its scheduler would have done it at init_s)
    return rover


def test_the_gps_time_is_saved_while_disarmed_only_after_its_first(tmp_path: Path) -> None:
    store = tmp_path / "signing.json"
    rover = _rover(store)
    rover.mav.signing.timestamp = 1  # far behind the GPS's time
    rover.armed = True  # the first GPS time is taken even armed (AP_RTC has no source yet)
    now = rover.t0 + 1.0
    saves = rover.signing_saves
    rover._gps_update(now)
    assert rover.signing_saves == saves + 1 and abs(rover.signing_timestamp - signing_wall_clock()) < 100_000
    first = json.loads(store.read_text())["timestamp"]
    rover._gps_update(now + 1.5 * GPS_PERIOD)  # armed: the same source may not move the clock
    assert rover.signing_saves == saves + 1 and json.loads(store.read_text())["timestamp"] == first
    rover.armed = False
    time.sleep(0.02)  # (the wall clock moves on between two GPS times)
    rover._gps_update(now + 3 * GPS_PERIOD)
    assert rover.signing_saves == saves + 2 and json.loads(store.read_text())["timestamp"] > first


def test_a_rebooted_rover_starts_a_minute_past_the_saved_timestamp(tmp_path: Path) -> None:
    store = tmp_path / "signing.json"
    first = _rover(store)
    first._gps_update(first.t0 + 1.0)
    saved = json.loads(store.read_text())["timestamp"]
    assert _rover(store).signing_timestamp == saved + SIGNING_BOOT_AHEAD
