"""``scmbridge status``: why is it (not) moving? One line per robot and node, from the status every node publishes
each second (``scm/<robot>/status/<node>``): the driver host's line says whether the vehicle is *moving* or
*stopped* (its measured speed), whether a person engaged it and what it is given; the station's, driving, or the one
reason it is not (estop latched by whom, operator
took control, waiting for engage, no pose, link down, mission paused or finished), the link, the pose's age, the
pairs learned and the mission's progress. ``--watch`` prints it again every second until Ctrl-C.

Nodes publish their status each second and at once when it changes, and answer a query with their last one, so
what it prints is how things stand when it is asked, as soon as every node asked about has answered.
A paused mission says what stands in the way now, or, once the robot is fit again, ``scmbridge mission
resume``; a robot parked at its goal is ``parked``.

Exit status: 0 when every robot asked about is driving (or parked at its goal) with no estop latched, 1 when one is
not (a robot whose station or driver host is missing is one: its ``missing`` line says so; an estop latched on a
robot whose mission is finished is one), 2 when no node answered (with the endpoints tried), 3 when the lab's access
control denies this identity the statuses (a robot's certificate; said at once).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from dataclasses import dataclass, field

import msgspec
import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg, robots_arg
from bridge.core.errors import Denied, UsageError
from bridge.nodes.node import add_zenoh_args, endpoints_tried, zenoh_config
from bridge.nodes.tlsid import identity
from bridge.nodes.zsession import open_session
from bridge.tools.identity import DEFAULT_ROLES, DENIED_WAIT_S, denial

#: a node's status older than this is reported as silent (they publish each second)
STALE_S = 3.0
#: the station's states in which its robot is doing what it should (driving, or done): for a station older than the
#: typed reason
GOOD = ("driving", "running", "finished", "parked")
#: the station's typed reasons (``Status.reason``) under which its robot is doing what it should (driving, at its goal)
GOOD_REASONS = ("ok", "goal_reached")
#: a vehicle whose measured speed (m/s) or yaw rate (rad/s) reaches either is *moving*; below both, *stopped*
MOVING_V = 0.02
MOVING_OMEGA = 0.05


@dataclass
class Seen:
    """The latest status of every node heard, with the time it arrived."""

    latest: dict[tuple[str, str], tuple[M.Status, float]] = field(default_factory=dict)
    malformed: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample) -> None:  # Zenoh's thread: decode and store
        parts = str(sample.key_expr).split("/")
        try:
            st = M.decode(sample.payload.to_bytes(), M.Status)
        except M.MessageError:
            with self.lock:
                self.malformed += 1
            return
        if len(parts) == 4:
            with self.lock:
                self.latest[(parts[1], parts[3])] = (st, time.monotonic())


def _state(st: M.Status) -> str:
    return st.state or ("ok" if st.ok else "not ok")


def driver_estop(st: M.Status) -> bool:
    """A driver host's status says an estop is latched: its typed reason (its state for a host older than it)."""
    return st.reason == "estop" if st.reason is not None else st.state == "estop"


def motion(st: M.Status) -> str | None:
    """*moving* or *stopped*, from the vehicle's measured speeds on a driver host's status (None: not measured)."""
    if st.measured is None:
        return None
    v, omega = st.measured
    return "moving" if abs(v) >= MOVING_V or abs(omega) >= MOVING_OMEGA else "stopped"


def node_line(robot: str, node: str, st: M.Status, age: float) -> str:
    """``rover1  driver   stopped   0.00 m/s, 0.00 rad/s | not engaged | link can: estop latched by operator | pose
    0.02 s old``: what a person needs at a glance. A driver host's line says what the vehicle does (*moving* or
    *stopped*, measured), beside whether a person engaged it and the host's reason; never "driving" for a robot
    that stands still."""
    if age > STALE_S:
        return f"{robot:<12} {node:<8} {'silent':<9} no status for {age:.0f} s (the node is down or unreachable)"
    parts = [st.text or st.reason or ("ok" if st.ok else "not ok")]
    moves = motion(st)
    if moves is not None and st.measured is not None:
        engaged = [] if st.engaged is None else ["engaged" if st.engaged else "not engaged"]
        parts = [f"{st.measured[0]:.2f} m/s, {st.measured[1]:.2f} rad/s", *engaged, *parts]
    if st.progress is not None:
        parts.append(f"mission {100 * st.progress:.0f}%")
    pairs = st.counters.get("refined_pairs")
    if pairs is not None:
        parts.append(f"pairs {pairs}")
    if st.changed_cells:
        parts.append(f"re-learned cells {', '.join(map(str, st.changed_cells))}")
    pose_ms = st.latencies_ms.get("telemetry_age")
    if pose_ms is not None:
        parts.append("pose never" if pose_ms >= 1e8 else f"pose {pose_ms / 1e3:.2f} s old")
    return f"{robot:<12} {node:<8} {moves or _state(st):<9} " + " | ".join(parts)


def robot_ok(statuses: dict[str, tuple[M.Status, float]], now: float) -> bool:
    """A robot is fine when its station and its driver host are heard, no estop is latched on it, and the station
    drives (or is parked at the goal), by the typed reasons (the states for a node older than that field), never
    the words."""
    station, driver = statuses.get("station"), statuses.get("driver")
    if station is None or driver is None or now - station[1] > STALE_S or now - driver[1] > STALE_S:
        return False
    if driver_estop(driver[0]):
        return False
    st = station[0]
    if st.reason is not None:
        return st.ok and st.reason in GOOD_REASONS
    return st.ok and (st.state in GOOD or (not st.state and st.ok))


