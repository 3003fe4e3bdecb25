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
import os
import queue
import re
import socket
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg, robots_arg
from bridge.core.errors import UsageError
from bridge.nodes.node import Inputs, add_zenoh_args, stop_on_signals, zenoh_config
from bridge.nodes.zsession import open_session
from bridge.tools.mcap_format import META_END, META_START, NONCANONICAL, PROFILE, ChannelSpec, classify


def parse_bytes(text: str) -> int:
    """A size: ``65536``, ``64k``, ``10M``, ``1G`` (powers of 1024)."""
    m = re.fullmatch(r"\s*(\d+)\s*([kKmMgG]?)i?[bB]?\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r} is not a size (e.g. 65536, 64k, 10M, 1G)")
    n = int(m[1]) * {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30}[m[2].lower()]
    if n <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return n


# Sizes of MCAP records (the spec's layouts), for the conservative estimate of a file's size once closed.
_REC = 9  # opcode + record length
_MSG = _REC + 2 + 4 + 8 + 8  # + data
_INDEX_ENTRY = 16  # a message's (log_time, offset) in its chunk's message index
_INDEX_HEAD = _REC + 2 + 4  # one message index record per channel per chunk
_CHUNK_HEAD = _REC + 8 + 8 + 8 + 4 + 4 + 4 + 8  # + compression name + data
_CHUNK_INDEX = _REC + 8 + 8 + 8 + 8 + 4 + 8 + 4 + 4 + 8 + 8  # + 10 per channel
# DataEnd 13, statistics 55 (+10 per channel, counted with the channel), 6 summary offsets 156, two metadata
# indexes ~120, footer 29, magic 8; rounded up, with room for zstd's frame overhead on the last chunk
_FIXED_TAIL = 512
_END_META = 512  # the end-of-recording metadata record (~250 bytes)


def _schema_size(spec: ChannelSpec) -> int:
    return _REC + 2 + 4 + len(spec.schema_name) + 4 + len("jsonschema") + 4 + len(spec.schema)


def _channel_size(spec: ChannelSpec) -> int:
    return _REC + 2 + 2 + 4 + len(spec.topic.encode()) + 4 + len("json") + 4 + 64


