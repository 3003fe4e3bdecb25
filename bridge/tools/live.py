"""``scmbridge view``: a live view of robots while they drive, in Foxglove (the viewer many labs already use).

It subscribes to ``scm/<robot>/**`` (``--robot``, repeatable) or ``scm/**`` (``--all``) and serves the Foxglove
WebSocket protocol (the Foxglove SDK's server, on 127.0.0.1:8765 by default): open Foxglove (app or browser) and
connect to ``ws://HOST:PORT``. Clients that speak the protocol by its first name, ``foxglove.websocket.v1``
(Lichtblick, older Foxglove Studio), are let in as well as the SDK's ``foxglove.sdk.v1`` (the SDK's server accepts only
the latter; :mod:`bridge.tools.ws_front`). Per robot:

- ``/<robot>/pose`` (``foxglove.PoseInFrame`` in frame ``world``) and ``/<robot>/scene`` (``foxglove.SceneUpdate``:
  the mission's path, its obstacles as cylinders, the goal, the trail driven so far, the teacher's predicted plan),
  for the 3D panel;
- ``/<robot>/cmd``, ``/teacher``, ``/applied``, ``/limits``, ``/status/<node>``: the wire messages as JSON (with
  their JSON schemas), for plots and raw-message panels: commands and methods, learned limits, health.

``--mcap FILE`` also writes everything it shows into an MCAP file from the same calls (the SDK's writer). The
mission drawn is the one published on ``scm/<robot>/mission``, else ``--mission FILE``, else the paper's S-path.
Messages that fail to decode are counted and skipped. Runs until SIGINT/SIGTERM or ``--duration``.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
import warnings
from collections import deque
from typing import Any

import msgspec
import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg, robots_arg
from bridge.core.config import load_mission, mission_from_spec
from bridge.nodes.node import add_zenoh_args, stop_on_signals, zenoh_config
from bridge.nodes.zsession import open_session
from bridge.tools.ws_front import SubprotocolFront
from transfer.mission import Mission

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    import foxglove
    from foxglove import channels as fc
    from foxglove import messages as fm

log = logging.getLogger("scmbridge.view")

JSON_TOPICS: dict[str, type[msgspec.Struct]] = {"cmd": M.Command, "teacher": M.TeacherCommand,
                                                 "applied": M.Applied, "limits": M.Limits}
#: nodes whose status channels a named robot has from the start
NODES = ("station", "driver")
TRAIL = 2000  # poses kept per robot for the trail


def json_schema(kind: type[msgspec.Struct]) -> dict[str, Any]:
    """The message's JSON schema as an object schema at the top (msgspec puts it behind a ``$ref``)."""
    raw = msgspec.json.schema(kind)
    defs = raw.get("$defs", {})
    top = dict(defs[raw["$ref"].rsplit("/", 1)[1]]) if "$ref" in raw else dict(raw)
    if defs:
        top["$defs"] = defs
    return top


def _ts(t: float) -> fm.Timestamp:
    sec = int(t)
    return fm.Timestamp(sec=sec, nsec=int((t - sec) * 1e9))


def _quat(theta: float) -> fm.Quaternion:
    return fm.Quaternion(x=0.0, y=0.0, z=math.sin(theta / 2.0), w=math.cos(theta / 2.0))


def _line(points, color: tuple[float, float, float, float], thickness: float = 0.03) -> fm.LinePrimitive:
    return fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, thickness=thickness, scale_invariant=False,
                            points=[fm.Point3(x=float(x), y=float(y), z=0.0) for x, y in points],
                            color=fm.Color(r=color[0], g=color[1], b=color[2], a=color[3]))


class RobotView:
    """One robot's channels and what it has seen (trail, plan, mission)."""

    def __init__(self, robot: str, mission: Mission) -> None:
        self.robot = robot
        self.mission = mission
        self.trail: deque[tuple[float, float]] = deque(maxlen=TRAIL)
        self.plan: list[tuple[float, float]] = []
        self.pose = fc.PoseInFrameChannel(f"/{robot}/pose")
        self.scene = fc.SceneUpdateChannel(f"/{robot}/scene")
        self.json: dict[str, foxglove.Channel] = {}
        self.t_scene = 0.0
        for name, kind in JSON_TOPICS.items():
            self.channel(name, kind)
        for node in NODES:
            self.channel(f"status/{node}", M.Status)

    def channel(self, name: str, kind: type[msgspec.Struct]) -> foxglove.Channel:
        ch = self.json.get(name)
        if ch is None:
            ch = self.json[name] = foxglove.Channel(f"/{self.robot}/{name}", schema=json_schema(kind))
        return ch

    def state(self, st: M.LearnerState) -> None:
        now = time.time()
        self.trail.append((st.x, st.y))
        self.pose.log(fm.PoseInFrame(timestamp=_ts(now), frame_id="world", pose=fm.Pose(
            position=fm.Vector3(x=st.x, y=st.y, z=0.0), orientation=_quat(st.theta))))
        if now - self.t_scene >= 0.2:  # the scene (path, obstacles, trail) at 5 Hz is plenty for a person
            self.t_scene = now
            self.scene.log(self.scene_update(now))

    def scene_update(self, now: float) -> fm.SceneUpdate:
        m = self.mission
        cylinders = [fm.CylinderPrimitive(
            pose=fm.Pose(position=fm.Vector3(x=float(x), y=float(y), z=0.1), orientation=_quat(0.0)),
            size=fm.Vector3(x=2 * float(r), y=2 * float(r), z=0.2), bottom_scale=1.0, top_scale=1.0,
            color=fm.Color(r=0.6, g=0.6, b=0.6, a=0.8)) for x, y, r in m.obstacles]
        lines = [_line(m.path.points, (0.2, 0.2, 0.2, 1.0))]
        if len(self.trail) > 1:
            lines.append(_line(self.trail, (0.1, 0.4, 0.9, 1.0), 0.04))
        if len(self.plan) > 1:
            lines.append(_line(self.plan, (0.9, 0.5, 0.1, 1.0), 0.02))
        gx, gy = m.goal
        goal = fm.CylinderPrimitive(
            pose=fm.Pose(position=fm.Vector3(x=float(gx), y=float(gy), z=0.005), orientation=_quat(0.0)),
            size=fm.Vector3(x=2 * m.goal_tolerance, y=2 * m.goal_tolerance, z=0.01), bottom_scale=1.0,
            top_scale=1.0, color=fm.Color(r=0.1, g=0.7, b=0.2, a=0.4))
        entity = fm.SceneEntity(timestamp=_ts(now), frame_id="world", id=f"{self.robot}-mission", lines=lines,
                                cylinders=[*cylinders, goal])
        return fm.SceneUpdate(entities=[entity])


