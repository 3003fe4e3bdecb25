"""``scmbridge bench attack`` rows on MAVLink 2 signing (docs/SECURITY.md's attack table): a forged far-future
timestamp at the driver's client and on the driver's own stream to the emulated rover, and signed traffic replayed
after the rover's reboot; with the helpers the tests use (a pymavlink signer, forged HEARTBEATs, the takeover
frames, a rover booted with a signing store). pymavlink framing against the driver's MAVLink client and the emulated
rover (sim_learner/mavlink_rover.py), on loopback; each row's docstring gives its "before".
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from bench.attack_rigs import (
    Result,
    until,
)

TEN_YEARS = 10 * 365 * 86400 * 100_000  # in MAVLink signing units (10 us)


class Frames:
    """A pymavlink ``file`` that keeps the frames it is given."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def signer(key: bytes, sysid: int, compid: int, link_id: int, timestamp: int):
    """A MAVLink 2 sender of ``sysid/compid`` signing with ``key`` from ``timestamp``, link ``link_id``; its frames
    in the returned :class:`Frames` (the attack rows and tests/integration/test_mavlink_signing.py,
    tests/integration/test_sitl.py)."""
    from sim_learner.mavlink_dialect import mavutil_v2

    out = Frames()
    mav = mavutil_v2().mavlink.MAVLink(out, srcSystem=sysid, srcComponent=compid)
    mav.signing.secret_key, mav.signing.sign_outgoing = key, True
    mav.signing.link_id, mav.signing.timestamp = link_id, timestamp
    return mav, out


def forged_heartbeat(sysid: int, compid: int, link_id: int = 0, *, key: bytes = bytes(32), now: int | None = None,
                     gcs: bool = False) -> bytes:
    """One HEARTBEAT on the signing stream ``sysid/compid/link_id``, signed with a key that is not the link's
    (``key``, default all zeros) and stamped ten years ahead of ``now`` (default the signing wall clock): the packet
    that poisoned pymavlink's signing state (docs/SECURITY.md). A rover's heartbeat, or a ground station's (``gcs``)."""
    from sim_learner.mavlink_dialect import mavutil_v2
    from sim_learner.mavlink_signing import signing_wall_clock

    mav = mavutil_v2().mavlink
    forger, out = signer(key, sysid, compid, link_id, (signing_wall_clock() if now is None else now) + TEN_YEARS)
    if gcs:
        forger.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    else:
        forger.heartbeat_send(mav.MAV_TYPE_GROUND_ROVER, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)
    return out.frames[0]


