"""``scmbridge estop``: stop one robot or every robot now, or release a latched stop, and see who latched it.

``--robot R`` (or ``--robots A,B`` or ``--all``) publishes an Estop on each robot's ``scm/<robot>/estop`` and asks
its driver host (a query on the same key, answered with the latch state) until it confirms, sending again at each
try, for up to ``--timeout`` seconds. ``--all`` means every robot known on the network: those whose driver host
answers, those whose driver host's liveliness token is present (a stalled host keeps it until its session expires)
and those whose nodes publish status. ``--release`` releases the latch; a driver host honours it only from a
source its configuration names (``estop_release_sources``), so ``--source`` must be one of them, and only when it
is fresh and new: each release carries this machine's wall-clock time and a random nonce, and a driver host refuses
one more than 10 s off its own clock or seen before (a recorded release replayed) or without them (an older
tool), and the latch it answers with says why. A stop is always honoured.

Prints one line per driver host (latched or released, by whom). Exit status: 0 when every robot confirmed the asked
state, 1 naming every robot that did not (or when none was found), 2 when the router cannot be reached, 3 when the
lab's access control denies this certificate's role the estop (the observer, a robot; deploy/README.md). A release
that a driver host answers but does not take names the reason: its ``estop_release_sources``.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg, robots_arg
from bridge.core.errors import Denied
from bridge.nodes.node import add_zenoh_args, zenoh_config
from bridge.nodes.zsession import open_session
from bridge.tools.identity import denial

#: seconds one try waits for a driver host's answer
TRY_TIMEOUT_S = 0.5
#: seconds ``--all`` listens for status and liveliness to find robots that do not answer at once
DISCOVER_S = 1.2


def latch_states(session: zenoh.Session, selector: str, timeout: float) -> dict[str, M.EstopState]:
    """``{robot/node: EstopState}`` from every driver host that answers a query on ``selector`` in time."""
    out: dict[str, M.EstopState] = {}
    # every host of a robot answers on the same key: Zenoh's default consolidation would keep one reply per key
    for reply in session.get(selector, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is None:
            continue
        try:
            st = M.decode(reply.ok.payload.to_bytes(), M.EstopState)
        except M.MessageError:
            continue
        robot = str(reply.ok.key_expr).split("/")[1]
        out[f"{robot}/{st.node}"] = st
    return out


def known_robots(session: zenoh.Session, wait: float) -> set[str]:
    """Every robot something on the network speaks for: estop answers, liveliness tokens, status publishers."""
    robots: set[str] = set()
    lock = threading.Lock()

    def on_status(sample: zenoh.Sample) -> None:
        with lock:
            robots.add(str(sample.key_expr).split("/")[1])

    sub = session.declare_subscriber(f"{M.PREFIX}/*/status/**", on_status)
    try:
        found = {k.split("/")[0] for k in latch_states(session, f"{M.PREFIX}/*/estop", TRY_TIMEOUT_S)}
        for reply in session.liveliness().get(f"{M.PREFIX}/*/alive/**", timeout=TRY_TIMEOUT_S):
            if reply.ok is not None:
                found.add(str(reply.ok.key_expr).split("/")[1])
        time.sleep(max(0.0, wait - 2 * TRY_TIMEOUT_S))  # nodes publish status each second
    finally:
        sub.undeclare()
    with lock:
        return found | robots


def confirm(session: zenoh.Session, robots: list[str], msg_for, engaged: bool, deadline: float,
            ) -> dict[str, dict[str, M.EstopState]]:
    """Send the estop to each robot not yet confirmed and ask it, until all confirm or the deadline passes.
    Returns ``{robot: {robot/node: state}}`` of the last answers (empty for a robot that never answered)."""
    answers: dict[str, dict[str, M.EstopState]] = {r: {} for r in robots}
    pending = list(robots)
    while pending:
        for robot in pending:
            session.put(M.key(robot, "estop"), M.encode(msg_for()))
        for robot in pending:
            left = deadline - time.monotonic()
            got = latch_states(session, M.key(robot, "estop"), max(0.05, min(TRY_TIMEOUT_S, left)))
            if got:
                answers[robot] = got
        pending = [r for r in pending
                   if not answers[r] or any(st.latched != engaged for st in answers[r].values())]
        if not pending or time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    return answers


def arguments(ap: argparse.ArgumentParser) -> None:
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--robot", type=robot_arg, help="the robot to stop")
    who.add_argument("--robots", type=robots_arg, help="these robots (comma-separated names)")
    who.add_argument("--all", action="store_true", help="every robot found on the network")
    ap.add_argument("--release", action="store_true", help="release a latched estop (needs a configured --source)")
    ap.add_argument("--source", default="operator", help="who you are (driver hosts release only named sources)")
    ap.add_argument("--reason", default="", help="why, for the driver hosts' logs")
    ap.add_argument("--timeout", type=positive_float, default=5.0,
                    help="seconds to keep trying until every robot confirms")
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    engaged = not args.release
    deadline = time.monotonic() + args.timeout
    conf = zenoh_config(args)
    with open_session(conf) as session:
        if args.all:
            robots = sorted(known_robots(session, DISCOVER_S))
            if not robots:
                print(f"scmbridge estop: no robot found (no answer on {M.PREFIX}/*/estop, no liveliness token, "
                      "no status)", file=sys.stderr)
                return 1
        else:
            robots = [args.robot] if args.robot else list(args.robots)

        def msg_for() -> M.Estop:
            return M.Estop(stamp=time.monotonic(), engaged=engaged, source=args.source, reason=args.reason,
                           wall_time=time.time(), nonce=M.new_nonce())  # a release is taken fresh and once

        answers = confirm(session, robots, msg_for, engaged, max(deadline, time.monotonic() + TRY_TIMEOUT_S))
    failed, denied = [], []
    for robot in robots:
        states = answers[robot]
        for name, st in sorted(states.items()):
            state = f"LATCHED by {st.source or 'unknown'}" if st.latched else "released"
            print(f"{name}: {state}" + (f" ({st.reason})" if st.reason else ""))
        if states and all(st.latched == engaged for st in states.values()):
            continue
        failed.append(robot)
        # the router drops an estop this identity may not send without a word (an observer may still ask the latch)
        why = denial(conf, robot, "put", M.key(robot, "estop"), "release an estop" if args.release else
                     "latch an estop")
        if why:
            print(f"{robot}: {why}", file=sys.stderr)
            denied.append(robot)
        elif not states:
            print(f"{robot}: no driver host confirmed within {args.timeout:g} s", file=sys.stderr)
        elif args.release and any(st.release_refused for st in states.values()):  # the host says why
            for name, st in sorted(states.items()):
                if st.release_refused:
                    print(f"{name}: release {st.release_refused}", file=sys.stderr)
        elif args.release:  # the host answered and kept its latch, without saying why (an older host)
            print(f"{robot}: release not confirmed: a driver host releases only from a source named in its "
                  f"estop_release_sources (driver configuration), and --source {args.source!r} is not one of them "
                  "(or a new estop latched it again, or the host could not save the release: its reason above)",
                  file=sys.stderr)
    if failed:
        print(f"scmbridge estop: not confirmed by {', '.join(failed)}", file=sys.stderr)
    if denied and len(denied) == len(failed):
        return Denied.EXIT
    return 1 if failed else 0
