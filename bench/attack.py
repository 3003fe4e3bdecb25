"""``scmbridge bench attack``: every attack a hostile probe found, run against the real components (JSON).

Each attack sets up what it needs (the emulated devices on loopback or a python-can ``virtual`` channel, the real
drivers, the driver host's gate and latch, the station's pairer and pair store, the clock estimate; for the trust
attacks real UDP sockets and a man in the middle, pymavlink framing, a real DriverHost on a real state directory,
real Zenoh sessions) and reports what reached the vehicle and what was learned:

``{"attack": name, "reached_vehicle": ..., "learned": ..., "ok": bool, ...}``; ``ok`` means nothing unsafe moved a
vehicle and nothing implausible was learned. ``--short`` runs each attack briefly (the suite runs it so). The last
line of the JSON is ``"all_ok"``. docs/SECURITY.md's attack table quotes it.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bench.attack_rigs import (
    Result,
    Tap,
    _LatchRig,
    _Station,
    _ZenohHost,
    distance_from,
    drive_udp,
    position,
    tapped_driver,
    udp_robot,
    until,
)
from bench.common import emit


def forged_command_in_epoch(short: bool) -> Result:
    """A forged Command with the station's epoch and seq + 135, stamped 90 ms after a real one (the epoch is
    readable off an open network): applied? how long is the real station locked out?"""
    from bridge.core import wire as M
    from bridge.core.gate import CommandGate
    from bridge.nodes.driver_config import DEFAULT_HARD_LIMITS, DriverSection

    g = CommandGate(DEFAULT_HARD_LIMITS.bounds(), cmd_timeout=DriverSection().cmd_timeout)
    epoch, t = 0x5EED, 100.0
    forged_applied, locked = 0, 0
    for k in range(40 if short else 400):
        seq = k + 1
        t += 0.1
        g.offer(M.Command(stamp=t, seq=seq, v=0.2, omega=0.0, method="scm", epoch=epoch), t + 0.002)
        if g.decide(t + 0.002).cmd_seq != seq:
            locked += 1
        if k % 10 == 5:
            forged = M.Command(stamp=t + 0.09, seq=seq + 135, v=0.5, omega=1.0, method="scm", epoch=epoch)
            g.offer(forged, t + 0.09)
            d = g.decide(t + 0.09)
            forged_applied += d.driving and d.v == 0.5
    return {"reached_vehicle": {"forged_commands_applied": forged_applied, "real_commands_locked_out": locked},
            "learned": None, "conflict_reported": g.conflict(t + 0.1) is not None,
            "ok": forged_applied == 0 and locked == 0}


def unsealed_command(driver, k: int = 0, v: float = 0.95) -> bytes:
    """A Command datagram a forger makes without the key: unsealed, with the real UDP ``driver``'s epoch and its next
    seq (+ ``k``), both readable off an open network, at ``v`` m/s (0.95: within the robot's own limit of 1.0)."""
    from bridge.core import wire as M

    return M.encode(M.Command(stamp=time.monotonic(), seq=driver.seq + 1 + k, v=v, omega=0.0, method="scm",
                              valid_ms=300, sender="driver", epoch=driver.epoch))


def spoof_from(robot, data: bytes, source: tuple[str, int]) -> None:
    """``data`` handled by the emulated UDP ``robot`` as if it came from ``source`` (the driver's address: an attacker
    on its segment, which pinning an address and port does not stop)."""
    with robot._lock:
        robot._handle(data, source, time.monotonic())


def udp_spoof(short: bool) -> Result:
    """An unsealed Command (v = 0.95, the robot's own limit 1.0) from the driver's own address and epoch."""
    from bridge.core.auth import make_key
    from bridge.tools.procs import free_udp_port
    from drivers import open_driver
    from drivers.udp import UdpLinkConfig
    from sim_learner.dynamics import mpc_learner
    from sim_learner.udp_robot import UdpRobot
    from sim_learner.vehicle import SimVehicle

    with tempfile.TemporaryDirectory() as d:
        key = Path(d) / "udp.key"
        secret = make_key(key)
        vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
        bind = free_udp_port()
        with UdpRobot(vehicle, peer=("127.0.0.1", bind), key=secret) as robot:
            driver = open_driver("udp", UdpLinkConfig(robot_port=robot.port, bind_port=bind, key_file=str(key)))
            try:
                driver.open(time.monotonic())
                for k in range(5 if short else 50):
                    spoof_from(robot, unsealed_command(driver, k), ("127.0.0.1", bind))
                moved = vehicle.distance
                refused = robot.counters["unauthenticated"]
            finally:
                driver.close()
    return {"reached_vehicle": {"distance_m": moved}, "learned": None, "refused": refused,
            "ok": moved == 0.0 and refused > 0}


def mavlink_unsigned(short: bool) -> Result:
    """Unsigned set-points and an arming command from another ground station to a rover with signing set up."""
    from sim_learner.dynamics import mpc_learner
    from sim_learner.mavlink_dialect import mavutil_v2
    from sim_learner.mavlink_rover import MavlinkRover
    from sim_learner.vehicle import SimVehicle

    mavutil = mavutil_v2()
    mav = mavutil.mavlink
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    rover = MavlinkRover(vehicle, init_s=0.2, ekf_position_s=0.4, signing_key=bytes(range(32))).start()
    try:
        gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{rover.port}", source_system=255)
        for _ in range(3 if short else 20):
            gcs.mav.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 15,
                                      0, 0, 0, 0, 0)
            gcs.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
            gcs.mav.set_position_target_local_ned_send(0, 1, 1, mav.MAV_FRAME_BODY_NED, 0x05E7, 0, 0, 0, 1.0, 0, 0,
                                                       0, 0, 0, 0, 0.5)
            time.sleep(0.1)
        time.sleep(0.3)
        gcs.close()
        result = {"reached_vehicle": {"distance_m": vehicle.distance, "armed": rover.armed, "mode": rover.mode_name,
                                      "commands_handled": len(rover.commands)},
                  "learned": None, "refused": rover.bad_signatures}
    finally:
        rover.stop()
    result["ok"] = (result["reached_vehicle"]["distance_m"] == 0.0 and not result["reached_vehicle"]["armed"]
                    and result["reached_vehicle"]["commands_handled"] == 0)
    return result


