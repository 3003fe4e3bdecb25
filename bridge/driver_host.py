"""``scmbridge driver``: the driver host, between Zenoh and one vehicle link (DESIGN.md sections 1, 5, 6).

It subscribes to ``scm/<robot>/cmd`` and ``scm/<robot>/estop``, checks every command (decoded and validated:
finite and in wire range; fresh: received less than min(valid_ms, cmd_timeout) ago; not older than the last one
applied; clamped to the configured hard limits), hands it to the link driver and echoes what the vehicle really
got on ``applied``; it publishes the link's telemetry as ``state`` and its own health on ``status``. It owns the
deadman: no valid command for ``cmd_timeout`` (0.3 s default) stops the vehicle. An estop latches a stop until an
``Estop(engaged=False)``. All stamps are this host's ``time.monotonic()``, so the station can pair ``applied`` with
``state`` without any clock synchronisation.

``--emulate`` (CAN only) hosts the emulated motor controllers on the same python-can ``virtual`` channel inside
this process: the wire between driver and controllers is python-can, not a shortcut (this machine has no vcan).
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import msgspec
import numpy as np

from bridge import wire as M
from bridge.cliutil import pose_arg
from bridge.config import load_driver
from bridge.wire import Keys, status_key
from bridge.zsession import make_config, open_session
from transfer.domain import Bounds

log = logging.getLogger("scmbridge.driver")


@dataclass(frozen=True)
class Decision:
    """What the vehicle gets this tick."""

    v: float
    omega: float
    reason: str  # cmd | clamped | deadman | estop | stale | start
    cmd_seq: int | None = None


@dataclass
class CommandGate:
    """Freshness, clamping, deadman and estop latch: the driver host's safety logic, pure (times are arguments)."""

    limits: Bounds
    cmd_timeout: float = 0.3
    latest: M.Command | None = None
    received_at: float = -float("inf")
    last_seq: int = -1
    estopped: bool = False
    counters: dict[str, int] = field(default_factory=lambda: {
        "accepted": 0, "out_of_order": 0, "deadman_trips": 0, "stale": 0, "clamped": 0, "estops": 0})
    _deadman_active: bool = True

    def offer(self, cmd: M.Command, now: float) -> bool:
        """A decoded command arrived at ``now``; False if it is older than what was already applied."""
        if cmd.seq <= self.last_seq:
            self.counters["out_of_order"] += 1
            return False
        self.latest, self.received_at, self.last_seq = cmd, now, cmd.seq
        self.counters["accepted"] += 1
        return True

    def estop(self, engaged: bool) -> None:
        if engaged and not self.estopped:
            self.counters["estops"] += 1
        self.estopped = engaged

    def decide(self, now: float) -> Decision:
        if self.estopped:
            return Decision(0.0, 0.0, "estop")
        cmd = self.latest
        age = now - self.received_at
        if cmd is None or age >= self.cmd_timeout:
            if not self._deadman_active and cmd is not None:
                self.counters["deadman_trips"] += 1
                log.warning("deadman: no valid command for %.3f s, vehicle stopped", age)
            self._deadman_active = True
            return Decision(0.0, 0.0, "deadman" if cmd is not None else "start")
        if age >= cmd.valid_ms / 1000.0:
            self.counters["stale"] += 1
            return Decision(0.0, 0.0, "stale", cmd.seq)
        self._deadman_active = False
        v = min(max(cmd.v, self.limits.v[0]), self.limits.v[1])
        w = min(max(cmd.omega, self.limits.w[0]), self.limits.w[1])
        if (v, w) != (cmd.v, cmd.omega):
            self.counters["clamped"] += 1
            return Decision(v, w, "clamped", cmd.seq)
        return Decision(v, w, "cmd", cmd.seq)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scmbridge driver", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--link", choices=["can", "mavlink", "udp"], required=True)
    ap.add_argument("--config", help="driver TOML (see deploy/driver.example.toml)")
    ap.add_argument("--robot", default=None)
    ap.add_argument("--listen", action="append", default=[], help="Zenoh endpoint to listen on (repeatable)")
    ap.add_argument("--connect", action="append", default=[], help="Zenoh endpoint to connect to (repeatable)")
    ap.add_argument("--mode", choices=["peer", "client", "router"], default="peer", help="Zenoh session mode")
    ap.add_argument("--zenoh-config", help="a Zenoh JSON5 config file (deploy/), endpoints above override it")
    ap.add_argument("--rate", type=float, default=None, help="control loop rate, Hz (default 50)")
    ap.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    ap.add_argument("--emulate", action="store_true", help="host emulated CAN motor controllers in-process")
    ap.add_argument("--model", default="mpc", help="learner model for --emulate (mpc, experiment, scaled)")
    ap.add_argument("--x0", type=pose_arg, default=(0.0, 0.0, 0.0), help="start pose x,y,theta for --emulate")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s driver %(levelname)s %(message)s")

    cfg = load_driver(args.config)
    robot = args.robot or cfg.robot
    keys = Keys(robot)
    dcfg = cfg.driver
    rate = float(args.rate or dcfg.rate_hz)
    limits = dcfg.hard_limits.bounds()
    gate = CommandGate(limits, dcfg.cmd_timeout)
    link_cfg = getattr(cfg.link, args.link)
    x0 = args.x0
    if args.emulate:
        if args.link != "can":
            ap.error("--emulate hosts CAN motor controllers; run `scmbridge learner` for the other links")
        link_cfg = msgspec.structs.replace(link_cfg, interface="virtual", channel=f"scm-{robot}", initial_pose=x0)

    from drivers import open_driver

    driver = open_driver(args.link, link_cfg)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    lock = threading.Lock()
    wake = threading.Event()
    malformed = {"cmd": 0, "estop": 0}

    def on_cmd(sample) -> None:
        now = time.monotonic()
        try:
            cmd = M.decode(sample.payload.to_bytes(), M.Command)
        except M.MessageError as exc:
            with lock:
                malformed["cmd"] += 1
            log.debug("dropped command: %s", exc)
            return
        with lock:
            gate.offer(cmd, now)
        wake.set()  # apply it now, not at the next tick: command latency is not a multiple of the period

    def on_estop(sample) -> None:
        try:
            e = M.decode(sample.payload.to_bytes(), M.Estop)
        except M.MessageError:
            with lock:
                malformed["estop"] += 1
            return
        with lock:
            gate.estop(e.engaged)
        log.warning("estop %s by %s: %s", "engaged" if e.engaged else "released", e.source, e.reason)

    ecus = None
    if args.emulate:
        from sim_learner.can_ecu import DiffDriveEcus
        from sim_learner.dynamics import model_by_name
        from sim_learner.vehicle import SimVehicle

        vehicle = SimVehicle(model_by_name(args.model), x0, now=time.monotonic())
        ecus = DiffDriveEcus({"interface": "virtual", "channel": link_cfg.channel}, vehicle,
                             left_node=link_cfg.left_node, right_node=link_cfg.right_node,
                             left_sign=link_cfg.left_sign, right_sign=link_cfg.right_sign,
                             wheel_radius=link_cfg.wheel_radius, track_width=link_cfg.track_width).start()
    zconf = make_config(mode=args.mode, listen=args.listen, connect=args.connect, config_file=args.zenoh_config)
    t_start = time.monotonic()
    try:
        with open_session(zconf) as session:
            session.declare_subscriber(keys.cmd, on_cmd)
            session.declare_subscriber(keys.estop, on_estop)
            pub_applied = session.declare_publisher(keys.applied)
            pub_state = session.declare_publisher(keys.state)
            pub_status = session.declare_publisher(status_key(robot, "driver"))
            driver.open(time.monotonic())
            log.info("driver host for %s on link %s at %.0f Hz", robot, args.link, rate)
            period = 1.0 / rate
            t_next = time.monotonic()
            seq_a = seq_s = seq_st = 0
            t_status = t_next
            missed = 0
            ticks: deque[float] = deque(maxlen=500)  # start times of the periodic ticks (jitter)
            periodic = True
            while not stop.is_set():
                now = time.monotonic()
                if periodic:
                    ticks.append(now)
                if args.duration is not None and now - t_start >= args.duration:
                    break
                with lock:
                    d = gate.decide(now)
                if d.reason in ("cmd", "clamped"):
                    driver.send(d.v, d.omega, now)
                else:
                    driver.stop(now)
                pub_applied.put(M.encode(M.Applied(stamp=now, seq=seq_a, v=d.v, omega=d.omega, reason=d.reason,
                                                   cmd_seq=d.cmd_seq)))
                seq_a += 1
                for p in driver.poll(now):
                    st = M.LearnerState(stamp=p.stamp, seq=seq_s, x=p.x, y=p.y, theta=p.theta, v=p.v, omega=p.omega,
                                        source=args.link)
                    try:
                        pub_state.put(M.encode(M.validated(st)))
                        seq_s += 1
                    except M.MessageError:
                        log.warning("telemetry out of range, not published: %s", st)
                if now >= t_status:
                    h = driver.health()
                    with lock:
                        counters = dict(gate.counters)
                        counters.update({f"malformed_{k}": v for k, v in malformed.items()})
                    counters.update({"link_malformed": h.malformed, "link_errors": h.errors, "missed_deadlines": missed,
                                     "frames_sent": h.frames_sent, "frames_received": h.frames_received,
                                     "ticks": len(ticks)})
                    lat = {}
                    if len(ticks) > 2:
                        dev = np.abs(np.diff(np.asarray(ticks)) - period) * 1e3
                        lat = {"jitter_p50": float(np.percentile(dev, 50)), "jitter_p99": float(np.percentile(dev, 99)),
                               "jitter_max": float(dev.max())}
                    pub_status.put(M.encode(M.Status(stamp=now, seq=seq_st, node="driver", ok=h.connected,
                                                     rates_hz={"loop": rate}, latencies_ms=lat, counters=counters,
                                                     text=f"link {args.link}")))
                    seq_st += 1
                    t_status = now + 1.0
                if periodic:
                    t_next += period
                delay = t_next - time.monotonic()
                if delay > 0:
                    periodic = not wake.wait(delay)  # woken by a command: an extra, immediate tick
                    wake.clear()
                else:
                    if periodic:
                        missed += 1
                        t_next = time.monotonic()
                    periodic = True
    finally:
        driver.close()
        if ecus is not None:
            ecus.stop()
    return 0
