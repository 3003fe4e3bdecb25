"""``scmbridge record``: every ``scm/...`` message (or some robots') into an MCAP file
(format: :mod:`bridge.tools.mcap_format`).

A message's ``log_time`` is when the recorder received it (the wall clock read once at start plus the monotonic time
since: it reads as a date and never jumps with NTP). Chunks are closed every ``--flush-every`` seconds or
``--chunk-bytes``, so a ``kill -9`` loses at most the last chunk; a clean stop writes the summary and fsyncs.
``--max-bytes`` stops before the file would exceed the limit; ``--rotate-bytes N --keep K`` writes ``OUT-0001.mcap``,
``OUT-0002.mcap``, ... each complete and at most N bytes, keeping the newest K. Samples are classified in the
recorder's loop, never on Zenoh's threads; a full queue drops and counts.
"""

from __future__ import annotations

import argparse
import queue
import re
import socket
import sys
import time
from pathlib import Path
from typing import Any

import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg, robots_arg
from bridge.core.errors import UsageError
from bridge.nodes.node import Inputs, add_zenoh_args, stop_on_signals, zenoh_config
from bridge.nodes.zsession import open_session
from bridge.tools.mcap_format import NONCANONICAL, classify
from bridge.tools.mcap_sink import McapSink


def parse_bytes(text: str) -> int:
    """A size: ``65536``, ``64k``, ``10M``, ``1G`` (powers of 1024)."""
    m = re.fullmatch(r"\s*(\d+)\s*([kKmMgG]?)i?[bB]?\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r} is not a size (e.g. 65536, 64k, 10M, 1G)")
    n = int(m[1]) * {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30}[m[2].lower()]
    if n <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return n



class Clock:
    """Receive times for ``log_time``: wall clock at start + monotonic since (readable as a date, never jumps)."""

    def __init__(self) -> None:
        self.wall0 = time.time_ns()
        self.mono0 = time.monotonic_ns()

    def log_time(self, mono_ns: int) -> int:
        return self.wall0 + (mono_ns - self.mono0)


def _start_meta(pattern: str, clock: Clock) -> dict[str, str]:
    from importlib import metadata

    try:
        version = metadata.version("scmbridge")
    except metadata.PackageNotFoundError:
        version = "unknown"
    return {"pattern": pattern, "host": socket.gethostname(), "scmbridge": version,
            "started_unix_ns": str(clock.wall0), "monotonic_at_start_ns": str(clock.mono0),
            "log_time": "receipt: wall clock at start + monotonic time since",
            "message_encoding": "json of the wire Struct (msgspec); wire.encode of it is the received MessagePack, "
                                f"else the received bytes are on {NONCANONICAL}"}