def estop_forgotten_on_restart(short: bool) -> Result:
    """An operator's estop, confirmed (the host answers the estop query once the latch is saved), then the driver
    host dies and is restarted (as systemd does). The first host's save is waited for: without it the restart raced
    the first host's writer thread (an estop not yet confirmed can be lost by a SIGKILL within milliseconds), and the
    temporary directory could go before the save."""
    from bridge.core import wire as M
    from bridge.nodes.driver_config import DriverConfig
    from bridge.nodes.driver_host import DriverHost

    class _NoLink:  # the host's gate and latch are what is attacked; no link is opened
        name = "none"

    with tempfile.TemporaryDirectory() as d:
        latch = Path(d) / "estop.bin"
        first = DriverHost(DriverConfig(), "can", _NoLink(), "r1", 50.0, latch_path=latch)
        first.on_estop(M.Estop(stamp=1.0, engaged=True, source="operator", reason="attack"), 1.0)
        assert first.latch.close(5.0)  # confirmed, then the host dies
        second = DriverHost(DriverConfig(), "can", _NoLink(), "r1", 50.0, latch_path=latch)
        second.engaged = True
        second.gate.offer(M.Command(stamp=2.0, seq=1, v=0.3, omega=0.0, method="scm", epoch=7), 2.0)
        d2 = second.gate.decide(2.01)
        assert second.latch.close(5.0)
    return {"reached_vehicle": {"drives_after_restart": d2.driving}, "learned": None,
            "latched_after_restart": second.gate.estopped, "ok": not d2.driving and second.gate.estopped}


def _pairer():
    from bridge.nodes.pairing import IntervalPairer
    from transfer.domain import Bounds
    from transfer.paper import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W

    lb, tb = Bounds(MPC_LEARNER_V, MPC_LEARNER_W), Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
    top_v, top_w = max(abs(x) for x in (*lb.v, *tb.v)), max(abs(x) for x in (*lb.w, *tb.w))
    return IntervalPairer(0.1, max_speed=1.5 * top_v + 0.1, max_turn=1.5 * top_w + 0.2, command_bounds=lb,
                          teacher_bounds=Bounds((-top_v, top_v), (-top_w, top_w)), margin=1.5), 1.5 * top_v


def _drive_pairer(p, n: int, inject: Callable[[int, float], None], echo: float = 0.2) -> list:
    from transfer.teacher.unicycle import step

    x, t, pairs = np.zeros(3), 0.0, []
    for i in range(n):
        if i % 5 == 0:
            out = p.applied(t, echo, 0.0, "cmd", received=t + 0.003)
            pairs += [out] if out else []
        t += 0.02
        x = step(x, np.array([0.2, 0.0]), 0.02)
        inject(i, t)
        out = p.state(t, x, received=t + 0.003)
        pairs += [out] if out else []
    return pairs


def forged_state_stamp(short: bool) -> Result:
    """One forged ``state`` stamped 1e11 in the middle of real telemetry: does pairing stop for good?"""
    p, _ = _pairer()
    pairs = _drive_pairer(p, 150 if short else 1500, lambda i, t: p.state(1e11, np.ones(3), received=t)
                          if i == 20 else None)
    return {"reached_vehicle": None, "learned": {"pairs_after": len(pairs), "implausible_stamps": p.implausible_stamp},
            "ok": len(pairs) >= 10}


