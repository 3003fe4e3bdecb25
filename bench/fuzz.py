"""``scmbridge bench fuzz``: mutated input at every trust boundary, each receiver's count checked against what was sent.

Inputs (``--inputs``, all by default), ``--per-input N`` payloads each, seeded (``--seed``):

- ``zenoh_cmd``, ``zenoh_estop``: MessagePack payloads on ``scm/<robot>/cmd`` and ``scm/<robot>/estop`` into a real
  driver host process (``scmbridge driver --link can --emulate``) behind a Zenoh router in this process. The oracle
  is the wire contract (:func:`bridge.core.wire.decode`): the host's final status must count every payload that fails it
  in ``malformed_<input>`` and every other command in exactly one gate counter (``accepted`` or a refusal); for
  estops the latch counters (``estops``, ``estop_releases``, ``estop_release_refused``) must be what the documented
  latch rule gives for the valid ones, in order. Every ``applied`` echo is checked as it arrives: it decodes (finite,
  in wire range), it is inside the hard limits, a stop is exactly zero.
- ``udp_driver``, ``udp_robot``: datagrams at the UDP-shim driver (from its pinned robot address and from a
  stranger) and at the emulated robot (from its pinned peer and from a stranger), each on loopback ports bound here.
  Each side counts every datagram once: foreign, malformed (the wire contract), or one of its stream's verdicts.
- ``can_decoder``: frames straight into ``drivers.can.decode``; ``can_driver``: frames on a python-can ``virtual``
  channel at a running CAN driver, impersonating its controllers; ``can_ecu``: frames at the emulated controllers,
  impersonating the driver. The oracle is CANSimple as the shipped DBC lays it out (standard 11-bit id, a known
  command, the DBC's length, finite floats), read with ``struct``. A strict decoder counts every frame that is not
  CANSimple; an ODrive ignores some of them (unknown commands, other nodes, extended ids) without counting: for the
  controllers the count must be exactly the frames every device counts, or exactly those plus all the others.
- ``mavlink_driver``, ``mavlink_rover``: MAVLink bytes (UDP datagrams) at the driver's pymavlink parser (a scripted
  vehicle on a loopback port) and at the emulated rover. The oracle is a second pymavlink parser fed the same
  datagrams: the receiver's ``BAD_DATA`` count must equal the oracle's. Each datagram starts on a frame marker and
  leaves no partial frame behind, so the count does not depend on how the receiver's reads split the stream.

Mutations: random bytes; bit flips, truncations and extensions of valid encodings; valid structure with NaN, inf or
huge values; unknown fields; wrong types; missing fields; huge sequence numbers and epochs; long strings and arrays;
in between, valid messages of a real stream. After each input the vehicle side is checked (the emulated vehicle's
``SimVehicle.command`` calls, or the ``applied`` echoes): no non-finite or out-of-limits command, and a real
command still drives.

``rss_rounds_mb``: the driver host's RSS before and after each of ``--rounds`` rounds of ``--round-size`` Zenoh
``cmd`` payloads (a fresh process). ``rss_probe``: the same rounds against a driver-host-like process of this module
(a :class:`bridge.nodes.driver_host.DriverHost` with its Zenoh session and emulated controllers) that also reports the
Python heap (``tracemalloc``), glibc's heap (``mallinfo2``: in use, and free but kept) and its RSS after
``malloc_trim(0)``: where the growth is, and whether it is returned.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import math
import os
import random
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import tracemalloc
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import msgspec

from bench.common import can_ecus, open_can_driver
from bridge.core import wire as M
from bridge.core.errors import UsageError
from bridge.core.gate import DRIVING
from bridge.nodes.node import add_zenoh_args, rss_mb, rss_parts

#: the driver host's default hard limits (``bridge.nodes.driver_config.DEFAULT_HARD_LIMITS``); the host runs with no
#: config file
HARD_V, HARD_W = (-0.5, 0.5), (-1.0, 1.0)
#: every input, in the order they run
INPUTS = ("zenoh_cmd", "zenoh_estop", "udp_driver", "udp_robot", "can_decoder", "can_driver", "can_ecu",
          "mavlink_driver", "mavlink_rover")
LOCAL = "127.0.0.1"
GATE_VERDICTS = ("accepted", "out_of_order", "old_epoch", "foreign_epoch", "seq_jump", "stamp_jump")


# ============================================================================================= small helpers
def zenoh_segments(pid: int) -> int:
    """Zenoh shared-memory segments (``/dev/shm/*.zenoh``) mapped by ``pid``."""
    with contextlib.suppress(OSError), open(f"/proc/{pid}/maps") as f:
        return len({line.split()[-1] for line in f if line.rstrip().endswith(".zenoh")})
    return 0


def wait_until(pred: Callable[[], bool], timeout: float, step: float = 0.002) -> bool:
    t_end = time.monotonic() + timeout
    while True:
        if pred():
            return True
        if time.monotonic() >= t_end:
            return False
        time.sleep(step)


def udp_socket(port: int = 0) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((LOCAL, port))
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    return s


def drain(sock: socket.socket) -> list[tuple[bytes, tuple]]:
    """Every datagram waiting on ``sock``, without blocking."""
    out = []
    sock.setblocking(False)
    while True:
        try:
            out.append(sock.recvfrom(65536))
        except (BlockingIOError, InterruptedError):
            return out


class Crashes:
    """Uncaught exceptions in this process's threads (``threading.excepthook``) and those the harness caught around
    a receiver's own calls; ``with Crashes() as c:`` ... ``c.count``."""

    def __init__(self) -> None:
        self.events: list[str] = []
        self._old = None

    def __enter__(self) -> Crashes:
        self._old = threading.excepthook

        def hook(args) -> None:  # recorded with where it was raised, not printed (the JSON carries it)
            name = args.thread.name if args.thread is not None else "?"
            tb = traceback.extract_tb(args.exc_traceback)
            where = f" ({Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
            self.events.append(f"thread {name}: {args.exc_type.__name__}: {args.exc_value}{where}")

        threading.excepthook = hook
        return self

    def __exit__(self, *exc: object) -> None:
        threading.excepthook = self._old

    def caught(self, where: str, exc: BaseException) -> None:
        self.events.append(f"{where}: {type(exc).__name__}: {exc}")

    @property
    def count(self) -> int:
        return len(self.events)


class VehicleSpy:
    """Wraps a ``SimVehicle.command``: every call is checked (finite, inside ``|v| <= v_max``, ``|omega| <= w_max``)
    before the vehicle gets it."""

    def __init__(self, vehicle, v_max: float = math.inf, w_max: float = math.inf) -> None:
        self.vehicle = vehicle
        self.v_max, self.w_max = v_max, w_max
        self.calls = self.nonfinite = self.over_limits = 0
        self.max_abs = [0.0, 0.0]
        self.last: tuple[float, float] | None = None
        real = vehicle.command

        def command(v: float, omega: float, now: float) -> None:
            self.calls += 1
            self.last = (v, omega)
            if not (math.isfinite(v) and math.isfinite(omega)):
                self.nonfinite += 1
            else:
                self.max_abs = [max(self.max_abs[0], abs(v)), max(self.max_abs[1], abs(omega))]
                if abs(v) > self.v_max or abs(omega) > self.w_max:
                    self.over_limits += 1
            return real(v, omega, now)

        vehicle.command = command

    def report(self) -> dict:
        return {"commands": self.calls, "nonfinite": self.nonfinite, "over_limits": self.over_limits,
                "max_abs_v": round(self.max_abs[0], 4), "max_abs_omega": round(self.max_abs[1], 4)}

    @property
    def ok(self) -> bool:
        return self.nonfinite == 0 and self.over_limits == 0

    def speed(self) -> float:
        return float(self.vehicle.advance(time.monotonic()).v)


def new_vehicle(x0: tuple[float, float, float] = (0.0, 0.0, 0.0)):
    from sim_learner.dynamics import mpc_learner
    from sim_learner.vehicle import SimVehicle

    return SimVehicle(mpc_learner(), x0, now=time.monotonic())


def _result(sent: int, counted: int, expected: int, exact: bool, crashes: Crashes, t0: float,
            rss: tuple[float | None, float | None], process: str, **extra: Any) -> dict:
    return {"sent": sent, "counted": counted, "expected": expected, "exact": bool(exact), "crashes": crashes.count,
            "crash_events": crashes.events[:10], "seconds": round(time.monotonic() - t0, 2),
            "rss_mb": {"process": process, "before": rss[0], "after": rss[1]}, **extra}


# ================================================================================ MessagePack mutations
NONFINITE = (math.nan, math.inf, -math.inf)
OUT_OF_RANGE_F = (1e13, -1e13, 1e300, -1e300, 3.4e38)  # beyond every float bound of the wire contract
WRONG_TYPES: tuple[Any, ...] = ("x", None, [1.0], {"a": 1}, True, b"\x00\x01", -1, 2**64 - 1, 1.5, "")
HUGE_INTS = (2**63 - 1, 2**63, 2**64 - 1, -1, -(2**63), 2**62 + 12345)
BAD_UTF8 = b"\xa3\xff\xfe\xfd"  # msgpack fixstr of 3 bytes that are not UTF-8
#: mutation kinds a wire decoder must refuse whatever the message (unknown fields, truncations, out-of-range...)
MUST_REJECT = ("truncate", "nonfinite", "out_of_range", "unknown_field", "missing_field", "long_string",
               "big_array", "bad_utf8")


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


class Tally:
    """Per mutation kind: sent, and how many the oracle refused."""

    def __init__(self) -> None:
        self.sent: Counter[str] = Counter()
        self.refused: Counter[str] = Counter()

    def add(self, kind: str, refused: bool) -> None:
        self.sent[kind] += 1
        self.refused[kind] += refused

    def contract_violations(self) -> int:
        """Payloads of a kind the contract must refuse that the oracle accepted (a hole in the wire contract)."""
        return sum(self.sent[k] - self.refused[k] for k in MUST_REJECT if k in self.sent)

    def report(self) -> dict:
        return {k: [self.sent[k], self.refused[k]] for k in sorted(self.sent)}


# ================================================================================ Zenoh into a driver host
class HostRig:
    """The driver host as its own process (``--link can --emulate``: the emulated controllers inside it), a client
    of a Zenoh router in this process on a free 127.0.0.1 port. Every ``applied`` echo is checked as it arrives;
    the latest ``state`` and ``status`` are kept. ``with HostRig(workdir, robot) as rig:``; the process is always
    stopped and the session closed."""

    def __init__(self, workdir: Path, robot: str, probe: bool = False, shm: bool = True) -> None:
        self.workdir, self.robot, self.probe, self.shm = Path(workdir), robot, probe, shm
        self.keys = M.Keys(robot)
        self.lock = threading.Lock()
        self.status: M.Status | None = None
        self.states: list[tuple[float, float, float]] = []  # (stamp, x, y), the last 2000
        self.applied = Counter()  # n, bad (did not decode), over_limits, nonzero_stop, by reason
        self.last_driving: tuple[float, float, float] | None = None  # (stamp, v, omega) of the last cmd/clamped echo
        self.proc: subprocess.Popen | None = None
        self.stack = ExitStack()

    # ------------------------------------------------------------------------------------------ life cycle
    def __enter__(self) -> HostRig:
        from bridge.nodes.zsession import free_port, make_config, open_session, tcp
        from bridge.tools.procs import Children

        try:
            port = free_port()
            self.endpoint = tcp(port)
            conf = make_config(mode="router", listen=[tcp(port)])
            conf.insert_json5("transport/shared_memory/enabled", json.dumps(self.shm))  # every hop as the host
            self.session = self.stack.enter_context(open_session(conf))
            kids = self.stack.enter_context(Children())
            k = self.keys
            self.session.declare_subscriber(k.applied, self._on_applied)
            self.session.declare_subscriber(k.state, self._on_state)
            self.session.declare_subscriber(M.status_key(self.robot, "driver"), self._on_status)
            self.log_path = self.workdir / f"driver-{self.robot}.log"
            log = self.stack.enter_context(open(self.log_path, "w"))
            client = ["--mode", "client", "--connect", self.endpoint]
            # the host's session with Zenoh's shared-memory transport on (zenoh's default, which scmbridge's
            # configs turn off) or off, through a lab-style file (a file that sets it is obeyed)
            conf = self.workdir / f"zenoh-{self.robot}.json5"
            conf.write_text(json.dumps({"mode": "client", "scouting": {"multicast": {"enabled": False}},
                                        "transport": {"shared_memory": {"enabled": self.shm}}}))
            client += ["--zenoh-config", str(conf)]
            if self.probe:  # a driver-host-like process of this module that also reports its heap
                self.proc = kids.spawn(["bench", "fuzz", "--probe-host", self.robot, *client], subprocess.PIPE,
                                       stdin=subprocess.PIPE, text=True, bufsize=1)
            else:
                self.proc = kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--robot", self.robot,
                                        *client, "--duration", "86400"],
                                       log)
            if not wait_until(lambda: self.status is not None and self.status.ok, 90.0, 0.05):
                raise RuntimeError(f"the driver host did not come up (log: {self.log_path})")
        except BaseException:
            self.stack.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        if self.probe and self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(OSError, ValueError):
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(timeout=10)
        self.stack.close()

    # ----------------------------------------------------------------------------------------- listeners
    def _on_applied(self, sample) -> None:
        try:
            a = M.decode(sample.payload.to_bytes(), M.Applied)
        except M.MessageError:
            with self.lock:
                self.applied["bad"] += 1  # not finite, or outside the wire's ranges
            return
        with self.lock:
            c = self.applied
            c["n"] += 1
            c[f"reason_{a.reason}"] += 1
            if not (HARD_V[0] <= a.v <= HARD_V[1] and HARD_W[0] <= a.omega <= HARD_W[1]):
                c["over_limits"] += 1
            if a.reason not in DRIVING and (a.v != 0.0 or a.omega != 0.0):
                c["nonzero_stop"] += 1
            if a.reason in DRIVING:
                self.last_driving = (a.stamp, a.v, a.omega)

    def _on_state(self, sample) -> None:
        st = M.decode(sample.payload.to_bytes(), M.LearnerState)
        with self.lock:
            self.states.append((st.stamp, st.x, st.y))
            del self.states[:-2000]

    def _on_status(self, sample) -> None:
        st = M.decode(sample.payload.to_bytes(), M.Status)
        with self.lock:
            self.status = st

    # ------------------------------------------------------------------------------------------- queries
    def counters(self) -> dict[str, int]:
        with self.lock:
            return dict(self.status.counters) if self.status else {}

    def status_after(self, t: float, timeout: float = 5.0) -> dict[str, int]:
        """The counters of the first status stamped after ``t`` (the host's clock is this machine's monotonic)."""
        wait_until(lambda: self.status is not None and self.status.stamp > t, timeout, 0.02)
        return self.counters()

    def rss(self) -> float | None:
        return rss_mb(self.proc.pid) if self.proc else None

    def applied_report(self) -> dict:
        with self.lock:
            return dict(self.applied)

    def vehicle_ok(self) -> bool:
        with self.lock:
            c = self.applied
            return c["bad"] == 0 and c["over_limits"] == 0 and c["nonzero_stop"] == 0

    def crashes(self) -> list[str]:
        """The host process gone, or a traceback / panic in its log."""
        out = []
        if self.proc is not None and self.proc.poll() is not None:
            out.append(f"driver host exited with {self.proc.returncode}")
        if not self.probe:
            with contextlib.suppress(OSError), open(self.log_path, errors="replace") as f:
                for line in f:
                    if "Traceback" in line or "panicked" in line:
                        out.append(line.strip()[:200])
        return out

    def publisher(self, key: str):
        import zenoh

        # BLOCK: a full queue holds the publisher instead of dropping the sample (every payload must arrive)
        return self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)

    # -------------------------------------------------------------------------------------------- driving
    def drives(self, v: float = 0.25, seconds: float = 1.2) -> dict:
        """After a silence longer than the deadman (any fuzzed stream goes quiet), a new station run's commands:
        the echo must say they were applied as sent, and the vehicle's state must move."""
        time.sleep(0.45)
        pub = self.publisher(self.keys.cmd)
        epoch = M.new_epoch()
        t0 = time.monotonic()
        seq = 0
        while time.monotonic() - t0 < seconds:
            seq += 1
            pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=v, omega=0.0, method="scm",
                                       sender="bench", epoch=epoch)))
            time.sleep(0.02)
        time.sleep(0.1)
        with self.lock:
            applied = self.last_driving is not None and self.last_driving[0] > t0 and self.last_driving[1:] == (v, 0.0)
            xy = [(x, y) for t, x, y in self.states if t > t0 + 0.3]
        moved = math.hypot(xy[-1][0] - xy[0][0], xy[-1][1] - xy[0][1]) if len(xy) > 1 else 0.0
        pub.undeclare()
        return {"applied_as_sent": bool(applied), "moved_m": round(moved, 3), "ok": bool(applied and moved > 0.02)}


def _settle(rig: HostRig, total: Callable[[dict], int], target: int, timeout: float) -> dict:
    """Wait until the host's status shows ``total(counters) >= target`` (or the timeout), then one more status."""
    wait_until(lambda: total(rig.counters()) >= target, timeout, 0.05)
    return rig.status_after(time.monotonic(), 3.0)


def _delta(after: dict, before: dict, keys) -> int:
    return sum(after.get(k, 0) - before.get(k, 0) for k in keys)


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


def fuzz_cmd_payloads(rig: HostRig, n: int, rng: random.Random) -> dict:
    """``n`` payloads on ``cmd``; every one must be counted once: malformed, or one gate verdict."""
    before = rig.counters()
    tally = Tally()
    mut = MsgMutator(rng, COMMAND, CommandStream(rng))
    pub = rig.publisher(rig.keys.cmd)
    bad = 0
    for _ in range(n):
        kind, data = mut.next()
        refused = not wire_ok(data, M.Command)
        tally.add(kind, refused)
        bad += refused
        pub.put(data)
    pub.undeclare()
    keys = ("malformed_cmd", *GATE_VERDICTS)
    after = _settle(rig, lambda c: _delta(c, before, keys), n, 30.0 + n / 2000)
    malformed = _delta(after, before, ("malformed_cmd",))
    verdicts = {k: _delta(after, before, (k,)) for k in GATE_VERDICTS}
    return {"sent": n, "counted": malformed, "expected": bad,
            "exact": malformed == bad and sum(verdicts.values()) == n - bad,
            "decoded": n - bad, "gate_verdicts": verdicts, "contract_violations": tally.contract_violations(),
            "kinds_sent_refused": tally.report()}


def _estop_dict(rng: random.Random) -> dict:
    msg = {"stamp": time.monotonic(), "seq": rng.randrange(1000), "engaged": rng.random() < 0.5,
           "source": rng.choice(["operator", "operator", "fuzzer", "", "station", "Operator", "operator "]),
           "reason": rng.choice(["", "test", "x" * 100])}
    return msg


class LatchModel:
    """The documented estop rule (docs/ARCHITECTURE.md section 6), counted as the driver host counts it: anyone
    engages; only a configured source releases; ``estops`` counts engagements of an unlatched host,
    ``estop_releases`` and ``estop_release_refused`` the releases of a latched one."""

    def __init__(self, release_sources: tuple[str, ...] = ("operator",)) -> None:
        self.sources = release_sources
        self.latched = False
        self.counts = Counter()

    def offer(self, e: M.Estop) -> None:
        if e.engaged:
            self.counts["estops"] += not self.latched
            self.latched = True
        elif self.latched:
            if e.source in self.sources:
                self.counts["estop_releases"] += 1
                self.latched = False
            else:
                self.counts["estop_release_refused"] += 1


def _cmd_on(rig: HostRig, n: int, rng: random.Random) -> dict:
    t0 = time.monotonic()
    crashes = Crashes()
    rss0 = rig.rss()
    res = fuzz_cmd_payloads(rig, n, rng)
    rss1 = rig.rss()
    drive = rig.drives()
    crashes.events += rig.crashes()
    return _result(res.pop("sent"), res.pop("counted"), res.pop("expected"), res.pop("exact"), crashes, t0,
                   (rss0, rss1), "driver host", **res,
                   vehicle={"applied_echoes": rig.applied_report(), "ok": rig.vehicle_ok()}, drives_after=drive)


def _estop_on(rig: HostRig, n: int, rng: random.Random) -> dict:
    """``n`` payloads on ``estop`` (and a station's commands between them): malformed ones counted, the valid ones'
    latch counters as the rule gives them; the operator releases the estop at the end and driving resumes."""
    t0 = time.monotonic()
    crashes = Crashes()
    rss0 = rig.rss()
    before = rig.counters()
    tally = Tally()
    mut = MsgMutator(rng, ESTOP, lambda: _estop_dict(rng))
    model = LatchModel()
    epub, cpub = rig.publisher(rig.keys.estop), rig.publisher(rig.keys.cmd)
    stream = CommandStream(rng)
    bad = 0
    for _ in range(n):
        kind, data = mut.next()
        try:
            model.offer(M.decode(data, M.Estop))
            refused = False
        except M.MessageError:
            refused = True
        tally.add(kind, refused)
        bad += refused
        epub.put(data)
        if rng.random() < 0.05:
            cpub.put(msgspec.msgpack.encode(stream()))
    latch_keys = ("estops", "estop_releases", "estop_release_refused")
    want = sum(model.counts.values())
    after = _settle(rig, lambda c: _delta(c, before, ("malformed_estop", *latch_keys)), bad + want,
                    30.0 + n / 2000)
    malformed = _delta(after, before, ("malformed_estop",))
    latch = {k: _delta(after, before, (k,)) for k in latch_keys}
    rss1 = rig.rss()
    # the operator releases (a configured source), and a new station run drives
    epub.put(M.encode(M.Estop(stamp=time.monotonic(), engaged=False, source="operator", reason="bench")))
    epub.undeclare()
    cpub.undeclare()
    drive = rig.drives()
    crashes.events += rig.crashes()
    rule = {k: model.counts[k] for k in latch_keys}
    return _result(n, malformed, bad, malformed == bad and latch == rule, crashes, t0, (rss0, rss1), "driver host",
                   decoded=n - bad, latch_counters={"host": latch, "rule": rule},
                   contract_violations=tally.contract_violations(), kinds_sent_refused=tally.report(),
                   vehicle={"applied_echoes": rig.applied_report(), "ok": rig.vehicle_ok()}, drives_after=drive)


def fuzz_zenoh(n: int, seed: int, workdir: Path, inputs=("zenoh_cmd", "zenoh_estop")) -> dict:
    """The Zenoh inputs, one after the other into one driver host process (the applied echoes are checked over
    the whole run, so each input's ``vehicle`` covers the ones before it too)."""
    out = {}
    with HostRig(workdir, f"fuzz{os.getpid()}") as rig:
        if "zenoh_cmd" in inputs:
            out["zenoh_cmd"] = _cmd_on(rig, n, random.Random(seed))
        if "zenoh_estop" in inputs:
            out["zenoh_estop"] = _estop_on(rig, n, random.Random(seed + 1))
    return out


# ======================================================================================== RSS under the fuzz
class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]


def _libc():
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = _MallInfo2
        return libc
    except (OSError, AttributeError):  # not glibc, or a glibc older than 2.33
        return None


def heap_report(first: tracemalloc.Snapshot | None = None) -> dict:
    """This process's RSS, its Python heap as tracemalloc sees it, glibc's heap (all arenas) and, against the
    ``first`` snapshot, the five Python allocation sites that grew most."""
    mb = 1024 * 1024
    cur, peak = tracemalloc.get_traced_memory()
    out: dict[str, Any] = {"rss_mb": rss_mb(), "python_traced_mb": round(cur / mb, 2),
                           "python_traced_peak_mb": round(peak / mb, 2),
                           "tracemalloc_overhead_mb": round(tracemalloc.get_tracemalloc_memory() / mb, 2),
                           "threads": threading.active_count()}
    with contextlib.suppress(OSError), open("/proc/self/status") as f:
        out["os_threads"] = next((int(line.split()[1]) for line in f if line.startswith("Threads:")), None)
    libc = _libc()
    if libc is not None:
        mi = libc.mallinfo2()
        out.update({"malloc_in_use_mb": round((mi.uordblks + mi.hblkhd) / mb, 2),
                    "malloc_free_kept_mb": round(mi.fordblks / mb, 2),
                    "malloc_heap_mb": round(mi.arena / mb, 2), "malloc_mmapped_mb": round(mi.hblkhd / mb, 2)})
    if first is not None:
        diff = tracemalloc.take_snapshot().compare_to(first, "lineno")[:5]
        out["python_top_growth"] = [{"where": str(d.traceback[0]), "kb": round(d.size_diff / 1024, 1),
                                     "count": d.count_diff} for d in diff]
    return out


def probe_host(args: argparse.Namespace) -> int:
    """A driver-host-like process for the RSS study: the real
    :class:`bridge.nodes.driver_host.DriverHost` with its Zenoh
    session and the emulated CAN controllers in-process (as ``scmbridge driver --link can --emulate``), under
    tracemalloc. Lines on stdin: ``measure`` prints ``PROBE {json}`` (:func:`heap_report`), ``trim`` calls glibc's
    ``malloc_trim(0)`` first, ``quit`` stops it."""
    import logging

    from bridge.nodes.driver_config import load_driver
    from bridge.nodes.driver_host import DriverHost
    from bridge.nodes.node import stop_on_signals, zenoh_config
    from bridge.nodes.zsession import open_session
    from drivers import open_driver
    from sim_learner.can_ecu import DiffDriveEcus

    args.robot = args.probe_host
    logging.basicConfig(level=logging.ERROR)
    tracemalloc.start(1)
    cfg = load_driver(None)
    link = msgspec.structs.replace(cfg.link.can, interface="virtual", channel=f"scm-{args.robot}")
    host = DriverHost(cfg, "can", open_driver("can", link), args.robot, cfg.driver.rate_hz)
    host.engage_on_start = True  # as `scmbridge driver --engage`
    ecus = DiffDriveEcus({"interface": "virtual", "channel": link.channel}, new_vehicle(),
                         left_node=link.left_node, right_node=link.right_node, left_sign=link.left_sign,
                         right_sign=link.right_sign, wheel_radius=link.wheel_radius,
                         track_width=link.track_width).start()
    stop = stop_on_signals()
    first: list[tracemalloc.Snapshot] = []

    def control() -> None:
        for line in sys.stdin:
            word = line.strip()
            if word == "quit":
                break
            if word == "trim" and _libc() is not None:
                _libc().malloc_trim(0)
            if not first:
                first.append(tracemalloc.take_snapshot())
            print("PROBE " + json.dumps(heap_report(first[0])), flush=True)
        stop.set()

    threading.Thread(target=control, name="probe-control", daemon=True).start()
    try:
        with open_session(zenoh_config(args)) as session:
            host.serve(session, stop, None)
    finally:
        host.driver.close()
        ecus.stop()
    return 0


def _probe(rig: HostRig, word: str = "measure") -> dict:
    rig.proc.stdin.write(word + "\n")
    rig.proc.stdin.flush()
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end:
        line = rig.proc.stdout.readline()
        if not line:
            break
        if line.startswith("PROBE "):
            return json.loads(line[6:])
    raise RuntimeError("the probe host did not answer")


def rss_rounds(rounds: int, size: int, seed: int, workdir: Path, probe: bool = False, shm: bool = True) -> dict:
    """The ``cmd`` fuzz in ``rounds`` rounds of ``size`` into one fresh host; RSS (and its parts) before and after
    each round; with ``probe``, the host's heap too, and what ``malloc_trim(0)`` returns at the end."""
    rng = random.Random(seed)
    robot = f"fuzzrss{'p' if probe else ''}{'' if shm else 'n'}{os.getpid()}"
    with HostRig(workdir, robot, probe=probe, shm=shm) as rig:
        time.sleep(1.0)
        out: dict[str, Any] = {"rss_mb": [rig.rss()], "parts_mb": [rss_parts(rig.proc.pid)], "exact": []}
        if probe:
            out["heap"] = [_probe(rig)]
        for _ in range(rounds):
            res = fuzz_cmd_payloads(rig, size, rng)
            time.sleep(1.0)
            out["rss_mb"].append(rig.rss())
            out["parts_mb"].append(rss_parts(rig.proc.pid))
            out["exact"].append(res["exact"])
            if probe:
                out["heap"].append(_probe(rig))
        if probe:
            out["after_malloc_trim"] = _probe(rig, "trim")
        out["crashes"] = rig.crashes()
    r = out["rss_mb"]
    steps = [round(b - a, 1) for a, b in zip(r, r[1:])]
    out["growth_per_round_mb"] = steps
    growth = r[-1] - r[0]
    out["trend"] = "plateau" if len(steps) >= 3 and max(steps[-2:]) <= max(1.0, 0.1 * growth) else "growing"
    return out


def rss_senders(senders: int, per_sender: int, seed: int, workdir: Path, shm: bool = True) -> dict:
    """``senders`` Zenoh sessions one after the other (a station restarted, a tool run on the same machine), each
    putting ``per_sender`` payloads of 4-64 KiB on ``cmd`` (above Zenoh's 3072-byte shared-memory threshold) and
    closing: the host's RSS, its parts and the Zenoh segments it maps after each, and 10 s after the last.
    ``shm``: every session with Zenoh's shared-memory transport on (zenoh's default) or off (scmbridge's)."""
    import zenoh

    from bridge.nodes.zsession import make_config, open_session

    rng = random.Random(seed)
    with HostRig(workdir, f"fuzzsnd{'' if shm else 'n'}{os.getpid()}", shm=shm) as rig:
        pid = rig.proc.pid
        time.sleep(1.0)
        rows = [{"after_sender": 0, **rss_parts(pid), "zenoh_segments": zenoh_segments(pid)}]
        before = rig.counters().get("malformed_cmd", 0)
        for k in range(senders):
            conf = make_config(mode="client", connect=[rig.endpoint])
            conf.insert_json5("transport/shared_memory/enabled", json.dumps(shm))  # as the host's
            with open_session(conf) as s:
                pub = s.declare_publisher(rig.keys.cmd, congestion_control=zenoh.CongestionControl.BLOCK)
                time.sleep(0.3)
                for _ in range(per_sender):
                    pub.put(rng.randbytes(rng.randint(4096, 65536)))
                wait_until(lambda n=(k + 1) * per_sender: rig.counters().get("malformed_cmd", 0) - before >= n,
                           30.0, 0.05)
            time.sleep(1.0)
            rows.append({"after_sender": k + 1, **rss_parts(pid), "zenoh_segments": zenoh_segments(pid)})
        time.sleep(10.0)
        rows.append({"after_sender": senders, "waited_s": 10, **rss_parts(pid), "zenoh_segments": zenoh_segments(pid)})
        counted = rig.status_after(time.monotonic()).get("malformed_cmd", 0) - before
    per = sorted(b["rss"] - a["rss"] for a, b in zip(rows[1:], rows[2:-1]))
    return {"shared_memory": shm, "rows": rows, "counted_exactly": counted == senders * per_sender,
            "rss_per_further_sender_mb": round(per[len(per) // 2], 1) if per else None}  # the median


def rss_verdict(rounds: dict, probe: dict | None, senders_on: dict | None, senders_off: dict | None) -> dict:
    """The numbers that say where the growth is and whether it is bounded."""
    p0, p1 = rounds["parts_mb"][0], rounds["parts_mb"][-1]
    out: dict[str, Any] = {
        "one_sender": {"trend": rounds["trend"], "rss_mb": [rounds["rss_mb"][0], rounds["rss_mb"][-1]],
                       "growth_mb": {k: round(p1.get(k, 0) - p0.get(k, 0), 1) for k in ("rss", "anon", "file",
                                                                                            "shmem")}}}
    if probe is not None:
        h0, h1, ht = probe["heap"][0], probe["heap"][-1], probe["after_malloc_trim"]
        out["heap"] = {k: [h0.get(k), h1.get(k)] for k in ("python_traced_mb", "malloc_in_use_mb",
                                                           "malloc_free_kept_mb", "os_threads")}
        out["heap"]["rss_returned_by_malloc_trim_mb"] = round(h1["rss_mb"] - ht["rss_mb"], 1)
    for name, res in (("senders_shm_on", senders_on), ("senders_shm_off", senders_off)):
        if res is not None:
            out[name] = {"rss_per_further_sender_mb": res["rss_per_further_sender_mb"],
                         "zenoh_segments": [r["zenoh_segments"] for r in res["rows"]],
                         "shmem_mb": [r.get("shmem") for r in res["rows"]]}
    return out


# ================================================================================================== UDP shim
class StateStream(Stream):
    """A robot's valid states (its epoch, its seq)."""

    def __call__(self) -> dict:
        rng = self.rng
        return {"stamp": time.monotonic(), "seq": self.seq + 1, "x": rng.uniform(-50, 50), "y": rng.uniform(-50, 50),
                "theta": rng.uniform(-7, 7), "v": rng.uniform(-1, 1), "omega": rng.uniform(-2, 2),
                "source": "udp-robot", "epoch": self.epoch}


def _udp_burst(mut: MsgMutator, rng: random.Random, tally: Tally, kind: type, peer: socket.socket,
               stranger: socket.socket, to: tuple, size: int) -> tuple[int, int]:
    """Send ``size`` mutated payloads to ``to``: 15 % from ``stranger`` (foreign, never judged), the rest from the
    pinned ``peer``, each judged by the wire contract for ``kind`` and tallied. Returns (foreign, refused)."""
    foreign = refused_n = 0
    for _ in range(size):
        mk, data = mut.next()
        if rng.random() < 0.15:
            stranger.sendto(data, to)
            foreign += 1
        else:
            peer.sendto(data, to)
            refused = not wire_ok(data, kind)
            tally.add(mk, refused)
            refused_n += refused
    return foreign, refused_n


@contextlib.contextmanager
def _answering(sock: socket.socket, reply: Callable[[bytes], bytes]) -> Iterator[dict]:
    """While inside: every datagram arriving on ``sock`` is answered with ``reply(datagram)``; ``peer["addr"]`` is
    the last sender's address."""
    peer: dict = {}
    stop = threading.Event()
    sock.settimeout(0.05)

    def run() -> None:
        while not stop.is_set():
            try:
                data, addr = sock.recvfrom(65536)
            except (TimeoutError, OSError):
                continue
            peer["addr"] = addr
            with contextlib.suppress(OSError):
                sock.sendto(reply(data), addr)

    t = threading.Thread(target=run, name="fuzz-answer", daemon=True)
    t.start()
    try:
        yield peer
    finally:
        stop.set()
        t.join(timeout=2.0)


def udp_driver(n: int, seed: int, workdir: Path | None = None) -> dict:
    """Datagrams at the UDP driver: from its pinned robot address (a socket bound here) and from a stranger. Every
    datagram is counted once: foreign, malformed, a pose, or one of the stream's refusals. Afterwards an emulated
    robot takes the pinned address and the driver drives it."""
    from drivers import open_driver
    from drivers.udp import UdpLinkConfig
    from sim_learner.udp_robot import UdpRobot

    rng = random.Random(seed)
    t0, rss0, crashes = time.monotonic(), rss_mb(), Crashes()
    with crashes, ExitStack() as stack:
        fake, stranger = udp_socket(), udp_socket()
        stack.callback(fake.close)
        stack.callback(stranger.close)
        robot_port = fake.getsockname()[1]
        driver = open_driver("udp", UdpLinkConfig(robot_port=robot_port, bind_port=0, state_timeout_s=0.3,
                                                  open_timeout=5.0))
        stack.callback(driver.close)
        stream = StateStream(rng)

        def hello() -> bytes:
            msg = stream()
            stream.commit()
            return msgspec.msgpack.encode(msg)

        with _answering(fake, lambda _data: hello()) as peer:
            driver.open(time.monotonic())
        addr = peer["addr"]
        rss0 = rss_mb()
        h0 = driver.health(time.monotonic())
        base = (h0.frames_received, h0.malformed, h0.detail)
        mut = MsgMutator(rng, STATE, stream, max_blob=1400)
        tally = Tally()
        sent = foreign = bad = 0
        poses = []
        refusals = ("state_out_of_order", "state_seq_jump", "state_old_epoch", "state_foreign_epoch")
        while sent < n:  # bursts the driver's socket buffer holds (it has the kernel's default size)
            size = min(64, n - sent)
            f, b = _udp_burst(mut, rng, tally, M.LearnerState, fake, stranger, addr, size)
            sent, foreign, bad = sent + size, foreign + f, bad + b
            t_end = time.monotonic() + 5.0
            while time.monotonic() < t_end:
                try:
                    poses += driver.poll(time.monotonic())
                except Exception as exc:  # a crash of the receiver, counted
                    crashes.caught("poll", exc)
                    break
                if driver.health(time.monotonic()).frames_received - base[0] >= sent:
                    break
                time.sleep(0.001)
            driver.send(0.2, 0.1, time.monotonic())
        h = driver.health(time.monotonic())
        d = h.detail
        got = {"frames": h.frames_received - base[0], "malformed": h.malformed - base[1],
               "foreign": d.foreign - base[2].foreign, "poses": len(poses),
               "refused": sum(getattr(d, k) - getattr(base[2], k) for k in refusals)}
        want = {"frames": sent, "malformed": bad, "foreign": foreign, "poses+refused": sent - foreign - bad}
        exact = (got["frames"] == sent and got["malformed"] == bad and got["foreign"] == foreign
                 and got["poses"] + got["refused"] == want["poses+refused"])
        nonfinite = sum(not all(math.isfinite(a) for a in (p.x, p.y, p.theta, p.v or 0.0, p.omega or 0.0))
                        for p in poses)
        # what the driver sent its robot meanwhile: only what it was told (or stops), finite
        cmds = [M.decode(b, M.Command) for b, src in drain(fake) if src[:2] == addr[:2]]
        wrong = sum((c.v, c.omega) not in ((0.2, 0.1), (0.0, 0.0)) for c in cmds)
        rss1 = rss_mb()
        # a real robot on the pinned address (the fuzzed stream has gone silent): it must be driven
        fake.close()
        vehicle = new_vehicle()
        spy = VehicleSpy(vehicle, 1.0, 2.0)
        robot = UdpRobot(vehicle, port=robot_port, peer=addr[:2], watchdog=0.3).start()
        stack.callback(robot.stop)
        drive = _drive(driver, spy, 0.25, crashes)
    return _result(sent, got["malformed"], bad, exact, crashes, t0, (rss0, rss1), "bench (driver in-process)",
                   got=got, want=want, contract_violations=tally.contract_violations(),
                   kinds_sent_refused=tally.report(), nonfinite_poses=nonfinite,
                   vehicle={"commands_to_robot": len(cmds), "not_as_told": wrong, "ok": wrong == 0},
                   drives_after=drive)


def _drive(driver, spy: VehicleSpy, v: float, crashes: Crashes, seconds: float = 1.2) -> dict:
    """Drive ``v`` for ``seconds`` through ``driver`` (polling it as the host does): the vehicle must get it."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        now = time.monotonic()
        try:
            driver.poll(now)
            driver.send(v, 0.0, now)
        except Exception as exc:
            crashes.caught("drive", exc)
            break
        time.sleep(0.02)
    last = spy.last
    speed = spy.speed()
    got = last is not None and abs(last[0] - v) < 1e-5 and abs(last[1]) < 1e-5
    return {"vehicle_got": [round(a, 6) for a in last] if last else None, "speed": round(speed, 3),
            "health_ok": bool(driver.health(time.monotonic()).ok), "ok": bool(got and speed > 0.0)}


def udp_robot(n: int, seed: int, workdir: Path | None = None) -> dict:
    """Datagrams at the emulated UDP robot: from its pinned peer (a socket bound here) and from a stranger. Every
    datagram is counted once (``received`` = foreign + malformed + a stream refusal + over its limits + applied);
    the vehicle never gets a non-finite command or one beyond the robot's own limits. Afterwards a real driver takes
    the peer's address and drives it."""
    from drivers import open_driver
    from drivers.udp import UdpLinkConfig
    from sim_learner.udp_robot import UdpRobot

    rng = random.Random(seed)
    t0, rss0, crashes = time.monotonic(), rss_mb(), Crashes()
    with crashes, ExitStack() as stack:
        peer, stranger = udp_socket(), udp_socket()
        stack.callback(peer.close)
        stack.callback(stranger.close)
        vehicle = new_vehicle()
        spy = VehicleSpy(vehicle, 1.0, 2.0)
        robot = UdpRobot(vehicle, peer=peer.getsockname(), watchdog=0.3, v_max=1.0, omega_max=2.0).start()
        stack.callback(robot.stop)
        to = (LOCAL, robot.port)
        rss0 = rss_mb()
        c0 = dict(robot.counters)
        mut = MsgMutator(rng, COMMAND, CommandStream(rng, "driver", (3.0, 5.0)), max_blob=1400)
        tally = Tally()
        sent = foreign = bad = 0
        while sent < n:  # a burst the robot's socket holds even if its thread does not run meanwhile (a loaded
            size = min(48, n - sent)  # machine): 128 of up to 1.4 KB overflowed the kernel's buffer
            f, b = _udp_burst(mut, rng, tally, M.Command, peer, stranger, to, size)
            sent, foreign, bad = sent + size, foreign + f, bad + b
            if not wait_until(lambda s=sent: robot.counters["received"] - c0["received"] >= s, 5.0, 0.001):
                break
        c = {k: v - c0[k] for k, v in robot.counters.items()}
        verdicts = ("applied", "out_of_order", "seq_jump", "old_epoch", "foreign_epoch", "over_limits")
        exact = (c["received"] == sent and c["foreign"] == foreign and c["malformed"] == bad
                 and sum(c[k] for k in verdicts) == sent - foreign - bad)
        rss1 = rss_mb()
        peer_port = peer.getsockname()[1]
        peer.close()
        driver = open_driver("udp", UdpLinkConfig(robot_port=robot.port, bind_port=peer_port, open_timeout=5.0))
        stack.callback(driver.close)
        try:
            driver.open(time.monotonic())
            drive = _drive(driver, spy, 0.25, crashes)
        except Exception as exc:
            crashes.caught("driver open", exc)
            drive = {"ok": False}
    return _result(sent, c["malformed"], bad, exact, crashes, t0, (rss0, rss1), "bench (robot in-process)",
                   counters={k: c[k] for k in ("received", "foreign", "malformed", *verdicts)},
                   contract_violations=tally.contract_violations(), kinds_sent_refused=tally.report(),
                   vehicle={**spy.report(), "ok": spy.ok}, drives_after=drive)


# ================================================================================================== CAN bus
#: CANSimple command ids and field sizes as ODrive's CAN protocol documents them (cmd_id = the low 5 bits)
HEARTBEAT, ESTOP_CMD, SET_AXIS_STATE, GET_ENCODER_ESTIMATES, SET_CONTROLLER_MODE, SET_INPUT_VEL, CLEAR_ERRORS = (
    0x01, 0x02, 0x07, 0x09, 0x0B, 0x0D, 0x18)
CLOSED_LOOP, VELOCITY_CONTROL, PASSTHROUGH = 8, 2, 1


class CanSpec:
    """The oracle: CANSimple as the shipped DBC (``drivers/odrive_cansimple.dbc``) lays it out, checked with
    ``struct``: a standard 11-bit id, a command the DBC knows, exactly its length (a remote frame: any), its float32
    fields finite."""

    def __init__(self) -> None:
        from importlib import resources

        import cantools

        text = resources.files("drivers").joinpath("odrive_cansimple.dbc").read_text()
        db = cantools.database.load_string(text, database_format="dbc")
        self.msgs = {m.frame_id: (m.name, m.length, [s.start // 8 for s in m.signals if s.is_float])
                     for m in db.messages}

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


def _frame(node: int, cmd: int, data: bytes = b"", **kw):
    import can

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

    def next(self):
        import can

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
            arb = (arb & ~0x1F) | rng.choice([c for c in range(32) if c not in (1, 2, 7, 9, 11, 13, 24)])
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


def _controller_frames(rng: random.Random, nodes: tuple[int, ...]):
    """What motor controllers send: Heartbeats (closed loop, no error) and encoder estimates."""

    def make():
        node = rng.choice(nodes)
        if rng.random() < 0.4:
            return _frame(node, HEARTBEAT, struct.pack("<IBBBx", 0, CLOSED_LOOP, 0, 1))
        return _frame(node, GET_ENCODER_ESTIMATES, struct.pack("<ff", rng.uniform(-100, 100), rng.uniform(-5, 5)))

    return make


def can_decoder(n: int, seed: int, workdir: Path | None = None) -> dict:
    """Frames straight into ``drivers.can.decode``: it must refuse (ValueError) exactly what the oracle refuses and
    raise nothing else. Error frames and frames of every kind included."""
    import can

    from drivers.can import decode

    rng = random.Random(seed)
    spec = CanSpec()
    t0, rss0, crashes = time.monotonic(), rss_mb(), Crashes()
    mut = CanMutator(rng, _controller_frames(rng, (0, 1)), (0, 1))
    tally = Tally()
    refused = disagree = bad = 0
    for i in range(n):
        kind, f = mut.next()
        if i % 50 == 0:
            kind, f = "error_frame", can.Message(arbitration_id=rng.randrange(1 << 29), is_error_frame=True,
                                                 data=rng.randbytes(8))
        ok = spec.valid(f)
        bad += not ok
        tally.add(kind, not ok)
        try:
            node, name, sig = decode(f)
            got_ok = all(math.isfinite(v) for v in sig.values() if isinstance(v, float))
        except ValueError:
            got_ok = False
            refused += 1
        except Exception as exc:
            crashes.caught("decode", exc)
            got_ok = None
        disagree += got_ok is not None and got_ok != ok
    return _result(n, refused, bad, disagree == 0 and refused == bad, crashes, t0, (rss0, rss_mb()),
                   "bench (decoder in-process)", disagreements=disagree, kinds_sent_refused=tally.report())


def can_driver(n: int, seed: int, workdir: Path | None = None) -> dict:
    """Frames on a ``virtual`` channel at a running CAN driver (its emulated controllers on the same channel),
    impersonating the controllers. Every frame the oracle refuses must be counted malformed; a frame the oracle
    takes is sent to a node the driver does not use (a valid frame of another device, counted nowhere). Then
    valid-structure encoder estimates with huge values from the driver's own nodes (odometry garbage: informative,
    not counted here), and driving must still work (after the operator's ``clear_faults`` if the link latched a
    fault)."""
    import can

    rng = random.Random(seed)
    spec = CanSpec()
    own = (0, 1)
    t0, rss0, crashes = time.monotonic(), rss_mb(), Crashes()
    with crashes, ExitStack() as stack:
        channel = f"fuzz-{uuid.uuid4().hex[:8]}"
        vehicle = new_vehicle()
        spy = VehicleSpy(vehicle, 0.5 + 1e-6, 1.0 + 1e-6)
        # ODrive's axis.config.watchdog_timeout set to 2 s here (the rig's default is 0.5 s): the controllers, the
        # driver and this harness share one interpreter, and a scheduling stall of it on a loaded machine is not
        # what this input tests (CI once tripped an axis between re-arming and the drive). The faults the fuzzed
        # frames cause (an Estop, an IDLE request) are still latched and cleared by the operator below.
        can_ecus(stack, channel, vehicle, watchdog=2.0)
        driver = open_can_driver(stack, channel)
        bus = can.Bus(interface="virtual", channel=channel)
        stack.callback(bus.shutdown)
        mut = CanMutator(rng, _controller_frames(rng, own), own)
        tally = Tally()
        rss0 = rss_mb()
        m0 = driver.health(time.monotonic()).malformed
        sent = bad = 0
        poses = []

        def poll() -> None:
            try:
                for _ in range(3):  # the virtual bus delivers on send: the frames are queued already
                    poses.extend(driver.poll(time.monotonic()))
            except Exception as exc:
                crashes.caught("poll", exc)

        while sent < n:
            for _ in range(min(200, n - sent)):
                kind, f = mut.next()
                ok = spec.valid(f)
                if ok and not f.is_extended_id and (f.arbitration_id >> 5) in own:
                    f.arbitration_id = (rng.randrange(2, 64) << 5) | (f.arbitration_id & 0x1F)
                bus.send(f)
                tally.add(kind, not ok)
                bad += not ok
                sent += 1
            poll()
            driver.send(0.2, 0.1, time.monotonic())
        counted = driver.health(time.monotonic()).malformed - m0
        rss1 = rss_mb()
        # valid structure, garbage values: encoder estimates from the driver's own nodes
        k = max(20, n // 50)
        n_poses = len(poses)
        m1 = driver.health(time.monotonic()).malformed
        for i in range(k):
            node = own[i % 2]
            val = rng.choice([3.4e38, -3.4e38, 1e30, 1e7, -1e7, rng.uniform(-1e6, 1e6)])
            bus.send(_frame(node, GET_ENCODER_ESTIMATES, struct.pack("<ff", val, rng.choice([0.0, val]))))
            if i % 10 == 9:
                poll()
        poll()
        garbage = poses[n_poses:]
        beyond = sum(not (abs(p.x) <= 1e6 and abs(p.y) <= 1e6 and abs(p.theta) <= 1e3) for p in garbage)
        refused_garbage = driver.health(time.monotonic()).malformed - m1

        def tick() -> bool:  # the driver host's tick with no command: poll, then zeros (which feed the watchdog)
            poll()
            driver.send(0.0, 0.0, time.monotonic())
            return driver.health(time.monotonic()).ok

        # Three Heartbeat periods of ticks before judging the link: a fuzzed frame can disarm an axis as a real
        # ODrive would obey it (an Estop, an IDLE request), and the driver learns it from the next Heartbeat only.
        # (CI once judged the link in between: the drive found the left axis IDLE.)
        t_settle = time.monotonic() + 0.3
        while time.monotonic() < t_settle:
            tick()
            time.sleep(0.02)
        # the operator's act if the link latched a fault meanwhile, then drive; is the odometry sane again?
        cleared = not driver.health(time.monotonic()).ok
        if cleared:
            driver.clear_faults(time.monotonic())
            wait_until(tick, 3.0, 0.02)
        n_before = len(poses)
        drive = _drive(driver, spy, 0.25, crashes)
        poll()
        after = poses[n_before:]
        sane = bool(after) and all(abs(p.x) <= 1e6 and abs(p.y) <= 1e6 and abs(p.theta) <= 1e3 for p in after)
        nonfinite = sum(not all(math.isfinite(a) for a in (p.x, p.y, p.theta, p.v or 0.0, p.omega or 0.0))
                        for p in poses)
    return _result(sent, counted, bad, counted == bad, crashes, t0, (rss0, rss1), "bench (driver in-process)",
                   kinds_sent_refused=tally.report(), nonfinite_poses=nonfinite,
                   huge_estimates={"sent": k, "counted_malformed": refused_garbage, "poses": len(garbage),
                                   "poses_beyond_wire_range": beyond, "odometry_in_range_after": sane},
                   operator_clear_faults=cleared, vehicle={**spy.report(), "ok": spy.ok}, drives_after=drive)


def _master_frames(rng: random.Random, nodes: tuple[int, ...], spec: CanSpec):
    """What a driver sends its controllers: set-points (finite, some huge), arming, controller mode, clears,
    encoder requests, a rare Estop."""
    state_len = spec.length(SET_AXIS_STATE, 4)

    def make():
        node = rng.choice(nodes)
        r = rng.random()
        if r < 0.55:
            return _frame(node, SET_INPUT_VEL, struct.pack("<ff", rng.uniform(-8, 8), 0.0))
        if r < 0.7:
            state = rng.choice([CLOSED_LOOP, CLOSED_LOOP, 1, rng.randrange(2**32)])
            return _frame(node, SET_AXIS_STATE, struct.pack("<I", state).ljust(state_len, b"\0"))
        if r < 0.8:
            return _frame(node, SET_CONTROLLER_MODE, struct.pack("<II", VELOCITY_CONTROL, PASSTHROUGH))
        if r < 0.9:
            return _frame(node, CLEAR_ERRORS, b"\0")
        if r < 0.98:
            return _frame(node, GET_ENCODER_ESTIMATES, b"", is_remote_frame=True)
        return _frame(node, ESTOP_CMD, b"")

    return make


def _ecu_class(f, spec: CanSpec, nodes: tuple[int, ...]) -> str:
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


class _EcuLife:
    """The emulated controllers on ``channel`` (no cyclic encoder estimates: every estimate on the bus answers a
    remote request, the batch marker), armed by ``arm`` frames from ``bus``."""

    def __init__(self, channel: str, vehicle, bus, arm: list) -> None:
        from sim_learner.can_ecu import DiffDriveEcus

        while bus.recv(timeout=0) is not None:  # what a pair that died had sent before it died
            pass
        self.ecus = DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle,
                                  encoder_period=3600.0).start()
        first, t_end = 0, time.monotonic() + 2.0  # the one cyclic pair of estimates, sent at start
        while first < 2 and time.monotonic() < t_end:
            f = bus.recv(timeout=0.05)
            first += f is not None and f.arbitration_id & 0x1F == GET_ENCODER_ESTIMATES
        for f in arm:
            bus.send(f)

    @property
    def alive(self) -> bool:
        t = self.ecus._thread
        return t is not None and t.is_alive()

    def close(self) -> None:
        self.ecus.stop()


def can_ecu(n: int, seed: int, workdir: Path | None = None) -> dict:
    """Frames at the emulated controllers, impersonating the driver (re-arming them every batch so that the
    set-points drive). ``malformed`` must be exactly the frames every device counts, or exactly those plus all the
    other non-CANSimple frames (a strict decoder); the vehicle never gets a non-finite command. Controllers whose
    thread dies are counted (with the exception), replaced, and the batch left out of the counts. Afterwards a real
    driver opens the bus, arms the controllers and drives."""
    import can

    rng = random.Random(seed)
    spec = CanSpec()
    own = (0, 1)
    t0, crashes = time.monotonic(), Crashes()
    with crashes, ExitStack() as stack:
        channel = f"fuzz-{uuid.uuid4().hex[:8]}"
        vehicle = new_vehicle()
        wheel = 2.0 * 2.0 * math.pi * 0.1 * (1 + 1e-9)  # the controllers' vel_limit (2 turns/s) x circumference
        spy = VehicleSpy(vehicle, wheel, 2.0 * wheel / 0.4)  # at most both wheels at the limit (track 0.4 m)
        bus = can.Bus(interface="virtual", channel=channel)
        stack.callback(bus.shutdown)
        state_len = spec.length(SET_AXIS_STATE, 4)
        arm = [f for node in own for f in (
            _frame(node, CLEAR_ERRORS, b"\0"),
            _frame(node, SET_CONTROLLER_MODE, struct.pack("<II", VELOCITY_CONTROL, PASSTHROUGH)),
            _frame(node, SET_AXIS_STATE, struct.pack("<I", CLOSED_LOOP).ljust(state_len, b"\0")))
            if (f.arbitration_id & 0x1F) != SET_CONTROLLER_MODE or spec.valid(f)]
        lives = [_EcuLife(channel, vehicle, bus, arm)]
        stack.callback(lambda: lives[-1].close())
        rss0 = rss_mb()
        mut = CanMutator(rng, _master_frames(rng, own, spec), own)
        tally = Tally()
        counts = Counter()  # frames of the batches the controllers lived through, by class
        counted = sent = lost = 0

        def is_request(f) -> bool:
            return (f.is_remote_frame and not f.is_extended_id and not f.is_error_frame
                    and f.arbitration_id & 0x1F == GET_ENCODER_ESTIMATES and (f.arbitration_id >> 5) in own)

        while sent < n:
            batch, classes = list(arm), Counter()
            for _ in range(min(40, n - sent)):  # small batches: a crash loses one
                kind, f = mut.next()
                cls = _ecu_class(f, spec, own)
                classes[cls] += 1
                tally.add(kind, cls != "valid")
                batch.append(f)
            batch.append(_frame(own[0], GET_ENCODER_ESTIMATES, b"", is_remote_frame=True))
            life = lives[-1]
            m0 = life.ecus.malformed
            answers = got = 0
            for f in batch:
                answers += is_request(f)
                bus.send(f)
            sent += len(batch) - len(arm) - 1
            t_end = time.monotonic() + 5.0
            while got < answers and time.monotonic() < t_end and life.alive:
                f = bus.recv(timeout=0.01)
                if f is not None and not f.is_remote_frame and f.arbitration_id & 0x1F == GET_ENCODER_ESTIMATES:
                    got += 1
            if got < answers:  # the controllers died (or stopped answering): a crash, a new pair, batch left out
                if life.alive:
                    crashes.events.append("controllers stopped answering encoder requests")
                lost += len(batch) - len(arm) - 1
                life.close()
                lives[-1] = _EcuLife(channel, vehicle, bus, arm)
                continue
            counted += life.ecus.malformed - m0
            counts.update(classes)
        d, e = counts["definite"], counts["either"]
        rss1 = rss_mb()
        try:
            drive = _drive(open_can_driver(stack, channel), spy, 0.25, crashes)
        except Exception as exc:
            crashes.caught("driver open", exc)
            drive = {"ok": False}
    return _result(sent, counted, d, counted in (d, d + e), crashes, t0, (rss0, rss1), "bench (controllers in-process)",
                   exact_rule="counted == every device's (definite) or definite + either (a strict decoder)",
                   classes={"valid": counts["valid"], "definite": d, "either": e},
                   strict_decoder=counted == d + e, crash_signatures=dict(Counter(crashes.events)),
                   lost_in_crashed_batches=lost, kinds_sent_refused=tally.report(),
                   vehicle={**spy.report(), "ok": spy.ok}, drives_after=drive)


# ================================================================================================== MAVLink
GUIDED_MODE, HOLD_MODE = 15, 4
MAV_CMD_DO_SET_MODE, MAV_CMD_ARM, MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_REQUEST_PROTOCOL_VERSION = 176, 400, 511, 519
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


def _vehicle_templates(rng: random.Random):
    """What an ArduPilot Rover sends a ground station."""

    def make(enc):
        r = rng.random()
        if r < 0.25:
            base = 1 | (128 if rng.random() < 0.7 else 0)
            return enc.heartbeat_encode(10, 3, base, rng.choice([GUIDED_MODE, GUIDED_MODE, HOLD_MODE, 0]), 4)
        if r < 0.5:
            return enc.local_position_ned_encode(rng.randrange(2**32), *(rng.uniform(-50, 50) for _ in range(6)))
        if r < 0.75:
            return enc.attitude_encode(rng.randrange(2**32), *(rng.uniform(-3.1, 3.1) for _ in range(6)))
        if r < 0.85:
            return enc.statustext_encode(rng.randrange(8), rng.randbytes(rng.randint(1, 50)))
        if r < 0.92:
            return enc.command_ack_encode(rng.choice([MAV_CMD_DO_SET_MODE, MAV_CMD_ARM, 511]), rng.randrange(6))
        return enc.param_value_encode(rng.randbytes(16), rng.uniform(-1e3, 1e3), 9, 900, rng.randrange(900))

    return make


def _gcs_templates(rng: random.Random):
    """What a ground station (the driver) sends an ArduPilot Rover."""

    def make(enc):
        r = rng.random()
        if r < 0.15:
            return enc.heartbeat_encode(6, 8, 0, 0, 0)
        if r < 0.45:
            cmd, p1, p2 = rng.choice([(MAV_CMD_DO_SET_MODE, 1, GUIDED_MODE), (MAV_CMD_DO_SET_MODE, 1, HOLD_MODE),
                                      (MAV_CMD_ARM, 1, 0), (MAV_CMD_ARM, 0, 0),
                                      (MAV_CMD_SET_MESSAGE_INTERVAL, rng.choice([30, 32, 33]), rng.choice([5e4, 1e5])),
                                      (rng.randrange(65536), rng.uniform(-10, 10), rng.uniform(-10, 10))])
            return enc.command_long_encode(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, 0)
        if r < 0.9:
            frame = 8 if rng.random() < 0.8 else rng.randrange(22)
            mask = 0x05E7 if rng.random() < 0.8 else rng.randrange(65536)
            return enc.set_position_target_local_ned_encode(rng.randrange(2**32), 1, 1, frame, mask, 0, 0, 0,
                                                            rng.uniform(-3, 3), 0, 0, 0, 0, 0, 0, rng.uniform(-3, 3))
        return enc.manual_control_encode(1, *(rng.randint(-1000, 1000) for _ in range(4)), 0)

    return make


#: The MAVLink driver's telemetry contract (drivers/mavlink.py module docstring): which fields of a vehicle's
#: LOCAL_POSITION_NED / ATTITUDE must be finite and within what magnitude, else the message is malformed.
MAV_TELEMETRY_BOUNDS = {"LOCAL_POSITION_NED": {"x": 1e6, "y": 1e6, "vx": 100.0, "vy": 100.0},
                        "ATTITUDE": {"yaw": 2 * math.pi, "yawspeed": 100.0}}


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


def mavlink_driver(n: int, seed: int, workdir: Path | None = None) -> dict:
    """MAVLink datagrams at the driver's pymavlink parser, from a scripted vehicle (a socket bound here that the
    driver opened GUIDED and armed): the driver must receive every message the oracle parser gets out of them
    and count exactly its BAD_DATA. What the driver sends meanwhile must be what it was told (or a stop); a valid
    GUIDED heartbeat afterwards and the driver's set-point reaches the vehicle again."""
    from drivers import open_driver
    from drivers.mavlink import MavlinkLinkConfig

    rng = random.Random(seed)
    L = mavlink2()
    t0, rss0, crashes = time.monotonic(), rss_mb(), Crashes()
    with crashes, ExitStack() as stack:
        fake = udp_socket()
        stack.callback(fake.close)
        enc = L.MAVLink(None, srcSystem=1, srcComponent=1)

        def heartbeat() -> bytes:
            return bytes(enc.heartbeat_encode(10, 3, 1 | 128, GUIDED_MODE, 4).pack(enc))

        asked = mav_parser()

        def vehicle(data: bytes) -> bytes:
            """A ready ArduPilot Rover as the driver's open() needs it: GUIDED and armed, every command
            acknowledged to its sender, position (an EKF origin) streaming."""
            out = heartbeat()
            for m in mav_parse(asked, data):
                if m.get_type() == "COMMAND_LONG":
                    out += bytes(enc.command_ack_encode(m.command, 0, 0, 0, m.get_srcSystem(),
                                                        m.get_srcComponent()).pack(enc))
            out += bytes(enc.local_position_ned_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(enc))
            return out + bytes(enc.attitude_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(enc))

        driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:{LOCAL}:{fake.getsockname()[1]}",
                                                          rate_hz=20, open_timeout=5.0))
        stack.callback(driver.close)
        with _answering(fake, vehicle) as peer:
            driver.open(time.monotonic())
        addr = peer["addr"]
        time.sleep(0.1)  # the answers to the driver's last requests
        driver.poll(time.monotonic())
        drain(fake)
        rss0 = rss_mb()
        h0 = driver.health(time.monotonic())
        base = (h0.frames_received, h0.malformed)
        mut, oracle, tally = MavMutator(rng, _vehicle_templates(rng)), MavOracle(vehicle=(1, 1)), Tally()
        sent = 0
        while sent < n:
            for _ in range(min(64, n - sent)):
                kind, data = mut.next()
                msgs = oracle.feed(data)
                tally.add(kind, any(m.get_type() == "BAD_DATA" or oracle.is_invalid(m) for m in msgs))
                fake.sendto(data, addr)
                sent += 1
            t_end = time.monotonic() + 5.0
            while time.monotonic() < t_end:
                try:
                    driver.poll(time.monotonic())
                except Exception as exc:
                    crashes.caught("poll", exc)
                    break
                # a BAD_DATA or invalid telemetry is malformed, every other message received
                h = driver.health(time.monotonic())
                if h.frames_received - base[0] + h.malformed - base[1] >= oracle.total:
                    break
                time.sleep(0.001)
            driver.send(0.2, 0.1, time.monotonic())
        h = driver.health(time.monotonic())
        got = {"messages": h.frames_received - base[0] + h.malformed - base[1], "bad_data": h.malformed - base[1]}
        want = {"messages": oracle.total, "bad_data": oracle.bad + oracle.invalid}
        out_parser = mav_parser()
        setpoints = [m for b, _ in drain(fake) for m in mav_parse(out_parser, b)
                     if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
        f32 = struct.unpack("<ff", struct.pack("<ff", 0.2, -0.1))
        wrong = sum((m.vx, m.yaw_rate) not in (f32, (0.0, 0.0)) for m in setpoints)
        rss1 = rss_mb()
        conn = getattr(driver, "conn", None)  # what the driver and its pymavlink connection keep
        kept = {"statustexts": len(getattr(driver, "statustexts", [])),
                "pymavlink_message_types": sum(len(st.messages) for st in getattr(conn, "sysid_state", {}).values()),
                "pymavlink_systems": len(getattr(conn, "sysid_state", {})),
                "pymavlink_params": sum(len(ps.params) for ps in getattr(conn, "param_state", {}).values())}
        # the vehicle says GUIDED and armed again, with a fresh position: the next set-point must reach it as told
        fake.sendto(vehicle(b""), addr)
        time.sleep(0.05)
        driver.poll(time.monotonic())
        driver.send(0.25, 0.0, time.monotonic())
        time.sleep(0.05)
        last = [m for b, _ in drain(fake) for m in mav_parse(out_parser, b)
                if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
        drive_ok = bool(last) and (last[-1].vx, last[-1].yaw_rate) == (0.25, 0.0)
    return _result(sent, got["bad_data"], want["bad_data"], got == want, crashes, t0, (rss0, rss1),
                   "bench (driver in-process)", invalid_telemetry=oracle.invalid, got=got, want=want,
                   types=dict(oracle.types.most_common(12)),
                   kinds_sent_badly=tally.report(), kept_by_driver=kept,
                   vehicle={"setpoints": len(setpoints), "not_as_told": wrong, "ok": wrong == 0},
                   drives_after={"setpoint": [last[-1].vx, last[-1].yaw_rate] if last else None, "ok": drive_ok})


class _RoverLife:
    """One emulated rover and the ground-station socket that talks to it (GUIDED and armed), acknowledgements
    counted."""

    def __init__(self, spy: VehicleSpy) -> None:
        from sim_learner.mavlink_rover import MavlinkRover

        self.rover = MavlinkRover(spy.vehicle, wp_speed=2.0, str_rat_max=2.0).start()
        self.gcs = udp_socket()
        self.to = (LOCAL, self.rover.port)
        self.enc = mavlink2().MAVLink(None, srcSystem=255, srcComponent=190)
        self.reader = mav_parser()
        self.acks = 0
        for b in (self.pack(self.enc.heartbeat_encode(6, 8, 0, 0, 0)), self.command(MAV_CMD_DO_SET_MODE, 1, 15),
                  self.command(MAV_CMD_ARM, 1)):
            self.send(b)
        wait_until(lambda: self.read_acks() >= 2, 5.0, 0.01)
        self.acks = 0

    def pack(self, msg) -> bytes:
        return bytes(msg.pack(self.enc))

    def command(self, cmd: int, p1: float = 0, p2: float = 0) -> bytes:
        return self.pack(self.enc.command_long_encode(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, 0))

    def setpoint(self, vx: float) -> bytes:
        return self.pack(self.enc.set_position_target_local_ned_encode(0, 1, 1, 8, 0x05E7, 0, 0, 0, vx, 0, 0, 0, 0,
                                                                       0, 0, 0.0))

    def send(self, data: bytes) -> None:
        self.gcs.sendto(data, self.to)

    def read_acks(self) -> int:
        for data, _ in drain(self.gcs):
            self.acks += sum(m.get_type() == "COMMAND_ACK" for m in mav_parse(self.reader, data))
        return self.acks

    @property
    def alive(self) -> bool:
        t = self.rover._thread
        return t is not None and t.is_alive()

    def close(self) -> None:
        self.gcs.close()
        self.rover.stop()


def mavlink_rover(n: int, seed: int, workdir: Path | None = None) -> dict:
    """MAVLink datagrams at the emulated rover from a ground-station socket bound here (GUIDED and armed first),
    in batches: its BAD_DATA count must equal the oracle's, and every COMMAND_LONG it decodes is acknowledged (each
    batch ends with one and waits for all the acknowledgements); the vehicle never gets a non-finite command or one
    beyond WP_SPEED / ATC_STR_RAT_MAX. A rover whose thread dies is counted (with the exception), replaced by a new
    one, and the batch it died in is left out of the counts. Afterwards: what a NaN velocity set-point makes of the
    vehicle, and a real driver opens the rover (GUIDED, armed) and drives it."""
    from drivers import open_driver
    from drivers.mavlink import MavlinkLinkConfig

    rng = random.Random(seed)
    t0, crashes = time.monotonic(), Crashes()
    with crashes, ExitStack() as stack:
        spy = VehicleSpy(new_vehicle(), 2.0, 2.0)
        lives = [_RoverLife(spy)]
        stack.callback(lambda: lives[-1].close())
        life = lives[0]
        rss0 = rss_mb()
        mut, tally = MavMutator(rng, _gcs_templates(rng), sysid=255, compid=190), Tally()
        oracle = MavOracle(vehicle=(life.rover.sysid, life.rover.compid))
        sent = lost = 0
        want = got = want_acks = got_acks = 0
        while sent < n:
            bad0, long0, rbad0, acks0 = oracle.bad, oracle.commands_for_vehicle, life.rover.bad, life.acks
            batch = 0
            for _ in range(min(64, n - sent)):
                kind, data = mut.next()
                msgs = oracle.feed(data)
                tally.add(kind, any(m.get_type() == "BAD_DATA" for m in msgs))
                life.send(data)
                batch += 1
            mark = life.command(MAV_CMD_REQUEST_PROTOCOL_VERSION)
            oracle.feed(mark)
            life.send(mark)
            sent += batch
            longs = oracle.commands_for_vehicle - long0  # ArduPilot acknowledges each COMMAND_LONG addressed to it
            wait_until(lambda w=acks0 + longs, lf=life: lf.read_acks() >= w or not lf.alive, 5.0, 0.001)
            if not life.alive:  # died in this batch: counted as a crash, the batch left out, a new rover
                lost += batch
                life.close()
                life = lives[-1] = _RoverLife(spy)
                continue
            want, got = want + oracle.bad - bad0, got + life.rover.bad - rbad0
            want_acks, got_acks = want_acks + longs, got_acks + life.acks - acks0
        rss1 = rss_mb()
        # what does a NaN velocity set-point do to the vehicle? (then a stop)
        for b in (life.command(MAV_CMD_DO_SET_MODE, 1, GUIDED_MODE), life.command(MAV_CMD_ARM, 1),
                  life.setpoint(math.nan)):
            life.send(b)
        time.sleep(0.2)
        nan_probe = {"vehicle_got": list(spy.last) if spy.last else None, "rover_alive": life.alive}
        life.send(life.setpoint(0.0))
        life.gcs.close()
        try:
            driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:{LOCAL}:{life.rover.port}", rate_hz=20,
                                                              open_timeout=5.0))
            stack.callback(driver.close)
            driver.open(time.monotonic())
            driver.engage(time.monotonic())  # a person's act: GUIDED and armed
            drive = _drive(driver, spy, 0.25, crashes)
        except Exception as exc:
            crashes.caught("driver open", exc)
            drive = {"ok": False}
    signatures = Counter(crashes.events)
    return _result(sent, got, want, got == want and got_acks == want_acks, crashes, t0, (rss0, rss1),
                   "bench (rover in-process)", crash_signatures=dict(signatures), lost_in_crashed_batches=lost,
                   command_acks={"want": want_acks, "got": got_acks}, types=dict(oracle.types.most_common(12)),
                   kinds_sent_badly=tally.report(), nonfinite_setpoints_sent=oracle.nonfinite_setpoints,
                   nan_setpoint=nan_probe, vehicle={**spy.report(), "ok": spy.ok}, drives_after=drive)


# ===================================================================================================== main
IN_PROCESS: dict[str, Callable[[int, int, Path], dict]] = {
    "udp_driver": udp_driver, "udp_robot": udp_robot, "can_decoder": can_decoder, "can_driver": can_driver,
    "can_ecu": can_ecu, "mavlink_driver": mavlink_driver, "mavlink_rover": mavlink_rover}


def fuzz(per_input: int, seed: int, inputs: tuple[str, ...], workdir: Path, rounds: int = 0,
        round_size: int = 0, probe: bool = False, senders: int = 0, per_sender: int = 0) -> dict:
    """Every input asked for (``per_input`` payloads each), then the RSS rounds; one JSON-ready dict."""
    out: dict[str, Any] = {"per_input": per_input, "seed": seed, "inputs": {}}
    zenoh_inputs = tuple(i for i in inputs if i.startswith("zenoh_"))
    if zenoh_inputs:
        out["inputs"].update(fuzz_zenoh(per_input, seed, workdir, zenoh_inputs))
    for k, name in enumerate(inputs):
        if name in IN_PROCESS:
            out["inputs"][name] = IN_PROCESS[name](per_input, seed + 10 + k, workdir)
    res = out["inputs"]
    out["summary"] = {name: {"sent": r["sent"], "counted": r["counted"], "expected": r["expected"],
                             "exact": r["exact"], "crashes": r["crashes"],
                             "vehicle_ok": r.get("vehicle", {}).get("ok"),
                             "drives_after": r.get("drives_after", {}).get("ok"), "seconds": r["seconds"],
                             "rss_mb": [r["rss_mb"]["before"], r["rss_mb"]["after"]]} for name, r in res.items()}
    out["all_exact"] = all(r["exact"] for r in res.values())
    out["all_vehicle_ok"] = all(r.get("vehicle", {}).get("ok", True) for r in res.values())
    if rounds > 0:
        r = rss_rounds(rounds, round_size, seed + 100, workdir)
        out["rss_rounds_mb"] = r["rss_mb"]
        out["rss_rounds"] = r
        out["rss_rounds_shm_off"] = rss_rounds(rounds, round_size, seed + 100, workdir, shm=False)
        pr = on = off = None
        if probe:
            out["rss_probe"] = pr = rss_rounds(rounds, round_size, seed + 100, workdir, probe=True)
        if senders > 0:
            out["rss_senders"] = on = rss_senders(senders, per_sender, seed + 200, workdir)
            out["rss_senders_shm_off"] = off = rss_senders(senders, per_sender, seed + 200, workdir, shm=False)
        out["rss_verdict"] = rss_verdict(r, pr, on, off)
    return out


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--per-input", type=int, default=100_000, help="payloads per input (default 100000)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--inputs", default=",".join(INPUTS), help=f"comma-separated subset of {', '.join(INPUTS)}")
    ap.add_argument("--rounds", type=int, default=5, help="RSS study: rounds of Zenoh cmd payloads (0: none)")
    ap.add_argument("--round-size", type=int, default=50_000, help="RSS study: payloads per round")
    ap.add_argument("--no-probe", action="store_true", help="RSS study without the heap-reporting probe host")
    ap.add_argument("--senders", type=int, default=4, help="RSS study: successive sender sessions (0: none)")
    ap.add_argument("--per-sender", type=int, default=2000, help="RSS study: 4-64 KiB payloads per sender")
    ap.add_argument("--probe-host", default=None, metavar="ROBOT", help=argparse.SUPPRESS)  # the RSS study's child
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    if args.probe_host:
        return probe_host(args)
    inputs = tuple(i.strip() for i in args.inputs.split(",") if i.strip())
    unknown = [i for i in inputs if i not in INPUTS]
    if unknown or args.per_input < 1 or args.rounds < 0:
        raise UsageError(f"unknown inputs {unknown}" if unknown else "--per-input >= 1 and --rounds >= 0")
    with tempfile.TemporaryDirectory(prefix="scm-fuzz-") as tmp:
        out = fuzz(args.per_input, args.seed, inputs, Path(tmp), args.rounds, args.round_size, not args.no_probe,
                  args.senders, args.per_sender)
    from bench.common import emit

    emit(out)
    return 0 if out["all_exact"] and out["all_vehicle_ok"] else 1
