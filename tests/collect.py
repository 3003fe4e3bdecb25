"""What the integration tests share: collecting the decoded messages of Zenoh keys, and waiting on them."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from bridge.core import wire as M
from tests.wait import until


class Collector:
    """Subscribes keys on a session and keeps every decoded message (with its receive time) per key."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self.lock = threading.Lock()
        self.got: dict[str, list] = {}
        self.times: dict[str, list[float]] = {}

    def listen(self, key: str, kind: type) -> list:
        """Start keeping ``key``'s messages decoded as ``kind``; returns the list they are appended to."""
        bucket, times = self.got.setdefault(key, []), self.times.setdefault(key, [])

        def cb(sample) -> None:
            msg = M.decode(sample.payload.to_bytes(), kind)
            with self.lock:
                bucket.append(msg)
                times.append(time.monotonic())

        self.session.declare_subscriber(key, cb)
        return bucket

    def snapshot(self, key: str) -> list:
        with self.lock:
            return list(self.got[key])

    def holds(self, pred: Callable[[], bool]) -> bool:
        """``pred()`` now, called under the lock (what came so far, as the callbacks leave it)."""
        with self.lock:
            return bool(pred())

    def wait(self, pred: Callable[[], bool], timeout: float) -> bool:
        """Poll ``pred`` (called under the lock) until it holds or ``timeout`` passes (looked at once more then, so
        a zero ``timeout`` is a look now)."""
        return bool(until(lambda: self.holds(pred), timeout))
