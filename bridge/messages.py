"""Wire contracts: one msgspec Struct per Zenoh key (DESIGN.md section 4), MessagePack on the wire.

Constructing or encoding a Struct does not validate; *decoding* does (types, ``Meta`` ranges, NaN/inf against
the bounds, unknown fields). So every trust boundary decodes with :func:`decode`, which raises
:class:`MessageError` with the reason; callers count and drop. The bounds below are sanity bounds of the wire
format (a command of 1000 m/s is not a command), not the vehicle's hard limits, which the driver host applies.

Stamps are ``time.monotonic()`` seconds of the *sender's* clock. Pairing in the station only compares stamps that
come from one clock (the driver host's ``state`` and ``applied``), so base station and robot need no clock sync.
"""

from __future__ import annotations

from typing import Annotated, Literal, TypeVar

import msgspec
from msgspec import Meta, Struct

# Finite floats: a NaN or inf fails the ge/le comparison at decode time and is rejected.
Stamp = Annotated[float, Meta(ge=0.0, le=1e12)]
Seq = Annotated[int, Meta(ge=0, le=2**63 - 1)]
Coord = Annotated[float, Meta(ge=-1e6, le=1e6)]  # metres
Angle = Annotated[float, Meta(ge=-1e3, le=1e3)]  # radians (not necessarily wrapped)
Speed = Annotated[float, Meta(ge=-100.0, le=100.0)]  # m/s
Rate = Annotated[float, Meta(ge=-100.0, le=100.0)]  # rad/s
Name = Annotated[str, Meta(max_length=64)]
Text = Annotated[str, Meta(max_length=1024)]

Method = Literal["scm", "affine", "barycentric", "direct", "perturb", "stop", "calibrate", "manual"]


class _Msg(Struct, forbid_unknown_fields=True, omit_defaults=True):
    """Base: unknown fields are an error, defaults are not sent."""


class LearnerState(_Msg, kw_only=True):
    """``scm/<robot>/state``: the learner's pose in ENU (x east, y north, theta CCW from x), from its telemetry."""

    stamp: Stamp
    seq: Seq
    x: Coord
    y: Coord
    theta: Angle
    v: Speed | None = None
    omega: Rate | None = None
    source: Name = ""


class Command(_Msg, kw_only=True):
    """``scm/<robot>/cmd``: the learner command to apply, how it was obtained and for how long it is valid.

    ``valid_ms`` counts from the moment the driver host receives the message (clocks need not agree).
    """

    stamp: Stamp
    seq: Seq
    v: Speed
    omega: Rate
    method: Method
    valid_ms: Annotated[int, Meta(ge=1, le=10_000)] = 300
    region: Annotated[list[Annotated[int, Meta(ge=0)]], Meta(max_length=8)] = []


class TeacherCommand(_Msg, kw_only=True):
    """``scm/<robot>/teacher``: the teacher's own command and the prediction behind it (logging and plots)."""

    stamp: Stamp
    seq: Seq
    v: Speed
    omega: Rate
    solver: Name = ""
    ok: bool = True
    predicted_x: Annotated[list[Coord], Meta(max_length=512)] = []
    predicted_y: Annotated[list[Coord], Meta(max_length=512)] = []


class Applied(_Msg, kw_only=True):
    """``scm/<robot>/applied``: what the vehicle really got and when (driver-host clock).

    ``cmd_seq`` is the ``Command.seq`` it came from, or absent for a stop the driver host decided itself
    (``reason`` says why: deadman, estop, stale, shutdown).
    """

    stamp: Stamp
    seq: Seq
    v: Speed
    omega: Rate
    reason: Literal["cmd", "clamped", "deadman", "estop", "stale", "shutdown", "start"]
    cmd_seq: Seq | None = None


class PairRecord(_Msg, kw_only=True, array_like=True):
    """One refined command pair ``<u_T, u_L>`` with its stable id, version and cluster size."""

    id: Annotated[int, Meta(ge=0)]
    version: Annotated[int, Meta(ge=0)]
    count: Annotated[int, Meta(ge=0)]
    teacher_v: Speed
    teacher_omega: Rate
    learner_v: Speed
    learner_omega: Rate


class Pairs(_Msg, kw_only=True):
    """``scm/<robot>/pairs``: the refined pairs and the learned limits on the teacher domain (query reply)."""

    stamp: Stamp
    robot: Name
    pairs: Annotated[list[PairRecord], Meta(max_length=100_000)] = []
    limits_box: Annotated[list[Annotated[float, Meta(ge=-100, le=100)]], Meta(min_length=4, max_length=4)] | None = (
        None  # [v_min, v_max, omega_min, omega_max] on the teacher domain
    )
    limits_hull: Annotated[list[Annotated[list[Annotated[float, Meta(ge=-100, le=100)]], Meta(min_length=2, max_length=2)]], Meta(max_length=10_000)] = []  # noqa: E501


class Status(_Msg, kw_only=True):
    """``scm/<robot>/status``: health of one node; counters only grow."""

    stamp: Stamp
    seq: Seq
    node: Name
    ok: bool = True
    rates_hz: dict[Name, Annotated[float, Meta(ge=0, le=1e6)]] = {}
    latencies_ms: dict[Name, Annotated[float, Meta(ge=0, le=1e9)]] = {}
    counters: dict[Name, Annotated[int, Meta(ge=0)]] = {}
    text: Text = ""


class Estop(_Msg, kw_only=True):
    """``scm/<robot>/estop``: stop now. ``engaged=False`` releases a latched estop."""

    stamp: Stamp
    seq: Seq = 0
    engaged: bool = True
    source: Name = ""
    reason: Text = ""


class MessageError(ValueError):
    """A payload that failed to decode or validate; the receiver counts it and drops it."""


M = TypeVar("M", bound=Struct)

_encoder = msgspec.msgpack.Encoder()
_decoders: dict[type, msgspec.msgpack.Decoder] = {}


def encode(msg: Struct) -> bytes:
    """MessagePack bytes of ``msg`` (no validation: senders build messages from checked values)."""
    return _encoder.encode(msg)


def decode(data: bytes | bytearray | memoryview, kind: type[M]) -> M:
    """Decode *and validate* ``data`` as ``kind``; raise :class:`MessageError` naming the problem."""
    dec = _decoders.get(kind)
    if dec is None:
        dec = _decoders[kind] = msgspec.msgpack.Decoder(kind)
    try:
        return dec.decode(data)
    except (msgspec.ValidationError, msgspec.DecodeError, UnicodeDecodeError) as exc:
        # msgspec lets invalid UTF-8 in a str field escape as UnicodeDecodeError (found by hypothesis)
        raise MessageError(f"bad {kind.__name__}: {exc}") from exc


def validated(msg: M) -> M:
    """Round-trip a locally built message through the decoder: the cheap way to check it before sending."""
    return decode(encode(msg), type(msg))


__all__ = [
    "Applied",
    "Command",
    "Estop",
    "LearnerState",
    "MessageError",
    "Method",
    "PairRecord",
    "Pairs",
    "Status",
    "TeacherCommand",
    "decode",
    "encode",
    "validated",
]
