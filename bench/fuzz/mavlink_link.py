"""The MAVLink inputs: datagrams at the driver's pymavlink parser (from a scripted vehicle) and at the emulated rover
(from a ground-station socket), BAD_DATA counted against the oracle's; afterwards the link must still drive."""

from __future__ import annotations

import math
import random
import struct
import time
from collections import Counter
from contextlib import ExitStack
from pathlib import Path

from bench.fuzz.harness import (
    LOCAL,
    Crashes,
    Tally,
    VehicleSpy,
    answering,
    drain,
    drive_link,
    new_vehicle,
    result,
    udp_socket,
    wait_until,
)
from bench.fuzz.mavlink_frames import (
    GUIDED,
    MAV_CMD_ARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_REQUEST_PROTOCOL_VERSION,
    VELOCITY_YAWRATE_MASK,
    MavMutator,
    MavOracle,
    gcs_templates,
    mav_parse,
    mav_parser,
    mavlink2,
    vehicle_templates,
)
from bridge.nodes.node import rss_mb


def mavlink_driver(n: int, seed: int, workdir: Path | None = None) -> dict:
    """MAVLink datagrams at the driver's pymavlink parser, from a scripted vehicle (a socket bound here that the
    driver opened GUIDED and armed): the driver must receive every message the oracle parser gets out of them
    and count exactly its BAD_DATA. What the driver sends meanwhile must be what it was told (or a stop); a valid
    GUIDED heartbeat afterwards and the driver's set-point reaches the vehicle again."""
    from drivers import open_driver
    from drivers.mavlink import MavlinkLinkConfig

    rng = random.Random(seed)
    L = mavlink2()
    t0, rss0, crashes = time.monotonic(), rss_mb(), Crashes()
    with crashes, ExitStack() as stack:
        fake = udp_socket()
        stack.callback(fake.close)
        enc = L.MAVLink(None, srcSystem=1, srcComponent=1)

        def heartbeat() -> bytes:
            return bytes(enc.heartbeat_encode(10, 3, 1 | 128, GUIDED, 4).pack(enc))

        asked = mav_parser()

        def vehicle(data: bytes) -> bytes:
            """A ready ArduPilot Rover as the driver's open() needs it: GUIDED and armed, every command
            acknowledged to its sender, position (an EKF origin) streaming."""
            out = heartbeat()
            for m in mav_parse(asked, data):
                if m.get_type() == "COMMAND_LONG":
                    out += bytes(enc.command_ack_encode(m.command, 0, 0, 0, m.get_srcSystem(),
                                                        m.get_srcComponent()).pack(enc))
            out += bytes(enc.local_position_ned_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(enc))
            return out + bytes(enc.attitude_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(enc))

        driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:{LOCAL}:{fake.getsockname()[1]}",
                                                          rate_hz=20, open_timeout=5.0))
        stack.callback(driver.close)
        with answering(fake, vehicle) as peer:
            driver.open(time.monotonic())
        addr = peer["addr"]
        time.sleep(0.1)  # the answers to the driver's last requests
        driver.poll(time.monotonic())
        drain(fake)
        rss0 = rss_mb()
        h0 = driver.health(time.monotonic())
        base = (h0.frames_received, h0.malformed)
        mut, oracle, tally = MavMutator(rng, vehicle_templates(rng)), MavOracle(vehicle=(1, 1)), Tally()
        sent = 0
        while sent < n:
            for _ in range(min(64, n - sent)):
                kind, data = mut.next()
                msgs = oracle.feed(data)
                tally.add(kind, any(m.get_type() == "BAD_DATA" or oracle.is_invalid(m) for m in msgs))
                fake.sendto(data, addr)
                sent += 1
            t_end = time.monotonic() + 5.0
            while time.monotonic() < t_end:
                try:
                    driver.poll(time.monotonic())
                except Exception as exc:
                    crashes.caught("poll", exc)
                    break
                # a BAD_DATA or invalid telemetry is malformed, every other message received
                h = driver.health(time.monotonic())
                if h.frames_received - base[0] + h.malformed - base[1] >= oracle.total:
                    break
                time.sleep(0.001)
            driver.send(0.2, 0.1, time.monotonic())
        h = driver.health(time.monotonic())
        got = {"messages": h.frames_received - base[0] + h.malformed - base[1], "bad_data": h.malformed - base[1]}
        want = {"messages": oracle.total, "bad_data": oracle.bad + oracle.invalid}
        out_parser = mav_parser()
        setpoints = [m for b, _ in drain(fake) for m in mav_parse(out_parser, b)
                     if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
        f32 = struct.unpack("<ff", struct.pack("<ff", 0.2, -0.1))
        wrong = sum((m.vx, m.yaw_rate) not in (f32, (0.0, 0.0)) for m in setpoints)
        rss1 = rss_mb()
        conn = getattr(driver, "conn", None)  # what the driver and its pymavlink connection keep
        kept = {"statustexts": len(getattr(driver, "statustexts", [])),
                "pymavlink_message_types": sum(len(st.messages) for st in getattr(conn, "sysid_state", {}).values()),
                "pymavlink_systems": len(getattr(conn, "sysid_state", {})),
                "pymavlink_params": sum(len(ps.params) for ps in getattr(conn, "param_state", {}).values())}
        # the vehicle says GUIDED and armed again, with a fresh position: the next set-point must reach it as told
        fake.sendto(vehicle(b""), addr)
        time.sleep(0.05)
        driver.poll(time.monotonic())
        driver.send(0.25, 0.0, time.monotonic())
        time.sleep(0.05)
        last = [m for b, _ in drain(fake) for m in mav_parse(out_parser, b)
                if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
        drive_ok = bool(last) and (last[-1].vx, last[-1].yaw_rate) == (0.25, 0.0)
    return result(sent, got["bad_data"], want["bad_data"], got == want, crashes, t0, (rss0, rss1),
                   "bench (driver in-process)", invalid_telemetry=oracle.invalid, got=got, want=want,
                   types=dict(oracle.types.most_common(12)),
                   kinds_sent_badly=tally.report(), kept_by_driver=kept,
                   vehicle={"setpoints": len(setpoints), "not_as_told": wrong, "ok": wrong == 0},
                   drives_after={"setpoint": [last[-1].vx, last[-1].yaw_rate] if last else None, "ok": drive_ok})


class _RoverLife:
    """One emulated rover and the ground-station socket that talks to it (GUIDED and armed), acknowledgements
    counted."""

    def __init__(self, spy: VehicleSpy) -> None:
        from sim_learner.mavlink_rover import MavlinkRover

        self.rover = MavlinkRover(spy.vehicle, wp_speed=2.0, str_rat_max=2.0).start()
        self.gcs = udp_socket()
        self.to = (LOCAL, self.rover.port)
        self.enc = mavlink2().MAVLink(None, srcSystem=255, srcComponent=190)
        self.reader = mav_parser()
        self.acks = 0
        for b in (self.pack(self.enc.heartbeat_encode(6, 8, 0, 0, 0)), self.command(MAV_CMD_DO_SET_MODE, 1, GUIDED),
                  self.command(MAV_CMD_ARM, 1)):
            self.send(b)
        wait_until(lambda: self.read_acks() >= 2, 5.0, 0.01)
        self.acks = 0

    def pack(self, msg) -> bytes:
        return bytes(msg.pack(self.enc))

    def command(self, cmd: int, p1: float = 0, p2: float = 0) -> bytes:
        return self.pack(self.enc.command_long_encode(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, 0))

    def setpoint(self, vx: float) -> bytes:
        return self.pack(self.enc.set_position_target_local_ned_encode(0, 1, 1, 8, VELOCITY_YAWRATE_MASK, 0, 0, 0, vx,
                                                                       0, 0, 0, 0, 0, 0, 0.0))

    def send(self, data: bytes) -> None:
        self.gcs.sendto(data, self.to)

    def read_acks(self) -> int:
        for data, _ in drain(self.gcs):
            self.acks += sum(m.get_type() == "COMMAND_ACK" for m in mav_parse(self.reader, data))
        return self.acks

    @property
    def alive(self) -> bool:
        t = self.rover._thread
        return t is not None and t.is_alive()

    def close(self) -> None:
        self.gcs.close()
        self.rover.stop()


def mavlink_rover(n: int, seed: int, workdir: Path | None = None) -> dict:
    """MAVLink datagrams at the emulated rover from a ground-station socket bound here (GUIDED and armed first),
    in batches: its BAD_DATA count must equal the oracle's, and every COMMAND_LONG it decodes is acknowledged (each
    batch ends with one and waits for all the acknowledgements); the vehicle never gets a non-finite command or one
    beyond WP_SPEED / ATC_STR_RAT_MAX. A rover whose thread dies is counted (with the exception), replaced by a new
    one, and the batch it died in is left out of the counts. Afterwards: what a NaN velocity set-point makes of the
    vehicle, and a real driver opens the rover (GUIDED, armed) and drives it."""
    from drivers import open_driver
    from drivers.mavlink import MavlinkLinkConfig

    rng = random.Random(seed)
    t0, crashes = time.monotonic(), Crashes()
    with crashes, ExitStack() as stack:
        spy = VehicleSpy(new_vehicle(), 2.0, 2.0)
        lives = [_RoverLife(spy)]
        stack.callback(lambda: lives[-1].close())
        life = lives[0]
        rss0 = rss_mb()
        mut, tally = MavMutator(rng, gcs_templates(rng), sysid=255, compid=190), Tally()
        oracle = MavOracle(vehicle=(life.rover.sysid, life.rover.compid))
        sent = lost = 0
        want = got = want_acks = got_acks = 0
        while sent < n:
            bad0, long0, rbad0, acks0 = oracle.bad, oracle.commands_for_vehicle, life.rover.bad, life.acks
            batch = 0
            for _ in range(min(64, n - sent)):
                kind, data = mut.next()
                msgs = oracle.feed(data)
                tally.add(kind, any(m.get_type() == "BAD_DATA" for m in msgs))
                life.send(data)
                batch += 1
            mark = life.command(MAV_CMD_REQUEST_PROTOCOL_VERSION)
            oracle.feed(mark)
            life.send(mark)
            sent += batch
            longs = oracle.commands_for_vehicle - long0  # ArduPilot acknowledges each COMMAND_LONG addressed to it
            wait_until(lambda w=acks0 + longs, lf=life: lf.read_acks() >= w or not lf.alive, 5.0, 0.001)
            if not life.alive:  # died in this batch: counted as a crash, the batch left out, a new rover
                lost += batch
                life.close()
                life = lives[-1] = _RoverLife(spy)
                continue
            want, got = want + oracle.bad - bad0, got + life.rover.bad - rbad0
            want_acks, got_acks = want_acks + longs, got_acks + life.acks - acks0
        rss1 = rss_mb()
        # what does a NaN velocity set-point do to the vehicle? (then a stop)
        for b in (life.command(MAV_CMD_DO_SET_MODE, 1, GUIDED), life.command(MAV_CMD_ARM, 1),
                  life.setpoint(math.nan)):
            life.send(b)
        time.sleep(0.2)
        nan_probe = {"vehicle_got": list(spy.last) if spy.last else None, "rover_alive": life.alive}
        life.send(life.setpoint(0.0))
        life.gcs.close()
        try:
            driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:{LOCAL}:{life.rover.port}", rate_hz=20,
                                                              open_timeout=5.0))
            stack.callback(driver.close)
            driver.open(time.monotonic())
            driver.engage(time.monotonic())  # a person's act: GUIDED and armed
            drive = drive_link(driver, spy, 0.25, crashes)
        except Exception as exc:
            crashes.caught("driver open", exc)
            drive = {"ok": False}
    signatures = Counter(crashes.events)
    return result(sent, got, want, got == want and got_acks == want_acks, crashes, t0, (rss0, rss1),
                   "bench (rover in-process)", crash_signatures=dict(signatures), lost_in_crashed_batches=lost,
                   command_acks={"want": want_acks, "got": got_acks}, types=dict(oracle.types.most_common(12)),
                   kinds_sent_badly=tally.report(), nonfinite_setpoints_sent=oracle.nonfinite_setpoints,
                   nan_setpoint=nan_probe, vehicle={**spy.report(), "ok": spy.ok}, drives_after=drive)
