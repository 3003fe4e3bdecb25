"""An example external teacher: a lab's own controller driving a robot through scmbridge's transfer service.

It uses only the wire schema (``bridge.core.wire``) and Zenoh: it reads the robot's pose (``scm/<robot>/state``) and the
learned limits the station publishes (``scm/<robot>/limits``), computes a teacher command with a pure-pursuit
controller along a mission's path, bounds it by the learned limits as the paper's teacher does, and publishes it
on ``scm/<robot>/teacher`` at 10 Hz. The station (``[teacher] kind = "external"``) maps each command into the
learner's command space and drives the robot; at the goal this teacher says stop (an exact zero command).

    python deploy/examples/external_teacher.py --robot rover1 --zenoh-config /etc/scmbridge/teacher.json5 \
        --mission bridge/missions/paper_s_path.toml

It takes the Zenoh options every scmbridge command takes (``--zenoh-config`` a TLS client config that ``scmbridge
deploy client --name teacher`` writes, for the lab's access control with ``deploy acl --teacher-cn teacher``; or
``--mode client --connect tcp/...`` on a test network) and prints what it does: where it connects, then each second
the pose, the command and the limits it bounds it by, and the goal when it gets there.
"""

from __future__ import annotations

import argparse
import math
import threading
import time

import msgspec
import zenoh

from bridge.core import wire as W
from bridge.nodes.node import add_zenoh_args, endpoints_tried, zenoh_config
from bridge.nodes.zsession import open_session


def load_path(mission: str) -> tuple[list[tuple[float, float]], float]:
    """Waypoints and goal tolerance of a mission file (the same MissionSpec the station reads)."""
    with open(mission, "rb") as f:
        spec = msgspec.toml.decode(f.read(), type=W.MissionSpec)
    return [(float(x), float(y)) for x, y in spec.path], spec.goal_tolerance


class PurePursuit:
    """Steer toward the path point ``lookahead`` metres ahead of the closest one."""

    def __init__(self, path: list[tuple[float, float]], tolerance: float, lookahead: float = 0.5) -> None:
        self.path, self.tol, self.lookahead = path, tolerance, lookahead
        self.seg = [math.dist(a, b) for a, b in zip(path, path[1:])]
        self.i = 0  # progress index: never goes back (the path may come close to itself)

    def command(self, x: float, y: float, th: float, box: list[float]) -> tuple[float, float]:
        v_min, v_max, w_min, w_max = box
        window = range(self.i, min(len(self.path), self.i + 50))
        self.i = min(window, key=lambda k: math.dist((x, y), self.path[k]))
        if self.i >= len(self.path) - 2 and math.dist((x, y), self.path[-1]) < self.tol:
            return 0.0, 0.0  # at the goal: stop
        k, ahead = self.i, 0.0
        while k < len(self.path) - 1 and ahead < self.lookahead:
            ahead += self.seg[k]
            k += 1
        tx, ty = self.path[k]
        alpha = math.remainder(math.atan2(ty - y, tx - x) - th, 2 * math.pi)
        v = v_max if abs(alpha) < 0.5 else max(v_min, 0.5 * v_max)
        w = 2.0 * v * math.sin(alpha) / max(self.lookahead, 1e-6)
        return v, min(max(w, w_min), w_max)  # the learned limits bound the teacher


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robot", required=True)
    ap.add_argument("--mission", required=True, help="mission file (TOML)")
    add_zenoh_args(ap)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--duration", type=float, default=None)
    args = ap.parse_args()
    path, tol = load_path(args.mission)
    ctl = PurePursuit(path, tol)
    keys = W.Keys(args.robot)
    latest: dict[str, object] = {"state": None, "box": [0.05, 0.3, -0.2, 0.2]}
    lock = threading.Lock()

    def on_state(sample: zenoh.Sample) -> None:
        try:
            st = W.decode(sample.payload.to_bytes(), W.LearnerState)
        except W.MessageError:
            return
        with lock:
            latest["state"] = st

    def on_limits(sample: zenoh.Sample) -> None:
        try:
            lim = W.decode(sample.payload.to_bytes(), W.Limits)
        except W.MessageError:
            return
        with lock:
            latest["box"] = lim.box

    epoch, seq = W.new_epoch(), 0
    t_end = None if args.duration is None else time.monotonic() + args.duration
    with open_session(zenoh_config(args)) as session:
        print(f"external teacher for {args.robot}: connected ({endpoints_tried(args)}); following {args.mission} "
              f"({len(path)} waypoints), publishing {keys.teacher} at {args.rate:g} Hz", flush=True)
        session.declare_subscriber(keys.state, on_state)
        session.declare_subscriber(keys.limits, on_limits)
        pub = session.declare_publisher(keys.teacher)
        t_say, at_goal = 0.0, False
        while t_end is None or time.monotonic() < t_end:
            with lock:
                st, box = latest["state"], list(latest["box"])
            now = time.monotonic()
            if st is None and now >= t_say:
                print(f"waiting for the robot's pose on {keys.state}", flush=True)
                t_say = now + 5.0
            if st is not None:
                v, w = ctl.command(st.x, st.y, st.theta, box)
                msg = W.TeacherCommand(stamp=now, seq=seq, v=v, omega=w, solver="pure-pursuit",
                                       sender="example-teacher", epoch=epoch)
                pub.put(W.encode(msg))
                seq += 1
                if (v, w) == (0.0, 0.0) and not at_goal:
                    print(f"goal reached at ({st.x:.2f}, {st.y:.2f}): commanding stop", flush=True)
                at_goal = (v, w) == (0.0, 0.0)
                if now >= t_say and not at_goal:
                    print(f"pose ({st.x:.2f}, {st.y:.2f}, {st.theta:.2f}) -> v {v:.3f} m/s, omega {w:.3f} rad/s "
                          f"(learned limits v [{box[0]:.2f}, {box[1]:.2f}], omega [{box[2]:.2f}, {box[3]:.2f}])",
                          flush=True)
                    t_say = now + 1.0
            time.sleep(1.0 / args.rate)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
