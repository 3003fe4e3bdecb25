"""The recording's MCAP file(s) as ``scmbridge record`` writes them: channels and schemas registered on first use,
chunks closed by size or time (a ``kill -9`` loses at most the open chunk), a size limit or rotation into numbered
files, each closed with an end-of-recording metadata record and fsynced."""

from __future__ import annotations

import os
import time
from collections import Counter
from pathlib import Path
from typing import Any

from bridge.tools.mcap_format import META_END, META_START, PROFILE, ChannelSpec

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
    a size limit or rotation (``scmbridge record --max-bytes``, ``--rotate-bytes``). Single-threaded: only the
    recorder's loop calls it."""

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
