"""MAVLink datagrams for the fuzz: the mutator (every datagram sealed), what a rover and a ground station send (the
templates), and the oracle: a second pymavlink parser fed the same datagrams."""

from __future__ import annotations

import math
import os
import random
import struct
from collections import Counter
from collections.abc import Callable
from typing import Any

from bench.fuzz.harness import NONFINITE
from drivers.mavlink import POSITION_MAX, SPEED_MAX, YAW_MAX, YAW_RATE_MAX
from sim_learner.mavlink_rover import GUIDED, HOLD, MAV, VELOCITY_YAWRATE_MASK

MAV_CMD_DO_SET_MODE, MAV_CMD_ARM = MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_CMD_COMPONENT_ARM_DISARM
MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_REQUEST_PROTOCOL_VERSION = (MAV.MAV_CMD_SET_MESSAGE_INTERVAL,
                                                                  MAV.MAV_CMD_REQUEST_PROTOCOL_VERSION)
INT_RANGES = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535), "int16_t": (-32768, 32767),
              "uint32_t": (0, 2**32 - 1), "int32_t": (-(2**31), 2**31 - 1), "uint64_t": (0, 2**64 - 1),
              "int64_t": (-(2**63), 2**63 - 1)}


def mavlink2():
    """pymavlink's MAVLink 2 ardupilotmega module: what the driver and the emulated rover speak."""
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


def mav_parser():
    """A fresh pymavlink parser as a receiver has it (robust parsing: garbage comes out as BAD_DATA)."""
    p = mavlink2().MAVLink(None)
    p.robust_parsing = True
    return p


def mav_parse(parser, data: bytes) -> list:
    """Every message ``parser`` gets out of ``data`` (with what it already held)."""
    return parser.parse_buffer(data) or []


