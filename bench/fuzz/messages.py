"""MessagePack payloads of the wire contract's messages, mutated around the valid ones a real stream sends."""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from typing import Any

import msgspec

from bench.fuzz.harness import NONFINITE
from bridge.core import wire as M

OUT_OF_RANGE_F = (1e13, -1e13, 1e300, -1e300, 3.4e38)  # beyond every float bound of the wire contract
WRONG_TYPES: tuple[Any, ...] = ("x", None, [1.0], {"a": 1}, True, b"\x00\x01", -1, 2**64 - 1, 1.5, "")
HUGE_INTS = (2**63 - 1, 2**63, 2**64 - 1, -1, -(2**63), 2**62 + 12345)
BAD_UTF8 = b"\xa3\xff\xfe\xfd"  # msgpack fixstr of 3 bytes that are not UTF-8


class Spec:
    """What a message of one kind looks like, for mutating it: its float, int, str and list fields and the fields
    that have no default."""

    def __init__(self, kind: type, floats: tuple[str, ...], ints: tuple[str, ...], strs: tuple[str, ...],
                 lists: tuple[str, ...], required: tuple[str, ...]) -> None:
        self.kind, self.floats, self.ints, self.strs, self.lists, self.required = kind, floats, ints, strs, lists, \
            required


COMMAND = Spec(M.Command, ("stamp", "v", "omega"), ("seq", "epoch", "valid_ms"), ("sender", "method"), ("region",),
               ("stamp", "seq", "v", "omega", "method"))
ESTOP = Spec(M.Estop, ("stamp",), ("seq",), ("source", "reason"), (), ("stamp",))
STATE = Spec(M.LearnerState, ("stamp", "x", "y", "theta", "v", "omega"), ("seq", "epoch"), ("source",), (),
             ("stamp", "seq", "x", "y", "theta"))


def wire_ok(data: bytes, kind: type) -> bool:
    """The oracle: does ``data`` decode and validate as ``kind`` under the wire contract?"""
    try:
        M.decode(data, kind)
    except M.MessageError:
        return False
    return True


