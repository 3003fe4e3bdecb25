"""``scmbridge calibrate``: the paper's calibration stage on a real robot, through its driver host over Zenoh.

It runs the station's loop with a calibration plan instead of a teacher (:mod:`transfer.calibration`): a grid of
learner commands (the paper's 5 x 5 by default, extremes included, so the learned limits are measured), each held
for ``hold_s``, driving back toward the start between commands, and stopping at the distance or time bound. The
pairs it makes go into the station's pair store (the same file, persisted atomically), so a mission started
afterwards with that store begins from calibrated pairs and measured limits. It uses the station's configuration
(``[calibration]``, bounds, store) and its identity on the wire: do not run it while a station drives the same
robot (the driver host follows one sender at a time and would refuse it). Under the lab's access control it needs
the station's rights (it publishes the robot's cmd and limits): run it on the base station with the station's
client configuration (station-client.json5, the station's certificate) while the robot's station is stopped; with
another identity (the operator's) it is denied at once (exit status 3) instead of never moving the robot.
Progress is logged per command. The bound on time is --duration (the configuration's max_time_s by default).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import msgspec

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg
from bridge.core.config import ConfigError, load_mission, load_station
from bridge.core.errors import Denied
from bridge.nodes.mission_control import Fitness
from bridge.nodes.node import add_zenoh_args, stop_on_signals, zenoh_config
from bridge.nodes.station import Station
from bridge.nodes.zsession import open_session
from bridge.tools.identity import denial
from transfer.calibration import CalibrationPlan


def grid_arg(text: str) -> tuple[int, int]:
    """``5x5`` / ``3x7``: at least two commands per axis."""
    try:
        nv, nw = (int(a) for a in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not NVxNW (e.g. 5x5)") from None
    if not (2 <= nv <= 21 and 2 <= nw <= 21):
        raise argparse.ArgumentTypeError(f"{text!r}: each axis needs 2 to 21 commands")
    return nv, nw


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--config", help="station TOML ([calibration], bounds, store)")
    ap.add_argument("--robot", type=robot_arg, default=None, help="robot name (overrides the config)")
    ap.add_argument("--store", default=None, help="pair store file (overrides the config)")
    ap.add_argument("--grid", type=grid_arg, default=None, help="commands per axis, e.g. 5x5 (overrides the config)")
    ap.add_argument("--hold", type=positive_float, default=None, help="seconds each command is held")
    ap.add_argument("--max-distance", type=positive_float, default=None, help="m from the start before stopping")
    ap.add_argument("--duration", type=positive_float, default=None, help="seconds before stopping (the config's "
                    "max_time_s by default)")
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    cfg = load_station(args.config)
    c = cfg.calibration
    overrides = {k: v for k, v in (("grid", args.grid), ("hold_s", args.hold), ("max_distance_m", args.max_distance),
                                   ("max_time_s", args.duration)) if v is not None}
    if "max_distance_m" in overrides and c.return_radius_m >= overrides["max_distance_m"]:
        overrides["return_radius_m"] = 0.4 * overrides["max_distance_m"]
    if overrides:
        try:
            c = msgspec.convert({**msgspec.structs.asdict(c), **overrides}, type(c))
        except msgspec.ValidationError as exc:
            raise ConfigError("command line", "calibration", str(exc)) from None
    robot = M.check_robot(args.robot or cfg.robot)
    store = Path(args.store) if args.store else cfg.store_file(robot)
    plan = CalibrationPlan(cfg.learner_bounds.bounds(), c.grid, hold_s=c.hold_s, max_distance=c.max_distance_m,
                           return_radius=c.return_radius_m, max_time_s=c.max_time_s)
    station = Station(cfg, robot, cfg.station.rate_hz, store, load_mission(cfg.station.mission or None),
                      calibration=plan)
    # running calibration is a person's act by itself: the stage starts at once
    station.control.request(M.MissionRequest(stamp=0.0, action="start", source="scmbridge calibrate"),
                            Fitness("not checked yet"), 0.0)
    conf = zenoh_config(args)
    denied = denial(conf, robot, "put", M.key(robot, "cmd"), "calibrate (it commands the robot as its station does)")
    if denied:  # under the lab's access control nothing it sent would arrive: the robot would never move
        raise Denied(f"{denied}; run calibrate with the station's identity (--zenoh-config "
                     "/etc/scmbridge/station-client.json5) while the robot's station is stopped (deploy/README.md)")
    stop = stop_on_signals()
    try:
        with open_session(conf) as session:
            station.serve(session, stop, c.max_time_s + 30.0, exit_at_goal=True)
    finally:
        station.persist()
    done = plan.finished
    box = station.store.limits.box
    print(f"calibration: {done.reason if done else 'interrupted'}; {station.store.raw_count} raw / "
          f"{len(station.store.refined())} refined pairs in {store}; learned limits v [{box.v[0]:.3f}, "
          f"{box.v[1]:.3f}] m/s, omega [{box.w[0]:.3f}, {box.w[1]:.3f}] rad/s")
    return 0 if done is not None else 1
