"""The recording format of ``scmbridge record``: one MCAP channel per Zenoh key, one JSON Schema per wire message.

Messages are stored as JSON with a JSON Schema (``json`` + ``jsonschema``: the pair Foxglove decodes without a
plugin), not as the wire's MessagePack. Nothing is lost: each message is decoded (validated), written as msgspec's
JSON of the Struct, and when re-encoding that JSON does not give back the received bytes, the bytes are also kept on
``/scmbridge/noncanonical``; a sample that does not decode goes to ``/scmbridge/malformed`` with the reason. Reading
scans the data section, so a file whose recorder was killed reads up to its last complete chunk.
"""

from __future__ import annotations

import json
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
    "status": M.Status, "estop": M.Estop, "control": M.MissionState, "engage": M.EngageState,
    "journal": M.StationJournal,
}
if set(TOPIC_KINDS) != set(M.TOPICS):  # a topic added to the wire contract must be added here
    raise ImportError(f"bridge.tools.mcap_format knows topics {sorted(TOPIC_KINDS)}, the wire contract "
                      f"{sorted(M.TOPICS)}")

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


def rename_robot(key: str, renames: dict[str, str]) -> str:
    """``scm/A/...`` -> ``scm/B/...`` for a rename ``A=B``."""
    parts = key.split("/", 2)
    if len(parts) == 3 and parts[1] in renames:
        return f"{parts[0]}/{renames[parts[1]]}/{parts[2]}"
    return key


def wire_bytes(entry: Entry, renames: dict[str, str]) -> tuple[str, bytes]:
    """The key and MessagePack bytes to publish for a recorded wire message (robot names renamed, also in the
    ``robot`` field of ``limits`` and ``pairs``)."""
    msg = entry.message()
    if renames and isinstance(msg, (M.Limits, M.Pairs)) and msg.robot in renames:
        msg = msgspec.structs.replace(msg, robot=renames[msg.robot])
    return rename_robot(entry.topic, renames), M.encode(msg)
