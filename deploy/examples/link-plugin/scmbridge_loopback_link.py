"""A loopback vehicle link: a point that moves exactly as commanded, for bringing a lab up without a robot.

The whole of what a link owes scmbridge (docs/ARCHITECTURE.md, "Adding a link"): ``CONFIG``, the ``[link.loopback]``
section of a driver host's file; ``DRIVER``, built from it and doing no I/O before ``open``; ``EMULATED``. It is
registered by its package's ``scmbridge.links`` entry point (pyproject.toml beside it), not by an edit of scmbridge.
Its health is pure (no clock read, no state change) and every time it needs is the ``now`` it is given.
"""

from __future__ import annotations

import math
from typing import Annotated

from bridge.core.config import Cfg, meta
from drivers.base import FailsafeReport, LinkHealth, Pose


class LoopbackLinkConfig(Cfg):
    """``[link.loopback]``: a point vehicle that moves exactly as commanded."""

    gain: Annotated[float, meta("how much of each command the point executes", gt=0.0, le=10.0)] = 1.0
    start_x: Annotated[float, meta("x at open, m", ge=-100.0, le=100.0)] = 0.0


class LoopbackDriver:
    """The :class:`drivers.base.Driver` protocol on a point: ``send`` sets its speeds, ``poll`` integrates them."""

    name = "loopback"

    def __init__(self, config: LoopbackLinkConfig) -> None:
        self.config = config
        self.pose = (config.start_x, 0.0, 0.0)
        self.cmd = (0.0, 0.0)
        self.last: float | None = None
        self.opened = self.engaged = False
        self.sent = self.received = 0

    def open(self, now: float) -> None:
        self.opened, self.last = True, now

    def engage(self, now: float, clear_faults: bool = False) -> None:
        self.engaged = self.opened

    def failsafe(self) -> FailsafeReport:
        return FailsafeReport(drive_on_s=0.0, text="a loopback point stops with its host")

    def send(self, v: float, omega: float, now: float) -> None:
        self.cmd = (self.config.gain * v, self.config.gain * omega)
        self.sent += 1

    def stop(self, now: float) -> None:
        self.cmd = (0.0, 0.0)

    def poll(self, now: float) -> list[Pose]:
        if not self.opened or self.last is None:
            return []
        dt, self.last = max(0.0, now - self.last), now
        x, y, th = self.pose
        v, w = self.cmd
        self.pose = (x + v * dt * math.cos(th), y + v * dt * math.sin(th), th + w * dt)
        self.received += 1
        return [Pose(now, *self.pose, v, w)]

    def health(self, now: float) -> LinkHealth:
        ok = self.opened and self.engaged
        reason = "ok" if ok else "not_engaged" if self.opened else "closed"
        return LinkHealth(connected=self.opened, ok=ok, text="ready" if ok else reason.replace("_", " "),
                          frames_sent=self.sent, frames_received=self.received, reason=reason)

    def clear_faults(self, now: float) -> None:
        pass

    def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0,
              now: float | None = None) -> None:
        self.cmd = (0.0, 0.0)
        self.opened = self.engaged = False


CONFIG = LoopbackLinkConfig
DRIVER = LoopbackDriver
EMULATED = False
