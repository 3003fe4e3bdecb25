"""``scmbridge bench pairing``: how good the command pairs from a link's own telemetry are (JSON).

A real driver drives an emulated learner (the MAVLink rover over UDP on 127.0.0.1, the ODrive controllers on a
python-can ``virtual`` channel, or the UDP shim's robot on 127.0.0.1) as the driver host does: a tick every 20 ms
(poll, then send), a new random command every ``--command-period`` s (the station's 10 Hz), each send echoed as the
host's ``applied`` stamp. The poses and echoes go through the station's
:class:`bridge.nodes.pairing.Reorder` and :class:`bridge.nodes.pairing.IntervalPairer`, and
each pair is compared with the learner's true response to its command (``LearnerModel.response``: what a perfect
pairing would measure).

Printed: the commands, the pairs formed and rejected, and the pairs' error (median, p90) in m/s and rad/s. The
pairing is judged on its medians; a loaded machine delays ticks and commands, not the vehicle's stamps.
"""

from __future__ import annotations

import argparse
import time
from contextlib import ExitStack
from typing import Any

import numpy as np

from bench.common import can_ecus, emit, open_can_driver
from bridge.core.config import StationSection
from bridge.nodes.driver_config import DriverSection

TICK = 1.0 / DriverSection().rate_hz  # the driver host's default tick
STATION_TICK = 1.0 / StationSection().rate_hz  # the station's default tick


def _opened(stack: ExitStack, link: str, config: Any) -> Any:
    from drivers import open_driver

    driver = open_driver(link, config)
    stack.callback(driver.close)
    driver.open(time.monotonic())
    driver.engage(time.monotonic())  # what a person's scmbridge engage does
    return driver


def _mavlink(stack: ExitStack, vehicle: Any) -> Any:
    from drivers.mavlink import MavlinkLinkConfig
    from sim_learner.mavlink_rover import MavlinkRover

    rover = MavlinkRover(vehicle).start()
    stack.callback(rover.stop)
    return _opened(stack, "mavlink", MavlinkLinkConfig(url=f"udpout:127.0.0.1:{rover.port}", open_timeout=10.0))


def _can(stack: ExitStack, vehicle: Any) -> Any:
    import uuid

    channel = f"pairing-{uuid.uuid4().hex[:8]}"
    can_ecus(stack, channel, vehicle)
    return open_can_driver(stack, channel)


def _udp(stack: ExitStack, vehicle: Any) -> Any:
    from bridge.tools.procs import free_udp_port
    from drivers.udp import UdpLinkConfig
    from sim_learner.udp_robot import UdpRobot

    port = free_udp_port()  # the driver's port, which the robot is pinned to
    robot = UdpRobot(vehicle, peer=("127.0.0.1", port)).start()
    stack.callback(robot.stop)
    return _opened(stack, "udp", UdpLinkConfig(insecure=True, robot_port=robot.port, bind_port=port))


#: link -> a factory of its emulated learner and an opened driver on it (both closed with the stack)
LINKS = {"mavlink": _mavlink, "can": _can, "udp": _udp}


def measure(link: str, seconds: float, seed: int = 0, command_period: float = 0.1, pair_dt: float = 0.1,
        min_span: float | None = None) -> dict:
    """Drive ``seconds`` of random commands through ``link`` and judge the pairs (see the module docstring)."""
    from bridge.nodes.pairing import IntervalPairer, Reorder
    from sim_learner.dynamics import mpc_learner
    from sim_learner.vehicle import SimVehicle

    model = mpc_learner()
    rng = np.random.default_rng(seed)
    (v0, v1), (w0, w1) = model.v_range, model.w_range
    events: list[tuple[float, int, Any, float]] = []  # (stamp, kind, payload, published)
    with ExitStack() as stack:
        driver = LINKS[link](stack, SimVehicle(model, (0.0, 0.0, 0.0), now=time.monotonic()))
        u = (0.0, 0.0)
        k = commands = 0
        t_next = t_cmd = t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            now = time.monotonic()
            events += [(p.stamp, 1, np.array([p.x, p.y, p.theta]), now) for p in driver.poll(now)]
            # a new command each command_period on the clock, as the station's tick sends them (not each
            # per_command ticks: ticks caught up after a stall come in a burst, and commands changed within one
            # would each be held for a moment no pair can span); periods missed in a stall are skipped
            if now >= t_cmd:  # the middle of the learner's range: no clamping, no standstill
                u = (float(rng.uniform(v0 + 0.25 * (v1 - v0), v1 - 0.25 * (v1 - v0))),
                     float(rng.uniform(w0 + 0.2 * (w1 - w0), w1 - 0.2 * (w1 - w0))))
                commands += 1
                t_cmd += command_period
                if t_cmd <= now:  # behind after a stall: the next one a whole period from now
                    t_cmd = now + command_period
            driver.send(*u, now)
            events.append((now, 0, u, now))  # the host's applied echo, stamped when sent
            k += 1
            t_next += TICK
            time.sleep(max(0.0, t_next - time.monotonic()))
    # as the station takes them: what reached it by each 10 Hz tick (the driver host publishes poses when it polls
    # them, echoes when it sends), through the station's reorder buffer
    pairer, reorder = IntervalPairer(pair_dt, min_span), Reorder()
    pairs = []
    ticks: dict[int, list[tuple[float, int, Any, float]]] = {}
    for stamp, kind, e, published in events:
        ticks.setdefault(int((published - t0) / STATION_TICK) + 1, []).append((stamp, kind, e, published))
    for n in range(1, max(ticks, default=0) + 1 + int(reorder.window / STATION_TICK) + 1):
        for stamp, kind, e, published in ticks.get(n, []):
            reorder.push(stamp, kind, published, (stamp, kind, e))
        for t, kind, e in reorder.ready(t0 + n * STATION_TICK):
            out = pairer.applied(t, e[0], e[1], "cmd") if kind == 0 else pairer.state(t, e)
            if out is not None:
                pairs.append(out)
    err = np.array([np.abs(uT - model.response(uL)) for uT, uL in pairs]).reshape(-1, 2)

    def stats(a: np.ndarray) -> dict[str, float]:
        return ({"median": float(np.median(a)), "p90": float(np.percentile(a, 90))} if a.size
                else {"median": float("nan"), "p90": float("nan")})

    return {"link": link, "seconds": seconds, "seed": seed, "commands": commands, "ticks": k,
            "pair_dt": pair_dt, "min_span": pairer.min_span, "formed": pairer.formed, "rejected": pairer.rejected,
            "out_of_order": pairer.out_of_order,
            "error_v_mps": stats(err[:, 0]), "error_omega_radps": stats(err[:, 1])}


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--link", choices=sorted(LINKS), default="mavlink")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of commands")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--command-period", type=float, default=0.1, help="s between new commands (the station's tick)")
    ap.add_argument("--min-span", type=float, default=None, help="the pairer's minimum span, s (default: its own)")


def run(args: argparse.Namespace) -> int:
    emit(measure(args.link, args.duration, args.seed, args.command_period, min_span=args.min_span))
    return 0
