"""``scmbridge record`` and ``scmbridge replay``: every ``scm/...`` message into an MCAP file, and back onto Zenoh.

**Format.** One MCAP channel per Zenoh key (the channel's topic *is* the key, e.g. ``scm/rover1/status/driver``),
one MCAP schema per wire message type (``scmbridge.Command``, ...). Messages are stored as **JSON with a JSON Schema**
(message encoding ``json``, schema encoding ``jsonschema``), not as the MessagePack that travels on the wire:

- ``json`` + ``jsonschema`` is the pair MCAP lists as well known and Foxglove decodes without a plugin; MessagePack
  is not a well-known MCAP message encoding and no common viewer reads it, so a file of raw MessagePack would need
  this project to be opened at all.
- Nothing is lost. Each message is decoded (so validated) with :func:`bridge.core.wire.decode`, written as msgspec's
  JSON of the Struct (shortest round-trip floats, so every number is exact; fields left at their default are left
  out, as on the wire, and the schema names the default), and the recorder checks, per message, that re-encoding
  that JSON with :func:`bridge.core.wire.encode` gives back the received bytes exactly. When it does not (a sender
  with another MessagePack encoder: other field order, float32, explicit defaults), the received bytes are also
  written, base64, on the ``/scmbridge/noncanonical`` channel with the same receive time. So the wire bytes of
  every recorded message are either what ``wire.encode`` makes of its JSON (what ``replay`` publishes) or stored
  verbatim. Schemas are the JSON Schema msgspec derives from the wire Structs (``msgspec.json.schema``), with the
  root inlined because Foxglove wants ``"type": "object"`` at the top; ``bytes`` are base64 with
  ``contentEncoding``.
- A sample that does not decode (bad MessagePack, out of range, unknown field, a key outside the wire contract, a
  DELETE) never stops the recorder: it goes to ``/scmbridge/malformed`` with its key, the reason and its bytes.

**Times.** A message's ``log_time`` is when the recorder received it: the wall clock read once at start plus the
monotonic time since (so it reads as a date in a viewer and never jumps with NTP); ``publish_time`` is the same
(the senders' stamps are their own monotonic clocks, inside the message). Messages are written in arrival order.

**Survives being killed.** Chunks are closed and handed to the OS every ``--flush-s`` (1 s) or ``--chunk-bytes``
(128 KiB), whichever comes first, so a ``kill -9`` leaves a file whose summary section is missing but whose data
section is complete up to the last chunk: MCAP readers read it by scanning (``mcap.reader.NonSeekingReader``, and
:func:`read_recording` here, which stops quietly at a torn tail). A clean stop (SIGINT, SIGTERM, ``--duration``, a
size limit) writes the summary and fsyncs.

**Bounded disk.** ``--max-bytes N``: the file never exceeds N bytes (the size after closing is estimated
conservatively before each message); when the next message would not fit, recording stops and says so.
``--rotate-bytes N --keep K``: ``run-0001.mcap``, ``run-0002.mcap``, ... each at most N bytes, each a complete MCAP
file with its own schemas and channels, only the last K kept. Either way the recorder's queue is bounded too:
samples that arrive faster than the disk takes them are counted as dropped.

**Replay** publishes the recorded messages on their keys (``wire.encode`` of each message) at the recorded pace,
``--speed X`` times faster, or ``--fast``. Commands move robots: ``cmd`` and ``estop`` are only replayed with
``--with-commands`` (a replayed ``cmd`` of a new epoch is accepted by a driver host that never saw it, and a
replayed estop release would release a live estop).
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import re
import socket
import sys
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
from msgspec import Struct

from bridge.core import wire as M

#: the wire message of each topic of ``scm/<robot>/<topic>`` (``status`` has one more chunk: the node)
TOPIC_KINDS: dict[str, type[Struct]] = {
    "state": M.LearnerState, "cmd": M.Command, "teacher": M.TeacherCommand, "applied": M.Applied,
    "pairs": M.Pairs, "limits": M.Limits, "mission": M.MissionSpec, "mocap": M.LearnerState,
    "status": M.Status, "estop": M.Estop,
}
if set(TOPIC_KINDS) != set(M.TOPICS):  # a topic added to the wire contract must be added here
    raise ImportError(f"bridge.tools.record knows topics {sorted(TOPIC_KINDS)}, the wire contract {sorted(M.TOPICS)}")

SCHEMA_PREFIX = "scmbridge."
MALFORMED = "/scmbridge/malformed"
NONCANONICAL = "/scmbridge/noncanonical"
#: topics a replay publishes only with --with-commands: they move (or release) a robot
ACTUATING = ("cmd", "estop")
PROFILE = ""  # MCAP profile: none of the registered ones (ros1, ros2) applies
META_START = "scmbridge.record"
META_END = "scmbridge.record.end"


class RawSample(Struct, kw_only=True):
    """A sample kept as the bytes that arrived: one that failed to decode (``/scmbridge/malformed``) or one whose
    bytes are not what ``wire.encode`` makes of its JSON (``/scmbridge/noncanonical``)."""

    key: str
    error: str = ""
    size: int
    payload: bytes  # JSON: base64 with "contentEncoding": "base64"


def parse_key(key: str) -> tuple[str, str]:
    """``(robot, topic)`` of a key of the wire contract; ``ValueError`` naming the problem otherwise."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != M.PREFIX:
        raise ValueError(f"key {key!r} is not scm/<robot>/<topic>")
    robot, topic = parts[1], parts[2]
    M.check_robot(robot)
    if topic not in TOPIC_KINDS:
        raise ValueError(f"key {key!r}: unknown topic {topic!r}")
    if topic == "status":
        if len(parts) != 4:
            raise ValueError(f"key {key!r}: status is scm/<robot>/status/<node>")
        M.check_robot(parts[3])
    elif len(parts) != 3:
        raise ValueError(f"key {key!r} has chunks after its topic")
    return robot, topic


