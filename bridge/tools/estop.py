"""``scmbridge estop``: stop one robot or every robot now, or release a latched stop, and see who latched it.

``scmbridge estop --robot R`` (or ``--all``) publishes an :class:`bridge.core.wire.Estop` on ``scm/<robot>/estop``,
then asks the driver hosts (a Zenoh query on the same key, which each answers with its latch state) and prints one
line per driver host: latched or not, and by whom. ``--release`` releases the latch; a driver host honours it only
from a source its configuration names (``estop_release_sources``, default ``operator``), so ``--source`` must be
one of them; the release is logged there with the source, and it is the operator action that lets a link clear
its controllers' latched faults. Exit status: 0 when every driver host that answered is in the asked state, 1
otherwise (or when none answered).
"""

from __future__ import annotations

import argparse
import sys
import time

import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg
from bridge.nodes.node import add_zenoh_args, zenoh_config
from bridge.nodes.zsession import open_session


def latch_states(session: zenoh.Session, selector: str, timeout: float) -> dict[str, M.EstopState]:
    """``{robot/node: EstopState}`` from every driver host that answers a query on ``selector`` in time."""
    out: dict[str, M.EstopState] = {}
    for reply in session.get(selector, timeout=timeout):
        if reply.ok is None:
            continue
        try:
            st = M.decode(reply.ok.payload.to_bytes(), M.EstopState)
        except M.MessageError:
            continue
        robot = str(reply.ok.key_expr).split("/")[1]
        out[f"{robot}/{st.node}"] = st
    return out


def arguments(ap: argparse.ArgumentParser) -> None:
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--robot", type=robot_arg, help="the robot to stop")
    who.add_argument("--all", action="store_true", help="every robot whose driver host answers")
    ap.add_argument("--release", action="store_true", help="release a latched estop (needs a configured --source)")
    ap.add_argument("--source", default="operator", help="who you are (driver hosts release only named sources)")
    ap.add_argument("--reason", default="", help="why, for the driver hosts' logs")
    ap.add_argument("--timeout", type=positive_float, default=1.0,
                    help="seconds to wait for the driver hosts' answers")
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    engaged = not args.release
    with open_session(zenoh_config(args)) as session:
        if args.all:
            robots = sorted({k.split("/")[0] for k in latch_states(session, "scm/*/estop", args.timeout)})
            if not robots:
                print("scmbridge estop: no driver host answered on scm/*/estop", file=sys.stderr)
                return 1
        else:
            robots = [M.check_robot(args.robot)]
        for robot in robots:
            msg = M.Estop(stamp=time.monotonic(), engaged=engaged, source=args.source, reason=args.reason)
            session.put(M.key(robot, "estop"), M.encode(msg))
        time.sleep(0.2)  # the driver hosts apply it at once; give the put a moment before asking
        states: dict[str, M.EstopState] = {}
        for robot in robots:
            states.update(latch_states(session, M.key(robot, "estop"), args.timeout))
    missing = [r for r in robots if not any(k.startswith(f"{r}/") for k in states)]
    for name, st in sorted(states.items()):
        state = f"LATCHED by {st.source or 'unknown'}" if st.latched else "released"
        print(f"{name}: {state}" + (f" ({st.reason})" if st.reason else ""))
    for r in missing:
        print(f"{r}: no driver host answered", file=sys.stderr)
    return 0 if states and not missing and all(st.latched == engaged for st in states.values()) else 1
