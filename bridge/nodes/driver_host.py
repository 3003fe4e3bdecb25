"""``scmbridge driver``: the driver host, between Zenoh and one vehicle link (docs/ARCHITECTURE.md).

It subscribes to ``scm/<robot>/cmd`` and ``scm/<robot>/estop`` and answers queries on the estop key with its latch
state. Every command is decoded (so validated: finite, in wire range) and goes through the pure
:class:`bridge.core.gate.CommandGate`: the next of its sender's ``(epoch, seq)`` stream, fresh (received less than
min(valid_ms, cmd_timeout) ago), a stop applied as exactly zero, anything else clamped to the configured hard
limits. The host hands the result to the link driver only while the link says the vehicle is fit to drive
(``health().ok``) and its telemetry is fresh; otherwise it stops the vehicle and says why. Each tick it echoes what
the vehicle really got on ``applied``, publishes the link's poses as ``state`` (its own epoch and sequence) and,
each second, a truthful ``status``. Commands are applied as they arrive (latency is not a multiple of the period),
but the link never gets more than ``max_send_hz`` of them. An estop latches a stop; only a source named in
``estop_release_sources`` releases it, and a release is the operator action that lets the link clear its
controllers' latched faults. All stamps are this host's ``time.monotonic()``, so the station pairs ``applied``
with ``state`` without any clock synchronisation.

``--emulate`` (CAN only) hosts the emulated motor controllers on the same python-can ``virtual`` channel inside
this process: the wire between driver and controllers is python-can, not a shortcut.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from collections import deque

import msgspec
import numpy as np
import zenoh

from bridge.core import wire as M
from bridge.core.args import pose_arg, positive_float, robot_arg
from bridge.core.clock import ClockOffset
from bridge.core.config import DriverConfig, load_driver
from bridge.core.errors import UsageError
from bridge.core.gate import CommandGate, Decision
from bridge.nodes.node import Inputs, add_zenoh_args, stop_on_signals, zenoh_config
from bridge.nodes.zsession import open_session
from drivers.base import Driver, LinkHealth

log = logging.getLogger("scmbridge.driver")


def blocked_reason(health: LinkHealth) -> str:
    """The ``applied`` reason for a vehicle the link says is not fit to drive."""
    if not health.connected:
        return "link_down"
    return "operator" if health.text.startswith("operator") else "fault"


class DriverHost:
    """One robot's driver host: the gate, the link and the Zenoh side (see the module docstring)."""

    def __init__(self, cfg: DriverConfig, link: str, driver: Driver, robot: str, rate_hz: float) -> None:
        d = cfg.driver
        self.link, self.driver, self.robot = link, driver, robot
        self.keys = M.Keys(robot)
        self.period = 1.0 / rate_hz
        self.min_gap = 1.0 / d.max_send_hz
        self.max_telemetry_age = d.max_telemetry_age_s
        self.gate = CommandGate(d.hard_limits.bounds(), d.cmd_timeout, tuple(d.estop_release_sources))
        self.inputs = Inputs()
        self.lock = threading.Lock()  # the gate is shared with Zenoh's callback threads
        self.wake = threading.Event()
        self.clear_requested = False
        self.epoch = M.new_epoch()
        self.seq = {"applied": 0, "state": 0, "status": 0}
        self.last_pose = -math.inf
        self.last_decision = Decision(0.0, 0.0, "start")
        self.health = LinkHealth()
        self.missed = 0
        self.ticks: deque[float] = deque(maxlen=500)  # start times of the periodic ticks (jitter)
        self.pubs: dict[str, zenoh.Publisher] = {}
        self.pose_source = d.pose_source
        self.mocap_clock = ClockOffset(d.mocap_window_s)
        self.mocap: list[M.LearnerState] = []  # restamped samples waiting for the loop

    # ---------------------------------------------------------------------------------------------- inputs
    def on_mocap(self, st: M.LearnerState, now: float) -> None:
        """A motion-capture sample: its own stamp put on this host's clock (:mod:`bridge.core.clock`). A sample
        stamped ahead of any possible delivery is dropped (``mocap_dropped``: forged, or a clock step not yet
        confirmed); a confirmed step of the bridge's clock restarts the estimate (``mocap_clock_restarts``)."""
        with self.lock:
            t, verdict = self.mocap_clock.judge(st.stamp, now)
            if verdict != "ok":
                self.inputs.count("mocap_clock_restarts" if verdict == "restarted" else "mocap_dropped")
            if t is not None and t > 0:
                self.mocap.append(msgspec.structs.replace(st, stamp=t))

    def on_cmd(self, cmd: M.Command, now: float) -> None:
        with self.lock:
            accepted = self.gate.offer(cmd, now)
        if accepted:
            self.wake.set()  # apply it now, not at the next tick

    def on_estop(self, e: M.Estop, now: float) -> None:
        with self.lock:
            changed = self.gate.estop(e)
            if changed and not e.engaged:
                self.clear_requested = True
        if changed:
            log.warning("estop %s by %r: %s", "engaged" if e.engaged else "released", e.source, e.reason)
        self.wake.set()

    def on_estop_query(self, query: zenoh.Query) -> None:
        with self.lock:
            st = M.EstopState(stamp=time.monotonic(), node=f"driver-{self.link}", latched=self.gate.estopped,
                              source=self.gate.estop_source, reason=self.gate.estop_reason)
        query.reply(self.keys.estop, M.encode(st))

    # ------------------------------------------------------------------------------------------------ tick
    def decide(self, now: float) -> Decision:
        """The gate's decision, overruled by the link's health and the telemetry's age."""
        self.health = self.driver.health()
        with self.lock:
            d = self.gate.decide(now)
            clear, self.clear_requested = self.clear_requested, False
        if clear:
            log.warning("operator released the estop: clearing the link's latched faults")
            self.driver.clear_faults(now)
        if d.driving and not self.health.ok:
            return Decision(0.0, 0.0, blocked_reason(self.health), d.cmd_seq)
        if d.driving and now - self.last_pose > self.max_telemetry_age:
            return Decision(0.0, 0.0, "no_telemetry", d.cmd_seq)
        return d

    def tick(self, now: float) -> None:
        d = self.decide(now)
        if d.driving:
            self.driver.send(d.v, d.omega, now)
        else:
            self.driver.stop(now)
        if d.reason != self.last_decision.reason and not d.driving:
            log.info("vehicle stopped: %s", d.reason)
        self.last_decision = d
        self._put("applied", M.Applied(stamp=now, seq=self.seq["applied"], v=d.v, omega=d.omega, reason=d.reason,
                                       cmd_seq=d.cmd_seq))
        self.seq["applied"] += 1
        for st in self.poses(now):
            try:
                self._put("state", M.validated(st))
            except M.MessageError:
                self.inputs.count("telemetry_out_of_range")
                log.warning("telemetry out of range, not published: %s", st)
                continue
            self.seq["state"] += 1
            self.last_pose = max(self.last_pose, now)

    def poses(self, now: float) -> list[M.LearnerState]:
        """This tick's poses: the link's telemetry, or the motion-capture samples (the link is polled either way:
        its frames carry the vehicle's health)."""
        link = self.driver.poll(now)
        if self.pose_source == "mocap":
            with self.lock:
                samples, self.mocap = self.mocap, []
            return [msgspec.structs.replace(s, seq=self.seq["state"] + i, epoch=self.epoch, source="mocap")
                    for i, s in enumerate(sorted(samples, key=lambda s: s.stamp))]
        return [M.LearnerState(stamp=p.stamp, seq=self.seq["state"] + i, x=p.x, y=p.y, theta=p.theta, v=p.v,
                               omega=p.omega, source=self.link, epoch=self.epoch) for i, p in enumerate(link)]

    def status(self, now: float) -> M.Status:
        """Health as it is: ok only if the link is fit, the telemetry fresh and no estop is latched."""
        h = self.health
        with self.lock:
            counters = dict(self.gate.counters)
            estop = (self.gate.estopped, self.gate.estop_source)
        counters.update(self.inputs.snapshot())
        counters.update({"link_malformed": h.malformed, "link_errors": h.errors, "missed_deadlines": self.missed,
                         "frames_sent": h.frames_sent, "frames_received": h.frames_received, "ticks": len(self.ticks)})
        flat = {**h.detail, **h.detail.get("counters", {})}  # a link may group its counters under "counters"
        counters.update({f"link_{k}": int(v) for k, v in flat.items() if isinstance(v, (int, bool)) and int(v) >= 0})
        pose_age = now - self.last_pose
        problems = []
        if not h.ok:
            problems.append(h.text)
        if pose_age > self.max_telemetry_age:
            problems.append("no telemetry yet" if math.isinf(pose_age) else f"no telemetry for {pose_age:.1f} s")
        if estop[0]:
            problems.append(f"estop latched by {estop[1] or 'unknown'}")
        lat = {"telemetry_age": min(pose_age, 1e6) * 1e3}
        if len(self.ticks) > 2:
            dev = np.abs(np.diff(np.asarray(self.ticks)) - self.period) * 1e3
            lat.update({"jitter_p50": float(np.percentile(dev, 50)), "jitter_p99": float(np.percentile(dev, 99)),
                        "jitter_max": float(dev.max())})
        text = f"link {self.link}: " + ("; ".join(problems) if problems else f"driving ({self.last_decision.reason})")
        msg = M.Status(stamp=now, seq=self.seq["status"], node="driver", ok=not problems,
                       rates_hz={"loop": 1.0 / self.period}, latencies_ms=lat, counters=counters, text=text[:1024])
        self.seq["status"] += 1
        return msg

    # ------------------------------------------------------------------------------------------------ run
    def _put(self, topic: str, msg: msgspec.Struct) -> None:
        self.pubs[topic].put(M.encode(msg))

    def serve(self, session: zenoh.Session, stop: threading.Event, duration: float | None) -> None:
        """Declare the host's keys, open the link and run the loop until ``stop`` or ``duration``."""
        k = self.keys
        self.inputs.subscribe(session, k.cmd, M.Command, "cmd", self.on_cmd)
        self.inputs.subscribe(session, k.estop, M.Estop, "estop", self.on_estop)
        session.declare_queryable(k.estop, self.on_estop_query)
        self.alive = session.liveliness().declare_token(M.alive_key(self.robot, "driver"))
        if self.pose_source == "mocap":
            self.inputs.subscribe(session, k.mocap, M.LearnerState, "mocap", self.on_mocap)
        self.pubs = {"applied": session.declare_publisher(k.applied), "state": session.declare_publisher(k.state),
                     "status": session.declare_publisher(M.status_key(self.robot, "driver"))}
        self._put("status", M.Status(stamp=time.monotonic(), seq=self.seq["status"], node="driver", ok=False,
                                     text=f"link {self.link}: opening (vehicle not yet ready)"))
        self.seq["status"] += 1
        self.driver.open(time.monotonic())  # may block up to the link's open_timeout (MAVLink: EKF, arming)
        log.info("driver host for %s on link %s at %.0f Hz (epoch %x)", self.robot, self.link, 1 / self.period,
                 self.epoch)
        self.loop(stop, duration)

    def loop(self, stop: threading.Event, duration: float | None) -> None:
        """Periodic ticks, plus an immediate tick for each accepted command; ticks are never closer than
        ``1 / max_send_hz``, so the link's send rate is bounded whatever arrives."""
        t_start = t_next = time.monotonic()
        t_status = t_start
        last_tick = -math.inf
        while not stop.is_set():
            gap = last_tick + self.min_gap - time.monotonic()
            if gap > 0:
                stop.wait(gap)
            now = time.monotonic()
            if duration is not None and now - t_start >= duration:
                return
            periodic = now >= t_next
            if periodic:
                self.ticks.append(now)
            self.tick(now)
            last_tick = now
            if now >= t_status:
                self._put("status", self.status(now))
                t_status = now + 1.0
            if periodic:
                t_next += self.period
                if t_next <= time.monotonic():
                    self.missed += 1
                    t_next = time.monotonic() + self.period
            delay = t_next - time.monotonic()
            if delay > 0 and self.wake.wait(delay):
                self.wake.clear()


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--link", choices=["can", "mavlink", "udp"], required=True)
    ap.add_argument("--config", help="driver TOML (scmbridge config show --kind driver; deploy/driver*.example.toml)")
    ap.add_argument("--robot", type=robot_arg, default=None, help="robot name (overrides the config)")
    add_zenoh_args(ap)
    ap.add_argument("--rate", type=positive_float, default=None, help="control loop rate, Hz (overrides the config)")
    ap.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    ap.add_argument("--emulate", action="store_true", help="host emulated CAN motor controllers in-process")
    ap.add_argument("--model", default="mpc", help="learner model for --emulate (mpc, experiment, scaled)")
    ap.add_argument("--x0", type=pose_arg, default=(0.0, 0.0, 0.0), help="start pose x,y,theta for --emulate")


