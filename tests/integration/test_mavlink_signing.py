"""MAVLink 2 signing that one forged packet cannot poison, and replays refused after the vehicle reboots.

Findings this answers (a hostile test, emulated links): pymavlink records a message's signing timestamp before it
checks the signature, so one packet with a wrong key and a far-future timestamp made every later genuine message
"too old" (the driver host's link stayed down >= 60 s; sent to the emulated rover, an estop then took 2.8 s); and
signed traffic recorded off the wire armed and drove a rebooted emulated rover within MAVLink's one-minute window.
docs/SECURITY.md has the pymavlink report. Real pymavlink framing over UDP on 127.0.0.1, free ports; the forged
packet, the recorded takeover and the rover that keeps its signing timestamp are bench.attack's (its rows send the
same).
"""

from __future__ import annotations

import json
import socket
import time

import pytest

from bench.attack_mavlink import boot_signing_rover, forged_heartbeat, rover_ready, send_frames, signer, takeover_frames
from bench.attack_rigs import until
from bridge.core.auth import make_key
from drivers import open_driver
from drivers.mavlink import MavlinkLinkConfig
from drivers.mavlink.client import verify_before_recording
from sim_learner.dynamics import mpc_learner
from sim_learner.mavlink_dialect import MAV
from sim_learner.mavlink_rover import GUIDED, MavlinkRover
from sim_learner.mavlink_signing import signing_wall_clock
from sim_learner.vehicle import SimVehicle


@pytest.fixture
def keys(tmp_path):
    good, other = tmp_path / "good.key", tmp_path / "other.key"
    return make_key(good), make_key(other), good


def test_pymavlink_alone_is_poisoned_by_one_forged_packet_and_the_wrapper_is_not(keys) -> None:
    """The defect on its own, then the project's fix on the same bytes (docs/SECURITY.md)."""
    key, other, _ = keys
    now = signing_wall_clock()
    genuine, g_out = signer(key, 1, 1, 0, now)
    forged = forged_heartbeat(1, 1, 0, key=other, now=now)
    for _ in range(3):
        genuine.heartbeat_send(MAV.MAV_TYPE_GROUND_ROVER, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)
    for fixed in (False, True):
        rx = MAV.MAVLink(None, srcSystem=255, srcComponent=190)
        rx.robust_parsing = True
        rx.signing.secret_key, rx.signing.timestamp = key, now
        if fixed:
            verify_before_recording(rx)
        got = [m for f in [forged, *g_out.frames] for m in (rx.parse_buffer(f) or [])
               if m.get_type() == "HEARTBEAT"]
        assert rx.signing.badsig_count >= 1
        assert len(got) == (3 if fixed else 0), (fixed, len(got))


def test_one_forged_packet_does_not_take_the_drivers_link_down(keys) -> None:
    key, other, key_file = keys
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with MavlinkRover(vehicle, init_s=0.1, ekf_position_s=0.2, signing_key=key) as rover:
        driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:127.0.0.1:{rover.port}", open_timeout=10.0,
                                                          heartbeat_timeout=1.5, signing_key_file=str(key_file)))
        try:
            driver.open(time.monotonic())
            driver.engage(time.monotonic())
            before = driver.health(time.monotonic()).detail.bad_signatures
            forged = forged_heartbeat(rover.sysid, rover.compid, 0, key=other)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # any source: udpout reads them all
                s.sendto(forged, driver.client.conn.port.getsockname())
            assert until(lambda: driver.health(time.monotonic()).detail.bad_signatures > before, 10.0,
                         lambda: driver.poll(time.monotonic()))
            poses: list = []
            # a window longer than heartbeat_timeout in which the link must NOT go down (it would be down by
            # then), and until more than 10 poses came (counted, not timed: a stalled process takes longer)
            t_next = t0 = time.monotonic()
            while (time.monotonic() - t0 < 2.0 or len(poses) <= 10) and time.monotonic() - t0 < 20.0:
                poses += driver.poll(time.monotonic())
                t_next += 0.02
                time.sleep(max(0.0, t_next - time.monotonic()))  # pacing: the host's 50 Hz poll
            h = driver.health(time.monotonic())
            assert h.ok and len(poses) > 10, h
            assert h.detail.bad_signatures == before + 1  # the forged packet, and no genuine message after it
            assert rover.armed and rover.custom_mode == GUIDED
        finally:
            driver.close()


