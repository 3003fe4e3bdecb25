"""``scmbridge estop``: stop one robot or every robot now, or release a latched stop, and see who latched it.

A stop is sent first and confirmed after: ``--robot R`` (or ``--robots A,B``) publishes an Estop on each robot's
``scm/<robot>/estop`` at once; ``--all`` publishes one on ``scm/*/estop`` (every driver host hears it) and on each
robot of the ``--fleet`` list before it looks for anyone. Then it asks the driver hosts (a query on the same keys,
answered with the latch state; all robots at once), sending again to each robot not yet confirmed, for up to
``--timeout`` seconds. ``--all`` also looks for robots on the network: those whose driver host answers, whose
liveliness token is present (a stalled host keeps it until its session expires) or whose nodes publish status; each
found is sent a stop too. ``--fleet FILE`` (a TOML file with ``[fleet] robots = [...]`` and/or the ``[fleet.shards]``
of deploy/README.md) names the lab's robots: one that never answers is named and fails the exit status, while names
seen on the network that are not in the fleet and never answer (a stale or fake liveliness token) are counted in one
line. Output is bounded: at most a few names per line. When the network was still listing its liveliness tokens at
the end of the discovery window (thousands of them on a loaded machine), the tool says so and counts the names it saw
as a lower bound.

``--release`` releases the latch; a driver host honours it only from a source its configuration names
(``estop_release_sources``), so ``--source`` must be one of them, and only addressed to its current start (its epoch
and a reading of its clock, from its answer) with a nonce not seen before: a release recorded and replayed, made for
an earlier start of the host, or from an older tool without them is refused, and the latch it answers with says
why. A stop is always honoured.

Prints one line per driver host whose answer confirms the asked state (latched or released, by whom). Exit status: 0
when every robot confirmed it, 1 naming every robot that did not (or when none was found), 2 when the router cannot
be reached, 3 when the lab's access control denies this certificate's role the estop (the observer, a robot;
deploy/README.md): then no robot's answer is printed as if it were this estop's. A release that a driver host answers
but does not take names the reason: its ``estop_release_sources``.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import tomllib
import zenoh

from bridge.core import wire as M
from bridge.core.acts import address_of, stamped
from bridge.core.args import positive_float, robot_arg, robots_arg
from bridge.core.errors import Denied, UsageError
from bridge.core.paths import read_bounded
from bridge.nodes.node import add_zenoh_args, zenoh_config
from bridge.nodes.zsession import open_session
from bridge.tools.identity import denial

#: seconds one try waits for the driver hosts' answers
TRY_TIMEOUT_S = 0.5
#: seconds ``--all`` listens for status and liveliness to find robots that do not answer at once
DISCOVER_S = 1.2
#: a liveliness query that took at least this share of its bound is taken as cut by it (answers may be missing)
CUT_SHARE = 0.95
#: names printed in one line at most (the rest counted)
SHOWN = 12
#: names that never answered sent a stop of their own at each try of ``--all`` at most (the wildcard reaches all)
SILENT_SENT = 64
ALL = f"{M.PREFIX}/*/estop"


def latch_states(session: zenoh.Session, selector: str, timeout: float) -> dict[str, M.EstopState]:
    """``{robot/node: EstopState}`` from every driver host that answers a query on ``selector`` in time."""
    return _collect([session.get(selector, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE)])


def _collect(handlers: list) -> dict[str, M.EstopState]:
    """The answers of queries already sent (all at once: each handler is read after all were sent)."""
    out: dict[str, M.EstopState] = {}
    for handler in handlers:
        # every host of a robot answers on the same key: Zenoh's default consolidation would keep one reply per key
        for reply in handler:
            if reply.ok is None:
                continue
            try:
                st = M.decode(reply.ok.payload.to_bytes(), M.EstopState)
            except M.MessageError:
                continue
            robot = str(reply.ok.key_expr).split("/")[1]
            out[f"{robot}/{st.node}"] = st
    return out


def ask_all(session: zenoh.Session, robots: list[str], timeout: float, wildcard: bool = False,
            ) -> dict[str, dict[str, M.EstopState]]:
    """``{robot: {robot/node: state}}``: every robot asked at once (one query on ``scm/*/estop`` with
    ``wildcard``, else one per robot, all sent before any answer is read)."""
    opts = dict(timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE)
    handlers = [session.get(ALL, **opts)] if wildcard else [session.get(M.key(r, "estop"), **opts) for r in robots]
    out: dict[str, dict[str, M.EstopState]] = {}
    for name, st in _collect(handlers).items():
        out.setdefault(name.split("/")[0], {})[name] = st
    return out


def known_robots(session: zenoh.Session, wait: float) -> tuple[set[str], bool]:
    """Every robot something on the network speaks for (estop answers, liveliness tokens, status publishers), and
    whether that list is complete: False when the liveliness query was still being answered when its share of the
    window ran out (thousands of tokens on a loaded machine), so that names may be missing."""
    robots: set[str] = set()
    lock = threading.Lock()

    def on_status(sample: zenoh.Sample) -> None:
        with lock:
            robots.add(str(sample.key_expr).split("/")[1])

    sub = session.declare_subscriber(f"{M.PREFIX}/*/status/**", on_status)
    start = time.monotonic()
    try:
        found = {k.split("/")[0] for k in latch_states(session, ALL, TRY_TIMEOUT_S)}
        # the tokens' replies may take the rest of the window (thousands of them on a loaded machine): the query
        # ends as soon as the router has answered, so a longer bound costs nothing where they come at once
        bound = max(TRY_TIMEOUT_S, wait - TRY_TIMEOUT_S)
        asked = time.monotonic()
        for reply in session.liveliness().get(f"{M.PREFIX}/*/alive/**", timeout=bound):
            if reply.ok is not None:
                found.add(str(reply.ok.key_expr).split("/")[1])
        complete = time.monotonic() - asked < CUT_SHARE * bound  # it ended on the router's last answer, not its bound
        time.sleep(max(0.0, wait - (time.monotonic() - start)))  # nodes publish status each second
    finally:
        sub.undeclare()
    with lock:
        return found | robots, complete


def send(session: zenoh.Session, robots: list[str], msg: M.Estop, wildcard: bool = False) -> None:
    """Publish ``msg`` on every robot's estop key (and on ``scm/*/estop`` with ``wildcard``): puts do not wait."""
    data = M.encode(msg)
    if wildcard:
        session.put(ALL, data)
    for robot in robots:
        session.put(M.key(robot, "estop"), data)


def confirm(session: zenoh.Session, robots: list[str], msg_for, engaged: bool, deadline: float,
            wildcard: bool = False, named: frozenset[str] = frozenset()) -> dict[str, dict[str, M.EstopState]]:
    """Ask every robot at once and send the estop again to each robot not yet confirmed (a release addressed to
    each of its driver hosts: ``msg_for(address)``), until all confirm or the deadline passes. With ``wildcard``
    (``--all``) a stop goes on ``scm/*/estop`` and to each robot that answered or is ``named`` (the fleet), and to
    at most :data:`SILENT_SENT` names that never answered (thousands of puts to fake names queue ahead of the real
    answers). Returns ``{robot: {robot/node: state}}`` of the last answers (empty for a robot that never
    answered)."""
    answers: dict[str, dict[str, M.EstopState]] = {r: {} for r in robots}

    def unconfirmed() -> list[str]:
        return [r for r in robots if not answers[r] or any(st.latched != engaged for st in answers[r].values())]

    def ask(pending: list[str]) -> None:  # each try waits a whole try's time: the last one too
        got = ask_all(session, pending, TRY_TIMEOUT_S, wildcard)
        for robot in pending:
            if got.get(robot):
                answers[robot] = got[robot]

    pending = list(robots)
    if not engaged:
        ask(pending)  # a release names the start of each host it is for: learn them first
    while pending:
        if engaged and wildcard:  # one stop every host hears, then each robot that answered or is named
            silent = [r for r in pending if not answers[r] and r not in named]
            send(session, [r for r in pending if answers[r] or r in named] + silent[:SILENT_SENT], msg_for(None),
                 wildcard=True)
        for robot in pending if not wildcard or not engaged else ():
            if engaged:
                session.put(M.key(robot, "estop"), M.encode(msg_for(None)))
            for st in answers[robot].values() if not engaged else ():
                session.put(M.key(robot, "estop"), M.encode(msg_for(address_of(st))))
        ask(pending)
        pending = unconfirmed()
        if not pending or time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    return answers


def fleet_robots(path: Path | None) -> list[str]:
    """The lab's robots from a fleet file: ``[fleet] robots`` and every robot of ``[fleet.shards]``."""
    if path is None:
        return []
    try:
        data = tomllib.loads(read_bounded(path, 1 << 20).decode())
    except (OSError, ValueError) as exc:
        raise UsageError(f"fleet file {path}: {exc}") from None
    fleet = data.get("fleet", {}) if isinstance(data, dict) else {}
    names = list(fleet.get("robots", []))
    for shard in fleet.get("shards", {}).values():
        names.extend(shard)
    try:
        return sorted({robot_arg(str(n)) for n in names})
    except (argparse.ArgumentTypeError, ValueError) as exc:
        raise UsageError(f"fleet file {path}: {exc}") from None


def shown(names: list[str]) -> str:
    """``names`` joined, at most :data:`SHOWN` of them (the rest counted)."""
    more = len(names) - SHOWN
    return ", ".join(names[:SHOWN]) + (f" and {more} more" if more > 0 else "")


def arguments(ap: argparse.ArgumentParser) -> None:
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--robot", type=robot_arg, help="the robot to stop")
    who.add_argument("--robots", type=robots_arg, help="these robots (comma-separated names)")
    who.add_argument("--all", action="store_true", help="every robot found on the network (and in --fleet)")
    ap.add_argument("--fleet", type=Path, default=None,
                    help="the lab's robots (TOML: [fleet] robots = [...] or [fleet.shards]): each must confirm")
    ap.add_argument("--release", action="store_true", help="release a latched estop (needs a configured --source)")
    ap.add_argument("--source", default="operator", help="who you are (driver hosts release only named sources)")
    ap.add_argument("--reason", default="", help="why, for the driver hosts' logs")
    ap.add_argument("--timeout", type=positive_float, default=5.0,
                    help="seconds to keep trying until every robot confirms")
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    engaged = not args.release
    deadline = time.monotonic() + args.timeout
    fleet = fleet_robots(args.fleet)
    conf = zenoh_config(args)

    def msg_for(to) -> M.Estop:
        msg = M.Estop(stamp=time.monotonic(), engaged=engaged, source=args.source, reason=args.reason)
        return msg if engaged else stamped(msg, to)  # a release is addressed, fresh and once

    with open_session(conf) as session:
        named = sorted(set(fleet) | ({args.robot} if args.robot else set(args.robots or ())))
        if engaged:  # stop first: before anything is looked for or waited on
            send(session, named, msg_for(None), wildcard=args.all)
        robots, strangers, complete = named, [], True
        if args.all:
            seen, complete = known_robots(session, DISCOVER_S)
            found = sorted(seen - set(named))
            robots = sorted(set(named) | set(found))
            if not robots:
                print(f"scmbridge estop: no robot found (no answer on {ALL}, no liveliness token, no status)",
                      file=sys.stderr)
                return 1
        answers = confirm(session, robots, msg_for, engaged, max(deadline, time.monotonic() + TRY_TIMEOUT_S),
                          wildcard=args.all, named=frozenset(named))
        if fleet:  # names the fleet does not list, which never answered: not the lab's robots
            strangers = [r for r in robots if r not in fleet and not answers[r]]
            robots = [r for r in robots if r not in strangers]
    return report(args, conf, robots, strangers, answers, engaged, complete)


def report(args: argparse.Namespace, conf, robots: list[str], strangers: list[str],
           answers: dict[str, dict[str, M.EstopState]], engaged: bool, complete: bool = True) -> int:
    """Print what was confirmed and who was not; the exit status (see the module docstring). ``complete`` False:
    the network was still listing its liveliness tokens when the discovery window ended, which is said, and the
    count of names seen is a lower bound."""
    failed, denied, silent = [], [], []
    for robot in robots:
        states = answers[robot]
        if states and all(st.latched == engaged for st in states.values()):
            for name, st in sorted(states.items()):
                state = f"LATCHED by {st.source or 'unknown'}" if st.latched else "released"
                print(f"{name}: {state}" + (f" ({st.reason})" if st.reason else ""))
            continue
        failed.append(robot)
        # the router drops an estop this identity may not send without a word (an observer may still ask the
        # latch): the robot's own state is then not this estop's answer, and is not printed as one
        why = denial(conf, robot, "put", M.key(robot, "estop"), "release an estop" if args.release else
                     "latch an estop")
        if why:
            if len(denied) < SHOWN:
                print(f"{robot}: {why}", file=sys.stderr)
            denied.append(robot)
            continue
        if not states:
            silent.append(robot)
            continue
        for name, st in sorted(states.items()):  # not denied: the host's own answer, said as not this estop's
            state = f"LATCHED by {st.source or 'unknown'}" if st.latched else "released"
            print(f"{name}: still {state} (not confirmed)", file=sys.stderr)
        if args.release and any(st.release_refused for st in states.values()):  # the host says why
            for name, st in sorted(states.items()):
                if st.release_refused:
                    print(f"{name}: release {st.release_refused}", file=sys.stderr)
        elif args.release:  # the host answered and kept its latch, without saying why (an older host)
            print(f"{robot}: release not confirmed: a driver host releases only from a source named in its "
                  f"estop_release_sources (driver configuration), and --source {args.source!r} is not one of them "
                  "(or a new estop latched it again, or the host could not save the release: its reason above)",
                  file=sys.stderr)
    if not complete:
        sent = f" (the stop on {ALL} went to every driver host that listens)" if engaged else ""
        print(f"the network was still listing its liveliness tokens when the {DISCOVER_S:g} s discovery window "
              f"ended: names may be missing below{sent}", file=sys.stderr)
    if silent:
        print(f"no driver host confirmed within {args.timeout:g} s: {shown(silent)}", file=sys.stderr)
    if strangers:
        at_least = "" if complete else "at least "
        print(f"{at_least}{len(strangers)} name(s) seen on the network, not in the fleet list, never answered (a "
              f"stale or fake liveliness token, or another lab's): {shown(strangers)}", file=sys.stderr)
    if failed:
        print(f"scmbridge estop: not confirmed by {shown(failed)}", file=sys.stderr)
    if denied and len(denied) == len(failed):
        return Denied.EXIT
    return 1 if failed else 0
