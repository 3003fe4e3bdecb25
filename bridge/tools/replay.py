"""``scmbridge replay``: publish a recording's messages on their Zenoh keys at the recorded pace (``--speed X`` times
faster, or ``--fast``). Commands move robots: ``cmd`` and ``estop`` are replayed only with ``--with-commands`` (a
replayed ``cmd`` of a new epoch is accepted by a driver host that never saw it, and a replayed estop release would
release a live estop).

``--through-station``: no Zenoh; the recorded station's journal is fed, in this process, to a fresh station core
built from ``--config`` and ``--store`` (the run's), on the recorded clock, and each command it makes is compared
with the one the station published: identical bit for bit, or the first tick that differs and why
(:mod:`bridge.tools.replay_station`; docs/OPERATING.md, "Why did it do that at t = 35 s"). Exit 0: every command
identical; 1: one differs (or none could be compared).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg
from bridge.core.errors import UsageError
from bridge.nodes.node import add_zenoh_args, stop_on_signals, zenoh_config
from bridge.nodes.zsession import open_session
from bridge.tools.mcap_format import ACTUATING, Recording, iter_recording, parse_key, wire_bytes


def _rename_arg(text: str) -> tuple[str, str]:
    a, sep, b = text.partition("=")
    try:
        if not sep:
            raise ValueError("expected A=B")
        return M.check_robot(a), M.check_robot(b)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--robot-rename {text!r}: {exc}") from None


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("files", nargs="+", help="MCAP file(s), in order (a rotated recording: all its files)")
    pace = ap.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=positive_float, default=1.0, help="X times the recorded pace")
    pace.add_argument("--fast", action="store_true", help="as fast as Zenoh takes them")
    ap.add_argument("--robot-rename", type=_rename_arg, action="append", default=[], metavar="A=B",
                    help="publish robot A's keys as robot B's (repeatable)")
    ap.add_argument("--with-commands", action="store_true",
                    help="also replay cmd and estop (they move or release a robot: never next to a live one)")
    ap.add_argument("--wait", type=float, default=5.0,
                    help="seconds to wait for a subscriber of the first key before publishing (0: do not wait)")
    station = ap.add_argument_group("--through-station (in process, no Zenoh)")
    station.add_argument("--through-station", action="store_true",
                         help="feed the recorded station's journal to a fresh station core and compare its commands "
                              "with the recorded ones, bit for bit")
    station.add_argument("--config", help="the run's station TOML (default: the defaults)")
    station.add_argument("--store", help="the pair store file the run started from (default: none, an empty one)")
    station.add_argument("--robot", type=robot_arg, default=None,
                         help="the robot whose station to replay (default: the only one recorded)")
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    for f in args.files:
        if not Path(f).is_file():
            raise UsageError(f"{f}: no such file")
    if args.through_station:
        return through_station(args)
    renames = dict(args.robot_rename)


    stop = stop_on_signals()
    rec = Recording([Path(f) for f in args.files])
    counts: Counter[str] = Counter()
    t0_log = t0 = None
    with open_session(zenoh_config(args)) as session:
        pubs: dict[str, Any] = {}
        for entry in iter_recording(args.files, rec):
            if stop.is_set():
                break
            if not entry.is_wire:
                counts["skipped_" + entry.topic.rsplit("/", 1)[-1]] += 1
                continue
            if parse_key(entry.topic)[1] in ACTUATING and not args.with_commands:
                counts["skipped_commands"] += 1
                continue
            try:
                key, data = wire_bytes(entry, renames)
            except (ValueError, M.MessageError) as exc:
                counts["unreadable"] += 1
                print(f"scmbridge replay: skipped a message on {entry.topic}: {exc}", file=sys.stderr)
                continue
            pub = pubs.get(key)
            if pub is None:
                # BLOCK: a replay as fast as possible must not lose messages to Zenoh's default DROP
                pub = pubs[key] = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                if len(pubs) == 1 and args.wait > 0:
                    t_wait = time.monotonic() + args.wait
                    while not pub.matching_status.matching and time.monotonic() < t_wait and not stop.is_set():
                        time.sleep(0.02)
            if t0 is None:
                t0, t0_log = time.monotonic(), entry.log_time
            if not args.fast:
                delay = t0 + (entry.log_time - t0_log) / 1e9 / args.speed - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    break
            pub.put(data)
            counts["published"] += 1
        # Zenoh does not promise that closing a session flushes what it still has queued: give it a moment.
        time.sleep(0.3)
    took = time.monotonic() - t0 if t0 is not None else 0.0
    extra = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()) if k != "published")
    print(f"replayed {counts['published']} messages on {len(pubs)} keys in {took:.1f} s"
          + (f" ({extra})" if extra else "")
          + (f"; {len(rec.truncated)} file(s) end early (no summary: a killed recorder)" if rec.truncated else ""),
          flush=True)
    if counts["skipped_commands"]:
        print("scmbridge replay: cmd and estop were not replayed (--with-commands replays them)", file=sys.stderr)
    return 0




def through_station(args: argparse.Namespace) -> int:
    """``--through-station``: the recorded station replayed in process (:mod:`bridge.tools.replay_station`)."""
    from bridge.core.config import load_station
    from bridge.tools.replay_station import read_runs, replay, report

    cfg = load_station(args.config)
    if args.store is not None and not Path(args.store).is_file():
        raise UsageError(f"--store {args.store}: no such file")
    runs = {r: run for r, run in read_runs(args.files).items() if run.journal}
    if args.robot is not None:
        if args.robot not in runs:
            raise UsageError(f"no journal of {args.robot} in the recording (journals of: {', '.join(runs) or 'none'})")
        robot = args.robot
    elif len(runs) == 1:
        robot = next(iter(runs))
    else:
        raise UsageError("the recording holds no station journal (record with the recorder started before the "
                         "station)" if not runs
                         else f"journals of several robots ({', '.join(sorted(runs))}): name one with --robot")
    text, code = report(replay(runs[robot], cfg, Path(args.store) if args.store else None), robot)
    print(text, file=sys.stdout if code == 0 else sys.stderr, flush=True)
    return code
