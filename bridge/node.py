"""What every Zenoh node of scmbridge does the same way: decode-and-count subscriptions, a fixed-rate loop with
counted missed deadlines, stop on SIGINT/SIGTERM, and the Zenoh command-line options.

Callbacks run on Zenoh's threads: they only decode, count and hand the message over; all work is in the node's
loop (docs/ARCHITECTURE.md, "Threads and clocks").
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, TypeVar

import zenoh
from msgspec import Struct

from bridge import wire as M
from bridge.zsession import make_config

log = logging.getLogger("scmbridge.node")
S = TypeVar("S", bound=Struct)


class Inputs:
    """Thread-safe counters of a node's inputs (``malformed_<name>``, ...), shared by its callbacks and its loop."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.counts: Counter[str] = Counter()

    def count(self, name: str, n: int = 1) -> None:
        with self.lock:
            self.counts[name] += n

    def snapshot(self) -> dict[str, int]:
        with self.lock:
            return dict(self.counts)

    def subscribe(self, session: zenoh.Session, key: str, kind: type[S], name: str,
                  handler: Callable[[S, float], None]) -> Any:
        """Declare a subscriber on ``key`` that decodes (and so validates) each sample as ``kind``; a sample that
        does not decode is counted as ``malformed_<name>`` and dropped; ``handler(msg, receive_time)`` gets the rest.
        """

        def on_sample(sample: zenoh.Sample) -> None:
            now = time.monotonic()
            try:
                msg = M.decode(sample.payload.to_bytes(), kind)
            except M.MessageError as exc:
                self.count(f"malformed_{name}")
                log.debug("dropped %s on %s: %s", kind.__name__, key, exc)
                return
            handler(msg, now)

        return session.declare_subscriber(key, on_sample)


class FixedRate:
    """Absolute deadlines at ``rate_hz``: ``wait()`` sleeps until the next one (or until ``stop`` is set); a
    deadline already past when a tick ends is counted in ``missed`` and the schedule restarts from now."""

    def __init__(self, rate_hz: float, stop: threading.Event) -> None:
        self.period = 1.0 / float(rate_hz)
        self.stop = stop
        self.t_next = time.monotonic()
        self.missed = 0
        self.pending = False  # woken before the deadline: the next wait keeps the same deadline

    def wait(self, wake: threading.Event | None = None) -> bool:
        """Sleep to the next deadline; True when it is reached, False when ``wake`` was set first (an input that
        should be handled now: the deadline stays where it is, call ``wait`` again after handling it)."""
        if not self.pending:
            self.t_next += self.period
        delay = self.t_next - time.monotonic()
        if delay <= 0:
            self.missed += 1
            self.t_next = time.monotonic()
            self.pending = False
            return True
        if wake is not None and wake.wait(delay):
            wake.clear()
            self.pending = True
            return False
        if wake is None:
            self.stop.wait(delay)
        self.pending = False
        return True


def stop_on_signals() -> threading.Event:
    """An Event set by SIGINT or SIGTERM (the loop polls it; Zenoh's ``recv`` would ignore SIGINT)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def add_zenoh_args(ap: argparse.ArgumentParser) -> None:
    """The Zenoh options every node takes."""
    ap.add_argument("--listen", action="append", default=[], help="Zenoh endpoint to listen on (repeatable)")
    ap.add_argument("--connect", action="append", default=[], help="Zenoh endpoint to connect to (repeatable)")
    ap.add_argument("--mode", choices=["peer", "client", "router"], default="peer", help="Zenoh session mode")
    ap.add_argument("--zenoh-config", help="a Zenoh JSON5 config file (deploy/zenoh/); the endpoints above override it")


def zenoh_config(args: argparse.Namespace) -> zenoh.Config:
    return make_config(mode=args.mode, listen=args.listen, connect=args.connect, config_file=args.zenoh_config)


__all__ = ["FixedRate", "Inputs", "add_zenoh_args", "stop_on_signals", "zenoh_config"]
