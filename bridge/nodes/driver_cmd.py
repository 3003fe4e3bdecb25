"""``scmbridge driver``: the driver host, between Zenoh and one vehicle link (docs/ARCHITECTURE.md).

It subscribes to ``scm/<robot>/cmd`` and ``scm/<robot>/estop`` and answers queries on the estop key with its latch
state. A person is in charge: the host starts *not engaged* (a restart never takes a vehicle back) and sends nothing
but stops until a person engages it (``scmbridge engage``: a query on ``scm/<robot>/engage``; MAVLink: also the
operator selecting GUIDED and arming while the host runs; ``engage_on_start`` in the config). The estop latch is
kept in the state directory and re-read at start, so it survives a restart or a reboot; it fails safe: a latch that
could not be saved stops the host and refuses engage until a release is saved (status reason ``latch_unsaved``), and
a latch file missing beside the install marker, unreadable or not signed by this host starts latched
(:mod:`bridge.nodes.latch_store`). The state directory must stay the same across restarts (``SCMBRIDGE_STATE_DIR``):
a host given a fresh one says "first start in this state directory: no estop history". A link anyone on the network
can drive (UDP ``insecure``, ``--insecure``; MAVLink without signing) is said in the log and on status
(``unauthenticated_link``). Closing stops the vehicle, waits until it reports it has stopped, and only then disarms
(a vehicle engaged by this host). Every command is decoded (so validated: finite, in wire range) and goes through
the pure :class:`bridge.core.gate.CommandGate`: the next of its sender's ``(epoch, seq)`` stream, fresh (received
less than min(valid_ms, cmd_timeout) ago), a stop applied as exactly zero, anything else clamped to the configured
hard limits. The host hands the result to the link driver only while the link says the vehicle is fit to drive
(``health().ok``) and its telemetry is fresh; otherwise it stops the vehicle and says why. Each tick it echoes what
the vehicle really got on ``applied``, publishes the link's poses as ``state`` (its own epoch and sequence) and a
truthful ``status``, each second and at once when it changes. Commands are applied as they arrive (latency is not a
multiple of the period), but the link never gets more than ``max_send_hz`` of them. An estop latches a stop; only a
source named in ``estop_release_sources`` releases it, and a release is the operator action that lets the link clear
its controllers' latched faults. All stamps are on this host's monotonic clock, so the station pairs ``applied``
with ``state`` without any clock synchronisation.

``--emulate`` (CAN only) hosts the emulated motor controllers on the same python-can ``virtual`` channel inside
this process: the wire between driver and controllers is python-can, not a shortcut. The host lets them send what
is due before each read of the bus, as controllers on their own hardware would have.

The host itself, its loop and its pieces: :mod:`bridge.nodes.driver_host`.
"""

from __future__ import annotations

import argparse
import logging

import msgspec

from bridge.core import timebase
from bridge.core import wire as M
from bridge.core.args import pose_arg, positive_float, robot_arg
from bridge.core.auth import load_key
from bridge.core.clock import SYSTEM
from bridge.core.config import load_fence
from bridge.core.errors import UsageError
from bridge.nodes.driver_config import load_driver
from bridge.nodes.driver_host import DriverHost
from bridge.nodes.latch_store import latch_file
from bridge.nodes.node import add_zenoh_args, stop_on_signals, stopped_because, zenoh_config
from bridge.nodes.zsession import open_session
from drivers import REFUSED, link_names, open_driver

log = logging.getLogger("scmbridge.driver")


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--link", choices=link_names(), required=True)
    ap.add_argument("--config", help="driver TOML (scmbridge config show --kind driver; deploy/driver*.example.toml)")
    ap.add_argument("--robot", type=robot_arg, default=None, help="robot name (overrides the config)")
    add_zenoh_args(ap)
    ap.add_argument("--rate", type=positive_float, default=None, help="control loop rate, Hz (overrides the config)")
    ap.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    ap.add_argument("--emulate", action="store_true", help="host emulated CAN motor controllers in-process")
    ap.add_argument("--model", default="mpc", help="learner model for --emulate (mpc, experiment, scaled, miswired)")
    ap.add_argument("--x0", type=pose_arg, default=(0.0, 0.0, 0.0), help="start pose x,y,theta for --emulate")
    ap.add_argument("--drift", default=None, metavar="KIND[:AT[:OVER[:AMOUNT]]]",
                    help="for --emulate: the learner changes at run time, battery (the motors' top speed falls) or "
                         "wheel (the left wheel drags), AT s after the wheels first turn, over OVER s (default 20:10)")
    ap.add_argument("--engage", action="store_true",
                    help="engage the vehicle at start, as engage_on_start (a person at the keyboard; never in a unit "
                         "that restarts)")
    ap.add_argument("--fence", default=None, metavar="FILE",
                    help="(mavlink) upload the fence of FILE (a mission file's fence, or a station configuration's "
                         "[station] fence) to the vehicle as its own, enabled, Hold at a breach, after the link opens "
                         "and before anything is driven: the autopilot holds it even if the station and this host "
                         "die (every step confirmed by the vehicle; refused: the host exits)")
    ap.add_argument("--dry-run", action="store_true",
                    help="run the whole loop and publish applied, but send nothing to the vehicle (bring-up)")
    ap.add_argument("--insecure", action="store_true",
                    help="UDP link without a key_file ([link.udp] insecure = true): no authentication, anyone on the "
                         "network can drive the robot (loopback tests; said in the log and on status)")


