"""A loop that came back late says why: busy, not scheduled, or waiting (bridge.core.stalls.StallWatch). This is
what tells a lab whether a robot whose controllers' watchdog tripped had a slow driver host or an overloaded
machine."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

from bridge.core.stalls import StallWatch, Usage


def test_on_time_iterations_say_nothing_and_a_late_one_says_why() -> None:
    w = StallWatch(0.25)
    assert w.check(0.0, Usage(1.0, 10, 10, 0)) is None
    assert w.check(0.02, Usage(1.001, 11, 10, 0)) is None
    busy = w.check(0.62, Usage(1.5, 11, 14, 0))
    assert busy is not None and busy.startswith("loop stalled 0.60 s (busy") and "0.499 s CPU" in busy
    starved = w.check(1.62, Usage(1.52, 12, 60, 0))
    assert starved is not None and "not scheduled" in starved and "46 involuntary" in starved
    paged = w.check(2.5, Usage(1.53, 13, 61, 7))
    assert paged is not None and "memory pages" in paged and "7 major page faults" in paged
    waiting = w.check(3.5, Usage(1.54, 40, 62, 7))
    assert waiting is not None and "waiting" in waiting
    assert w.stalls == 4


def test_a_machine_its_hypervisor_did_not_run_is_named(monkeypatch) -> None:
    """Steal over the gap (a virtual machine's CPUs not run, every process on it frozen) is the machine's, not the
    process's: named as such, with the figures; an I/O stall alone still reads as waiting, with its figure."""
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    w = StallWatch(0.25)
    w.check(0.0, Usage(1.0, 10, 10, 0, steal=5.0, io_stall=3.0))
    frozen = w.check(1.44, Usage(1.004, 34, 18, 0, steal=7.6, io_stall=3.05))
    assert frozen is not None and "hypervisor" in frozen and "1.30 s steal per CPU, 0.05 s I/O stall" in frozen, frozen
    disk = w.check(2.5, Usage(1.01, 60, 19, 0, steal=7.6, io_stall=4.0))
    assert disk is not None and disk.startswith("loop stalled 1.06 s (waiting") and "0.95 s I/O stall" in disk, disk
    def readable(path: str) -> bool:
        try:
            with open(path, "rb") as f:
                return bool(f.readline())
        except OSError:
            return False

    real = Usage.now()  # where the kernel gives them, the machine's figures are read
    assert (real.steal is not None) == readable("/proc/stat")
    assert (real.io_stall is not None) == readable("/proc/pressure/io")
    if real.steal is not None:  # and each CPU's own, one per CPU /proc/stat lists
        assert real.steal_cpus is not None and len(real.steal_cpus) >= 1 and min(real.steal_cpus) >= 0.0


def test_one_virtual_cpu_its_hypervisor_held_is_named(monkeypatch) -> None:
    """A hypervisor may hold one virtual CPU while it runs the others: a thread on it stands still (the loop's, or
    one the loop waits for) while the process's other threads run on. Over the machine's mean that is only half of
    it on two CPUs, so the line gives the most of one CPU too, and names it where it covers most of the gap."""
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    w = StallWatch(0.25)
    w.check(0.0, Usage(1.0, 10, 10, 0, steal=5.0, steal_cpus=(2.0, 3.0)))
    held = w.check(0.66, Usage(1.027, 142, 30, 0, steal=5.62, steal_cpus=(2.01, 3.61)))
    assert held is not None and "one of the machine's virtual CPUs" in held, held
    assert "0.31 s steal per CPU, 0.61 s the most of one CPU" in held, held
    # the same gap with the steal spread over both CPUs and short of half of it: waiting, as before
    spread = w.check(1.32, Usage(1.05, 270, 31, 0, steal=5.92, steal_cpus=(2.16, 3.76)))
    assert spread is not None and spread.startswith("loop stalled 0.66 s (waiting"), spread
    # a CPU the kernel brought online meanwhile (another count of CPUs): no per-CPU figure, the mean as before
    other = w.check(2.0, Usage(1.06, 280, 32, 0, steal=5.92, steal_cpus=(2.16, 3.76, 0.0)))
    assert other is not None and "the most of one CPU" not in other and "steal per CPU" in other, other


def test_a_process_the_kernel_does_not_run_is_told_apart_from_a_busy_one() -> None:
    """A real process: stopped (SIGSTOP) for 0.6 s while it waited for its input, then computing until it has used
    0.6 s of CPU; its watch reports both gaps from the kernel's own accounting: the first with no CPU to speak of,
    the second with the 0.6 s, busy exactly when that is most of the gap (on a loaded machine the kernel may have run
    other tasks for longer, and then it says so)."""
    code = textwrap.dedent("""
        import sys, time
        from bridge.core.stalls import StallWatch, Usage
        w = StallWatch(0.25)
        w.check(time.monotonic(), Usage.now())
        print("ready", flush=True)
        sys.stdin.readline()  # the parent stops us (SIGSTOP) and continues us, then writes this line
        print(w.check(time.monotonic(), Usage.now()), flush=True)
        t = time.process_time()
        while time.process_time() - t < 0.6:
            pass
        print(w.check(time.monotonic(), Usage.now()), flush=True)
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdin is not None
        assert proc.stdout.readline().strip() == "ready"
        os.kill(proc.pid, signal.SIGSTOP)
        try:
            subprocess.run(["sleep", "0.6"], check=True)
        finally:
            os.kill(proc.pid, signal.SIGCONT)
        proc.stdin.write("go\n")
        proc.stdin.flush()
        stopped, busy = proc.stdout.readline(), proc.stdout.readline()
        assert "loop stalled" in stopped and "busy" not in stopped, stopped
        gap, cpu = (float(x) for x in re.fullmatch(r"loop stalled ([\d.]+) s \(.*; ([\d.]+) s CPU, .*\)\n", busy)
                    .groups())
        assert cpu >= 0.5, busy  # what the kernel counted for the 0.6 s spin (its accounting is tick-grained)
        assert "(busy" in busy or "(not scheduled" in busy, busy
        if abs(cpu - 0.5 * gap) > 0.01:  # the line's figures are rounded: no verdict to check right at the boundary
            assert ("(busy" in busy) == (cpu > 0.5 * gap), busy
    finally:
        proc.kill()
        proc.wait(10)


def test_a_blocked_loop_is_reported_while_it_is_blocked_with_where() -> None:
    """The watcher names the loop's innermost frame (here a lock it waits for) while the loop is still stuck, and
    once per stall, and where the process's other threads are (here the test's, waiting for the report)."""
    import logging
    import threading

    from bridge.core.stalls import BlockedLoop

    records: list[str] = []
    reported = threading.Event()

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record.getMessage())
            reported.set()

    logger = logging.getLogger("test.blocked_loop")
    logger.addHandler(Collect())
    stop, held = threading.Event(), threading.Lock()

    def stuck_on_the_lock() -> None:
        with held:
            pass

    def loop() -> None:
        watch = BlockedLoop(0.5, stop, logger).start()
        watch.beat()
        stuck_on_the_lock()
        watch.beat()
        watch.done()

    held.acquire()
    t = threading.Thread(target=loop)
    t.start()
    try:
        assert reported.wait(30.0), "no report while the loop was blocked"
        assert t.is_alive()  # said while it is blocked, not after
    finally:
        held.release()
        t.join(10.0)
    assert len(records) == 1 and records[0].startswith("loop blocked for "), records
    where, others = records[0].split("; the other threads: ")
    assert Path(__file__).name in where and "stuck_on_the_lock" in where.split(" <- ")[0], records[0]
    assert "MainThread threading.py:" in others and "blocked-loop" not in others, others  # the test, waiting
