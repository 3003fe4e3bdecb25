"""``scmbridge replay``: publish a recording's messages on their Zenoh keys at the recorded pace (``--speed X`` times
faster, or ``--fast``). Commands move robots: ``cmd`` and ``estop`` are replayed only with ``--with-commands`` (a
replayed ``cmd`` of a new epoch is accepted by a driver host that never saw it, and a replayed estop release would
release a live estop).
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
from bridge.core.args import positive_float
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
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    for f in args.files:
        if not Path(f).is_file():
            raise UsageError(f"{f}: no such file")
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