def kind_of(key: str) -> type[Struct]:
    """The wire Struct that travels on ``key`` (``ValueError`` for a key outside the contract)."""
    return TOPIC_KINDS[parse_key(key)[1]]


def json_schema(kind: type[Struct]) -> dict[str, Any]:
    """msgspec's JSON Schema of ``kind`` with the root definition inlined (Foxglove wants ``type: object`` at the
    top; nested Structs stay as internal ``$ref``s, which Foxglove resolves)."""
    s = msgspec.json.schema(kind)
    defs = dict(s.get("$defs", {}))
    root = s["$ref"].rsplit("/", 1)[-1]
    out = dict(defs.pop(root))
    if defs:
        out["$defs"] = defs
    return out


_json_encoder = msgspec.json.Encoder()
_json_decoders: dict[type, msgspec.json.Decoder] = {}


def to_json(msg: Struct) -> bytes:
    """The JSON stored for ``msg`` (see the module docstring)."""
    return _json_encoder.encode(msg)


def from_json(data: bytes, kind: type[Struct]) -> Any:
    """Decode and validate stored JSON as ``kind`` (``MessageError`` if it is not one)."""
    dec = _json_decoders.get(kind)
    if dec is None:
        dec = _json_decoders[kind] = msgspec.json.Decoder(kind)
    try:
        return dec.decode(data)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise M.MessageError(f"bad {kind.__name__}: {exc}") from exc


@dataclass(frozen=True)
class ChannelSpec:
    """What an MCAP channel and its schema are made of."""

    topic: str
    schema_name: str
    schema: bytes

    @staticmethod
    def for_kind(topic: str, kind: type[Struct]) -> ChannelSpec:
        return ChannelSpec(topic, SCHEMA_PREFIX + kind.__name__, _schema_bytes(kind))


_SCHEMAS: dict[type, bytes] = {}


def _schema_bytes(kind: type[Struct]) -> bytes:
    if kind not in _SCHEMAS:
        _SCHEMAS[kind] = json.dumps(json_schema(kind), separators=(",", ":")).encode()
    return _SCHEMAS[kind]


def classify(key: str, payload: bytes, is_put: bool = True) -> list[tuple[ChannelSpec, bytes, str]]:
    """What to write for one received sample: ``[(channel, json bytes, outcome)]`` where outcome is ``ok``,
    ``malformed`` or ``noncanonical`` (a noncanonical message gives two entries: its JSON and its raw bytes)."""
    if not is_put:
        raw = RawSample(key=key, error="DELETE sample", size=len(payload), payload=payload)
        return [(ChannelSpec.for_kind(MALFORMED, RawSample), to_json(raw), "malformed")]
    try:
        kind = kind_of(key)
        msg = M.decode(payload, kind)
    except (ValueError, M.MessageError) as exc:  # MessageError is a ValueError; both named for the reader
        raw = RawSample(key=key, error=str(exc)[:1024], size=len(payload), payload=payload)
        return [(ChannelSpec.for_kind(MALFORMED, RawSample), to_json(raw), "malformed")]
    data = to_json(msg)
    out = [(ChannelSpec.for_kind(key, kind), data, "ok")]
    if M.encode(from_json(data, kind)) != payload:
        raw = RawSample(key=key, size=len(payload), payload=payload)
        out.append((ChannelSpec.for_kind(NONCANONICAL, RawSample), to_json(raw), "noncanonical"))
    return out


