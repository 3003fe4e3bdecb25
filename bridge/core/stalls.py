"""A loop's stalls, said: why an iteration came late (:class:`StallWatch`: the process's CPU, context switches and
page faults, the machine's steal and I/O stall over the gap, from :class:`Usage`) and, while the loop is blocked,
where it is and where the process's other threads are (:class:`BlockedLoop`; docs/ARCHITECTURE.md, "Threads and
clocks").
"""

from __future__ import annotations

import logging
import os
import resource
import sys
import threading
import traceback
from dataclasses import dataclass
from pathlib import Path

from bridge.core.clock import SYSTEM, Clock


@dataclass(frozen=True)
class Usage:
    """What the process had used by a moment: CPU seconds, context switches it gave up (voluntary: it waited for
    something) and had taken from it (involuntary: the kernel ran another task), major page faults (it waited for
    a page from disk); and, machine-wide, the CPU seconds of steal summed over the CPUs (a virtual machine's CPUs its
    hypervisor did not run; ``/proc/stat``) and each CPU's own (``steal_cpus``: a hypervisor may hold one virtual
    CPU while it runs the others), and the seconds some task was stalled on I/O (``/proc/pressure/io``: unlike the
    CPUs' I/O wait it counts on a busy machine too); None where the kernel does not say."""

    cpu: float
    voluntary: int
    involuntary: int
    major_faults: int
    steal: float | None = None
    io_stall: float | None = None
    steal_cpus: tuple[float, ...] | None = None

    @classmethod
    def now(cls) -> Usage:
        r = resource.getrusage(resource.RUSAGE_SELF)
        total, cpus = _steal()
        return cls(r.ru_utime + r.ru_stime, r.ru_nvcsw, r.ru_nivcsw, r.ru_majflt, total, _io_stall(), cpus)


def _steal() -> tuple[float | None, tuple[float, ...] | None]:
    """The machine's steal so far, CPU seconds summed over its CPUs, and each CPU's (``/proc/stat``; Linux only)."""
    try:
        with open("/proc/stat", "rb") as f:
            total = int(f.readline().split()[8]) / _CLK_TCK
            cpus = []
            for line in f:
                if not line.startswith(b"cpu"):
                    break  # the CPUs' lines come first, each once
                cpus.append(int(line.split()[8]) / _CLK_TCK)
            return total, tuple(cpus) or None
    except (OSError, IndexError, ValueError):
        return None, None


def _io_stall() -> float | None:
    """Seconds so far in which some task of the machine was stalled on I/O (pressure stall information)."""
    try:
        with open("/proc/pressure/io", "rb") as f:
            return int(f.readline().rsplit(b"total=", 1)[1]) / 1e6
    except (OSError, IndexError, ValueError):
        return None


_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