def forged_state_and_applied(short: bool) -> Result:
    """Forged ``applied`` echoes claiming v = 121 m/s, and spoofed states 30 m away, in real telemetry."""
    p, top = _pairer()
    pairs = _drive_pairer(p, 150 if short else 1500, lambda i, t: p.state(t + 0.001, np.array([30.0, 0, 0]),
                                                                          received=t + 0.004) if i % 5 == 2 else None,
                          echo=121.0)
    q, _ = _pairer()
    far = _drive_pairer(q, 150 if short else 1500, lambda i, t: q.state(t + 0.001, np.array([30.0, 0, 0]),
                                                                        received=t + 0.004) if i % 5 == 2 else None)
    worst = max((abs(float(ut[0])) for ut, _ in far), default=0.0)
    return {"reached_vehicle": None, "learned": {"pairs_from_forged_echoes": len(pairs),
                                                 "fastest_teacher_v_learned": worst},
            "ok": not pairs and worst <= top and len(far) > 0}


def poisoned_store(short: bool) -> Result:
    """A persisted store holding a pair no vehicle can make (teacher v = 121): served after a restart?"""
    from bridge.core.paths import save_atomic
    from bridge.nodes.station_core import load_store
    from transfer.domain import Bounds
    from transfer.paper import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W
    from transfer.store import PairStore

    lb, tb = Bounds(MPC_LEARNER_V, MPC_LEARNER_W), Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
    s = PairStore(lb, tb, k_min=1)
    s.add([121.0, 0.0], [0.2, 0.0])
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "pairs.bin"
        save_atomic(f, s.to_bytes())
        store, how = load_store(f, lb, tb, (11, 11), 1)
    return {"reached_vehicle": None, "learned": {"served_pairs": len(store.refined()), "load": how},
            "ok": len(store.refined()) == 0}


def can_odometry(short: bool) -> Result:
    """Crafted encoder frames at 2 kHz, each a small plausible step, while the robot stands still."""
    from drivers.can import CanDriver, CanLinkConfig

    d = CanDriver(CanLinkConfig(max_wheel_speed=10.0))
    d.axes.phase = "running"
    d._encoder(d.left, 0.0, 0.0, 0.0)
    d._encoder(d.right, 0.0, 0.0, 0.0)
    n = 1000 if short else 4000  # frames per wheel at 2 kHz
    for k in range(1, n + 1):
        d._encoder(d.left, 0.02 * k, 0.0, k * 0.0005)
        d._encoder(d.right, -0.02 * k, 0.0, k * 0.0005)
    err = math.hypot(d.pose[0], d.pose[1])
    h = d.health(time.monotonic())
    allowed = 2 * math.pi * 0.1 * 0.5 * (n * 0.0005 + 0.1)  # what a wheel told to stand still may roll
    return {"reached_vehicle": None, "learned": {"odometry_error_m": round(err, 3), "allowed_m": round(allowed, 3)},
            "health_ok": h.ok, "ok": err <= allowed and not h.ok}


def mocap_forged_sample(short: bool) -> Result:
    """One motion-capture sample stamped 0.4 s ahead, then a clock stepped back by 0.45 s."""
    from bridge.core.clock import ClockOffset

    c = ClockOffset(5.0)
    shifted = 0
    for k in range(100):
        c.judge(k * 0.01 + 1000.0, k * 0.01 + 0.001)
    c.judge(100 * 0.01 + 1000.4, 100 * 0.01 + 0.001)
    for k in range(101, 200):
        t, verdict = c.judge(k * 0.01 + 1000.0, k * 0.01 + 0.002)
        shifted += verdict == "ok" and abs(t - (k * 0.01 + 0.001)) > 0.01
    misplaced = 0
    for k in range(200, 400):
        t, verdict = c.judge(k * 0.01 + 1000.0 - 0.45, k * 0.01 + 0.001)
        misplaced += verdict == "ok" and abs(t - (k * 0.01 + 0.001)) > 0.01
    return {"reached_vehicle": None, "learned": {"poses_shifted": shifted, "poses_misplaced_after_step": misplaced},
            "ok": shifted == 0 and misplaced == 0}


def second_station(short: bool) -> Result:
    """A second station publishes commands for the robot: does the first one still say ok?"""
    from bridge.core import wire as M
    from bridge.core.config import StationConfig, load_mission
    from bridge.nodes.station_core import StationCore

    with tempfile.TemporaryDirectory() as d:
        st = StationCore(StationConfig(), f"a{uuid.uuid4().hex[:6]}", 10.0, Path(d) / "p.bin", load_mission())
        st.why, st.reason = "driving", "ok"  # as after a tick that drove
        st.heard_command(M.Command(stamp=1.0, seq=1, v=0.1, omega=0.0, method="scm", epoch=st.epoch ^ 0xF), 1.0)
        s = st.status(1.5)
    return {"reached_vehicle": None, "learned": None, "station_ok": s.ok, "text": s.text, "ok": not s.ok}


# ------------------------------------------------------------------------------------------------------------------
# Issue 31: replays, the signing timestamp, latch tampering, who may act. Each row below runs the real components
# (UDP sockets on 127.0.0.1 with the emulated robot and the real UDP driver, pymavlink framing against the driver's
# client and the emulated rover, a real DriverHost with a real state directory, real Zenoh sessions where the attack
# goes through Zenoh). Each docstring's "before (...)" is what the same row measured with that fix taken out (on the
# base commit 791b027 where the row's API exists there, else with that one check switched off by a throwaway script),
# measured beside other load (2 shared cores); docs/SECURITY.md's attack table lists them.


