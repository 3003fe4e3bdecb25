"""``scmbridge mission place FILE --robot R``: a mission put where the robot stands now, in the frame its poses come in.

The mission (a file, or a shipped mission's name) is moved rigidly, path, obstacles and start together, so that its
start pose (or its first point, facing along the path, without one) lands on the robot's pose: the last poses its
driver host publishes on ``scm/<robot>/state`` (any link, or motion capture), heard for ``--duration`` seconds with
the robot standing still (one that moves is refused: place it where it stands). ``--at X,Y,HEADING`` places it at
that pose instead (metres, degrees counter-clockwise from east), with no robot asked.

The placed mission's ``frame`` names where its coordinates are measured from: ``ekf-origin`` for the MAVLink link
(ArduPilot's LOCAL_POSITION_NED: east and north of the EKF origin, not of home; docs/OPERATING.md, "First day with
your rover", says what happens when that origin moves), ``odometry`` for a CAN or UDP robot (where it booted),
``mocap`` for motion capture; ``--frame`` says it for ``--at``. It is written to ``--out FILE`` (a mission file,
``scmbridge station --mission`` reads it) or printed, and ``--send`` loads it into the robot's station as ``mission
send`` does (idle until a person's ``mission start``). The first line says where it was put. Exit status: 0 placed
(and accepted, with ``--send``), 1 refused by the station, 2 no pose or no station answered, 3 denied.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from pathlib import Path

import msgspec

from bridge.core import wire as M
from bridge.core.args import positive_float
from bridge.core.config import load_mission_spec
from bridge.core.errors import UsageError
from bridge.nodes.node import endpoints_tried, zenoh_config
from bridge.nodes.zsession import open_session
from bridge.tools import mission

#: the frame a link's poses are in (the driver host's ``LearnerState.source``)
FRAMES = {"mavlink": "ekf-origin", "can": "odometry", "udp": "odometry", "mocap": "mocap"}
#: a robot standing still: every pose heard within this of the last, m and rad, and no reported speed above it, m/s
STILL_M, STILL_RAD, STILL_SPEED = 0.05, math.radians(3.0), 0.05


def place(spec: M.MissionSpec, pose: tuple[float, float, float], frame: str) -> M.MissionSpec:
    """``spec`` moved rigidly so that its start pose (or its first point facing along its first segment) lands on
    ``pose`` (x, y, theta; ENU), renamed ``<name>@placed`` in ``frame``."""
    if spec.start is not None:
        sx, sy, sth = spec.start
    else:
        (sx, sy), (x1, y1) = spec.path[0], next((p for p in spec.path[1:] if p != spec.path[0]), spec.path[1])
        sth = math.atan2(y1 - sy, x1 - sx)
    px, py, pth = pose
    c, s = math.cos(pth - sth), math.sin(pth - sth)

    def move(x: float, y: float) -> list[float]:
        dx, dy = x - sx, y - sy
        return [px + c * dx - s * dy, py + s * dx + c * dy]

    return msgspec.structs.replace(spec, name=spec.name[:55] + "@placed", frame=frame,
                                   path=[move(x, y) for x, y in spec.path],
                                   obstacles=[[*move(x, y), r] for x, y, r in spec.obstacles],
                                   start=[px, py, math.remainder(pth, 2 * math.pi)])


def mission_toml(spec: M.MissionSpec) -> str:
    """A mission file for ``spec`` (what ``scmbridge station --mission`` and ``mission send`` read)."""
    def num(x: float) -> str:
        return repr(round(float(x), 6))

    rows = ",\n".join(f"  [{num(x)}, {num(y)}]" for x, y in spec.path)
    obs = ",\n".join(f"  [{num(x)}, {num(y)}, {num(r)}]" for x, y, r in spec.obstacles)
    start = "" if spec.start is None else f"start = [{', '.join(num(a) for a in spec.start)}]\n"
    return (f'name = "{spec.name}"\nframe = "{spec.frame}"\ngoal_tolerance = {num(spec.goal_tolerance)}\n'
            f"{start}obstacles = [\n{obs}\n]\npath = [\n{rows}\n]\n")


def still_pose(states: list[M.LearnerState]) -> tuple[float, float, float]:
    """The robot's pose from the poses heard (the last), refused with UsageError when it moved meanwhile."""
    last = states[-1]
    moved = [s for s in states if math.hypot(s.x - last.x, s.y - last.y) > STILL_M
             or abs(math.remainder(s.theta - last.theta, 2 * math.pi)) > STILL_RAD
             or (s.v is not None and abs(s.v) > STILL_SPEED)]
    if moved:
        raise UsageError(f"the robot is moving ({len(moved)} of {len(states)} poses away from its last or faster than "
                         f"{STILL_SPEED} m/s): place the mission where it stands still")
    return float(last.x), float(last.y), float(last.theta)


