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

:meth:`ClockOffset.judge` also catches what a window minimum alone lets through for a whole window: one sample
stamped ahead (forged, or the sender's clock stepped forward) would pull the minimum and shift every later sample;
a clock stepped back would leave every later sample early until the old minimum leaves the window. A sample whose
``receipt - stamp`` lies more than ``step`` below the estimate is dropped; ``confirm`` samples in a row that agree
on a new offset below it, or more than ``back_step`` above it (a step back; smaller lateness is delivery: samples
read in one batch, a busy radio), restart the estimate from them, within a few samples.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from bridge.core import timebase
from bridge.core.timebase import Event

#: a sample whose offset differs from the estimate by more than this is odd (delivery jitter is a few ms), s
STEP = 0.05
#: a sample later than this behind the estimate is odd: a clock stepped back, or a long stall, s
BACK_STEP = 0.2
#: odd samples in a row that agree on a new offset: the sender's clock stepped
CONFIRM = 3


class ClockOffset:
    """Sliding-window minimum of ``receipt - stamp`` with step detection (see the module docstring)."""

    def __init__(self, window_s: float = 5.0, step: float = STEP, back_step: float = BACK_STEP,
                 confirm: int = CONFIRM) -> None:
        if not (window_s > 0 and step > 0 and back_step > 0 and confirm >= 1):
            raise ValueError("the window and the steps must be positive, confirm at least 1")
        self.window_s, self.step, self.back_step = float(window_s), float(step), float(back_step)
        self.confirm = int(confirm)
        self._d: deque[tuple[float, float]] = deque()  # (receipt, receipt - stamp), offsets increasing
        self._odd: list[tuple[str, float]] = []  # (ahead | behind, receipt - stamp) of the odd samples in a row

    def reset(self) -> None:
        """Forget the estimate (the sender rebooted: a new clock)."""
        self._d.clear()
        self._odd.clear()

    def judge(self, stamp: float, receipt: float) -> tuple[float | None, str]:
        """The sample's time on this clock and the verdict: ``ok``; ``dropped`` (time None, not to be used: stamped
        ahead of any possible delivery, or later than ``back_step``, and not yet confirmed as a step);
        ``restarted`` (``confirm`` samples agreed on a new offset: the sender's clock stepped; the estimate starts
        again from them, this one at its receipt)."""
        d = receipt - stamp
        off = self.offset
        if off is None:
            return min(self.restamp(stamp, receipt), receipt), "ok"
        if off - self.step <= d <= off + self.back_step:
            self._odd.clear()
            return min(self.restamp(stamp, receipt), receipt), "ok"  # a late one keeps its own time
        kind = "ahead" if d < off else "behind"
        run = self._odd
        if run and (run[-1][0] != kind or abs(run[-1][1] - d) > self.step):
            run.clear()
        run.append((kind, d))
        if len(run) >= self.confirm:
            self.reset()
            self.restamp(stamp, receipt)
            return receipt, "restarted"
        return None, "dropped"

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
        """:meth:`judge` for a caller that must place every sample: ``(time, True)`` when it is ok, else
        ``(receipt, False)`` (dropped or restarted: the sample is put at its receipt and counted by the caller)."""
        t, verdict = self.judge(stamp, receipt)
        return (t, True) if verdict == "ok" and t is not None else (receipt, False)

    @property
    def offset(self) -> float | None:
        return self._d[0][1] if self._d else None


@functools.cache
def machine() -> str:
    """This machine and its boot, as a node's status says it (``Status.host``: ``lab-pc/3f2a9c1e``): two nodes
    with the same one share ``time.monotonic()`` (Linux's CLOCK_MONOTONIC counts from the boot), so ``scmbridge
    report`` can tell one machine from two without guessing from the stamps. Read once, when first asked (not when
    this module is imported: importing reads no file)."""
    import socket

    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip().replace("-", "")[:8]
    except OSError:
        boot = "noboot"
    return f"{socket.gethostname()[:55]}/{boot}"



class Clock(Protocol):
    """What a loop of bridge/nodes/ is given to tell the time and to wait (docs/ARCHITECTURE.md, "Threads and
    clocks"): call it for the monotonic time, s; :meth:`wall` the wall clock (a date, for people and files);
    :meth:`perf` a high-resolution counter for a duration's measurement only; :meth:`wait` an event's wait up to
    ``timeout`` s (True: it was set). :data:`SYSTEM` is the host's; tests/fakeclock.py moves only when a test moves
    it, so a loop's timing is tested without sleeping."""

    def __call__(self) -> float: ...

    def wall(self) -> float: ...

    def perf(self) -> float: ...

    def wait(self, event: Event, timeout: float | None) -> bool: ...


class SystemClock:
    """The host's clocks (:class:`Clock`), read through :mod:`bridge.core.timebase`: the one module of the control
    path that reads ``time``, the driver side's clock and wait too."""

    __call__ = staticmethod(timebase.monotonic)
    wall = staticmethod(timebase.wall)
    perf = staticmethod(timebase.perf)
    wait = staticmethod(timebase.wait)


#: the host's clocks: every node's default
SYSTEM = SystemClock()


#: s: a read of the wall clock's offset bracketed tighter than this is believed (:func:`wall_offset`)
OFFSET_BRACKET_S = 1e-3
#: tries at a tight bracket before the tightest is taken
OFFSET_TRIES = 3


def wall_offset(mono: Callable[[], float], wall: Callable[[], float]) -> tuple[float, float]:
    """The ``wall`` clock minus the ``mono`` one (a :class:`Clock` and its ``wall``), and the bracket it was read in
    (s; it is off by at most half of it). Two reads one after the other are off by however long the thread waited
    between them (preempted, or waiting for the interpreter behind another thread); here the monotonic read sits
    between two wall reads, and the tightest of up to :data:`OFFSET_TRIES` brackets is taken (the first under
    :data:`OFFSET_BRACKET_S`)."""
    best = (math.inf, 0.0)
    for _ in range(OFFSET_TRIES):
        w0 = wall()
        m = mono()
        w1 = wall()
        if w1 - w0 < best[0]:
            best = (w1 - w0, 0.5 * (w0 + w1) - m)
        if best[0] < OFFSET_BRACKET_S:
            break
    return best[1], max(best[0], 0.0)


class HeldOffset:
    """The ``wall`` clock minus the ``mono`` one, as :func:`wall_offset` reads it, held from read to read: a read whose
    bracket stayed wide (the thread kept losing the core or the interpreter through every try) keeps the last tight
    one, since the two clocks drift apart slowly; before the first tight read, the narrowest so far. Taking a wide
    read as it came would move a stamp mapped through it by up to half the bracket, and with it the motion between
    two stamps a check of plausibility judges. A step of the wall clock (NTP) is followed at the next tight read."""

    def __init__(self) -> None:
        self.value = 0.0
        self.bracket = math.inf  # the held read's bracket (s)

    def read(self, mono: Callable[[], float], wall: Callable[[], float]) -> float:
        """Read the offset of ``wall`` to ``mono`` again and return the one held (the class docstring)."""
        off, bracket = wall_offset(mono, wall)
        if bracket < OFFSET_BRACKET_S or bracket < self.bracket:
            self.value, self.bracket = off, bracket
        return self.value