def report(seen: Seen, robots: list[str] | None) -> tuple[list[str], bool]:
    """The lines to print and whether every robot is fine."""
    now = time.monotonic()
    with seen.lock:
        latest = dict(seen.latest)
    names = sorted(robots if robots is not None else {r for r, _ in latest})
    lines, all_ok = [], True
    for robot in names:
        nodes = {n: v for (r, n), v in latest.items() if r == robot}
        if not nodes:
            lines.append(f"{robot:<12} {'-':<8} {'silent':<9} no node of this robot answered")
            all_ok = False
            continue
        if "station" not in nodes:  # the station is down (or another host's, unreachable): say it, first
            lines.append(f"{robot:<12} {'station':<8} {'missing':<9} no status from the robot's station: it is down "
                         "or unreachable (the driver host stops the robot on its deadman; estop still reaches it)")
        if "driver" not in nodes:
            lines.append(f"{robot:<12} {'driver':<8} {'missing':<9} no status from the robot's driver host: it is down "
                         "or unreachable (the vehicle's own failsafe stops it; scmbridge doctor)")
        parked = "station" in nodes and nodes["station"][0].state == "parked"
        for node in sorted(nodes, key=lambda n: (n != "station", n != "driver", n)):
            st, at = nodes[node]
            if node == "driver" and parked and st.state == "driving":  # fit, and held at the goal by the station
                st = msgspec.structs.replace(st, state="parked")
            lines.append(node_line(robot, node, st, now - at))
        all_ok &= robot_ok(nodes, now)
    return lines, all_ok


def arguments(ap: argparse.ArgumentParser) -> None:
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--robot", type=robot_arg, help="the robot to report")
    who.add_argument("--robots", type=robots_arg, help="the robots to report, comma-separated")
    who.add_argument("--all", action="store_true", help="every robot whose nodes publish a status")
    ap.add_argument("--watch", action="store_true", help="print again every second until Ctrl-C")
    ap.add_argument("--timeout", type=positive_float, default=1.5,
                    help="seconds to listen for the nodes' statuses (they publish each second; default 1.5)")
    add_zenoh_args(ap)


def complete(seen: Seen, robots: list[str] | None) -> bool:
    """Whether every robot asked about (every robot heard, for ``--all``) has both its station and its driver host
    heard: then there is nothing more to wait for."""
    with seen.lock:
        nodes = set(seen.latest)
    names = robots if robots is not None else sorted({r for r, _ in nodes})
    return bool(names) and all((r, "station") in nodes and (r, "driver") in nodes for r in names)


def ask(session, seen: Seen, selectors: list[str], timeout: float) -> None:
    """Ask every node for its last status (each node's status key is also a queryable,
    :class:`bridge.nodes.node.StatusOut`): one round trip, instead of up to a second's wait for the next periodic
    one. A node too old to answer is heard by the subscription instead."""
    for sel in selectors:
        for reply in session.get(sel, timeout=max(0.05, timeout), consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is not None:
                seen.on_sample(reply.ok)


def _denial(conf, robots: list[str] | None, selector: str) -> str | None:
    """The denial this identity expects for reading the statuses (:func:`bridge.tools.identity.denial`)."""
    me = identity(conf)
    robot = robots[0] if robots else (me.cn if me is not None and me.cn not in DEFAULT_ROLES else "robot")
    try:
        return denial(conf, robot, "declare_subscriber", selector, "read the robots' status")
    except ValueError:
        return None


def run(args: argparse.Namespace) -> int:
    robots = None if args.all else (args.robots or [args.robot])
    selectors = ["scm/*/status/*"] if robots is None else [f"scm/{r}/status/*" for r in robots]
    seen = Seen()
    ok = False
    conf = zenoh_config(args)
    denied = _denial(conf, robots, selectors[0])
    timeout = min(args.timeout, DENIED_WAIT_S) if denied else args.timeout
    with open_session(conf) as session:
        subs = [session.declare_subscriber(s, seen.on_sample) for s in selectors]
        try:
            deadline = time.monotonic() + timeout
            ask(session, seen, selectors, deadline - time.monotonic())
            while not complete(seen, robots) and time.monotonic() < deadline:
                time.sleep(0.02)  # a node that did not answer the query (an older one): its next periodic status
            if not seen.latest:
                if denied:
                    raise Denied(denied)
                raise UsageError(f"no node's status arrived within {args.timeout:g} s on {', '.join(selectors)} "
                                 f"(tried {endpoints_tried(args)}); is the router up, and may this identity read "
                                 "scm/*/status?")
            lines, ok = report(seen, robots)
            print("\n".join(lines), flush=True)
            while args.watch:
                time.sleep(1.0)
                lines, ok = report(seen, robots)
                print(f"--- {time.strftime('%H:%M:%S')}\n" + "\n".join(lines), flush=True)
        except KeyboardInterrupt:
            pass
        finally:
            for s in subs:
                s.undeclare()
    if seen.malformed:
        print(f"scmbridge status: {seen.malformed} malformed status messages ignored", file=sys.stderr)
    return 0 if ok else 1