def udp_record(key_file: Path, tap: Tap, seconds: float) -> list[tuple[float, bytes]]:
    """The real UDP driver drives the robot at 0.3 m/s through the tap for ``seconds``: what it sent (the recording a
    replay is made of)."""
    with tapped_driver(key_file, tap) as driver:
        n0 = len(tap.recorded)
        drive_udp(driver, seconds, 0.3)
        return tap.recorded[n0:]


def udp_replay_after_reboot(short: bool) -> Result:
    """Keyed command datagrams recorded off the wire (a tap between the real UDP driver and the emulated robot) and
    replayed from the robot's peer address right after the robot rebooted (a new instance on the same port: it keeps
    nothing across a power cycle). drivers/udp.py's session (the robot's boot nonce and a recent reading of its clock
    under the keyed tag) makes the recording stale. before (791b027, --short, two runs): the replay drove the rebooted
    robot 0.355 and 0.359 m (49 of 49 and 50 of 50 replayed commands applied)."""
    from bridge.core.auth import make_key
    from bridge.tools.procs import free_udp_port

    with tempfile.TemporaryDirectory() as d:
        key_file = Path(d) / "udp.key"
        key = make_key(key_file)
        bind = free_udp_port()
        with Tap(bind) as tap:
            robot, vehicle = udp_robot(key, tap.addr)
            tap.robot = ("127.0.0.1", robot.port)
            try:
                capture = udp_record(key_file, tap, 1.0 if short else 1.5)
                potent = round(vehicle.distance, 3)
                port = robot.port
                robot.stop()
                robot, vehicle = udp_robot(key, tap.addr, port)  # the reboot
                start, applied = position(vehicle), robot.counters["applied"]
                tap.replay(capture)
                time.sleep(0.2)
                moved, obeyed = distance_from(vehicle, start), robot.counters["applied"] - applied
                refused = {k: v for k, v in robot.counters.items() if k in ("stale_session", "stale",
                                                                           "unauthenticated") and v}
            finally:
                robot.stop()
    return {"reached_vehicle": {"distance_m": moved, "replayed_commands_applied": obeyed}, "learned": None,
            "recording": {"datagrams": len(capture), "drove_m_when_recorded": potent}, "refused": refused,
            "ok": moved < 0.01 and obeyed == 0 and len(capture) > 10 and potent > 0.1}


def udp_held_back_commands(short: bool) -> Result:
    """The tap keeps the driver's commands back (the robot's states still reach the driver) and sends them all
    later, after the session's freshness window: each echoes a reading of the robot's clock too old to obey.
    before (791b027, --short, two runs): the held-back burst moved the robot 0.09 m (30 of 30 commands applied)."""
    from bridge.core.auth import make_key
    from bridge.tools.procs import free_udp_port

    with tempfile.TemporaryDirectory() as d:
        key_file = Path(d) / "udp.key"
        key = make_key(key_file)
        bind = free_udp_port()
        with Tap(bind) as tap:
            robot, vehicle = udp_robot(key, tap.addr)
            tap.robot = ("127.0.0.1", robot.port)
            try:
                with tapped_driver(key_file, tap) as driver:
                    tap.hold = True
                    n0 = len(tap.recorded)
                    drive_udp(driver, 0.6 if short else 1.0, 0.3)
                    held = tap.recorded[n0:]
                    time.sleep(0.6)  # the session's freshness window is 0.5 s (sim_learner/udp_robot.SESSION_FRESH_S)
                    start, applied = position(vehicle), robot.counters["applied"]
                    tap.replay(held, paced=False)
                    time.sleep(0.3)
                    moved, obeyed = distance_from(vehicle, start), robot.counters["applied"] - applied
                    refused = {k: v for k, v in robot.counters.items() if k in ("stale_session", "stale") and v}
            finally:
                robot.stop()
    return {"reached_vehicle": {"distance_m": moved, "held_commands_applied": obeyed}, "learned": None,
            "held": len(held), "refused": refused, "ok": moved < 0.01 and obeyed == 0 and len(held) > 10}


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
    from sim_learner.mavlink_rover import signing_wall_clock

    mavutil = mavutil_v2()
    mav = mavutil.mavlink
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
    from sim_learner.mavlink_rover import GUIDED, signing_wall_clock

    mavutil = mavutil_v2()
    mav = mavutil.mavlink
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
    rover = MavlinkRover(vehicle, port=port, init_s=0.1, ekf_position_s=0.2, signing_key=key, signing_store=store,
                         signing_save_s=0.2).start()
    until(lambda: rover_ready(rover), 3.0)
    return rover, vehicle


def rover_ready(rover) -> bool:
    """Whether the emulated ``rover`` has its origin and is in MANUAL (booted, nobody took it yet)."""
    return rover.has_origin(time.monotonic()) and rover.mode_name == "MANUAL"


