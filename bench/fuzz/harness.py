"""What every fuzzed input shares: waiting, loopback sockets, the crash log, the vehicle's spy, the mutation
tally, the one result form, and driving a link afterwards."""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

#: every socket and Zenoh endpoint of the fuzz is on loopback
LOCAL = "127.0.0.1"
NONFINITE = (math.nan, math.inf, -math.inf)
#: mutation kinds a wire decoder must refuse whatever the message (unknown fields, truncations, out-of-range...)
MUST_REJECT = ("truncate", "nonfinite", "out_of_range", "unknown_field", "missing_field", "long_string",
               "big_array", "bad_utf8")


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


def result(sent: int, counted: int, expected: int, exact: bool, crashes: Crashes, t0: float,
           rss: tuple[float | None, float | None], process: str, **extra: Any) -> dict:
    """One input's result: what was sent, what the receiver counted, what the oracle expected, and the rest."""
    return {"sent": sent, "counted": counted, "expected": expected, "exact": bool(exact), "crashes": crashes.count,
            "crash_events": crashes.events[:10], "seconds": round(time.monotonic() - t0, 2),
            "rss_mb": {"process": process, "before": rss[0], "after": rss[1]}, **extra}


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


@contextlib.contextmanager
def answering(sock: socket.socket, reply: Callable[[bytes], bytes]) -> Iterator[dict]:
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


def drive_link(driver, spy: VehicleSpy, v: float, crashes: Crashes, seconds: float = 1.2) -> dict:
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