def _emulated_ecus(cfg, model: str, x0: tuple[float, float, float], drift: str | None = None,
                   clock: timebase.Clock = timebase.monotonic):
    """The learner's two emulated motor controllers on the driver's virtual CAN channel (``--emulate``), changing
    at run time as ``drift`` says (``--drift``)."""
    from sim_learner.can_ecu import DiffDriveEcus, Drift
    from sim_learner.dynamics import model_by_name
    from sim_learner.vehicle import SimVehicle

    vehicle = SimVehicle(model_by_name(model), x0, now=clock())
    return DiffDriveEcus({"interface": "virtual", "channel": cfg.channel}, vehicle, left_node=cfg.left_node,
                         right_node=cfg.right_node, left_sign=cfg.left_sign, right_sign=cfg.right_sign,
                         wheel_radius=cfg.wheel_radius, track_width=cfg.track_width,
                         drift=Drift.parse(drift) if drift else None, clock=clock).start()


def run(args: argparse.Namespace) -> int:
    if args.emulate and args.link != "can":
        raise UsageError("--emulate hosts CAN motor controllers; run `scmbridge learner` for the other links")
    if args.drift is not None:
        if not args.emulate:
            raise UsageError("--drift changes the emulated controllers: give --emulate")
        from sim_learner.can_ecu import Drift

        try:
            Drift.parse(args.drift)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    cfg = load_driver(args.config)  # a mistake ends here, before any link or session opens
    for name, why in REFUSED:  # a lab's link package that registered wrongly: said, not silently missing
        log.warning("link %r of the scmbridge.links entry points not registered: %s", name, why)
    fence = []
    if args.fence is not None:
        if args.link != "mavlink":
            raise UsageError(f"--fence uploads ArduPilot's own fence: --link mavlink (the {args.link} link has none; "
                             "the station enforces a fence on every link)")
        fence = load_fence(args.fence)
    robot = M.check_robot(args.robot or cfg.robot)
    link_cfg = getattr(cfg.link, args.link)
    if args.emulate:
        link_cfg = msgspec.structs.replace(link_cfg, interface="virtual", channel=f"scm-{robot}",
                                           initial_pose=args.x0)
    if args.insecure:  # a person's opt-in, on the command line where it is seen (and on status, and in the log)
        if not hasattr(link_cfg, "insecure"):
            raise UsageError(f"--insecure is for --link udp (the {args.link} link has no such setting)")
        link_cfg = msgspec.structs.replace(link_cfg, insecure=True)
    for name in ("key_file", "signing_key_file"):  # a missing or unsafe key is one line now, not a retry loop later
        if getattr(link_cfg, name, ""):
            load_key(getattr(link_cfg, name), args.link)
    # the host's one clock, with its waits (the link's driver is built on the same one, the host's, by default)
    clock = SYSTEM
    host = DriverHost(cfg, args.link, open_driver(args.link, link_cfg), robot, args.rate or cfg.driver.rate_hz,
                      dry_run=args.dry_run, latch_path=latch_file(robot), clock=clock)
    host.options.engage_on_start = host.options.engage_on_start or args.engage
    host.options.fence = fence
    stop = stop_on_signals()
    ecus = _emulated_ecus(link_cfg, args.model, args.x0, args.drift, clock) if args.emulate else None
    if ecus is not None:
        host.options.co_located.append(ecus)
    try:
        with open_session(zenoh_config(args), wait=stop, what="driver host") as session:
            host.serve(session, stop, args.duration)
    finally:
        host.close()
        if ecus is not None:
            ecus.stop()
        log.info("driver host for %s stopped %s: the vehicle was given a stop%s", robot, stopped_because(stop),
                 "" if host.options.dry_run else " and released (what this host engaged)")
    return 0
