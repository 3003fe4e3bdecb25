"""``scmbridge doctor --link mavlink``'s judgements of a rover's parameters (bridge/tools/doctor_mavlink.py), each
with its fix; the whole check against ArduPilot's SITL is tests/integration/test_sitl_radio.py."""

from __future__ import annotations

from types import SimpleNamespace

from bridge.nodes.driver_config import load_driver
from bridge.tools.doctor_mavlink import check_arming, check_gcs_failsafe, check_guided_timeout, check_range
from drivers.mavlink.config import MavlinkLinkConfig

STOCK = {"FS_GCS_ENABLE": 0.0, "FS_GCS_TIMEOUT": 5.0, "FS_ACTION": 2.0, "FS_THR_ENABLE": 1.0, "MAV_GCS_SYSID": 255.0}


def _driver(tmp_path, text: str = ""):
    path = tmp_path / "driver.toml"
    path.write_text('robot = "rover1"\n' + text)
    return load_driver(path)


def test_the_gcs_failsafe_off_is_named_with_its_fix_and_whose_heartbeat_it_watches() -> None:
    (c, rc) = check_gcs_failsafe(MavlinkLinkConfig(), STOCK)
    assert c.level == "warn" and "FS_GCS_ENABLE 1, FS_ACTION 2 (Hold)" in c.text and "this host's" in c.text
    assert rc.level == "ok"
    companion = MavlinkLinkConfig(source_system=1, source_component=191)
    (c, _) = check_gcs_failsafe(companion, {**STOCK, "FS_GCS_ENABLE": 1.0})
    assert c.level == "ok" and "system 255's heartbeat (the ground station), not this host's" in c.text
    (c, _) = check_gcs_failsafe(companion, {**STOCK, "FS_GCS_ENABLE": 1.0, "FS_ACTION": 0.0})
    assert c.level == "warn" and "FS_ACTION 2" in c.text
    (_, rc) = check_gcs_failsafe(companion, {**STOCK, "FS_THR_ENABLE": 0.0})
    assert rc.level == "warn" and "FS_THR_ENABLE 1" in rc.text


def test_arming_checks_old_and_new_parameter_names() -> None:
    probe = SimpleNamespace(sys_status=None, texts=[])
    assert [c.level for c in check_arming(probe, {"ARMING_CHECK": 1.0, "ARMING_REQUIRE": 1.0})] == ["ok"]
    (c,) = check_arming(probe, {"ARMING_CHECK": 0.0})
    assert c.level == "warn" and "ARMING_CHECK 1" in c.text
    (c,) = check_arming(probe, {"ARMING_SKIPCHK": 0.0})
    assert c.level == "ok"
    levels = [(c.level, c.text) for c in check_arming(probe, {"ARMING_SKIPCHK": 4.0, "ARMING_REQUIRE": 0.0})]
    assert levels[0][0] == "warn" and "ARMING_SKIPCHK 0" in levels[0][1] and "ARMING_REQUIRE 1" in levels[1][1]
    failing = SimpleNamespace(sys_status=SimpleNamespace(onboard_control_sensors_present=0x10000000,
                                                         onboard_control_sensors_health=0),
                              texts=["PreArm: GPS 1: Bad fix"])
    last = check_arming(failing, {"ARMING_CHECK": 1.0})[-1]
    assert last.text == "the pre-arm checks fail now: PreArm: GPS 1: Bad fix"


def test_the_range_comes_from_wp_speed_and_the_turn_rate_cap_and_wider_hard_limits_are_named(tmp_path) -> None:
    p = {"WP_SPEED": 0.6, "CRUISE_SPEED": 2.0, "ATC_STR_RAT_MAX": 30.0}
    wide = _driver(tmp_path, "[driver.hard_limits]\nv = [-1.0, 1.0]\nw = [-1.0, 1.0]\n")
    ok, warn = check_range(p, wide)
    assert ok.level == "ok" and "v = [0.05, 0.6], w = [-0.5236, 0.5236]" in ok.text
    assert warn.level == "warn" and "v = [-0.6, 0.6], w = [-0.5236, 0.5236]" in warn.text
    narrow = _driver(tmp_path, "[driver.hard_limits]\nv = [-0.5, 0.5]\nw = [-0.5, 0.5]\n")
    assert [c.level for c in check_range(p, narrow)] == ["ok"]
    (c,) = check_range({**p, "WP_SPEED": 0.0}, narrow)  # 0: CRUISE_SPEED, as Rover does
    assert "v = [0.05, 2]" in c.text
    (c,) = check_range({"WP_SPEED": 0.6}, narrow)
    assert c.level == "warn" and "did not answer" in c.text


def test_the_deadman_must_act_before_guideds_own_timeout(tmp_path) -> None:
    assert check_guided_timeout(_driver(tmp_path)).level == "ok"
    assert check_guided_timeout(_driver(tmp_path, "[driver]\ncmd_timeout = 3.0\n")).level == "warn"


def test_a_gcs_failsafe_watching_this_host_faster_than_its_heartbeats_is_named() -> None:
    """A GCS failsafe watching this host with an FS_GCS_TIMEOUT within two of its HEARTBEAT periods holds a rover
    the host still drives (the emulated rover: tests/integration/test_mavlink_link.py); faster HEARTBEATs fix it."""
    on = {**STOCK, "FS_GCS_ENABLE": 1.0, "FS_GCS_TIMEOUT": 0.5}
    (c, _) = check_gcs_failsafe(MavlinkLinkConfig(), on)
    assert c.level == "warn" and "heartbeat_hz" in c.text and "holds the rover while this host drives" in c.text
    (c, _) = check_gcs_failsafe(MavlinkLinkConfig(heartbeat_hz=5.0), on)
    assert c.level == "ok"
    (c, _) = check_gcs_failsafe(MavlinkLinkConfig(source_system=1, source_component=191), on)
    assert c.level == "ok"  # it watches the ground station, not this host
