"""A process's log that never holds up the thread that logs (docs/ARCHITECTURE.md, "Threads and clocks").

A service logs from its control loop (a reason that changed, an estop, a deadman). Written there, a line waits for
stderr: a pipe its reader is not emptying, journald applying back-pressure, a log file on a disk that is flushing under
load. Meanwhile the loop does not tick: a driver host feeds no controller watchdog and a station sends no command,
for as long as the write blocks. So :func:`setup` gives the root logger a handler that formats the line in the
caller (its time is the call's, its values those of the moment) and hands it to one writer thread through a bounded
queue; only that thread writes to stderr.

- A full queue (stderr blocked for :data:`QUEUE_LINES` lines) drops the line and counts it; the writer says how many
  were dropped once it writes again ("N log lines dropped: ..."). A log is never worth a control loop's tick.
- :func:`flush` waits, bounded, until every line logged so far is written: the command-line entry point calls it
  before its own one-line error, so that line comes after the log lines before it.
- At exit the writer gets up to :data:`EXIT_FLUSH_S` to write what is queued (a node's last line, "stopped
  because ..."); a stderr that stays blocked does not keep the process from exiting. What is logged after that, and
  in a child forked from the process (a worker pool, which has no writer thread), is written as it is logged. A
  process killed with SIGKILL loses the lines still queued (the writer runs a line behind the loop, unless stderr is
  blocked).
"""

from __future__ import annotations

import atexit
import logging
import os
import queue
import sys
import threading
from typing import TextIO

#: lines the queue holds while stderr is blocked (about a megabyte of typical lines)
QUEUE_LINES = 10_000
#: seconds the writer gets at exit to write what is still queued
EXIT_FLUSH_S = 2.0


class _Sink(logging.Handler):
    """Formats in the caller, writes from its own thread (module docstring)."""

    def __init__(self, formatter: logging.Formatter, stream: TextIO | None = None, capacity: int = QUEUE_LINES) -> None:
        super().__init__()
        self.setFormatter(formatter)
        self.stream = stream  # None: sys.stderr as it is when a line is written
        self.lines: queue.Queue[str | threading.Event | None] = queue.Queue(capacity)
        self.count_lock = threading.Lock()
        self.dropped = 0
        self.direct = False  # written in the caller: after exit's flush, or in a forked child (no writer thread)
        self.writer = threading.Thread(target=self._write_all, name="log-writer", daemon=True)
        self.writer.start()

    def emit(self, record: logging.LogRecord) -> None:
        try:
            line = self.format(record)
        except Exception:
            self.handleError(record)
            return
        if self.direct:
            self._write(line)
            return
        try:
            self.lines.put_nowait(line)
        except queue.Full:
            with self.count_lock:
                self.dropped += 1

    def flush_queued(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s until every line queued before this call is written; whether it was."""
        if not self.writer.is_alive():
            return self.lines.empty()
        mark = threading.Event()
        try:
            self.lines.put(mark, timeout=timeout)
        except queue.Full:
            return False
        return mark.wait(timeout)

    def close_for_exit(self, timeout: float = EXIT_FLUSH_S) -> None:
        """At exit: the writer writes what is queued, within ``timeout`` s, and stops."""
        try:
            self.lines.put(None, timeout=timeout)
        except queue.Full:
            return
        self.writer.join(timeout)
        self.direct = True  # what later exit handlers log is written as they log it

    def forked(self) -> None:
        """In a child forked from this process (a worker pool), which has no writer thread: write in the caller."""
        self.direct = True

    def _write_all(self) -> None:
        while True:
            item = self.lines.get()
            if item is None:
                return
            if isinstance(item, threading.Event):
                item.set()
                continue
            with self.count_lock:
                dropped, self.dropped = self.dropped, 0
            if dropped:
                self._write(f"{dropped} log lines dropped: the log's output was blocked (the process went on)")
            self._write(item)

    def _write(self, line: str) -> None:
        stream = self.stream if self.stream is not None else sys.stderr
        try:
            stream.write(line + "\n")
            stream.flush()
        except (OSError, ValueError):  # a closed or broken stderr: the line is lost, the process goes on
            pass


_sink: _Sink | None = None


def setup(level: str, fmt: str) -> None:
    """The root logger at ``level``, its lines formatted with ``fmt``, written by the writer thread. As
    ``logging.basicConfig``: nothing changes if the root logger already has a handler (a test's capture)."""
    global _sink
    root = logging.getLogger()
    if root.handlers:
        return
    _sink = _Sink(logging.Formatter(fmt))
    root.addHandler(_sink)
    root.setLevel(getattr(logging, level.upper()))
    atexit.register(_sink.close_for_exit)
    os.register_at_fork(after_in_child=_sink.forked)


def flush(timeout: float = EXIT_FLUSH_S) -> bool:
    """Wait up to ``timeout`` s until every line logged so far is written (True at once without :func:`setup`)."""
    return True if _sink is None else _sink.flush_queued(timeout)


def print_line(text: str, stream: TextIO | None = None) -> None:
    """``text`` and its newline written in one call, then flushed (``stream``: ``sys.stdout`` as it is now).

    A line a program prints for a reader (a JSON summary, a probe's answer) must not be split by the log writer's
    lines: with stdout and stderr into one pipe (a child spawned with ``stderr=STDOUT``, a unit's journal) and Python
    unbuffered (``PYTHONUNBUFFERED=1``, which pytest-xdist's workers pass on to their children), ``print`` writes its
    parts (and the newline) one system call each, and a log line written meanwhile lands inside the line. One write
    of a line shorter than the pipe's atomic size (4096 bytes on Linux) reaches the pipe whole."""
    out = sys.stdout if stream is None else stream
    out.write(text + "\n")
    out.flush()


__all__ = ["EXIT_FLUSH_S", "QUEUE_LINES", "flush", "print_line", "setup"]