def hear_poses(args: argparse.Namespace) -> list[M.LearnerState]:
    """The poses the robot's driver host publishes, from the first one heard (``--timeout``) for ``--duration`` s."""
    got: list[M.LearnerState] = []
    first = threading.Event()
    lock = threading.Lock()

    def on(sample) -> None:
        try:
            st = M.decode(sample.payload.to_bytes(), M.LearnerState)
        except M.MessageError:
            return
        with lock:
            got.append(st)
        first.set()

    conf = zenoh_config(args)
    key = M.key(args.robot, "state")
    with open_session(conf) as session:
        sub = session.declare_subscriber(key, on)
        try:
            if not first.wait(args.timeout):
                raise UsageError(f"no pose from {args.robot} on {key} within {args.timeout:g} s (tried "
                                 f"{endpoints_tried(args)}): is its driver host running? Or give --at X,Y,HEADING")
            time.sleep(args.duration)  # the poses of a while, to see the robot stands still
        finally:
            sub.undeclare()
    with lock:
        return list(got)


def _pose_arg(text: str) -> tuple[float, float, float]:
    try:
        x, y, h = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected X,Y,HEADING (m, m, degrees)") from None
    if not all(math.isfinite(v) and abs(v) < 1e6 for v in (x, y, h)):
        raise argparse.ArgumentTypeError(f"{text!r}: not a pose")
    return x, y, math.radians(h)


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("file", help="the mission file, or a shipped mission's name (paper-s-path)")
    ap.add_argument("--at", type=_pose_arg, default=None, metavar="X,Y,HEADING",
                    help="place it at this pose (m, m, degrees CCW from east) instead of where the robot stands")
    ap.add_argument("--frame", default=None,
                    help="the placed mission's frame (default: the one the robot's poses come in; 'world' for --at)")
    ap.add_argument("--duration", type=positive_float, default=1.0,
                    help="seconds of poses to see the robot stands still")
    ap.add_argument("--out", default=None, help="write the placed mission here (default: print it)")
    ap.add_argument("--send", action="store_true", help="load it into the robot's station (idle until started)")
    mission._arguments(ap)


def run(args: argparse.Namespace) -> int:
    """Put a mission where the robot stands now (its pose on Zenoh, any link) or at ``--at``; write or send it."""
    spec = load_mission_spec(args.file)
    if args.at is not None:
        pose, frame = args.at, args.frame or "world"
    else:
        states = hear_poses(args)
        pose = still_pose(states)
        frame = args.frame or FRAMES.get(states[-1].source, states[-1].source or "world")
    placed = place(spec, pose, frame)
    text = mission_toml(placed)
    msgspec.toml.decode(text.encode(), type=M.MissionSpec)  # it reads back as a mission file, before it is used
    where = (f"placed {spec.name!r} at x {pose[0]:.3f} m, y {pose[1]:.3f} m, heading {math.degrees(pose[2]):.1f} deg "
             f"in frame {frame!r}")
    print(where, file=sys.stderr if args.out is None and not args.send else sys.stdout)
    if args.out is not None:
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")
    elif not args.send:
        sys.stdout.write(text)
    if args.send:
        return mission._run(args, "send", placed)
    return 0