class MsgMutator:
    """Mutated MessagePack payloads of one message kind around the valid ones ``valid()`` returns (as dicts)."""

    KINDS = (("valid", 14), ("random_bytes", 8), ("bit_flip", 12), ("truncate", 6), ("extend", 6),
             ("nonfinite", 9), ("out_of_range", 6), ("unknown_field", 5), ("wrong_type", 10), ("missing_field", 4),
             ("huge_seq_epoch", 8), ("long_string", 3), ("big_array", 2), ("bad_utf8", 2), ("large_blob", 1))

    def __init__(self, rng: random.Random, spec: Spec, valid: Callable[[], dict], max_blob: int = 65536) -> None:
        self.rng, self.spec, self.valid, self.max_blob = rng, spec, valid, max_blob
        kinds = [k for k, _ in self.KINDS if k != "big_array" or spec.lists]
        self.kinds = kinds
        self.weights = [w for k, w in self.KINDS if k in kinds]

    def next(self) -> tuple[str, bytes]:
        rng = self.rng
        kind = rng.choices(self.kinds, self.weights)[0]
        msg = self.valid()
        if kind == "valid":
            commit = getattr(self.valid, "commit", None)
            if commit is not None:
                commit()  # the stream's seq counts only what it really sends
            return kind, msgspec.msgpack.encode(msg)
        if kind == "random_bytes":
            return kind, rng.randbytes(rng.randint(0, 120))
        if kind == "large_blob":  # Zenoh: up to 64 KiB (several batches, a big allocation); UDP: up to an MTU
            return kind, rng.randbytes(rng.randint(self.max_blob // 2, self.max_blob))
        raw = msgspec.msgpack.encode(msg)
        if kind == "bit_flip":
            b = bytearray(raw)
            for _ in range(rng.randint(1, 4)):
                b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
            return kind, bytes(b)
        if kind == "truncate":
            return kind, raw[:rng.randrange(len(raw))]
        if kind == "extend":
            return kind, raw + rng.randbytes(rng.randint(1, 64))
        s = self.spec
        if kind == "nonfinite":
            msg[rng.choice(s.floats)] = rng.choice(NONFINITE)
        elif kind == "out_of_range":
            msg[rng.choice(s.floats)] = rng.choice(OUT_OF_RANGE_F)
        elif kind == "unknown_field":
            msg[rng.choice(["x_", "extra", "V", "seq2", "epoch_", "\u00e9"])] = rng.choice([1, 1.0, "a", None])
        elif kind == "wrong_type":
            msg[rng.choice([*s.floats, *s.ints, *s.strs, *s.lists])] = rng.choice(WRONG_TYPES)
        elif kind == "missing_field":
            del msg[rng.choice(s.required)]
        elif kind == "huge_seq_epoch":
            for f in s.ints:
                if f in ("seq", "epoch") and rng.random() < 0.7:
                    msg[f] = rng.choice(HUGE_INTS) if rng.random() < 0.6 else rng.getrandbits(63)
        elif kind == "long_string":
            msg[rng.choice(s.strs)] = "x" * rng.choice([1025, rng.randint(2000, 20000)])  # > every str bound
        elif kind == "big_array":
            msg[rng.choice(s.lists)] = list(range(rng.randint(9, 5000)))
        elif kind == "bad_utf8":
            field = rng.choice(s.strs)
            msg[field] = "\x00SENTINEL\x00"
            out = msgspec.msgpack.encode(msg)
            i = out.find(b"\xaa\x00SENTINEL\x00")
            return kind, out[:i] + BAD_UTF8 + out[i + 11:]
        try:
            return kind, msgspec.msgpack.encode(msg)
        except (OverflowError, TypeError):  # an int beyond 64 bits: send its raw uint64 marker instead
            return kind, b"\xcf" + rng.randbytes(8)


class Stream:
    """A sender's stream (one epoch, ``seq`` counting only what it really sends: :meth:`commit`)."""

    def __init__(self, rng: random.Random) -> None:
        self.rng, self.epoch, self.seq = rng, M.new_epoch(), 0

    def commit(self) -> None:
        self.seq += 1


class CommandStream(Stream):
    """A station's (or a driver's) valid commands, with the values a fuzzer likes: in range, beyond the limits,
    exact zeros, stops, very short validity."""

    def __init__(self, rng: random.Random, sender: str = "fuzz", span: tuple[float, float] = (0.8, 1.5)) -> None:
        super().__init__(rng)
        self.sender, self.span = sender, span

    def __call__(self) -> dict:
        rng = self.rng
        r = rng.random()
        v, w = (0.0, 0.0) if r < 0.05 else (rng.uniform(-99, 99), rng.uniform(-99, 99)) if r < 0.15 else (
            rng.uniform(-self.span[0], self.span[0]), rng.uniform(-self.span[1], self.span[1]))
        msg = {"stamp": time.monotonic(), "seq": self.seq + 1, "v": v, "omega": w,
               "method": rng.choice(["scm", "direct", "perturb", "stop", "affine", "calibrate"]),
               "sender": self.sender, "epoch": self.epoch}
        if rng.random() < 0.2:
            msg["valid_ms"] = rng.choice([1, 50, 300, 10_000])
        if rng.random() < 0.2:
            msg["region"] = [rng.randrange(100) for _ in range(rng.randint(0, 8))]
        return msg


class StateStream(Stream):
    """A robot's valid states (its epoch, its seq)."""

    def __call__(self) -> dict:
        rng = self.rng
        return {"stamp": time.monotonic(), "seq": self.seq + 1, "x": rng.uniform(-50, 50), "y": rng.uniform(-50, 50),
                "theta": rng.uniform(-7, 7), "v": rng.uniform(-1, 1), "omega": rng.uniform(-2, 2),
                "source": "udp-robot", "epoch": self.epoch}
