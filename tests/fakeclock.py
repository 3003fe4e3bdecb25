"""A fake monotonic clock for tests of code that takes its clock (the drivers, docs/ARCHITECTURE.md section 4): time
moves only when the test, or the code's injected ``sleep``, moves it, so no such test sleeps or depends on the
machine's load."""

from __future__ import annotations

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
