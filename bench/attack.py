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

from bench.attack_latch import (
    latch_disk_full_at_estop,
    latch_file_deleted,
    latch_file_forged_release,
    latch_other_state_dir,
)
from bench.attack_mavlink import (
    mavlink_forged_timestamp_at_driver,
    mavlink_forged_timestamp_at_rover,
    mavlink_replay_after_reboot,
)
from bench.attack_rigs import (
    Result,
    Tap,
    distance_from,
    drive_udp,
    position,
    tapped_driver,
    udp_robot,
)
from bench.attack_zenoh import forger_at_seq_plus_one, mission_after_goal, replayed_engage_and_release
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
    now = time.monotonic()  # the poll that reads them (their own stamps are the frames')
    d._encoder(d.left, 0.0, 0.0, 0.0, now)
    d._encoder(d.right, 0.0, 0.0, 0.0, now)
    n = 1000 if short else 4000  # frames per wheel at 2 kHz
    for k in range(1, n + 1):
        d._encoder(d.left, 0.02 * k, 0.0, k * 0.0005, now)
        d._encoder(d.right, -0.02 * k, 0.0, k * 0.0005, now)
    err = math.hypot(d.pose[0], d.pose[1])
    h = d.health(now)
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
        st.verdict.why, st.verdict.reason = "driving", "ok"  # as after a tick that drove
        st.heard_command(M.Command(stamp=1.0, seq=1, v=0.1, omega=0.0, method="scm", epoch=st.outbox.epoch ^ 0xF), 1.0)
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

ATTACKS: dict[str, Callable[[bool], Result]] = {
    f.__name__: f for f in (forged_command_in_epoch, udp_spoof, mavlink_unsigned, estop_forgotten_on_restart,
                            forged_state_stamp, forged_state_and_applied, poisoned_store, can_odometry,
                            mocap_forged_sample, second_station, udp_replay_after_reboot, udp_held_back_commands,
                            mavlink_forged_timestamp_at_driver, mavlink_forged_timestamp_at_rover,
                            mavlink_replay_after_reboot, latch_disk_full_at_estop, latch_file_deleted,
                            latch_file_forged_release, latch_other_state_dir, replayed_engage_and_release,
                            forger_at_seq_plus_one, mission_after_goal)}


def run_all(short: bool = False, names: list[str] | None = None, sitl: bool = False) -> dict:
    """Every attack (or ``names``), each isolated: one that raises is reported as not ok with its error. The
    driver hosts' latch records go to a temporary directory (bridge/nodes/latch_record.py), not this user's."""
    import os

    from bench.attack_files import FILE_ATTACKS
    from bench.attack_trust import TRUST_ATTACKS

    attacks = {**ATTACKS, **TRUST_ATTACKS, **FILE_ATTACKS}
    if sitl or (names and any(n.startswith("sitl_") for n in names)):
        from bench.attack_sitl import SITL_ATTACKS

        attacks.update(SITL_ATTACKS)
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
    from bench.attack_files import FILE_ATTACKS
    from bench.attack_trust import TRUST_ATTACKS

    ap.add_argument("--short", action="store_true", help="each attack briefly (as the suite runs it)")
    ap.add_argument("--sitl", action="store_true",
                    help="also the rows against ArduPilot's Rover SITL (sitl_host_killed, sitl_replay_after_reboot: "
                         "minutes; the binary as sim_learner/sitl.py finds it)")
    ap.add_argument("--only", default=None,
                    help=f"comma-separated attacks of: {', '.join([*ATTACKS, *TRUST_ATTACKS, *FILE_ATTACKS])}")


def run(args: argparse.Namespace) -> int:
    res = run_all(args.short, args.only.split(",") if args.only else None, args.sitl)
    emit(res)
    return 0 if res["all_ok"] else 1
