"""``scmbridge mission start|pause|resume|abort|status|send``: a person's requests to a robot's station.

Each is a Zenoh query on ``scm/<robot>/control`` (a :class:`bridge.core.wire.MissionRequest`), answered by the
station with what it did or why it refused, and where the mission is (``running``, ``paused: estop latched by
operator``, ...). A station starts idle and drives only after ``start``; after an estop, an operator takeover, a
lost link or a driver-host restart it pauses, and only ``resume`` drives on. ``send FILE`` loads a new mission
(idle until started); ``send FILE --reverse`` the same mission from its goal back to its start (a ``start`` with the
robot already at the goal is refused: it would end at once). Each request is addressed to the station's current run
(its epoch and a reading of its clock, from a ``status`` asked first) and carries a random nonce: the station refuses
one made for another run (recorded before a restart), one older than 10 s by its own clock or seen before (a
recorded request replayed), and one without them (an older tool, a recorded old-format payload); ``status`` needs
none; no clock sync is needed. A mission published on ``scm/<robot>/mission`` by a program (not a person's ``send``) is
named in the answer, with when it came, so it is looked at before ``start``. Prints the answer in one line. Exit
status: 0 accepted, 1 refused, 2 no station answered, 3 denied by the lab's access control (this certificate's role
may not ask: the observer, a robot; deploy/README.md), said at once.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import msgspec
import zenoh

from bridge.core import wire as M
from bridge.core.acts import address_of, stamped
from bridge.core.args import positive_float, robot_arg
from bridge.core.config import load_mission_spec
from bridge.core.errors import Denied, UsageError
from bridge.nodes.node import add_zenoh_args, endpoints_tried, zenoh_config
from bridge.nodes.zsession import open_session
from bridge.tools.identity import expected_denial, unnamed_hint

#: a fresh session needs a moment to reach the station: ask again this often until --timeout
RETRY_S = 0.25


def ask(session: zenoh.Session, robot: str, req: M.MissionRequest, timeout: float) -> M.MissionState | None:
    """The station's answer to ``req``, asking again until ``timeout``; None if no station answered. An act is
    addressed to the station's current run: each try first asks its status (its epoch and clock), then sends the
    act stamped with a new nonce and that address (:func:`bridge.core.acts.stamped`)."""
    t_end = time.monotonic() + timeout
    while True:
        to = None
        if req.action != "status":
            status = _get(session, robot, M.MissionRequest(stamp=req.stamp, action="status", source=req.source),
                          t_end)
            to = address_of(status) if status is not None else None
        if to is not None or req.action == "status":
            # the station is there (it answered the status): its answer is awaited until the timeout, not asked for
            # again (a slow station's answer to the first act would come after a second act it answered too)
            st = _get(session, robot, stamped(req, to), t_end, whole=req.action != "status")
            if st is not None:
                return st
        elif status is not None:  # an older station (no epoch): the act as it takes it
            st = _get(session, robot, stamped(req), t_end)
            if st is not None:
                return st
        if time.monotonic() + RETRY_S >= t_end:
            return None
        time.sleep(RETRY_S)


def _get(session: zenoh.Session, robot: str, req: M.MissionRequest, t_end: float,
         whole: bool = False) -> M.MissionState | None:
    """The station's answer to one query carrying ``req`` (None: none within a second, or until ``t_end`` when
    ``whole``, or no station)."""
    left = t_end - time.monotonic()
    wait = left if whole else min(1.0, left)
    for reply in session.get(M.key(robot, "control"), payload=M.encode(req), timeout=max(0.05, wait)):
        if reply.ok is None:
            continue
        try:
            return M.decode(reply.ok.payload.to_bytes(), M.MissionState)
        except M.MessageError:
            continue
    return None


def line(st: M.MissionState) -> str:
    head = f"{st.robot}: {'' if st.accepted else 'REFUSED: '}{st.text}"
    where = f"mission {st.mission!r} {st.phase}" + (f" ({st.reason})" if st.reason and st.phase != "running" else "")
    out = f"{head} | {where}, {100 * st.progress:.0f}% done"
    if st.replaced_by:  # not a person's send: say so before anyone starts it
        at = time.strftime("%H:%M:%S", time.localtime(st.replaced_at)) if st.replaced_at else "?"
        out += f" | WARNING: this mission came from {st.replaced_by} at {at}, not from a person's send: check it"
    return out


def _arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--robot", type=robot_arg, required=True, help="the robot whose station to ask")
    ap.add_argument("--source", default="operator", help="who you are (the station logs it)")
    ap.add_argument("--timeout", type=positive_float, default=3.0, help="seconds to wait for the station's answer")
    add_zenoh_args(ap)


def _run(args: argparse.Namespace, action: str, spec: M.MissionSpec | None = None) -> int:
    req = M.MissionRequest(stamp=time.monotonic(), action=action, spec=spec, source=args.source,
                           override=bool(getattr(args, "override", False)))
    conf = zenoh_config(args)
    key = M.key(args.robot, "control")
    what = "ask for a mission's status" if action == "status" else f"{action} a mission"
    denied, timeout = expected_denial(conf, args.robot, "query", key, what, args.timeout)
    with open_session(conf) as session:
        st = ask(session, args.robot, req, timeout)
    if st is None:
        if denied:
            raise Denied(denied)
        raise UsageError(f"no station answered on {key} within {args.timeout:g} s "
                         f"(tried {endpoints_tried(args)}){unnamed_hint(conf, args.robot)}")
    print(line(st), file=sys.stdout if st.accepted else sys.stderr)
    return 0 if st.accepted else 1


def _override(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--override", action="store_true",
                    help="the robot is outside the mission's corridor or the fence: drive on anyway, to have the "
                         "station drive it back (the guard re-arms once it is inside; docs/OPERATING.md)")


def arguments_start(ap: argparse.ArgumentParser) -> None:
    _arguments(ap)
    _override(ap)


def run_start(args: argparse.Namespace) -> int:
    """Start the robot's mission (from the beginning after it finished or was aborted)."""
    return _run(args, "start")


