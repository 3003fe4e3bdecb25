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
        self._due: list[tuple[float, int, Callable[[], None]]] = []  # (time, order, call): what happens when
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

    def perf(self) -> float:
        """``time.perf_counter``'s stand-in: the same fake time (a duration measured on it is the time moved)."""
        return self.t

    def at(self, t: float, call: Callable[[], None]) -> None:
        """Run ``call`` when a :meth:`wait` reaches time ``t`` (an input that arrives then: it sets the event)."""
        heapq.heappush(self._due, (float(t), next(self._order), call))

    def wait(self, event: threading.Event, timeout: float | None) -> bool:
        """``event.wait(timeout)``'s stand-in: the clock moves to each call due (:meth:`at`) up to ``timeout`` s
        on, running it; True at once when one sets ``event``, else the clock ends ``timeout`` s on (a
        :meth:`sleep`) and it says whether ``event`` is set."""
        if event.is_set():
            return True
        if timeout is None:
            if not self._due:
                raise RuntimeError("a wait without a timeout on a fake clock with nothing due would never end")
            timeout = max(0.0, self._due[0][0] - self.t)
        end = self.t + max(0.0, float(timeout))
        while self._due and self._due[0][0] <= end:
            t, _, call = heapq.heappop(self._due)
            self.t = max(self.t, t)
            call()
            if event.is_set():
                return True
        self.sleep(end - self.t)
        return event.is_set()
