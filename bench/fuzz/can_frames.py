"""CAN frames for the fuzz: the CANSimple oracle (the shipped DBC), the mutator, and what controllers and a driver
send (the templates the mutations start from)."""

from __future__ import annotations

import math
import random
import struct
from collections.abc import Callable
from typing import Any

import can

from bench.fuzz.harness import NONFINITE
from drivers.can import database
from sim_learner.can_ecu import (
    CLEAR_ERRORS,
    CLOSED_LOOP_CONTROL,
    GET_ENCODER_ESTIMATES,
    HEARTBEAT,
    INPUT_PASSTHROUGH,
    SET_AXIS_STATE,
    SET_CONTROLLER_MODE,
    SET_INPUT_VEL,
    VELOCITY_CONTROL,
)
from sim_learner.can_ecu import ESTOP as ESTOP_CMD

#: the CANSimple commands the controllers know (any other command id is unknown)
KNOWN_COMMANDS = (HEARTBEAT, ESTOP_CMD, SET_AXIS_STATE, GET_ENCODER_ESTIMATES, SET_CONTROLLER_MODE, SET_INPUT_VEL,
                  CLEAR_ERRORS)


class CanSpec:
    """The oracle: CANSimple as the shipped DBC (``drivers/odrive_cansimple.dbc``) lays it out, checked with
    ``struct``: a standard 11-bit id, a command the DBC knows, exactly its length (a remote frame: any), its float32
    fields finite."""

    def __init__(self) -> None:
        self.msgs = {m.frame_id: (m.name, m.length, [s.start // 8 for s in m.signals if s.is_float])
                     for m in database().messages}

    def valid(self, f) -> bool:
        if f.is_extended_id or f.is_error_frame:
            return False
        m = self.msgs.get(f.arbitration_id & 0x1F)
        if m is None:
            return False
        if f.is_remote_frame:
            return True
        if len(f.data) != m[1]:
            return False
        return all(math.isfinite(struct.unpack_from("<f", bytes(f.data), off)[0]) for off in m[2])

    def length(self, cmd: int, default: int) -> int:
        return self.msgs[cmd][1] if cmd in self.msgs else default


def can_frame(node: int, cmd: int, data: bytes = b"", **kw: Any) -> can.Message:
    """A standard-id CANSimple frame of ``cmd`` for ``node``."""
    return can.Message(arbitration_id=(node << 5) | cmd, data=data, is_extended_id=False, **kw)


class CanMutator:
    """Frames around valid templates: random frames, bit flips (data and id), truncations, extensions (to 8 bytes),
    NaN/inf and huge float32 values, unknown commands, other nodes, extended ids, remote frames."""

    KINDS = (("valid", 15), ("random", 10), ("bit_flip", 14), ("truncate", 10), ("extend", 6), ("nonfinite", 10),
             ("huge", 6), ("unknown_cmd", 8), ("other_node", 6), ("extended", 6), ("remote", 3), ("dlc_garbage", 4))

    def __init__(self, rng: random.Random, templates: Callable[[], Any], nodes: tuple[int, ...]) -> None:
        self.rng, self.templates, self.nodes = rng, templates, nodes
        self.kinds = [k for k, _ in self.KINDS]
        self.weights = [w for _, w in self.KINDS]

    def next(self) -> tuple[str, can.Message]:
        rng = self.rng
        kind = rng.choices(self.kinds, self.weights)[0]
        f = self.templates()
        data = bytearray(f.data)
        arb = f.arbitration_id
        ext = rtr = False
        if kind == "random":
            arb, data = rng.randrange(0x800), bytearray(rng.randbytes(rng.randint(0, 8)))
        elif kind == "bit_flip":
            for _ in range(rng.randint(1, 3)):
                if data and rng.random() < 0.8:
                    data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
                else:
                    arb ^= 1 << rng.randrange(11)
        elif kind == "truncate" and data:
            data = data[:rng.randrange(len(data))]
        elif kind == "extend":
            data += rng.randbytes(rng.randint(1, max(1, 8 - len(data)))) if len(data) < 8 else b""
            data = data[:8] if len(data) > 8 else data
        elif kind in ("nonfinite", "huge"):
            vals = NONFINITE if kind == "nonfinite" else (3.4e38, -3.4e38, 1e30, 1e7, -1e7, 1e-45)
            data = bytearray(struct.pack("<ff", rng.choice(vals), rng.choice(vals) if rng.random() < 0.3 else 0.5))
            arb = (arb & ~0x1F) | rng.choice([GET_ENCODER_ESTIMATES, SET_INPUT_VEL])
        elif kind == "unknown_cmd":
            arb = (arb & ~0x1F) | rng.choice([c for c in range(32) if c not in KNOWN_COMMANDS])
        elif kind == "other_node":
            arb = (rng.choice([n for n in range(64) if n not in self.nodes]) << 5) | (arb & 0x1F)
        elif kind == "extended":
            ext, arb = True, rng.choice([arb, rng.randrange(1 << 29)])
        elif kind == "remote":
            rtr, data = True, bytearray()
            arb = (arb & ~0x1F) | rng.choice([GET_ENCODER_ESTIMATES, GET_ENCODER_ESTIMATES, HEARTBEAT, SET_INPUT_VEL,
                                              SET_AXIS_STATE, CLEAR_ERRORS, rng.randrange(32)])
        elif kind == "dlc_garbage":
            data = bytearray(rng.randbytes(rng.choice([0, 1, 3, 4, 5, 7, 8])))
        return kind, can.Message(arbitration_id=arb, data=bytes(data), is_extended_id=ext, is_remote_frame=rtr,
                                 dlc=0 if rtr else len(data))


def controller_frames(rng: random.Random, nodes: tuple[int, ...]):
    """What motor controllers send: Heartbeats (closed loop, no error) and encoder estimates."""

    def make():
        node = rng.choice(nodes)
        if rng.random() < 0.4:
            return can_frame(node, HEARTBEAT, struct.pack("<IBBBx", 0, CLOSED_LOOP_CONTROL, 0, 1))
        return can_frame(node, GET_ENCODER_ESTIMATES, struct.pack("<ff", rng.uniform(-100, 100), rng.uniform(-5, 5)))

    return make


def master_frames(rng: random.Random, nodes: tuple[int, ...], spec: CanSpec):
    """What a driver sends its controllers: set-points (finite, some huge), arming, controller mode, clears,
    encoder requests, a rare Estop."""
    state_len = spec.length(SET_AXIS_STATE, 4)

    def make():
        node = rng.choice(nodes)
        r = rng.random()
        if r < 0.55:
            return can_frame(node, SET_INPUT_VEL, struct.pack("<ff", rng.uniform(-8, 8), 0.0))
        if r < 0.7:
            state = rng.choice([CLOSED_LOOP_CONTROL, CLOSED_LOOP_CONTROL, 1, rng.randrange(2**32)])
            return can_frame(node, SET_AXIS_STATE, struct.pack("<I", state).ljust(state_len, b"\0"))
        if r < 0.8:
            return can_frame(node, SET_CONTROLLER_MODE, struct.pack("<II", VELOCITY_CONTROL, INPUT_PASSTHROUGH))
        if r < 0.9:
            return can_frame(node, CLEAR_ERRORS, b"\0")
        if r < 0.98:
            return can_frame(node, GET_ENCODER_ESTIMATES, b"", is_remote_frame=True)
        return can_frame(node, ESTOP_CMD, b"")

    return make


def ecu_class(f, spec: CanSpec, nodes: tuple[int, ...]) -> str:
    """``valid`` (no device counts it), ``definite`` (every CANSimple device counts it: a set-point, state request or
    controller mode too short for its fields, or a non-finite velocity set-point), or ``either`` (not CANSimple as the
    DBC has it, but an ODrive ignores it silently: another node, an unknown command, an extended id, a remote frame,
    a length it does not check, a non-finite torque feed-forward)."""
    if spec.valid(f):
        return "valid"
    if f.is_extended_id or f.is_error_frame or f.is_remote_frame or (f.arbitration_id >> 5) not in nodes:
        return "either"
    cmd, data = f.arbitration_id & 0x1F, bytes(f.data)
    if cmd == SET_INPUT_VEL:
        return "definite" if len(data) < 8 or not math.isfinite(struct.unpack_from("<f", data)[0]) else "either"
    if cmd == SET_AXIS_STATE:
        return "definite" if len(data) < 4 else "either"
    if cmd == SET_CONTROLLER_MODE:
        return "definite" if len(data) < 8 else "either"
    return "either"
