"""``scmbridge learner``: a software learner behind a vehicle link, as its own process.

``--link can``: the learner's two emulated ODrive motor controllers on a python-can bus given by ``--interface`` /
``--channel`` (``udp_multicast`` inside a private network namespace to reach a driver host in another process,
``socketcan`` on a vcan device where the kernel has one). ``--link udp``: the UDP-shim robot on ``--host:--port``,
obeying and answering only ``--peer`` (the driver host's ``bind_host:bind_port``, 127.0.0.1:47801 by default; ``first``
pins the first valid sender instead), refusing commands beyond ``--v-max`` / ``--omega-max`` and stopping on its
``--watchdog``.
``--link mavlink``: the ArduPilot-Rover-like vehicle listening for a GCS on UDP ``--host:--port``.
Runs until ``--duration`` or SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import signal
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from bridge.core.args import pose_arg, positive_float
from bridge.core.auth import load_key
from bridge.core.errors import UsageError
from bridge.core.paths import state_dir

if TYPE_CHECKING:
    from sim_learner.vehicle import SimVehicle


def _peer_arg(text: str | None) -> tuple[str, int] | str:
    """``--peer``: ``HOST:PORT`` or ``first``; None is the robot's default (the driver host's default address)."""
    from sim_learner.udp_robot import DEFAULT_PEER

    if text is None:
        return DEFAULT_PEER
    if text == "first":
        return "first"
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UsageError(f"--peer {text!r}: expected HOST:PORT (the driver host's bind address) or 'first'")
    return host.strip("[]"), int(port)


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--link", choices=sorted(EMULATORS), required=True)
    ap.add_argument("--port", type=int, default=None, help="(udp, mavlink) UDP port on --host (47800 / 14550)")
    ap.add_argument("--host", default="127.0.0.1", help="(udp, mavlink) the address to listen on")
    ap.add_argument("--interface", default="udp_multicast")
    ap.add_argument("--channel", default="239.74.163.2")
    ap.add_argument("--model", default="mpc",
                    help="learner model: mpc, experiment, scaled, miswired (its yaw the wrong way round)")
    ap.add_argument("--x0", type=pose_arg, default=(0.0, 0.0, 0.0), help="start pose x,y,theta")
    ap.add_argument("--noise", type=float, default=0.0, help="position measurement noise std (m)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    ap.add_argument("--wheel-radius", type=float, default=0.1)
    ap.add_argument("--track-width", type=float, default=0.4)
    ap.add_argument("--drift", default=None, metavar="KIND[:AT[:OVER[:AMOUNT]]]",
                    help="(can) the learner changes at run time: battery (the motors' top speed falls) or wheel (the "
                         "left wheel drags), AT s after the wheels first turn, over OVER s (default 20:10; "
                         "sim_learner/can_ecu.py)")
    ap.add_argument("--peer", default=None, help="(udp) the driver host's HOST:PORT, the only sender obeyed and "
                    "answered (default 127.0.0.1:47801, the driver's default bind), or 'first': pin the first "
                    "valid sender")
    ap.add_argument("--v-max", type=float, default=1.0, help="(udp) the robot's own limit |v|, m/s: refused beyond")
    ap.add_argument("--omega-max", type=float, default=2.0, help="(udp) the robot's own limit |omega|, rad/s")
    ap.add_argument("--watchdog", type=float, default=0.5, help="(udp) no command for this long stops it, s")
    ap.add_argument("--key-file", default=None, help="(udp) the datagram key (scmbridge keys udp): commands must "
                    "carry its tag; (mavlink) the signing key: unsigned messages are refused")
    ap.add_argument("--signing-store", default=None, help="(mavlink) the file standing for the autopilot's storage: "
                    "the signing timestamp is kept there across restarts, as ArduPilot keeps it (default: "
                    "<state dir>/emulator/mavlink-PORT.signing; 'none': a key as just set by SETUP_SIGNING at each "
                    "start)")


def _mavlink(args: argparse.Namespace, vehicle: SimVehicle, stop: threading.Event) -> None:
    from sim_learner.mavlink_rover import MavlinkRover

    port = 14550 if args.port is None else args.port
    key = load_key(args.key_file) if args.key_file else None
    store = args.signing_store or str(state_dir() / "emulator" / f"mavlink-{port}.signing")
    with MavlinkRover(vehicle, args.host, port, signing_key=key,
                      signing_store=None if store == "none" or key is None else store) as rover:
        print(f"learner on mavlink udp {args.host}:{rover.port}, model {args.model}", flush=True)
        stop.wait(args.duration)


def _udp(args: argparse.Namespace, vehicle: SimVehicle, stop: threading.Event) -> None:
    from sim_learner.udp_robot import UdpRobot

    peer = _peer_arg(args.peer)
    port = 47800 if args.port is None else args.port
    with UdpRobot(vehicle, args.host, port, peer=peer, v_max=args.v_max, omega_max=args.omega_max,
                  watchdog=args.watchdog, key=load_key(args.key_file) if args.key_file else None) as robot:
        shown = "the first valid sender" if peer == "first" else f"{peer[0]}:{peer[1]}"
        print(f"learner on udp {args.host}:{robot.port}, model {args.model}, peer {shown}", flush=True)
        stop.wait(args.duration)


def _can(args: argparse.Namespace, vehicle: SimVehicle, stop: threading.Event) -> None:
    from sim_learner.can_ecu import DiffDriveEcus, Drift

    bus_kwargs = {"interface": args.interface, "channel": args.channel}
    if args.interface == "udp_multicast":
        bus_kwargs["fd"] = False
    drift = Drift.parse(args.drift) if args.drift else None
    with DiffDriveEcus(bus_kwargs, vehicle, wheel_radius=args.wheel_radius, track_width=args.track_width,
                       drift=drift):
        print(f"learner on {args.interface}:{args.channel}, model {args.model}", flush=True)
        stop.wait(args.duration)


#: the links this learner emulates, each by the device it behaves as (the drivers' registry marks the same links
#: ``EMULATED``; sim_learner does not import drivers, so a test checks the two agree)
EMULATORS: dict[str, Callable[[argparse.Namespace, SimVehicle, threading.Event], None]] = {
    "can": _can,
    "mavlink": _mavlink,
    "udp": _udp,
}


def run(args: argparse.Namespace) -> int:
    if args.drift is not None:
        if args.link != "can":
            raise UsageError("--drift changes the emulated CAN controllers (--link can)")
        from sim_learner.can_ecu import Drift

        try:
            Drift.parse(args.drift)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    if args.link == "udp":
        _peer_arg(args.peer)  # a mistake is one line before anything starts
        if not (0 < args.v_max < 1e3 and 0 < args.omega_max < 1e3 and 0 < args.watchdog < 60):
            raise UsageError("--v-max, --omega-max and --watchdog must be positive (and finite)")

    import numpy as np

    from sim_learner.dynamics import model_by_name
    from sim_learner.vehicle import SimVehicle

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    rng = np.random.default_rng(args.seed) if args.noise > 0 else None
    vehicle = SimVehicle(model_by_name(args.model), args.x0, now=time.monotonic(), pos_noise=args.noise, rng=rng)
    EMULATORS[args.link](args, vehicle, stop)
    return 0