class McapSink:
    """The recording's MCAP file(s): channels and schemas registered on first use, chunks closed by size or time,
    a size limit or rotation (see the module docstring). Single-threaded: only the recorder's loop calls it."""

    def __init__(self, out: Path, *, max_bytes: int | None = None, rotate_bytes: int | None = None, keep: int = 10,
                 chunk_bytes: int = 128 << 10, flush_s: float = 1.0, meta: dict[str, str] | None = None) -> None:
        from mcap.writer import CompressionType

        if max_bytes is not None and rotate_bytes is not None:
            raise ValueError("--max-bytes and --rotate-bytes exclude each other")
        self.out = Path(out)
        self.limit = max_bytes if rotate_bytes is None else rotate_bytes
        self.rotating = rotate_bytes is not None
        self.keep = keep
        self.chunk_bytes = chunk_bytes
        self.flush_s = flush_s
        self.meta = dict(meta or {})
        self.compression = CompressionType.ZSTD
        self.index = 0
        self.files: list[Path] = []  # every file this sink wrote, oldest first (deleted ones included)
        self.writer: Any = None
        self.f: Any = None
        self.counts: Counter[str] = Counter()

    # -- one file
    def path_for(self, index: int) -> Path:
        if not self.rotating:
            return self.out
        return self.out.with_name(f"{self.out.stem}-{index:04d}{self.out.suffix or '.mcap'}")

    def _open(self) -> None:
        from mcap.writer import Writer

        self.index += 1
        path = self.path_for(self.index)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.f = open(path, "wb")  # noqa: SIM115 (closed in _close_file)
        # chunks are closed here (flush), never by the writer: the size estimate needs to know what is pending
        self.writer = Writer(self.f, chunk_size=1 << 62, compression=self.compression)
        self.writer.start(profile=PROFILE, library="scmbridge record")
        self.writer.add_metadata(META_START, {**self.meta, "file_index": str(self.index)})
        self.files.append(path)
        self.schema_ids: dict[bytes, int] = {}
        self.channel_ids: dict[str, int] = {}
        self.channel_seq: Counter[int] = Counter()
        self.pending = 0  # uncompressed bytes of the open chunk
        self.pending_channels: set[int] = set()
        self.summary = 0  # schemas and channels repeated in the summary, chunk indexes
        self.file_messages = 0
        self.last_flush = time.monotonic()

    def _cost(self, spec: ChannelSpec, data: bytes) -> int:
        """Bytes this message adds to the closed file, at most (its schema and channel if new: twice, once in the
        data section and once in the summary)."""
        cost = _MSG + len(data) + _INDEX_ENTRY
        if spec.topic not in self.channel_ids:
            cost += 2 * _channel_size(spec) + _INDEX_HEAD + 10 + 10  # + its stats count and chunk index offset
            if spec.schema not in self.schema_ids:
                cost += 2 * _schema_size(spec)
        return cost

    def _closed_size(self, extra: int) -> int:
        """A bound on the file's size if it were closed after adding ``extra`` bytes to the open chunk."""
        chunk = _CHUNK_HEAD + 4 + _CHUNK_INDEX + (_INDEX_HEAD + 10) * (len(self.pending_channels) + 1)
        return self.f.tell() + self.pending + extra + chunk + self.summary + _FIXED_TAIL + _END_META

    def _ids(self, spec: ChannelSpec) -> int:
        cid = self.channel_ids.get(spec.topic)
        if cid is None:
            sid = self.schema_ids.get(spec.schema)
            if sid is None:
                sid = self.schema_ids[spec.schema] = self.writer.register_schema(spec.schema_name, "jsonschema",
                                                                                 spec.schema)
                self.summary += _schema_size(spec)
                self.pending += _schema_size(spec)
            meta = {"zenoh_key": spec.topic} if not spec.topic.startswith("/") else {}
            cid = self.channel_ids[spec.topic] = self.writer.register_channel(spec.topic, "json", sid, meta)
            self.summary += _channel_size(spec) + 10
            self.pending += _channel_size(spec)
        return cid

    def _flush_chunk(self) -> None:
        if self.pending_channels:
            self.writer.flush()  # closes the chunk, writes it and its message indexes, flushes to the OS
            self.summary += _CHUNK_INDEX + 4 + 10 * len(self.pending_channels)
        self.pending = 0
        self.pending_channels = set()
        self.last_flush = time.monotonic()

    def _close_file(self, reason: str) -> None:
        if self.writer is None:
            return
        self._flush_chunk()
        self.writer.add_metadata(META_END, {"reason": reason, **{k: str(v) for k, v in sorted(self.counts.items())},
                                            "file_messages": str(self.file_messages)})
        self.writer.finish()
        self.f.flush()
        os.fsync(self.f.fileno())
        self.f.close()
        self.writer = self.f = None

    # -- the recording
    def write(self, spec: ChannelSpec, data: bytes, log_time_ns: int) -> str:
        """Add one message; returns ``ok``, ``full`` (the size limit is reached: nothing was written, stop) or
        ``oversize`` (rotation: the message does not fit even an empty file; dropped and counted)."""
        if self.writer is None:
            self._open()
        if self.limit is not None and self._closed_size(self._cost(spec, data)) > self.limit:
            if not self.rotating:
                return "full"
            if self.file_messages == 0:
                self.counts["oversize"] += 1
                return "oversize"
            self._close_file("rotated")
            self._open()
            self._prune()
            if self._closed_size(self._cost(spec, data)) > self.limit:
                self.counts["oversize"] += 1
                return "oversize"
        cid = self._ids(spec)
        self.writer.add_message(cid, log_time_ns, data, log_time_ns, sequence=self.channel_seq[cid])
        self.channel_seq[cid] += 1
        self.pending += _MSG + len(data) + _INDEX_ENTRY
        self.pending_channels.add(cid)
        self.file_messages += 1
        if self.pending >= self.chunk_bytes:
            self._flush_chunk()
        return "ok"

    def tick(self, now: float) -> None:
        """Close the open chunk if it is ``flush_s`` old: what a kill -9 can lose is at most that."""
        if self.writer is not None and self.pending_channels and now - self.last_flush >= self.flush_s:
            self._flush_chunk()

    def _prune(self) -> None:
        for old in self.files[:-self.keep]:
            old.unlink(missing_ok=True)

    def close(self, reason: str) -> None:
        if self.writer is None and not self.files:
            self._open()  # an empty recording is still a valid file that says why it is empty
        self._close_file(reason)
        if self.rotating:
            self._prune()

    def kept(self) -> list[Path]:
        return [p for p in self.files if p.exists()]


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