def arguments_pause(ap: argparse.ArgumentParser) -> None:
    _arguments(ap)


def run_pause(args: argparse.Namespace) -> int:
    """Pause the running mission: the station publishes stops until a resume."""
    return _run(args, "pause")


def arguments_resume(ap: argparse.ArgumentParser) -> None:
    _arguments(ap)
    _override(ap)


def run_resume(args: argparse.Namespace) -> int:
    """Resume a paused mission; refused, with the reason, while an estop is latched, the robot is not fit, or it is
    outside the corridor or the fence (``--override``: resume to drive it back)."""
    return _run(args, "resume")


def arguments_abort(ap: argparse.ArgumentParser) -> None:
    _arguments(ap)


def run_abort(args: argparse.Namespace) -> int:
    """Abort the mission: stopped for good until a new start."""
    return _run(args, "abort")


def arguments_status(ap: argparse.ArgumentParser) -> None:
    _arguments(ap)


def run_status(args: argparse.Namespace) -> int:
    """Where the mission is and why."""
    return _run(args, "status")


def arguments_send(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("file", help="the mission file (TOML: scmbridge config show --kind mission), or a shipped "
                    "mission's name (paper-s-path)")
    ap.add_argument("--reverse", action="store_true",
                    help="the mission driven backwards along its path: from its goal back to its start (a robot "
                         "parked at the goal; a start there is refused, it would end at once)")
    _arguments(ap)


def reversed_spec(spec: M.MissionSpec) -> M.MissionSpec:
    """The same mission from its goal back to its start: the path reversed, the start pose at the old goal facing
    along the reversed path's first segment, the obstacles and the tolerance as they are."""
    path = [list(p) for p in reversed(spec.path)]
    k = next(i for i in range(1, len(path)) if path[i] != path[0])  # the first point away from the new start
    heading = math.atan2(path[k][1] - path[0][1], path[k][0] - path[0][0])
    name = spec.name[:55] + "-reversed"
    return msgspec.structs.replace(spec, name=name, path=path, start=[path[0][0], path[0][1], heading])


def run_send(args: argparse.Namespace) -> int:
    """Load a new mission into the station (idle until started); ``--reverse``: drive it back from its goal."""
    spec = load_mission_spec(args.file)  # a mistake is one line here, before anything is sent
    if args.reverse:
        spec = reversed_spec(spec)
    return _run(args, "send", spec)