# ------------------------------------------------------------------------------------------------- writing
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


# ----------------------------------------------------------------------------------------------- recording
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


def _record_args(argv: list[str] | None) -> argparse.Namespace:
    from bridge.nodes.cliutil import positive_float
    from bridge.nodes.node import add_zenoh_args

    ap = argparse.ArgumentParser(prog="scmbridge record", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--robot", help="record scm/ROBOT/**")
    who.add_argument("--all", action="store_true", help="record scm/** (every robot)")
    ap.add_argument("--out", required=True, help="the MCAP file (with --rotate-bytes: OUT-0001.mcap, ...)")
    ap.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    size = ap.add_mutually_exclusive_group()
    size.add_argument("--max-bytes", type=parse_bytes, default=None, help="stop when the file would exceed this")
    size.add_argument("--rotate-bytes", type=parse_bytes, default=None, help="start a new file at this size")
    ap.add_argument("--keep", type=int, default=10, help="with --rotate-bytes: files kept (the newest)")
    ap.add_argument("--chunk-bytes", type=parse_bytes, default=128 << 10, help="close a chunk at this size")
    ap.add_argument("--flush-s", type=positive_float, default=1.0, help="close a chunk at least this often, s")
    ap.add_argument("--queue", type=int, default=100_000, help="samples waiting for the disk before drops")
    ap.add_argument("--force", action="store_true", help="overwrite existing output files")
    add_zenoh_args(ap)
    args = ap.parse_args(argv)
    if args.robot is not None:
        try:
            M.check_robot(args.robot)
        except ValueError as exc:
            ap.error(str(exc))
    if args.keep < 1:
        ap.error("--keep must be >= 1")
    if args.keep != 10 and args.rotate_bytes is None:
        ap.error("--keep goes with --rotate-bytes")
    out = Path(args.out)
    existing = sorted(out.parent.glob(f"{out.stem}-[0-9][0-9][0-9][0-9]{out.suffix or '.mcap'}")) \
        if args.rotate_bytes else ([out] if out.exists() else [])
    if existing and not args.force:
        ap.error(f"{existing[0]} exists (--force overwrites)")
    return args


def record_main(argv: list[str] | None = None) -> int:
    """``scmbridge record``: subscribe, classify in the loop (not on Zenoh's threads), write, stop cleanly."""
    args = _record_args(argv)
    import zenoh

    from bridge.nodes.node import Inputs, stop_on_signals, zenoh_config
    from bridge.nodes.zsession import open_session

    pattern = f"{M.PREFIX}/{args.robot}/**" if args.robot else f"{M.PREFIX}/**"
    clock = Clock()
    sink = McapSink(Path(args.out), max_bytes=args.max_bytes, rotate_bytes=args.rotate_bytes, keep=args.keep,
                    chunk_bytes=args.chunk_bytes, flush_s=args.flush_s, meta=_start_meta(pattern, clock))
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
        sub = session.declare_subscriber(pattern, on_sample)
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
    return 0


def main(argv: list[str] | None = None) -> int:
    return record_main(argv)


# ------------------------------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class Entry:
    """One recorded message: its channel topic (the Zenoh key, or ``/scmbridge/...``), schema name, receive time
    (ns) and stored JSON."""

    topic: str
    schema: str
    log_time: int
    data: bytes

    @property
    def is_wire(self) -> bool:
        return not self.topic.startswith("/")

    def message(self) -> Any:
        """The wire Struct (or a :class:`RawSample` on the ``/scmbridge/...`` channels), validated."""
        if not self.is_wire:
            return from_json(self.data, RawSample)
        return from_json(self.data, kind_of(self.topic))


@dataclass
class Recording:
    """What reading one or more files found besides the messages."""

    files: list[Path]
    truncated: list[str] = field(default_factory=list)  # "<file>: <why the scan stopped>"
    metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    entries: int = 0


def iter_recording(paths: Iterable[str | Path], rec: Recording | None = None) -> Iterator[Entry]:
    """The messages of the files in file order (= arrival order), read by a linear scan: a file without its
    summary (a killed recorder) is read up to its last complete chunk and noted in ``rec.truncated``."""
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    for p in paths:
        path = Path(p)
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str]] = {}
        with open(path, "rb") as f:
            reader = StreamReader(f, validate_crcs=True)
            it = reader.records
            while True:
                try:
                    record = next(it)
                except StopIteration:
                    break
                except Exception as exc:  # a torn tail: EndOfFile, a short chunk, a bad CRC ... the data so far stands
                    if rec is not None:
                        rec.truncated.append(f"{path}: {type(exc).__name__}: {exc}"[:300])
                    break
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
                elif isinstance(record, Message):
                    topic, schema = channels[record.channel_id]
                    if rec is not None:
                        rec.entries += 1
                    yield Entry(topic, schema, record.log_time, record.data)
                elif isinstance(record, Metadata) and rec is not None:
                    rec.metadata.append((record.name, dict(record.metadata)))


def read_recording(paths: Iterable[str | Path]) -> tuple[list[Entry], Recording]:
    """All entries of the files (see :func:`iter_recording`) and what the scan found."""
    paths = [Path(p) for p in paths]
    rec = Recording(paths)
    return list(iter_recording(paths, rec)), rec


# ------------------------------------------------------------------------------------------------- replay
def rename_robot(key: str, renames: dict[str, str]) -> str:
    """``scm/A/...`` -> ``scm/B/...`` for a rename ``A=B``."""
    parts = key.split("/", 2)
    if len(parts) == 3 and parts[1] in renames:
        return f"{parts[0]}/{renames[parts[1]]}/{parts[2]}"
    return key


def _rename_arg(text: str) -> tuple[str, str]:
    a, sep, b = text.partition("=")
    try:
        if not sep:
            raise ValueError("expected A=B")
        return M.check_robot(a), M.check_robot(b)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--robot-rename {text!r}: {exc}") from None


def wire_bytes(entry: Entry, renames: dict[str, str]) -> tuple[str, bytes]:
    """The key and MessagePack bytes to publish for a recorded wire message (robot names renamed, also in the
    ``robot`` field of ``limits`` and ``pairs``)."""
    msg = entry.message()
    if renames and isinstance(msg, (M.Limits, M.Pairs)) and msg.robot in renames:
        msg = msgspec.structs.replace(msg, robot=renames[msg.robot])
    return rename_robot(entry.topic, renames), M.encode(msg)


def replay_main(argv: list[str] | None = None) -> int:
    """``scmbridge replay FILE...``: publish the recorded messages at the recorded pace (see the module docstring)."""
    from bridge.nodes.cliutil import positive_float
    from bridge.nodes.node import add_zenoh_args, stop_on_signals, zenoh_config
    from bridge.nodes.zsession import open_session

    ap = argparse.ArgumentParser(prog="scmbridge replay", description="republish a recording (scmbridge record) on "
                                 "its Zenoh keys at the recorded pace")
    ap.add_argument("files", nargs="+", help="MCAP file(s), in order (a rotated recording: all its files)")
    pace = ap.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=positive_float, default=1.0, help="X times the recorded pace")
    pace.add_argument("--fast", action="store_true", help="as fast as Zenoh takes them")
    ap.add_argument("--robot-rename", type=_rename_arg, action="append", default=[], metavar="A=B",
                    help="publish robot A's keys as robot B's (repeatable)")
    ap.add_argument("--with-commands", action="store_true",
                    help="also replay cmd and estop (they move or release a robot: never next to a live one)")
    ap.add_argument("--wait", type=float, default=5.0,
                    help="s to wait for a subscriber of the first key before publishing (0: do not wait)")
    add_zenoh_args(ap)
    args = ap.parse_args(argv)
    for f in args.files:
        if not Path(f).is_file():
            ap.error(f"{f}: no such file")
    renames = dict(args.robot_rename)

    import zenoh

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


__all__ = [
    "MALFORMED",
    "NONCANONICAL",
    "TOPIC_KINDS",
    "ChannelSpec",
    "Entry",
    "McapSink",
    "RawSample",
    "Recording",
    "classify",
    "from_json",
    "iter_recording",
    "json_schema",
    "kind_of",
    "main",
    "parse_bytes",
    "parse_key",
    "read_recording",
    "record_main",
    "rename_robot",
    "replay_main",
    "to_json",
    "wire_bytes",
]
