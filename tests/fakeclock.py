"""A fake monotonic clock for tests of code that takes its clock (the drivers, docs/ARCHITECTURE.md section 4): time
moves only when the test, or the code's injected ``sleep``, moves it, so no such test sleeps or depends on the
machine's load."""

from __future__ import annotations

import heapq
import itertools
import threading
from collections.abc import Callable


class FakeClock:
    """A monotonic clock (call it) that moves only by :meth:`advance` or :meth:`sleep`, with a wall clock a fixed
    offset away (:meth:`wall`, for python-can's stamps). ``on_read`` callbacks run at each reading of the clock (a
    device the test plays answers what the driver sent so far) and ``on_sleep`` ones at each sleep, after the time
    moved; both read the time as ``clock.t``."""

    def __init__(self, t: float = 1000.0, wall_offset: float = 1.7e9) -> None:
        self.t = t
        self.wall_offset = wall_offset
        self.on_read: list[Callable[[], None]] = []
        self.on_sleep: list[Callable[[], None]] = []
        self.slept = 0.0
        self._timers: list[tuple[float, int, Callable[[], None]]] = []
        self._order = itertools.count()

    def __call__(self) -> float:
        for hook in self.on_read:
            hook()
        return self.t

    def wall(self) -> float:
        """The wall clock (``time.time``'s stand-in) at this moment."""
        return self.t + self.wall_offset

    def advance(self, dt: float) -> float:
        """Move the clock ``dt`` s on; returns the new time."""
        self.t += dt
        return self.t

    def sleep(self, dt: float) -> None:
        """``time.sleep``'s stand-in: the clock moves ``dt`` s at once, then the ``on_sleep`` callbacks run."""
        self.slept += dt
        self.advance(dt)
        for hook in self.on_sleep:
            hook()

    def call_at(self, t: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` when the clock reaches ``t`` inside a :meth:`wait` (an input that arrives then: a command
        received, a link that goes silent), with ``clock.t`` at exactly ``t``."""
        heapq.heappush(self._timers, (t, next(self._order), fn))

    def wait(self, event: threading.Event, timeout: float) -> bool:
        """``event.wait(timeout)``'s stand-in (:data:`bridge.core.timebase.Wait`): the clock moves to the first
        :meth:`call_at` due within the timeout, runs it, and so on; the wait ends at once when the event is set
        (True), or after ``timeout`` (False)."""
        end = self.t + max(0.0, timeout)
        while not event.is_set() and self._timers and self._timers[0][0] <= end:
            t, _, fn = heapq.heappop(self._timers)
            self.t = max(self.t, t)
            fn()
        if event.is_set():
            return True
        self.slept += end - self.t
        self.t = end
        return False