def takeover_frames(key: bytes, sysid: int, compid: int) -> list[bytes]:
    """What a ground station (255/190, signing link 7) signed with ``key`` says now to take the vehicle
    ``sysid/compid`` over: GUIDED, arm, then ten forward set-points at 0.3 m/s; the frames, as the wire carries them
    (the recording a replay is made of)."""
    from sim_learner.mavlink_dialect import mavutil_v2
    from sim_learner.mavlink_rover import GUIDED
    from sim_learner.mavlink_signing import signing_wall_clock

    mav = mavutil_v2().mavlink
    gcs, out = signer(key, 255, 190, 7, signing_wall_clock())
    custom = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    gcs.command_long_send(sysid, compid, mav.MAV_CMD_DO_SET_MODE, 0, custom, GUIDED, 0, 0, 0, 0, 0)
    gcs.command_long_send(sysid, compid, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    for _ in range(10):
        gcs.set_position_target_local_ned_send(0, sysid, compid, mav.MAV_FRAME_BODY_NED, 0x05E7, 0, 0, 0, 0.3, 0, 0,
                                               0, 0, 0, 0, 0)
    return out.frames


def send_frames(frames: list[bytes], port: int) -> None:
    """``frames`` to 127.0.0.1:``port`` from a socket of their own, 5 ms apart (a replay of a recording)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for f in frames:
            s.sendto(f, ("127.0.0.1", port))
            time.sleep(0.005)


def boot_signing_rover(key: bytes, port: int, store: Path | None):
    """The emulated rover signing with ``key`` started on ``port`` (0: a free one) with its signing timestamp kept in
    ``store`` (None: forgotten at each boot), and the simulated vehicle it drives; waited for (3 s at most) until it
    has its origin and is in MANUAL (the caller checks it is)."""
    from sim_learner.dynamics import mpc_learner
    from sim_learner.mavlink_rover import MavlinkRover
    from sim_learner.vehicle import SimVehicle

    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    rover = MavlinkRover(vehicle, port=port, init_s=0.1, ekf_position_s=0.2, signing_key=key,
                         signing_store=store).start()  # ArduPilot's save period (30 s), its GPS time
    until(lambda: rover_ready(rover), 3.0)
    return rover, vehicle


def rover_ready(rover) -> bool:
    """Whether the emulated ``rover`` has its origin and is in MANUAL (booted, nobody took it yet)."""
    return rover.has_origin(time.monotonic()) and rover.mode_name == "MANUAL"


@contextmanager
def _signed_rover_and_driver(**link: float) -> Iterator[tuple[Any, Any, Any]]:
    """The emulated rover and the MAVLink driver on one signed link (a fresh key in a temporary directory), the
    driver opened and engaged: ``(vehicle, rover, driver)``; the driver closed and the rover stopped on the way
    out. ``link``: more of the driver's :class:`drivers.mavlink.MavlinkLinkConfig` (e.g. ``heartbeat_timeout``)."""
    from bridge.core.auth import make_key
    from drivers import open_driver
    from drivers.mavlink import MavlinkLinkConfig
    from sim_learner.dynamics import mpc_learner
    from sim_learner.mavlink_rover import MavlinkRover
    from sim_learner.vehicle import SimVehicle

    with tempfile.TemporaryDirectory() as d:
        key_file = Path(d) / "mav.key"
        key = make_key(key_file)
        vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
        with MavlinkRover(vehicle, init_s=0.1, ekf_position_s=0.2, signing_key=key) as rover:
            driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:127.0.0.1:{rover.port}", open_timeout=10.0,
                                                              signing_key_file=str(key_file), **link))
            try:
                driver.open(time.monotonic())
                driver.engage(time.monotonic())
                yield vehicle, rover, driver
            finally:
                driver.close()


def mavlink_forged_timestamp_at_driver(short: bool) -> Result:
    """One packet signed with a wrong key and a timestamp ten years ahead, sent to the driver's MAVLink client on a
    signed link to the emulated rover: the driver must keep hearing the rover (pymavlink records a stream's
    timestamp before it checks the signature; drivers/mavlink/client.verify_before_recording puts it back).
    before (the wrapper off, --short): no pose heard after it, the link down ("no heartbeat for 1.4 s"), 52
    genuine messages refused as bad signatures."""
    import socket

    with _signed_rover_and_driver(heartbeat_timeout=1.0) as (_vehicle, rover, driver):
        forged = forged_heartbeat(rover.sysid, rover.compid)
        before = driver.health(time.monotonic()).detail.bad_signatures
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # udpout reads from any source
            s.sendto(forged, driver.client.conn.port.getsockname())
        until(lambda: driver.health(time.monotonic()).detail.bad_signatures > before, 2.0,
              lambda: driver.poll(time.monotonic()))
        poses = 0
        t_end = time.monotonic() + (1.3 if short else 2.5)  # past the 1 s heartbeat timeout
        while time.monotonic() < t_end:
            poses += len(driver.poll(time.monotonic()))
            time.sleep(0.02)
        h = driver.health(time.monotonic())
    return {"reached_vehicle": None, "learned": None,
            "link": {"ok": h.ok, "text": h.text, "poses_after_forgery": poses,
                     "bad_signatures": h.detail.bad_signatures - before},
            "ok": h.ok and poses > 10}


