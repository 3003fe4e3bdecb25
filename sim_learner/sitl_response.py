"""The open-loop response of ArduPilot's Rover in SITL: commanded (v, omega) in GUIDED against what it achieves.

The paper's learners respond weaker than commanded and nonlinearly (paper §5.2: the cubic learner; §6: the Jackal's
7th-order yaw-rate distortion). A rover whose speed and turn-rate controllers close their loops hides such a
distortion; a parameter profile can put one back (``deploy/examples/sitl-weak.parm`` says which parameters and why).
This measures it, so that a profile's table is a measurement and not a hope: SITL boots with the profile, the pilot
engages GUIDED, and each grid point is held ``hold_s`` seconds as velocity + yaw-rate set-points at 10 Hz (as a
driver host sends them); the achieved forward speed (LOCAL_POSITION_NED projected on the heading) and turn rate
(ATTITUDE's yawspeed) are averaged over the point's last ``settle_s`` seconds.

``python -m sim_learner.sitl_response --params deploy/examples/sitl-weak.parm [--model rover-skid]`` prints the
table (markdown) and the ratios achieved / commanded. Commands here are ENU (omega counter-clockwise positive).
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sim_learner.sitl import Pilot, Sitl, find_sitl


@dataclass
class Point:
    """One grid point: the command, what the vehicle did in its last seconds."""

    v_cmd: float
    w_cmd: float
    v: float  # m/s, forward
    w: float  # rad/s, counter-clockwise

    @property
    def v_ratio(self) -> float:
        return self.v / self.v_cmd if self.v_cmd else math.nan

    @property
    def w_ratio(self) -> float:
        return self.w / self.w_cmd if self.w_cmd else math.nan


def forward_speed(position: Any, attitude: Any) -> float:
    """LOCAL_POSITION_NED's velocity projected on the heading at that message's instant, m/s.

    The two messages stream at their own phases, so ATTITUDE's yaw is brought to the velocity's ``time_boot_ms``
    with its own yaw rate: a rover turning at 0.2 rad/s with the streams 25 ms apart otherwise reads 0.3 m/s as
    0.299997 (the heading 5 mrad off).
    """
    dt_ms = (position.time_boot_ms - attitude.time_boot_ms + 2**31) % 2**32 - 2**31  # the 32-bit clock wraps
    yaw = attitude.yaw + attitude.yawspeed * dt_ms / 1000.0
    return float(position.vx * math.cos(yaw) + position.vy * math.sin(yaw))


def hold(pilot: Pilot, v: float, w: float, hold_s: float, settle_s: float) -> Point:
    """Send (v, w) at 10 Hz for ``hold_s`` s; average the forward speed and turn rate over the last ``settle_s``."""
    t0 = time.monotonic()
    vs: list[float] = []
    ws: list[float] = []
    while (now := time.monotonic()) < t0 + hold_s:
        pilot.velocity(v, -w)  # the vehicle's yaw rate is clockwise (NED)
        if now >= t0 + hold_s - settle_s:
            with pilot.cond:
                p, a = pilot.s.position, pilot.s.attitude
            if p is not None and a is not None:
                vs.append(forward_speed(p, a))
                ws.append(-a.yawspeed)
        time.sleep(0.1)
    return Point(v, w, sum(vs) / max(len(vs), 1), sum(ws) / max(len(ws), 1))


def measure(sitl: Sitl, vs: list[float], ws: list[float], hold_s: float = 5.0, settle_s: float = 2.0) -> list[Point]:
    """Engage GUIDED (armed) and hold every (v, w) of the grid in turn; stop and disarm after."""
    pilot = sitl.pilot
    assert pilot is not None
    pilot.set_mode("GUIDED")
    pilot.arm(True)
    points = []
    try:
        for v in vs:
            for w in ws:
                points.append(hold(pilot, v, w, hold_s, settle_s))
    finally:
        hold(pilot, 0.0, 0.0, 2.0, 0.5)
        pilot.arm(False)
    return points


def table(points: list[Point]) -> str:
    """A markdown table of the points."""
    rows = ["| v cmd m/s | omega cmd rad/s | v achieved | omega achieved | v ratio | omega ratio |",
            "|---|---|---|---|---|---|"]
    for p in points:
        rows.append(f"| {p.v_cmd:.2f} | {p.w_cmd:+.3f} | {p.v:.3f} | {p.w:+.3f} | "
                    f"{p.v_ratio:.2f} | {p.w_ratio:.2f} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sitl", default=None, help="the ardurover binary (default: find_sitl())")
    ap.add_argument("--model", default="rover-skid")
    ap.add_argument("--params", action="append", default=[], help="an extra .parm file (repeatable)")
    ap.add_argument("--v", default="0.1,0.2,0.3,0.45,0.6", help="commanded speeds, m/s")
    ap.add_argument("--w", default="0,0.15,0.3,0.45", help="commanded turn rates, rad/s (CCW)")
    ap.add_argument("--hold", type=float, default=5.0)
    args = ap.parse_args(argv)
    binary = Path(args.sitl) if args.sitl else find_sitl()
    vs = [float(x) for x in args.v.split(",")]
    ws = [float(x) for x in args.w.split(",")]
    with Sitl(binary, model=args.model, parm_files=args.params) as sitl:
        assert sitl.pilot is not None
        names = ("WP_SPEED", "ATC_STR_RAT_MAX", "ATC_STR_RAT_FF", "ATC_STR_RAT_P", "ATC_STR_RAT_I", "ATC_SPEED_P",
                 "ATC_SPEED_I", "CRUISE_SPEED", "CRUISE_THROTTLE", "MOT_THST_EXPO", "ATC_ACCEL_MAX")
        print({n: sitl.pilot.param(n) for n in names})
        points = measure(sitl, vs, ws, args.hold)
    print(table(points))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
