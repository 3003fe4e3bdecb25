"""Putting a pose source's own timestamps onto this host's clock (motion capture, docs/ARCHITECTURE.md section 4).

Pairing needs the applied command and the poses on one time base. A motion-capture bridge stamps each sample with
its own clock (the time the camera exposure happened, in whatever epoch), and delivers it over the network with a
variable delay. :class:`ClockOffset` keeps, over a sliding window, the least ``receipt - stamp`` seen: that is the
offset between the two clocks plus the *minimum* transport latency, so ``stamp + offset`` puts each sample at its
true time on this host's clock shifted by that small constant, without the delivery jitter (a late sample keeps its
own time). The constant shifts both ends of a pairing interval alike. Requirements: the minimum latency should be
small next to the pairing interval (a few ms against 100 ms), at least one sample in each window must arrive with
close to that minimum, and the two clocks' drift over the window must be negligible (5 s default: crystal clocks
drift ~50 ppm, 0.25 ms). Rate: at least twice the pairing rate (>= 20 Hz for 0.1 s pairs; mocap gives 100-240 Hz).
Pure: times are arguments.
"""

from __future__ import annotations

from collections import deque

#: a sample that the estimate puts further than this before its receipt restarts it (a few ms is normal)
MAX_AGE = 0.5


class ClockOffset:
    """Sliding-window minimum of ``receipt - stamp`` (see the module docstring); :meth:`restamp_checked` bounds it
    by ``max_age``."""

    def __init__(self, window_s: float = 5.0, max_age: float = MAX_AGE) -> None:
        if not (window_s > 0 and max_age > 0):
            raise ValueError("the window and the maximum age must be positive")
        self.window_s, self.max_age = float(window_s), float(max_age)
        self._d: deque[tuple[float, float]] = deque()  # (receipt, receipt - stamp), offsets increasing

    def reset(self) -> None:
        """Forget the estimate (the sender rebooted: a new clock)."""
        self._d.clear()

    def restamp(self, stamp: float, receipt: float) -> float:
        """The sample's time on the receiver's clock, after learning from this sample too."""
        d = receipt - stamp
        while self._d and self._d[-1][1] >= d:  # a monotone deque: the window's minimum is at the front
            self._d.pop()
        self._d.append((receipt, d))
        while self._d[0][0] < receipt - self.window_s:
            self._d.popleft()
        return stamp + self._d[0][1]

    def restamp_checked(self, stamp: float, receipt: float) -> tuple[float, bool]:
        """:meth:`restamp`, bounded: a result older than ``max_age`` before ``receipt`` means the sender's clock
        jumped (or one stamp was forged ahead and pulled the minimum), so the estimate starts again from this sample,
        which then lands at its receipt. Returns ``(time, True)``, or ``(receipt, False)`` after such a restart."""
        t = min(self.restamp(stamp, receipt), receipt)  # (the sample that sets the minimum: receipt, +- rounding)
        if t >= receipt - self.max_age:
            return t, True
        self.reset()
        self.restamp(stamp, receipt)
        return receipt, False

    @property
    def offset(self) -> float | None:
        return self._d[0][1] if self._d else None