def mavlink_forged_timestamp_at_rover(short: bool) -> Result:
    """The driver drives the emulated rover at 0.4 m/s on a signed link; the same forged packet is sent to the rover
    from the driver's own address on the driver's signing stream; then the driver's genuine stop must reach the rover
    promptly (the rover checks in the C library's order: signature, then timestamp). before (pymavlink's order in
    the rover, --short): the rover stood after 3.05 s (it refused the driver's stream; its GUIDED timeout stopped
    it), after: 0.17 s."""
    with _signed_rover_and_driver() as (vehicle, rover, driver):
        conn = driver.client.conn
        forged = forged_heartbeat(driver.config.source_system, conn.mav.srcComponent,
                                  conn.mav.signing.link_id, gcs=True)
        t_end = time.monotonic() + 0.5
        while time.monotonic() < t_end:  # the genuine station drives it
            driver.send(0.4, 0.0, time.monotonic())
            driver.poll(time.monotonic())
            time.sleep(0.02)
        speed = round(vehicle.advance(time.monotonic()).v, 3)
        bad = rover.bad_signatures
        conn.port.sendto(forged, ("127.0.0.1", rover.port))  # from the driver's own address
        until(lambda: rover.bad_signatures > bad, 2.0)
        t0 = time.monotonic()  # the genuine stop, sent each poll until the rover stands
        stopped = until(lambda: vehicle.advance(time.monotonic()).v == 0.0, 4.0,
                         lambda: (driver.stop(time.monotonic()), driver.poll(time.monotonic())))
        stop_s = round(time.monotonic() - t0, 2)
    return {"reached_vehicle": {"speed_before_stop": speed, "stop_s": stop_s, "stopped": stopped}, "learned": None,
            "ok": stopped and stop_s < 1.0 and speed > 0.1}


def mavlink_replay_after_reboot(short: bool) -> Result:
    """Signed traffic of a ground station (GUIDED, arm, a forward set-point) recorded off the wire while it took the
    emulated rover; the person disarms it; the rover reboots and the recording is replayed. The rover saves its
    signing timestamp as ArduPilot does (every 30 s; at once at each GPS time while disarmed) and starts a minute
    past it, so the recording is too old. before (no store: a rover that forgets its timestamp at boot, as the
    emulated rover did on 791b027; --short): armed, GUIDED, 0.014 m in 0.3 s; and with the store but the GPS's
    time saved only once at boot (the emulator before it followed AP_RTC): the recording was taken again."""
    from bridge.core.auth import make_key

    with tempfile.TemporaryDirectory() as d:
        key = make_key(Path(d) / "mav.key")
        store = Path(d) / "rover-signing.json"
        rover, vehicle = boot_signing_rover(key, 0, store)
        port = rover.port
        try:
            frames = takeover_frames(key, rover.sysid, rover.compid)
            send_frames(frames, port)  # the genuine traffic, as the wire carried it: it takes the rover
            potent = until(lambda: rover.armed and vehicle.distance > 0.0, 2.0)
            saves = rover.signing_saves
            rover.rc_arm(False)  # the person parks it (the transmitter's switch): disarmed, the GPS's time is saved
            until(lambda: rover.signing_saves > saves, 3.0)
        finally:
            rover.stop()
        rover, vehicle = boot_signing_rover(key, port, store)  # rebooted: the same storage
        try:
            bad = rover.bad_signatures
            send_frames(frames, port)
            until(lambda: rover.bad_signatures >= bad + len(frames) or rover.armed, 2.0)
            time.sleep(0.3 if short else 1.0)
            reached = {"armed": rover.armed, "mode": rover.mode_name, "distance_m": round(vehicle.distance, 3)}
            refused = rover.bad_signatures - bad
        finally:
            rover.stop()
    return {"reached_vehicle": reached, "learned": None, "recording_took_the_rover": potent, "refused": refused,
            "ok": potent and not reached["armed"] and reached["distance_m"] == 0.0 and reached["mode"] == "MANUAL"}