def mavlink_forged_timestamp_at_driver(short: bool) -> Result:
    """One packet signed with a wrong key and a timestamp ten years ahead, sent to the driver's MAVLink client on a
    signed link to the emulated rover: the driver must keep hearing the rover (pymavlink records a stream's
    timestamp before it checks the signature; drivers/mavlink/client.verify_before_recording puts it back).
    before (the wrapper off, --short): no pose heard after it, the link down ("no heartbeat for 1.4 s"), 52
    genuine messages refused as bad signatures."""
    import socket

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
                                                              heartbeat_timeout=1.0,
                                                              signing_key_file=str(key_file)))
            try:
                driver.open(time.monotonic())
                driver.engage(time.monotonic())
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
            finally:
                driver.close()
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
                                                              signing_key_file=str(key_file)))
            try:
                driver.open(time.monotonic())
                driver.engage(time.monotonic())
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
            finally:
                driver.close()
    return {"reached_vehicle": {"speed_before_stop": speed, "stop_s": stop_s, "stopped": stopped}, "learned": None,
            "ok": stopped and stop_s < 1.0 and speed > 0.1}


def mavlink_replay_after_reboot(short: bool) -> Result:
    """Signed traffic of a ground station (GUIDED, arm, a forward set-point) recorded off the wire while it took the
    emulated rover, replayed after the rover rebooted: the rover keeps its signing timestamp in its storage (as
    ArduPilot does) and starts a minute past it, so the recording is too old. before (no store: a rover that
    forgets its timestamp at boot, as the emulated rover did on 791b027; --short): armed, GUIDED, 0.014 m in 0.3 s."""
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
            until(lambda: rover.signing_saves > saves, 3.0)  # its periodic save (at a HEARTBEAT) after it
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


# ------------------------------------------------------------------------------------- the estop latch on disk


def latch_disk_full_at_estop(short: bool) -> Result:
    """The robot's disk is full when the operator's estop comes (the latch save fails with ENOSPC, injected as the
    host's saver: the bench runs as root, which a read-only directory does not stop), then the host restarts on the
    same state directory and someone engages. bridge/nodes/latch_store.py: the failed save removes the old
    (released) file and the host refuses engage, so the restart finds the marker without a file: latched. before
    (the save result's handling off: the failure ignored, the old released file left; --short, two runs): engaged
    after the restart, drove 0.073 m in 0.5 s both times."""
    import errno
    import os
    import threading

    from bridge.core.paths import save_atomic

    full = threading.Event()

    def saver(path: Path, data: bytes) -> None:
        if full.is_set():
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        save_atomic(path, data)

    with tempfile.TemporaryDirectory() as d, _LatchRig() as rig:
        latch = Path(d) / "state" / "estop-r1.bin"
        host = rig.host(latch, saver)
        full.set()
        rig.estop(host)
        refused_before_restart = not rig.engage_and_drive(host, 0.1)["engaged"]
        rig.stop(host)
        host = rig.host(latch, saver)
        after = rig.engage_and_drive(host, 0.5 if short else 1.5)
        full.clear()  # space freed: a person's release is saved, and the host drives again
        control = rig.control(host, 0.3)
    return {"reached_vehicle": after, "learned": None, "engage_refused_before_restart": refused_before_restart,
            "control_drove_m": control,
            "ok": not after["engaged"] and after["distance_m"] < 0.01 and refused_before_restart and control > 0.01}


def latch_file_deleted(short: bool) -> Result:
    """The operator latched the estop; while the host was stopped the latch file was deleted; the host restarts and
    someone engages. The install marker beside it says this directory has an estop history: a missing file is
    latched. before (``inspect_latch`` as a plain read: missing means never latched; --short, two runs): engaged,
    drove 0.092 and 0.073 m in 0.5 s."""
    with tempfile.TemporaryDirectory() as d, _LatchRig() as rig:
        latch = Path(d) / "estop-r1.bin"
        host = rig.host(latch)
        rig.estop(host)
        rig.stop(host)
        latch.unlink()
        host = rig.host(latch)
        after = rig.engage_and_drive(host, 0.5 if short else 1.5)
        control = rig.control(host, 0.3)
    return {"reached_vehicle": after, "learned": None, "control_drove_m": control,
            "ok": not after["engaged"] and after["distance_m"] < 0.01 and control > 0.01}


def forged_releases(other: Path) -> list[bytes]:
    """"Released" latch files someone else wrote: unsigned, with a made-up tag, the one another state directory's
    host signed (``other``), and one signed with another key (also tests/integration/test_driver_host.py)."""
    import os

    from bridge.core import wire as M
    from bridge.nodes.latch_store import Latch, sign_latch

    return [M.encode(Latch(latched=False, source="operator")),
            M.encode(Latch(latched=False, source="operator", tag=os.urandom(16))),
            other.read_bytes(),
            M.encode(sign_latch(os.urandom(32), Latch(latched=False, source="operator")))]