def arguments(ap: argparse.ArgumentParser) -> None:
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--robot", type=robot_arg, help="record scm/ROBOT/**")
    who.add_argument("--robots", type=robots_arg, help="record these robots (comma-separated)")
    who.add_argument("--all", action="store_true", help="record scm/** (every robot)")
    ap.add_argument("--out", required=True, help="the MCAP file (with --rotate-bytes: OUT-0001.mcap, ...)")
    ap.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    size = ap.add_mutually_exclusive_group()
    size.add_argument("--max-bytes", type=parse_bytes, default=None, help="stop when the file would exceed this")
    size.add_argument("--rotate-bytes", type=parse_bytes, default=None, help="start a new file at this size")
    ap.add_argument("--keep", type=int, default=10, help="with --rotate-bytes: files kept (the newest)")
    ap.add_argument("--chunk-bytes", type=parse_bytes, default=128 << 10, help="close a chunk at this size")
    ap.add_argument("--flush-every", type=positive_float, default=1.0,
                    help="close a chunk at least this often, seconds")
    ap.add_argument("--queue", type=int, default=100_000, help="samples waiting for the disk before drops")
    ap.add_argument("--force", action="store_true", help="overwrite existing output files")
    add_zenoh_args(ap)


def _check(args: argparse.Namespace) -> None:
    if args.keep < 1:
        raise UsageError("--keep must be >= 1")
    if args.keep != 10 and args.rotate_bytes is None:
        raise UsageError("--keep goes with --rotate-bytes")
    out = Path(args.out)
    existing = sorted(out.parent.glob(f"{out.stem}-[0-9][0-9][0-9][0-9]{out.suffix or '.mcap'}")) \
        if args.rotate_bytes else ([out] if out.exists() else [])
    if existing and not args.force:
        raise UsageError(f"{existing[0]} exists (--force overwrites)")


def run(args: argparse.Namespace) -> int:
    _check(args)
    robots = args.robots or ([args.robot] if args.robot else [])
    patterns = [f"{M.PREFIX}/{r}/**" for r in robots] or [f"{M.PREFIX}/**"]
    pattern = ", ".join(patterns)
    clock = Clock()
    sink = McapSink(Path(args.out), max_bytes=args.max_bytes, rotate_bytes=args.rotate_bytes, keep=args.keep,
                    chunk_bytes=args.chunk_bytes, flush_s=args.flush_every, meta=_start_meta(pattern, clock))
    stats = Inputs()  # the one counter Zenoh's threads touch: samples dropped on a full queue
    inbox: queue.Queue[tuple[str, bytes, bool, int]] = queue.Queue(maxsize=args.queue)
    put = zenoh.SampleKind.PUT

    def on_sample(sample: Any) -> None:  # Zenoh's thread: stamp and hand over, nothing else
        now = time.monotonic_ns()
        try:
            inbox.put_nowait((str(sample.key_expr), sample.payload.to_bytes(), sample.kind == put, now))
        except queue.Full:
            stats.count("dropped")

    reason = "stopped"

    def handle(item: tuple[str, bytes, bool, int]) -> bool:
        """Write one sample; False when the size limit is reached."""
        key, payload, is_put, mono_ns = item
        t = clock.log_time(mono_ns)
        sink.counts["dropped"] = stats.snapshot().get("dropped", 0)  # for the end record of a rotated file
        for spec, data, outcome in classify(key, payload, is_put):
            res = sink.write(spec, data, t)
            if res == "full":
                return False
            if res == "ok":
                sink.counts["messages" if outcome == "ok" else outcome] += 1
        return True

    stop = stop_on_signals()
    t_start = time.monotonic()
    with open_session(zenoh_config(args)) as session:
        subs = [session.declare_subscriber(p, on_sample) for p in patterns]
        first = sink.path_for(1)
        print(f"recording {pattern} into {first}" + (f" (rotating at {args.rotate_bytes} bytes, keeping "
                                                      f"{args.keep})" if args.rotate_bytes else ""), flush=True)
        try:
            while not stop.is_set():
                now = time.monotonic()
                if args.duration is not None and now - t_start >= args.duration:
                    reason = "duration"
                    break
                try:
                    item = inbox.get(timeout=0.05)
                except queue.Empty:
                    sink.tick(time.monotonic())
                    continue
                if not handle(item):
                    reason = "size limit"
                    break
                sink.tick(time.monotonic())
            else:
                reason = "signal"
        finally:
            for sub in subs:
                sub.undeclare()
    while reason != "size limit":  # what arrived before the subscriber went away
        try:
            item = inbox.get_nowait()
        except queue.Empty:
            break
        if not handle(item):
            reason = "size limit"
    sink.counts["dropped"] = stats.snapshot().get("dropped", 0)
    sink.close(reason)
    c = sink.counts
    kept = sink.kept()
    print(f"recorded {c['messages']} messages ({c['malformed']} malformed, {c['noncanonical']} noncanonical, "
          f"{c['dropped']} dropped, {c['oversize']} too big) into "
          f"{', '.join(str(p) for p in kept)} ({sum(p.stat().st_size for p in kept)} bytes); stopped: {reason}",
          flush=True)
    if reason == "size limit":
        print(f"scmbridge record: the size limit ({args.max_bytes} bytes) is reached: recording stopped",
              file=sys.stderr)
    if c["messages"] == 0:  # nothing is not a recording: a denied identity or nothing running looks the same
        print(f"scmbridge record: nothing received on {pattern}: nothing was published, or the router's access "
              "control does not let this identity read it (scmbridge doctor; the observer or operator certificate)",
              file=sys.stderr)
        return 1
    return 0