def _emulated_ecus(cfg, model: str, x0: tuple[float, float, float]):
    """The learner's two emulated motor controllers on the driver's virtual CAN channel (``--emulate``)."""
    from sim_learner.can_ecu import DiffDriveEcus
    from sim_learner.dynamics import model_by_name
    from sim_learner.vehicle import SimVehicle

    vehicle = SimVehicle(model_by_name(model), x0, now=time.monotonic())
    return DiffDriveEcus({"interface": "virtual", "channel": cfg.channel}, vehicle, left_node=cfg.left_node,
                         right_node=cfg.right_node, left_sign=cfg.left_sign, right_sign=cfg.right_sign,
                         wheel_radius=cfg.wheel_radius, track_width=cfg.track_width).start()


def run(args: argparse.Namespace) -> int:
    if args.emulate and args.link != "can":
        raise UsageError("--emulate hosts CAN motor controllers; run `scmbridge learner` for the other links")
    cfg = load_driver(args.config)  # a mistake ends here, before any link or session opens
    robot = M.check_robot(args.robot or cfg.robot)
    link_cfg = getattr(cfg.link, args.link)
    if args.emulate:
        link_cfg = msgspec.structs.replace(link_cfg, interface="virtual", channel=f"scm-{robot}",
                                           initial_pose=args.x0)
    from drivers import open_driver

    host = DriverHost(cfg, args.link, open_driver(args.link, link_cfg), robot, args.rate or cfg.driver.rate_hz)
    stop = stop_on_signals()
    ecus = _emulated_ecus(link_cfg, args.model, args.x0) if args.emulate else None
    try:
        with open_session(zenoh_config(args), wait=stop, what="driver host") as session:
            host.serve(session, stop, args.duration)
    finally:
        host.driver.close()
        if ecus is not None:
            ecus.stop()
    return 0