class StallWatch:
    """Says why a loop came back late: ``check(now, usage)`` each iteration returns, when more than ``threshold``
    seconds passed since the last one, a line for the log that tells apart a process that was busy (its own CPU
    time covers the gap), a machine whose hypervisor did not run it (steal: every process on it stood still), one
    virtual CPU its hypervisor held (a thread on it stood still while the others ran: the loop's, or one the loop
    waited for; the line gives the most of one CPU beside the mean), one the kernel did not run (involuntary
    switches, little CPU: the machine was too busy) and one that waited (on a lock, the disk, a page). A robot whose
    controllers' watchdog tripped is explained by it."""

    def __init__(self, threshold: float) -> None:
        self.threshold = float(threshold)
        self.last: tuple[float, Usage] | None = None
        self.stalls = 0

    def check(self, now: float, usage: Usage) -> str | None:
        last, self.last = self.last, (now, usage)
        if last is None or now - last[0] <= self.threshold:
            return None
        self.stalls += 1
        gap, before = now - last[0], last[1]
        cpu = usage.cpu - before.cpu
        inv, vol = usage.involuntary - before.involuntary, usage.voluntary - before.voluntary
        faults = usage.major_faults - before.major_faults
        steal, most, figures = None, None, []
        if usage.steal is not None and before.steal is not None:
            steal = (usage.steal - before.steal) / (os.cpu_count() or 1)
            figures.append(f"{steal:.2f} s steal per CPU")
        if usage.steal_cpus is not None and before.steal_cpus is not None \
                and len(usage.steal_cpus) == len(before.steal_cpus) > 1:
            most = max(a - b for a, b in zip(usage.steal_cpus, before.steal_cpus))
            figures.append(f"{most:.2f} s the most of one CPU")
        if usage.io_stall is not None and before.io_stall is not None:
            figures.append(f"{usage.io_stall - before.io_stall:.2f} s I/O stall")
        machine = f"; the machine: {', '.join(figures)}" if figures else ""
        if cpu >= 0.5 * gap:
            why = "busy: this process computed for most of it"
        elif steal is not None and steal >= 0.5 * gap:
            why = "the machine was not run: its hypervisor held the virtual CPUs"
        elif most is not None and most >= 0.5 * gap:
            why = "one of the machine's virtual CPUs was not run by its hypervisor: a thread on it stood still"
        elif faults:
            why = "waiting for memory pages from disk"
        elif inv > vol:
            why = "not scheduled: the machine's other tasks had the CPU"
        else:
            why = "waiting (a lock, the disk or the interpreter lock)"
        return (f"loop stalled {gap:.2f} s ({why}; {cpu:.3f} s CPU, {inv} involuntary and {vol} voluntary context "
                f"switches, {faults} major page faults{machine})")


class BlockedLoop:
    """Where a loop is stuck, said while it is: :meth:`beat` each iteration; a watcher thread that sees no beat for
    ``threshold`` seconds logs the loop thread's innermost frames once per stall (the stall watch's line, after it,
    gives the figures). A loop blocked on a lock, a file or a native call shows where; a process the kernel or its
    hypervisor did not run shows nothing here, since the watcher did not run either."""

    def __init__(self, threshold: float, stop: threading.Event, logger: logging.Logger, frames: int = 6,
                 clock: Clock = SYSTEM) -> None:
        self.threshold = float(threshold)
        self.stop, self.log, self.frames = stop, logger, int(frames)
        self.clock = clock
        self.last = clock()
        self.reported = False
        self.ident: int | None = None
        self._done = threading.Event()

    def start(self) -> BlockedLoop:
        """Watch the calling thread (the loop's) from a daemon thread until ``stop`` or :meth:`done`."""
        self.ident = threading.get_ident()
        self.last = self.clock()
        threading.Thread(target=self._watch, name="blocked-loop", daemon=True).start()
        return self

    def beat(self) -> None:
        self.last = self.clock()
        self.reported = False

    def done(self) -> None:
        """The loop has ended (what follows it, a shutdown, is not a blocked loop)."""
        self._done.set()

    def where(self) -> str | None:
        """The loop thread's innermost frames, innermost first (None if it is gone)."""
        frame = sys._current_frames().get(self.ident) if self.ident is not None else None
        if frame is None:
            return None
        stack = traceback.extract_stack(frame)[-self.frames:]
        return " <- ".join(f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in reversed(stack))

    def others(self) -> str:
        """The process's other threads, each at its innermost frame (the watcher's own left out): a thread that holds
        what the loop waits for (a lock, or the interpreter lock) is among these, at its last frame. The stall line's
        figures are the whole process's, so they alone do not say which of these the loop waited for."""
        names, me = {t.ident: t.name for t in threading.enumerate()}, threading.get_ident()
        return ", ".join(f"{names.get(i, i)} {Path(f.f_code.co_filename).name}:{f.f_lineno} {f.f_code.co_name}"
                         for i, f in sys._current_frames().items() if i not in (self.ident, me)) or "none"

    def _watch(self) -> None:
        while not (self.clock.wait(self._done, self.threshold / 4) or self.stop.is_set()):
            late = self.clock() - self.last
            if late > self.threshold and not self.reported:
                self.reported = True
                self.log.warning("loop blocked for %.2f s so far, in: %s; the other threads: %s", late, self.where(),
                                 self.others())
