"""``scmbridge router``: the lab's Zenoh router as a process of its own (deploy/README.md, step 3).

Every node of a lab (the station, each robot's driver host, the operator's and observer's tools) is a client of this
router; it carries no scmbridge logic, only Zenoh's routing and, with the file ``scmbridge deploy acl`` (or ``deploy
lab``) writes, mutual TLS and the access control. Running it apart from the station is what lets the operator's
tools work while the station is down: ``scmbridge status`` still says what each driver host reports (and that the
station is missing) and ``scmbridge estop --all`` still reaches every robot's driver host, instead of both failing
with "cannot reach the Zenoh router" and the robots stopping only by their deadman.

The router's access control is read once, when it starts: Zenoh cannot change it at runtime (zenoh.io, "Access
Control": "ACL config cannot be updated at runtime, and requires a restart"), so a robot added to the fleet costs a
router restart (deploy/README.md, "Adding a robot").
"""

from __future__ import annotations

import argparse
import json
import logging
import threading

import zenoh

from bridge.core.clock import SYSTEM, Clock
from bridge.core.errors import UsageError
from bridge.nodes import systemd
from bridge.nodes.node import stop_on_signals
from bridge.nodes.zsession import make_config, secured, tls_file_problem

log = logging.getLogger("scmbridge.router")


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--zenoh-config", help="the router's Zenoh JSON5 file (`scmbridge deploy acl` or `deploy lab` "
                                           "writes it: TLS and the access control); --listen overrides its endpoints")
    ap.add_argument("--listen", action="append", default=[],
                    help="an endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable; never every interface)")
    ap.add_argument("--connect", action="append", default=[],
                    help="another router to connect to (repeatable: two routers of one lab)")
    ap.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: run until "
                                                                 "SIGINT, SIGTERM or SIGHUP)")


def listening_on(conf: zenoh.Config) -> list[str]:
    """The endpoints ``conf`` listens on."""
    try:
        eps = json.loads(conf.get_json("listen/endpoints"))
    except Exception:  # a config without them
        return []
    if isinstance(eps, dict):  # Zenoh's per-mode default: the file names none
        eps = eps.get("router", [])
    return [str(e) for e in eps]


def acl_summary(conf: zenoh.Config) -> str:
    """The access control in one phrase (for the log line at start): off, or how many identities it names."""
    try:
        acl = json.loads(conf.get_json("access_control"))
    except Exception:
        return "no access control"
    if not acl or not acl.get("enabled"):
        return "no access control"
    names = sorted({cn for s in acl.get("subjects", []) for cn in s.get("cert_common_names", [])})
    return (f"access control (default {acl.get('default_permission', '?')}) naming {len(names)} identities: "
            f"{', '.join(names)}")


def router_config(args: argparse.Namespace) -> zenoh.Config:
    """The router's config: the file (its mode must be router) or loopback-safe defaults, ``--listen`` over it."""
    conf = make_config(mode="router", listen=args.listen, connect=args.connect, config_file=args.zenoh_config)
    try:
        mode = json.loads(conf.get_json("mode"))
    except Exception:
        mode = "router"
    if mode != "router":
        raise UsageError(f"--zenoh-config {args.zenoh_config} is a {mode}'s file: the router needs mode \"router\" "
                         "(scmbridge deploy acl writes it)")
    eps = listening_on(conf)
    if not eps:
        raise UsageError("name the endpoint to listen on: --listen tcp/ADDR:PORT or a --zenoh-config with "
                         "listen/endpoints (a router's default is every interface)")
    wild = [e for e in eps if "0.0.0.0" in e or "[::]" in e]
    if wild:
        raise UsageError(f"listen on the lab interface's address, not on every interface ({', '.join(wild)})")
    return conf


def run(args: argparse.Namespace) -> int:
    """The lab's Zenoh router, a process of its own: every node (station, driver hosts, the operator's tools)
    connects to it as a client, so the operator's tools keep working when the station stops (status says the
    station is missing; estop --all still reaches every robot). With the file `scmbridge deploy acl` writes: TLS
    only and the lab's access control, read once at start (Zenoh cannot reload it: a robot added to the fleet costs a
    restart, deploy/README.md). Tells systemd READY once it listens; runs until SIGINT, SIGTERM or SIGHUP."""
    conf = router_config(args)
    problem = tls_file_problem(conf)
    if problem:
        raise UsageError(f"the router cannot listen: {problem}")
    stop = stop_on_signals()
    eps = listening_on(conf)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        reason = str(exc).split(" at ", 1)[0].strip()
        raise UsageError(f"cannot listen on {', '.join(eps)} ({reason}): is the address this host's and the "
                         "port free, and are the certificates readable?") from None
    with session:
        what = f"listening on {', '.join(eps)}, {'TLS' if secured(conf) else 'no TLS'}, {acl_summary(conf)}"
        if not secured(conf):
            log.warning("this router speaks no TLS: anyone who reaches its network can publish commands and estop "
                        "releases (the demo and tests only; a lab runs the file `scmbridge deploy acl` writes)")
        log.info("router %s: %s", session.zid(), what)
        systemd.ready(what)
        end = None if args.duration is None else SYSTEM() + args.duration
        _wait(stop, end)
        systemd.stopping()
        log.info("router stopping: every client loses its link (driver hosts stop their robots by their deadman)")
    return 0


def _wait(stop: threading.Event, end: float | None, clock: Clock = SYSTEM) -> None:
    """Until ``stop`` is set (a signal) or ``end`` (on ``clock``) has passed."""
    while not stop.is_set():
        left = None if end is None else end - clock()
        if left is not None and left <= 0:
            return
        clock.wait(stop, 1.0 if left is None else min(left, 1.0))
