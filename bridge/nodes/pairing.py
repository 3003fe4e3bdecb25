"""Command pairs from live telemetry: which learner command really moved the vehicle between two poses.

The driver host echoes every command the vehicle got (``applied``) and publishes poses (``state``), both stamped
with its own monotonic clock. Events are fed in time order. A *segment* is a run of echoes carrying the same
driving command (reason ``cmd`` or ``clamped``); the first and the latest pose inside a segment bracket an interval
over which that one command was in force. A pair ``<f_T^-1(x(t1), x(t2)), u_L>`` is formed when the segment ends
(the command changes, or the vehicle is stopped) or when its bracketed span reaches ``dt`` (long segments give one
pair per ``dt``), and only if the span is at least ``min_span`` (0.4 ``dt`` by default). Deadman stops, estops
and telemetry gaps longer than ``max_gap`` never produce a pair. Pure: times are arguments.

Why 0.4 ``dt``: telemetry at twice the command rate (an ArduPilot vehicle's 20 Hz poses against 10 Hz commands)
puts two poses, one period apart, inside each command, so the span is ``dt / 2`` give or take the vehicle's
scheduling jitter. A minimum of exactly ``dt / 2`` rejected about half of those intervals for that jitter alone
(docs/ARCHITECTURE.md, section 4).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from transfer.pairs import teacher_equivalent

DRIVING = ("cmd", "clamped")
Pair = tuple[NDArray[np.float64], NDArray[np.float64]]


class IntervalPairer:
    """Turns time-ordered applied echoes and poses into command pairs (see the module docstring)."""

    def __init__(self, dt: float, min_span: float | None = None, max_gap: float | None = None) -> None:
        if dt <= 0:
            raise ValueError("dt must be positive")
        self.dt = float(dt)
        self.min_span = 0.4 * self.dt if min_span is None else float(min_span)
        self.max_gap = 2.0 * self.dt if max_gap is None else float(max_gap)
        self.segment: tuple[float, float] | None = None  # the command in force, None when not driving
        self.first: tuple[float, NDArray[np.float64]] | None = None
        self.last: tuple[float, NDArray[np.float64]] | None = None
        self.last_event = -np.inf
        self.rejected = 0
        self.formed = 0
        self.out_of_order = 0  # events older than one already fed: ignored

    def applied(self, stamp: float, v: float, omega: float, reason: str) -> Pair | None:
        if stamp < self.last_event:
            self.out_of_order += 1
            return None
        self.last_event = stamp
        key = (float(v), float(omega)) if reason in DRIVING else None
        if key == self.segment:
            return None
        out = self._close()
        self.segment, self.first, self.last = key, None, None
        return out

    def state(self, stamp: float, pose: NDArray[np.float64]) -> Pair | None:
        if stamp < self.last_event:
            self.out_of_order += 1
            return None
        self.last_event = stamp
        if self.segment is None:
            return None
        p = np.asarray(pose, dtype=float)
        prev = self.last if self.last is not None else self.first
        if prev is not None and stamp - prev[0] > self.max_gap:
            self.rejected += 1  # a telemetry gap: restart the interval here
            self.first, self.last = (stamp, p), None
            return None
        if self.first is None:
            self.first = (stamp, p)
            return None
        self.last = (stamp, p)
        if stamp - self.first[0] >= self.dt:
            out = self._close()
            self.first, self.last = (stamp, p), None
            return out
        return None

    def _close(self) -> Pair | None:
        if self.segment is None or self.first is None or self.last is None:
            return None
        (t1, x1), (t2, x2) = self.first, self.last
        if t2 - t1 < self.min_span:
            self.rejected += 1
            return None
        self.formed += 1
        return teacher_equivalent(x1, x2, t2 - t1), np.array(self.segment)