class MavMutator:
    """MAVLink datagrams around valid templates (``templates(encoder) -> message``): random bytes, bit flips,
    truncations, extensions, two frames in one datagram, fields set to NaN/inf/huge/extreme integers and random
    text (with a valid CRC), random payloads with a valid CRC, unknown message ids, MAVLink 1 frames, bad
    incompatibility flags, signed frames, other system ids.

    Every datagram is *sealed*: it starts on a frame marker and leaves no partial frame in a parser (zero padding
    completes one), so the messages a receiver gets out of the stream do not depend on how its reads split it."""

    KINDS = (("valid", 16), ("random_bytes", 8), ("bit_flip", 14), ("truncate", 8), ("extend", 6), ("concat", 5),
             ("weird_values", 14), ("random_payload", 8), ("unknown_msgid", 6), ("v1", 5), ("bad_incompat", 4),
             ("signed", 3), ("other_system", 3))

    def __init__(self, rng: random.Random, templates: Callable[[Any], Any], sysid: int = 1, compid: int = 1) -> None:
        self.rng, self.templates, self.sysid, self.compid = rng, templates, sysid, compid
        self.L = mavlink2()
        self.enc = self.L.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.kinds = [k for k, _ in self.KINDS]
        self.weights = [w for _, w in self.KINDS]

    def pack(self, msg, v1: bool = False, sysid: int | None = None) -> bytes:
        self.enc.srcSystem = self.sysid if sysid is None else sysid
        self.enc.srcComponent = self.compid
        self.enc.seq = self.rng.randrange(256)  # any sequence number: receivers only count losses with it
        return bytes(msg.pack(self.enc, force_mavlink1=v1))

    def _recrc(self, frame: bytearray) -> bytearray:
        """Recompute a MAVLink 2 frame's CRC (with its message's CRC_EXTRA)."""
        n = frame[1]
        msgid = frame[7] | frame[8] << 8 | frame[9] << 16
        crc = self.L.x25crc(bytes(frame[1:10 + n]))
        crc.accumulate(bytes([self.L.mavlink_map[msgid].crc_extra]))
        frame[10 + n:12 + n] = struct.pack("<H", crc.crc)
        return frame

    def weird(self, msg):
        rng = self.rng
        for i, name in enumerate(msg.fieldnames):
            ftype = msg.fieldtypes[i]
            alen = msg.array_lengths[msg.ordered_fieldnames.index(name)]
            if ftype == "char":
                if rng.random() < 0.6:
                    setattr(msg, name, rng.randbytes(rng.randint(0, max(1, alen))))
            elif alen:
                continue
            elif ftype in ("float", "double") and rng.random() < 0.6:
                setattr(msg, name, rng.choice([*NONFINITE, 3.4e38, -3.4e38, 1e30, -0.0, 1e-45]))
            elif ftype in INT_RANGES and rng.random() < 0.4:
                lo, hi = INT_RANGES[ftype]
                setattr(msg, name, rng.choice([lo, hi, rng.randint(lo, hi)]))
        return msg

    def raw(self) -> tuple[str, bytes]:
        rng = self.rng
        kind = rng.choices(self.kinds, self.weights)[0]
        msg = self.templates(self.enc)
        if kind == "weird_values":
            try:
                return kind, self.pack(self.weird(msg))
            except (struct.error, OverflowError, TypeError, ValueError):
                msg = self.templates(self.enc)
                kind = "valid"
        if kind == "v1":
            return kind, self.pack(msg, v1=True)
        if kind == "other_system":
            return kind, self.pack(msg, sysid=rng.randrange(256))
        frame = bytearray(self.pack(msg))
        if kind == "random_bytes":
            return kind, rng.randbytes(rng.randint(1, 120))
        if kind == "bit_flip":
            for _ in range(rng.randint(1, 4)):
                frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
        elif kind == "truncate":
            frame = frame[:rng.randrange(1, len(frame))]
        elif kind == "extend":
            frame += rng.randbytes(rng.randint(1, 40))
        elif kind == "concat":
            frame += (rng.randbytes(rng.randint(0, 6)) if rng.random() < 0.5 else b"") + self.pack(
                self.templates(self.enc))
        elif kind == "random_payload":
            n = frame[1]
            frame[10:10 + n] = rng.randbytes(n)
            frame = self._recrc(frame)
        elif kind == "unknown_msgid":
            msgid = rng.choice([m for m in (rng.randrange(1 << 24) for _ in range(4)) if m not in self.L.mavlink_map]
                               or [0xFFFFFF])
            n = rng.randint(0, 60)
            frame = bytearray(struct.pack("<BBBBBBBHB", 0xFD, n, 0, 0, rng.randrange(256), self.sysid,
                                          self.compid, msgid & 0xFFFF, msgid >> 16)) + rng.randbytes(n + 2)
        elif kind == "bad_incompat":
            frame[2] = rng.choice([0x02, 0x04, 0x80, 0xFE, 0x03])
            frame = self._recrc(frame)
        elif kind == "signed":
            frame[2] = 0x01
            frame = self._recrc(frame) + rng.randbytes(13)
        return kind, bytes(frame)

    def next(self) -> tuple[str, bytes]:
        kind, data = self.raw()
        if not data or data[0] not in (0xFD, 0xFE):
            data = bytes([self.rng.choice((0xFD, 0xFE))]) + data
        p = mav_parser()
        mav_parse(p, data)
        while p.buf_len() > 0:  # a partial frame pending: complete it with zeros
            pad = b"\0" * max(1, p.expected_length - p.buf_len())
            data += pad
            mav_parse(p, pad)
        return kind, data


def vehicle_templates(rng: random.Random):
    """What an ArduPilot Rover sends a ground station."""

    def make(enc):
        r = rng.random()
        if r < 0.25:
            base = 1 | (128 if rng.random() < 0.7 else 0)
            return enc.heartbeat_encode(10, 3, base, rng.choice([GUIDED, GUIDED, HOLD, 0]), 4)
        if r < 0.5:
            return enc.local_position_ned_encode(rng.randrange(2**32), *(rng.uniform(-50, 50) for _ in range(6)))
        if r < 0.75:
            return enc.attitude_encode(rng.randrange(2**32), *(rng.uniform(-3.1, 3.1) for _ in range(6)))
        if r < 0.85:
            return enc.statustext_encode(rng.randrange(8), rng.randbytes(rng.randint(1, 50)))
        if r < 0.92:
            return enc.command_ack_encode(rng.choice([MAV_CMD_DO_SET_MODE, MAV_CMD_ARM, MAV_CMD_SET_MESSAGE_INTERVAL]),
                                          rng.randrange(6))
        return enc.param_value_encode(rng.randbytes(16), rng.uniform(-1e3, 1e3), 9, 900, rng.randrange(900))

    return make


