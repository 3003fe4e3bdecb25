"""``scmbridge engage --robot R``: a person hands the vehicle to the system (or takes it back with ``--release``).

A driver host starts not engaged, also after a restart: it sends only stops until a person engages it. Engaging
is a query on ``scm/<robot>/engage`` answered by the driver host once done: MAVLink: GUIDED selected and armed,
each confirmed by the vehicle (or the vehicle's reason for refusing); CAN: both axes in closed loop (refused, naming
the axis, while one reports an error, unless ``--clear-faults``); UDP: the host starts sending commands. Refused
while an estop is latched. Engaging an engaged host says so and succeeds. The station still drives only after
``scmbridge mission start`` (or resume). The request is addressed to the driver host's current start (its epoch and
a reading of its clock, from its answer to a first request) and carries a random nonce: the host refuses one made
for another start (recorded before a restart), one older than 10 s by its own clock or seen before (a recorded
request replayed), and one without them (an older tool, a recorded old-format payload); no clock sync is needed.
``--release`` (a stop) is always honoured. Exit status: 0 done, 1 refused, 2 no driver host answered, 3 denied by the
lab's access control (this certificate's role may not engage: the observer, a robot; deploy/README.md), said at
once: a tool that knows its role from its certificate waits only a moment for an answer that cannot come.
"""

from __future__ import annotations

import argparse
import sys
import time

import zenoh

from bridge.core import wire as M
from bridge.core.acts import address_of, stamped
from bridge.core.args import positive_float, robot_arg
from bridge.core.errors import Denied, UsageError
from bridge.nodes.node import add_zenoh_args, endpoints_tried, zenoh_config
from bridge.nodes.zsession import open_session
from bridge.tools.identity import expected_denial, unnamed_hint

RETRY_S = 0.25


def ask(session: zenoh.Session, robot: str, req: M.EngageRequest, timeout: float) -> list[M.EngageState]:
    """Every driver host's answer to ``req`` (asking again until one answers or ``timeout`` passes). Each try is
    stamped now, with a new nonce, and addressed (:func:`bridge.core.acts.stamped`): a first request naming no
    process is answered by each host with its epoch and clock (an engage it refuses ``unaddressed``; a hand-back it
    takes), then each such host is asked once more, addressed to it: a driver host takes an engage fresh and once,
    and only as the act of its own start."""
    t_end = time.monotonic() + timeout
    while True:
        out = []
        for first in _get(session, robot, stamped(req), t_end):
            to = address_of(first)
            if first.accepted or to is None:  # taken as it was (a hand-back), or an older host's last word
                out.append(first)
                continue
            out.extend(st for st in _get(session, robot, stamped(req, to), t_end) if st.epoch == to.epoch)
        if out or time.monotonic() + RETRY_S >= t_end:
            return out
        time.sleep(RETRY_S)


def _get(session: zenoh.Session, robot: str, req: M.EngageRequest, t_end: float) -> list[M.EngageState]:
    """The answers of every driver host of ``robot`` to one query carrying ``req``."""
    out = []
    # every host answers on the same key: Zenoh's default consolidation would keep one reply per key
    for reply in session.get(M.key(robot, "engage"), payload=M.encode(req), timeout=max(0.1, t_end - time.monotonic()),
                             consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is None:
            continue
        try:
            out.append(M.decode(reply.ok.payload.to_bytes(), M.EngageState))
        except M.MessageError:
            continue
    return out


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--robot", type=robot_arg, required=True, help="the robot to engage")
    ap.add_argument("--release", action="store_true", help="hand the vehicle back: the host sends only stops")
    ap.add_argument("--clear-faults", action="store_true",
                    help="also clear what the motor controllers latched (look at the robot first)")
    ap.add_argument("--source", default="operator", help="who you are (the driver host logs it)")
    ap.add_argument("--timeout", type=positive_float, default=40.0,
                    help="seconds to wait for the driver host (engaging a vehicle can take a while: arming checks)")
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    req = M.EngageRequest(stamp=time.monotonic(), engaged=not args.release, source=args.source,
                          clear_faults=args.clear_faults)
    conf = zenoh_config(args)
    key = M.key(args.robot, "engage")
    denied, timeout = expected_denial(conf, args.robot, "query", key,
                                      "release a robot" if args.release else "engage a robot", args.timeout)
    with open_session(conf) as session:
        answers = ask(session, args.robot, req, timeout)
    if not answers:
        if denied:
            raise Denied(denied)
        raise UsageError(f"no driver host answered on {key} within {args.timeout:g} s "
                         f"(tried {endpoints_tried(args)}){unnamed_hint(conf, args.robot)}")
    for st in answers:
        print(f"{args.robot}/{st.node}: {'' if st.accepted else 'REFUSED: '}{st.text}",
              file=sys.stdout if st.accepted else sys.stderr)
    return 0 if all(st.accepted for st in answers) else 1