class LiveView:
    """Routes every ``scm/...`` sample to its robot's channels (see the module docstring)."""

    def __init__(self, mission: Mission) -> None:
        self.default_mission = mission
        self.robots: dict[str, RobotView] = {}
        self.lock = threading.Lock()
        self.counts = {"messages": 0, "malformed": 0}

    def robot(self, name: str) -> RobotView:
        view = self.robots.get(name)
        if view is None:
            view = self.robots[name] = RobotView(name, self.default_mission)
        return view

    def on_sample(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        if len(parts) < 3 or parts[0] != M.PREFIX:
            return
        robot, topic = parts[1], parts[2]
        data = sample.payload.to_bytes()
        try:
            with self.lock:
                self._route(self.robot(robot), topic, parts[3:], data)
                self.counts["messages"] += 1
        except M.MessageError:
            with self.lock:
                self.counts["malformed"] += 1

    def _route(self, view: RobotView, topic: str, rest: list[str], data: bytes) -> None:
        if topic == "state":
            view.state(M.decode(data, M.LearnerState))
        elif topic == "mission":
            spec = M.decode(data, M.MissionSpec)
            try:
                view.mission = mission_from_spec(spec)
            except ValueError as exc:
                raise M.MessageError(str(exc)) from exc
        elif topic == "status" and rest:
            st = M.decode(data, M.Status)
            view.channel(f"status/{rest[0]}", M.Status).log(msgspec.to_builtins(st))
        elif topic in JSON_TOPICS:
            msg = M.decode(data, JSON_TOPICS[topic])
            if isinstance(msg, M.TeacherCommand):
                view.plan = list(zip(msg.predicted_x, msg.predicted_y))
            view.channel(topic, JSON_TOPICS[topic]).log(msgspec.to_builtins(msg))


def arguments(ap: argparse.ArgumentParser) -> None:
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--robot", type=robot_arg, help="the robot to show")
    who.add_argument("--robots", type=robots_arg, help="the robots to show, comma-separated")
    who.add_argument("--all", action="store_true", help="every robot on the network")
    ap.add_argument("--host", default="127.0.0.1", help="the Foxglove WebSocket server's address")
    ap.add_argument("--port", type=int, default=8765, help="its port (0: any free one, printed)")
    ap.add_argument("--mcap", default=None, help="also write what is shown into this MCAP file")
    ap.add_argument("--mission", default=None, help="mission drawn until one is published (default: the S-path)")
    ap.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    # a named robot's channels exist from the start, so a viewer that connects sees them all in its first
    # advertisement; the address is printed once the Zenoh subscriptions are in place
    mission = load_mission(args.mission)
    named = [] if args.all else list(args.robots or [args.robot])
    selectors = ["scm/**"] if args.all else [f"scm/{r}/**" for r in named]
    view = LiveView(mission)
    for robot in named:
        view.robot(robot)
    stop = stop_on_signals()
    # the SDK's server on a loopback port of its own, behind the front that also lets foxglove.websocket.v1 clients in
    server = foxglove.start_server(name="scmbridge", host="127.0.0.1", port=0)
    try:
        front = SubprotocolFront(args.host, args.port, server.port)
    except OSError:
        server.stop()
        raise
    writer: Any = foxglove.open_mcap(args.mcap, allow_overwrite=True) if args.mcap else None
    try:
        with open_session(zenoh_config(args)) as session:
            for sel in selectors:
                session.declare_subscriber(sel, view.on_sample)
            print(f"foxglove live view on ws://{args.host}:{front.port} ({', '.join(selectors)})", flush=True)
            stop.wait(args.duration)
    finally:
        front.stop()
        server.stop()
        if writer is not None:
            writer.close()
    log.info("shown %d messages, %d malformed", view.counts["messages"], view.counts["malformed"])
    if view.counts["messages"] == 0:
        print(f"scmbridge view: nothing received on {', '.join(selectors)}: nothing was published, or the router's "
              "access control does not let this identity read it (scmbridge doctor)", file=sys.stderr)
        return 1
    return 0