def latch_file_forged_release(short: bool) -> Result:
    """The operator latched the estop; while the host was stopped the latch file was replaced by a "released" one
    this host did not sign (unsigned, a made-up tag, another state directory's host's own signed release, signed
    with a random key); after each, the host restarts and someone engages. Only a release under the robot's latch
    key (its install marker, 0600) is believed. before (``inspect_latch`` as a plain read: any file saying released
    believed; --short, two runs): engaged on 4 of 4, drove 0.061 and 0.048 m in all (0.15 s each)."""
    engaged, moved = 0, 0.0
    with tempfile.TemporaryDirectory() as d, _LatchRig() as rig:
        latch, other = Path(d) / "a" / "estop-r1.bin", Path(d) / "b" / "estop-r1.bin"
        rig.stop(rig.host(other))  # another state directory's host: its own key, a released file it signed
        host = rig.host(latch)
        rig.estop(host)
        rig.stop(host)
        forged = forged_releases(other)
        for data in forged:
            latch.write_bytes(data)
            host = rig.host(latch)
            after = rig.engage_and_drive(host, 0.15 if short else 0.5)
            engaged += after["engaged"]
            moved += after["distance_m"]
            rig.stop(host)
        control = rig.control(rig.host(latch), 0.8)  # (a new host: the robot follows its epoch 0.3 s after the last)
    return {"reached_vehicle": {"engaged": engaged, "of": len(forged), "distance_m": round(moved, 3)},
            "learned": None, "control_drove_m": control, "ok": engaged == 0 and moved < 0.01 and control > 0.01}


def latch_other_state_dir(short: bool) -> Result:
    """The operator latched the estop; the host restarts with another (empty) state directory (a changed
    SCMBRIDGE_STATE_DIR). It cannot know of the estop latched in the first one; what it must do is say so, at start:
    "first start in this state directory: no estop history" (log, and ``scmbridge doctor``), once. before
    (791b027's DriverHost, the same two directories): released, and nothing logged."""
    import logging

    class _Said(logging.Handler):
        def __init__(self) -> None:
            super().__init__(logging.INFO)
            self.texts: list[str] = []

        def emit(self, record: logging.LogRecord) -> None:
            self.texts.append(record.getMessage())

    said = _Said()
    logger = logging.getLogger("scmbridge.driver")
    level = logger.level
    logger.addHandler(said)
    logger.setLevel(logging.INFO)
    try:
        with tempfile.TemporaryDirectory() as d, _LatchRig() as rig:
            first = rig.host(Path(d) / "one" / "estop-r1.bin")
            rig.estop(first)
            rig.stop(first)
            said.texts.clear()
            other = rig.host(Path(d) / "two" / "estop-r1.bin")
            told = any("first start in this state directory: no estop history" in t for t in said.texts)
            fresh = other.latch.fresh_state
            rig.stop(other)
    finally:
        logger.removeHandler(said)
        logger.setLevel(level)
    return {"reached_vehicle": None, "learned": None, "said_no_estop_history": told, "fresh_state": fresh,
            "ok": told and fresh}


# ------------------------------------------------------------------------------------ who may act, over Zenoh


