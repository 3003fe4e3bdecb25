"""A log that never holds up the thread that logs (bridge/core/logsink.py): a blocked output costs the caller
nothing, drops are counted and said, a flush orders a later line after the log's, and a forked child writes itself.
The blocked output is a stream whose writes wait on an event, in this process; the real pipe is
tests/integration/test_blocked_log.py."""

from __future__ import annotations

import io
import logging
import os
import threading

import pytest

from bridge.core.logsink import _Sink


class Gate(io.StringIO):
    """A stream whose writes wait until :attr:`open` is set (a pipe nobody reads, journald pushing back)."""

    def __init__(self) -> None:
        super().__init__()
        self.open = threading.Event()
        self.waiting = threading.Event()

    def write(self, s: str) -> int:
        self.waiting.set()
        assert self.open.wait(10), "the test never opened the stream"
        return super().write(s)


def _logger(sink: _Sink, name: str) -> logging.Logger:
    log = logging.getLogger(name)
    log.propagate, log.handlers = False, [sink]
    log.setLevel(logging.INFO)
    return log


def test_a_blocked_output_costs_the_caller_nothing_and_its_drops_are_said_once_it_writes_again() -> None:
    stream = Gate()
    sink = _Sink(logging.Formatter("%(message)s"), stream, capacity=5)
    log = _logger(sink, "logsink-blocked")
    try:
        log.warning("first")
        assert stream.waiting.wait(5)  # the writer holds "first", blocked
        for i in range(20):  # the caller returns every time: 5 queued, 15 dropped and counted
            log.warning("line %d", i)
        assert sink.dropped == 15
        stream.open.set()
        assert sink.flush_queued(5)
        lines = stream.getvalue().splitlines()
        assert lines[0] == "first" and lines[1:7] == [
            "15 log lines dropped: the log's output was blocked (the process went on)",
            "line 0", "line 1", "line 2", "line 3", "line 4"], lines
    finally:
        stream.open.set()
        sink.close_for_exit(2.0)


def test_a_line_is_formatted_when_logged_and_written_in_order() -> None:
    stream = io.StringIO()
    sink = _Sink(logging.Formatter("%(levelname)s %(message)s"), stream)
    log = _logger(sink, "logsink-order")
    values = [1]
    log.info("values %s", values)
    values.append(2)  # logged before the change: the line says what was true when it was logged
    for i in range(100):
        log.info("n %d", i)
    assert sink.flush_queued(5)
    lines = stream.getvalue().splitlines()
    assert lines[0] == "INFO values [1]" and lines[1:] == [f"INFO n {i}" for i in range(100)]
    sink.close_for_exit(2.0)
    log.error("after exit's flush")  # written as it is logged
    assert stream.getvalue().splitlines()[-1] == "ERROR after exit's flush"


def test_a_broken_output_loses_the_line_not_the_process() -> None:
    class Broken(io.StringIO):
        def write(self, s: str) -> int:
            raise BrokenPipeError("reader gone")

    sink = _Sink(logging.Formatter("%(message)s"), Broken())
    log = _logger(sink, "logsink-broken")
    log.warning("lost")
    assert sink.flush_queued(5) and sink.writer.is_alive()
    sink.close_for_exit(2.0)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_a_forked_child_writes_its_lines_itself() -> None:
    r, w = os.pipe()
    stream = os.fdopen(w, "w")
    sink = _Sink(logging.Formatter("%(message)s"), stream)
    log = _logger(sink, "logsink-fork")
    os.register_at_fork(after_in_child=sink.forked)  # as setup() does for the process's sink
    pid = os.fork()
    if pid == 0:  # the child: no writer thread; its line must still come out
        try:
            log.warning("from the child")
        finally:
            os._exit(0)
    os.waitpid(pid, 0)
    stream.close()
    with os.fdopen(r) as f:
        assert f.read() == "from the child\n"
    sink.close_for_exit(2.0)


_SPLIT_CHILD = """
import json, sys, threading
from bridge.core import logsink
logsink.setup("info", "%(message)s")
log = __import__("logging").getLogger("spam")
def spam():
    while True:
        log.warning("w" * 120)
threading.Thread(target=spam, daemon=True).start()
for i in range(3000):
    logsink.print_line("PROBE " + json.dumps({"i": i, "pad": "x" * 700}))
"""


def test_a_printed_line_is_never_split_by_the_log_writers_lines() -> None:
    """stdout and stderr into one pipe, Python unbuffered (as pytest-xdist's workers run their children): each line
    ``print_line`` writes reaches the reader whole while the log's writer thread writes beside it."""
    import json
    import subprocess
    import sys

    env = dict(os.environ, PYTHONUNBUFFERED="1")
    out = subprocess.run([sys.executable, "-c", _SPLIT_CHILD], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         env=env, timeout=120, check=True).stdout.decode()
    lines = [line for line in out.splitlines() if line.startswith("PROBE ")]
    assert len(lines) == 3000
    assert [json.loads(line[6:])["i"] for line in lines] == list(range(3000))
    assert sum(line.startswith("w") for line in out.splitlines()) > 0  # the log wrote meanwhile