def test_one_forged_packet_does_not_block_the_rover_and_a_stop_is_prompt(keys) -> None:
    key, other, key_file = keys
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with MavlinkRover(vehicle, init_s=0.1, ekf_position_s=0.2, signing_key=key) as rover:
        driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:127.0.0.1:{rover.port}", open_timeout=10.0,
                                                          signing_key_file=str(key_file)))
        try:
            driver.open(time.monotonic())
            driver.engage(time.monotonic())
            conn = driver.client.conn
            forged = forged_heartbeat(driver.config.source_system, conn.mav.srcComponent, conn.mav.signing.link_id,
                                      key=other, gcs=True)
            before = rover.bad_signatures
            conn.port.sendto(forged, ("127.0.0.1", rover.port))  # from the driver's own address
            assert until(lambda: rover.bad_signatures > before, 10.0)
            until(lambda: vehicle.advance(time.monotonic()).v > 0.1, 10.0,
                  lambda: (driver.send(0.4, 0.0, time.monotonic()), driver.poll(time.monotonic())))
            assert vehicle.advance(time.monotonic()).v > 0.1  # genuine set-points still drive it
            t0 = time.monotonic()
            assert until(lambda: vehicle.advance(time.monotonic()).v == 0.0, 10.0,
                         lambda: (driver.stop(time.monotonic()), driver.poll(time.monotonic())))
            assert time.monotonic() - t0 < 1.0  # braking at 2 m/s^2 from 0.4 m/s: 0.2 s, not seconds
            assert rover.bad_signatures == before + 2  # the forged packet (bad signature, then not accepted unsigned)
        finally:
            driver.close()


def _boot(key: bytes, port: int, store) -> tuple[MavlinkRover, SimVehicle]:
    rover, vehicle = boot_signing_rover(key, port, store)
    assert rover_ready(rover)  # booted: its origin, in MANUAL
    return rover, vehicle


def test_signed_traffic_replayed_after_the_rovers_reboot_is_refused(keys, tmp_path) -> None:
    key, _, _ = keys
    store = tmp_path / "rover-signing.json"
    rover, vehicle = _boot(key, 0, store)
    port = rover.port
    try:
        frames = takeover_frames(key, rover.sysid, rover.compid)  # GUIDED, arm, forward: signed now
        send_frames(frames, port)  # the genuine traffic, as the wire carried it: it takes the rover
        assert until(lambda: rover.armed and vehicle.distance > 0.0, 10.0)
        saves = rover.signing_saves
        assert rover.rc_arm(False)  # the person parks it: disarmed, the GPS's next time is saved at once
        assert until(lambda: rover.signing_saves > saves, 10.0)
    finally:
        rover.stop()
    rover, vehicle = _boot(key, port, store)  # rebooted: the same storage
    try:
        before = rover.bad_signatures
        send_frames(frames, port)
        assert until(lambda: rover.bad_signatures >= before + len(frames), 10.0)
        time.sleep(0.2)  # absence: refused frames must not take it later either (watched over a window)
        assert not rover.armed and rover.mode_name == "MANUAL" and vehicle.distance == 0.0
    finally:
        rover.stop()


def test_without_a_persisted_timestamp_the_same_replay_would_take_a_rebooted_rover(keys, tmp_path) -> None:
    """The control: a vehicle that forgets its timestamp (the attack as found) takes the recorded traffic."""
    key, _, _ = keys
    rover, _ = _boot(key, 0, None)
    port = rover.port
    frames = takeover_frames(key, rover.sysid, rover.compid)  # GUIDED, arm, forward: signed now
    rover.stop()
    rover, vehicle = _boot(key, port, None)
    try:
        send_frames(frames, port)
        assert until(lambda: rover.armed, 10.0)
    finally:
        rover.stop()


def test_the_stored_timestamp_is_the_keys_and_starts_a_minute_ahead(keys, tmp_path) -> None:
    """load_signing_key: one minute past the stored timestamp; a store saved for another key is not this key's."""
    key, other, _ = keys
    store = tmp_path / "rover-signing.json"
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    first = MavlinkRover(vehicle, signing_key=key, signing_store=store)
    assert first.signing_saves == 1 and oct(store.stat().st_mode & 0o777) == "0o600"
    saved = first.signing_timestamp
    again = MavlinkRover(vehicle, signing_key=key, signing_store=store)
    assert again.signing_timestamp == saved + 60 * 100_000
    rekeyed = MavlinkRover(vehicle, signing_key=other, signing_store=store)  # SETUP_SIGNING with a new key
    assert abs(rekeyed.signing_timestamp - signing_wall_clock()) < 100_000


def test_the_gps_time_is_saved_at_once_while_disarmed_and_not_while_armed(keys, tmp_path) -> None:
    """AP_RTC takes the GPS's time while the vehicle is disarmed (and its first time whenever), and each time
    raises the signing timestamp and saves it at once; while armed it does not, and only the 30 s save remains."""
    key, _, _ = keys
    store = tmp_path / "rover-signing.json"
    rover, _ = _boot(key, 0, store)
    try:
        saves = rover.signing_saves
        assert until(lambda: rover.signing_saves > saves + 2, 10.0)  # disarmed: at the GPS's rate
        assert rover.rc_arm(True)
        armed_saves = rover.signing_saves
        time.sleep(1.0)  # window: five GPS times, none taken while armed (a wait for nothing to happen)
        assert rover.signing_saves <= armed_saves + 1  # (one GPS time may have been under way as it armed)
        armed_saves = rover.signing_saves
        assert rover.rc_arm(False)
        assert until(lambda: rover.signing_saves > armed_saves, 10.0)
        stored = json.loads(store.read_text())["timestamp"]
        assert abs(stored - signing_wall_clock()) < 2 * 100_000  # the GPS's time, as saved
    finally:
        rover.stop()