def replayed_engage_and_release(short: bool) -> Result:
    """Over Zenoh, with a station publishing commands: a person's engage and a person's estop release, recorded off
    the network, replayed after the person handed the robot back / latched the estop again; the same requests
    stamped a minute ago; and old-format ones (no time, no nonce). bridge/core/acts.ActGuard takes a request fresh
    and once. before (``ActGuard.check`` off, --short, two runs): the replayed, the stale and the old-format release
    each released the latch and each engage engaged; 34 and 32 ticks drove, 0.151 and 0.152 m."""
    from bridge.core import wire as M
    from bridge.core.acts import stamped

    out: dict = {}
    with _ZenohHost() as rig, _Station(rig, 0.3):
        def to():  # the host's address, as its answers give it to the person's tool
            return rig.host.acts.address(time.monotonic())

        engage = M.encode(stamped(M.EngageRequest(stamp=1.0, source="operator"), to()))  # recorded
        ans = rig.engage(engage)
        first = {"engage_engaged": bool(ans and ans.engaged)}  # the recording is potent
        release = M.encode(stamped(M.Estop(stamp=1.0, engaged=False, source="operator"), to()))
        rig.attacker.put(rig.keys.estop, M.encode(M.Estop(stamp=1.0, source="operator", reason="attack")))
        until(lambda: rig.host.gate.estopped, 2.0)
        rig.attacker.put(rig.keys.estop, release)  # the person's release, recorded off the network
        first["release_released"] = until(lambda: not rig.host.gate.estopped, 2.0)
        # the person hands the robot back and latches the estop: the robot is parked
        rig.engage(M.encode(M.EngageRequest(stamp=1.0, engaged=False, source="operator")))
        rig.attacker.put(rig.keys.estop, M.encode(M.Estop(stamp=1.0, source="operator", reason="parked")))
        until(lambda: rig.host.gate.estopped, 2.0)
        start, t0 = position(rig.vehicle), time.monotonic()
        stale = dict(stamp=1.0, target=rig.host.acts.epoch, echo=max(1e-3, time.monotonic() - 60.0))
        for kind, rel, eng in (
                ("replayed", release, engage),
                ("stale", M.encode(M.Estop(engaged=False, source="operator", nonce=M.new_nonce(), **stale)),
                 M.encode(M.EngageRequest(source="operator", nonce=M.new_nonce(), **stale))),
                ("unstamped", M.encode(M.Estop(stamp=1.0, engaged=False, source="operator")),
                 M.encode(M.EngageRequest(stamp=1.0, source="operator")))):
            rig.attacker.put(rig.keys.estop, rel)
            time.sleep(0.1)
            ans = rig.engage(eng)
            out[kind] = {"released": not rig.host.gate.estopped, "engaged": bool(ans and ans.engaged)}
        time.sleep(0.3 if short else 1.0)
        moved = distance_from(rig.vehicle, start)
        driven = sum(a.v != 0.0 for a in rig.since(t0))
        refused = {k: v for k, v in rig.host.inputs.snapshot().items() if "refused" in k and v}
        # the control: the person's own tool (fresh, a new nonce) releases and engages, and the station drives
        rig.attacker.put(rig.keys.estop, M.encode(stamped(M.Estop(stamp=1.0, engaged=False, source="operator"),
                                                          to())))
        until(lambda: not rig.host.gate.estopped, 2.0)
        ans = rig.engage(M.encode(stamped(M.EngageRequest(stamp=1.0, source="operator"), to())))
        t1 = time.monotonic()
        control = bool(ans and ans.engaged) and until(lambda: any(a.v != 0.0 for a in rig.since(t1)), 2.0)
    took = any(r["released"] or r["engaged"] for r in out.values())
    return {"reached_vehicle": {"distance_m": moved, "ticks_driven": driven, **out}, "learned": None,
            "refused": refused, "when_first_sent": first, "control_drives": control,
            "ok": not took and moved < 0.01 and driven == 0 and all(first.values()) and control}


def forger_at_seq_plus_one(short: bool) -> Result:
    """Over Zenoh, while the station drives the engaged robot at 0.2 m/s: a forger hears each command and publishes
    a copy at seq + 1 (the station's epoch) with v = 0.45, 1 ms after it. The real command then comes at a seq
    already taken with other content: two senders on one epoch, a conflict that stops the robot while it lasts.
    before (the gate's conflict check off, --short, two runs): 50 of 50 and 49 of 49 ticks applied the forger's
    0.45 m/s; status ok."""
    import threading

    from bridge.core import wire as M
    from bridge.core.acts import stamped

    with _ZenohHost() as rig, _Station(rig, 0.2):
        rig.engage(M.encode(stamped(M.EngageRequest(stamp=1.0, source="operator"),
                                    rig.host.acts.address(time.monotonic()))))
        drove = until(lambda: any(a.v == 0.2 for a in rig.since(0.0)), 3.0)  # the station drives it
        sent = [0]
        stop = threading.Event()
        with rig.client() as s:
            pub = s.declare_publisher(rig.keys.cmd)

            def on_cmd(sample) -> None:
                c = M.decode(sample.payload.to_bytes(), M.Command)
                if stop.is_set() or c.v == 0.45:
                    return
                pub.put(M.encode(M.Command(stamp=c.stamp + 0.001, seq=c.seq + 1, v=0.45, omega=0.5, method=c.method,
                                           sender=c.sender, epoch=c.epoch)))
                sent[0] += 1

            sub = s.declare_subscriber(rig.keys.cmd, on_cmd)
            t0 = time.monotonic()
            until(lambda: sent[0] > 0, 2.0)
            time.sleep(1.0 if short else 3.0)
            stop.set()
            sub.undeclare()
        during = rig.since(t0 + 0.2)  # from a few ticks after the first forgery
        status = rig.host.status(time.monotonic())
    forged = sum(a.v == 0.45 for a in during)
    return {"reached_vehicle": {"ticks": len(during), "forged_applied": forged,
                                "stopped_for_conflict": sum(a.reason == "conflict" for a in during)},
            "learned": None, "forged_sent": sent[0], "station_drove_first": drove,
            "status": {"ok": status.ok, "reason": status.reason}, "ok": forged == 0 and len(during) > 10 and sent[0] > 5
            and drove}