def gcs_templates(rng: random.Random):
    """What a ground station (the driver) sends an ArduPilot Rover."""

    def make(enc):
        r = rng.random()
        if r < 0.15:
            return enc.heartbeat_encode(6, 8, 0, 0, 0)
        if r < 0.45:
            cmd, p1, p2 = rng.choice([(MAV_CMD_DO_SET_MODE, 1, GUIDED), (MAV_CMD_DO_SET_MODE, 1, HOLD),
                                      (MAV_CMD_ARM, 1, 0), (MAV_CMD_ARM, 0, 0),
                                      (MAV_CMD_SET_MESSAGE_INTERVAL, rng.choice([30, 32, 33]), rng.choice([5e4, 1e5])),
                                      (rng.randrange(65536), rng.uniform(-10, 10), rng.uniform(-10, 10))])
            return enc.command_long_encode(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, 0)
        if r < 0.9:
            frame = 8 if rng.random() < 0.8 else rng.randrange(22)
            mask = VELOCITY_YAWRATE_MASK if rng.random() < 0.8 else rng.randrange(65536)
            return enc.set_position_target_local_ned_encode(rng.randrange(2**32), 1, 1, frame, mask, 0, 0, 0,
                                                            rng.uniform(-3, 3), 0, 0, 0, 0, 0, 0, rng.uniform(-3, 3))
        return enc.manual_control_encode(1, *(rng.randint(-1000, 1000) for _ in range(4)), 0)

    return make


#: The MAVLink driver's telemetry contract (drivers/mavlink/pose.py): which fields of a vehicle's LOCAL_POSITION_NED /
#: ATTITUDE must be finite and within what magnitude, else the message is malformed.
MAV_TELEMETRY_BOUNDS = {"LOCAL_POSITION_NED": {"x": POSITION_MAX, "y": POSITION_MAX, "vx": SPEED_MAX, "vy": SPEED_MAX},
                        "ATTITUDE": {"yaw": YAW_MAX, "yawspeed": YAW_RATE_MAX}}


class MavOracle:
    """Counts what a receiver's parser must get out of the datagrams sent: messages, BAD_DATA, by type; and, when
    ``vehicle`` (system, component) is given, the telemetry from it that breaks :data:`MAV_TELEMETRY_BOUNDS`
    (``invalid``) and the COMMAND_LONGs addressed to it (``commands_for_vehicle``: each one gets a COMMAND_ACK)."""

    def __init__(self, vehicle: tuple[int, int] | None = None) -> None:
        self.parser = mav_parser()
        self.vehicle = vehicle
        self.total = self.bad = self.invalid = self.commands_for_vehicle = 0
        self.types: Counter[str] = Counter()
        self.nonfinite_setpoints = 0

    def is_invalid(self, m) -> bool:
        t = m.get_type()
        bounds = MAV_TELEMETRY_BOUNDS.get(t)
        if bounds is None or (m.get_srcSystem(), m.get_srcComponent()) != self.vehicle:
            return False
        return not all(math.isfinite(getattr(m, f)) and abs(getattr(m, f)) <= lim for f, lim in bounds.items())

    def feed(self, data: bytes) -> list:
        msgs = mav_parse(self.parser, data)
        for m in msgs:
            t = m.get_type()
            self.total += 1
            self.bad += t == "BAD_DATA"
            self.types[t] += 1
            if self.vehicle is not None:
                self.invalid += self.is_invalid(m)
                sysid, compid = self.vehicle
                self.commands_for_vehicle += t == "COMMAND_LONG" and m.target_system in (0, sysid) and \
                    m.target_component in (0, compid)
            if t == "SET_POSITION_TARGET_LOCAL_NED" and not all(math.isfinite(a) for a in (m.vx, m.vy, m.yaw_rate)):
                self.nonfinite_setpoints += 1
        return msgs