def mission_after_goal(short: bool) -> Result:
    """A real station (bridge/nodes/station.py, its loop on a client session of a router on a free port) whose
    mission reached its goal ("finished"); an attacker's session publishes a MissionSpec on ``scm/<robot>/mission``
    (anyone may on the loopback default) and asks the station's ``control`` for its phase: the new mission must
    load idle, and only a person's start drives. before (791b027's ``MissionControl.replace``: a finished mission
    goes on with the new goal; two runs): phase "running" both times: the station drives with no person's act."""
    import threading

    from bridge.core import wire as M
    from bridge.core.config import StationConfig, load_mission, load_mission_spec
    from bridge.nodes.mission_control import MissionControl
    from bridge.nodes.station import Station
    from bridge.nodes.zsession import free_port, make_config, open_session, tcp

    robot, port = f"atk{uuid.uuid4().hex[:8]}", free_port()
    stop = threading.Event()
    with contextlib.ExitStack() as stack:
        d = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        stack.enter_context(open_session(make_config(mode="router", listen=[tcp(port)])))
        station = Station(StationConfig(), robot, 10.0, d / "pairs.bin", load_mission(),
                          control=MissionControl(robot, load_mission_spec(), "finished"))
        stack.callback(station.persist)  # (closes its writer thread; the save goes to the temporary directory)
        session = stack.enter_context(open_session(make_config(mode="client", connect=[tcp(port)])))
        loop = threading.Thread(target=station.serve, args=(session, stop, None, False, False), name="attack-station",
                                daemon=True)
        loop.start()
        stack.callback(loop.join, 10.0)
        stack.callback(stop.set)
        until(lambda: station.looping, 10.0)
        attacker = stack.enter_context(open_session(make_config(mode="client", connect=[tcp(port)])))

        def ask() -> M.MissionState | None:
            for reply in attacker.get(M.key(robot, "control"), timeout=5.0,
                                      payload=M.encode(M.MissionRequest(stamp=1.0, action="status"))):
                if reply.ok is not None:
                    return M.decode(reply.ok.payload.to_bytes(), M.MissionState)
            return None

        first = ask()
        attacker.put(M.key(robot, "mission"), M.encode(M.MissionSpec(name="attacker", path=[[0.0, 0.0], [2.0, 0.0]])))
        after, t_end = None, time.monotonic() + (2.0 if short else 5.0)
        while time.monotonic() < t_end:  # until the station has taken it (its next tick)
            after = ask()
            if after is not None and after.mission == "attacker":
                break
            time.sleep(0.05)
        taken = after is not None and after.mission == "attacker"
    phase = after.phase if after is not None else "no answer"
    return {"reached_vehicle": {"phase": phase, "station_drives": phase == "running"}, "learned": None,
            "phase_before": first.phase if first is not None else "no answer", "mission_taken": taken,
            "said": (after.reason if after is not None else "")[:120],
            "ok": taken and phase == "idle" and first is not None and first.phase == "finished"}


ATTACKS: dict[str, Callable[[bool], Result]] = {
    f.__name__: f for f in (forged_command_in_epoch, udp_spoof, mavlink_unsigned, estop_forgotten_on_restart,
                            forged_state_stamp, forged_state_and_applied, poisoned_store, can_odometry,
                            mocap_forged_sample, second_station, udp_replay_after_reboot, udp_held_back_commands,
                            mavlink_forged_timestamp_at_driver, mavlink_forged_timestamp_at_rover,
                            mavlink_replay_after_reboot, latch_disk_full_at_estop, latch_file_deleted,
                            latch_file_forged_release, latch_other_state_dir, replayed_engage_and_release,
                            forger_at_seq_plus_one, mission_after_goal)}


def run_all(short: bool = False, names: list[str] | None = None) -> dict:
    """Every attack (or ``names``), each isolated: one that raises is reported as not ok with its error. The
    driver hosts' latch records go to a temporary directory (bridge/nodes/latch_record.py), not this user's."""
    import os

    from bench.attack_trust import TRUST_ATTACKS

    attacks = {**ATTACKS, **TRUST_ATTACKS}
    with tempfile.TemporaryDirectory() as records, contextlib.ExitStack() as stack:
        if "SCMBRIDGE_RECORD_DIR" not in os.environ:
            os.environ["SCMBRIDGE_RECORD_DIR"] = records
            stack.callback(os.environ.pop, "SCMBRIDGE_RECORD_DIR", None)
        return _run(attacks, short, names)


def _run(attacks: dict, short: bool, names: list[str] | None) -> dict:
    out = []
    for name in names or list(attacks):
        t0 = time.monotonic()
        try:
            res = attacks[name](short)
        except Exception as exc:  # an attack that crashes a component is a finding, reported as such
            res = {"reached_vehicle": None, "learned": None, "ok": False, "error": f"{type(exc).__name__}: {exc}"}
        out.append({"attack": name, **res, "seconds": round(time.monotonic() - t0, 2)})
    return {"attacks": out, "all_ok": all(a["ok"] for a in out)}


def arguments(ap: argparse.ArgumentParser) -> None:
    from bench.attack_trust import TRUST_ATTACKS

    ap.add_argument("--short", action="store_true", help="each attack briefly (as the suite runs it)")
    ap.add_argument("--only", default=None,
                    help=f"comma-separated attacks of: {', '.join([*ATTACKS, *TRUST_ATTACKS])}")


def run(args: argparse.Namespace) -> int:
    res = run_all(args.short, args.only.split(",") if args.only else None)
    emit(res)
    return 0 if res["all_ok"] else 1
