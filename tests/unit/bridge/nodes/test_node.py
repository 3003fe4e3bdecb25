"""The nodes' one scheduler (``bridge.nodes.node.FixedRate``) and its send budget (``SendBudget``): the station ticks
on absolute deadlines; the driver host also at once when woken, re-phasing its period, within the link's budget
(docs/ARCHITECTURE.md, "Threads and clocks"). Only lower bounds of time are asserted (a wait never ends early);
how soon a woken tick comes is the driver host's tests' (tests/integration/test_driver_host.py)."""

from __future__ import annotations

import random
import threading
import time

import numpy as np

from bridge.nodes.node import FixedRate, SendBudget


def test_the_budget_lets_two_through_at_once_then_one_per_interval_and_bounds_every_window() -> None:
    b = SendBudget(100.0, 2, now=0.0)
    assert b.ready_at(0.0) == 0.0
    b.take(0.0)
    assert b.ready_at(0.0) == 0.0  # the burst: a command right after a periodic tick goes at once
    b.take(0.0)
    assert abs(b.ready_at(0.0) - 0.01) < 1e-9  # then 1 / rate_hz
    # greedy sends against requests at random times: over any window of T seconds at most 2 + rate * T
    rng = random.Random(1)
    b, sends, now = SendBudget(100.0, 2, now=0.0), [], 0.0
    for _ in range(5000):
        now += rng.expovariate(300.0) if rng.random() < 0.8 else rng.uniform(0.0, 0.05)
        t = b.ready_at(now)
        b.take(t)
        sends.append(t)
        now = t
    s = np.asarray(sends)
    for n in (2, 3, 10, 100):
        assert (s[n:] - s[:-n]).min() >= (n - 1) / 100.0 - 1e-9, n
    busiest = max(np.searchsorted(s, t + 1.0) - i for i, t in enumerate(s))
    assert busiest <= 2 + 100


def test_woken_ticks_keep_the_deadline_or_rephase_it_and_the_budget_holds() -> None:
    stop, wake = threading.Event(), threading.Event()
    keep = FixedRate(20.0, stop, wake=wake)  # the station: absolute deadlines
    deadline = keep.t_next + keep.period
    wake.set()
    assert keep.wait() is False and not wake.is_set()
    assert keep.wait() is True and keep.t_next == deadline and time.monotonic() >= deadline - 1e-3
    assert keep.missed == 0

    ticker = FixedRate(20.0, stop, wake=wake, max_hz=40.0, rephase=True)  # the driver host
    t_built = ticker.t_next  # the caller's first tick: one of the budget's two
    wake.set()
    t0 = time.monotonic()
    assert ticker.wait() is False
    t1 = time.monotonic()
    assert t0 <= ticker.t_next <= t1  # the woken tick restarted the period: the next deadline is one after it
    wake.set()  # a third tick in a row waits for the budget: 1 / max_hz after the first
    assert ticker.wait() is False and time.monotonic() >= t_built + 1 / 40.0 - 1e-3
    t3 = ticker.t_next
    assert ticker.wait() is True and time.monotonic() >= t3 + ticker.period - 1e-3

def test_a_tick_that_overruns_its_period_is_a_missed_deadline_and_the_schedule_restarts() -> None:
    stop = threading.Event()
    ticker = FixedRate(100.0, stop)
    time.sleep(0.05)  # the tick itself overran several periods
    t = time.monotonic()
    assert ticker.wait() is True and ticker.missed == 1 and ticker.t_next >= t
    assert ticker.late >= 0.05 - ticker.period - 1e-3
    assert ticker.wait() is True and ticker.missed == 1  # back on a schedule from then


def test_freezing_the_start_up_heap_leaves_a_full_collection_only_what_came_after() -> None:
    """``freeze_startup_heap`` (a station's start-up: its stores, solvers and modules out of every later full
    collection). In a child process: freezing pytest's own heap would change every later test's collections."""
    import subprocess
    import sys

    code = (
        "import gc\n"
        "from bridge.nodes.node import freeze_startup_heap\n"
        "startup = [[i] for i in range(50000)]\n"
        "freeze_startup_heap()\n"
        "frozen = gc.get_freeze_count()\n"
        "later = [[i] for i in range(100)]\n"
        "print(frozen >= 50000, len(gc.get_objects()) < frozen // 10)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.split() == ["True", "True"], out.stdout + out.stderr


_HELD_WHEN_SIGNALLED = """
import os, signal, sys, time
from bridge.nodes.node import stop_on_signals, stopped_because
stop, other = stop_on_signals(), stop_on_signals()
with stop._cond:  # as the main thread is inside stop.wait, holding the event's lock, when the signal comes
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(0.3)  # the handler runs here, between two bytecodes of this thread
print("set", stop.wait(10), other.wait(10), stopped_because(stop), flush=True)
"""


_ORPHANED_WHILE_STARTING = """
import os, signal
from bridge.core import lifeline
os.environ[lifeline.PARENT_ENV] = str(os.getppid())
lifeline.hold()
signal.signal(signal.SIGTERM, signal.SIG_IGN)  # as a SIGTERM lost during the start-up
os.getppid = lambda: 1  # the parent died meanwhile: the kernel handed this process to another
from bridge.nodes.node import stop_on_signals, stopped_because
stop = stop_on_signals()
print("set", stop.is_set(), stopped_because(stop), flush=True)
"""


def test_a_process_whose_parent_died_while_it_started_is_stopped_as_soon_as_it_can_stop() -> None:
    """The kernel's SIGTERM for a dead parent may come while the process is still starting, before its stop exists:
    once the stop is made it is set if the parent named in the environment is gone."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _ORPHANED_WHILE_STARTING], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["set", "True", "on", "SIGTERM", "(its", "parent", "had", "died)"]


def test_a_stop_signal_that_comes_while_the_main_thread_holds_the_stops_lock_still_stops_it() -> None:
    """A handler that set the event itself waited for the lock its own thread held, forever (the process asleep on a
    futex); the watcher thread sets it once the lock is free, every stop of the process, named by the signal."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _HELD_WHEN_SIGNALLED], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["set", "True", "True", "on", "SIGTERM"]


_TRACED_FROM_ITS_START = """
import json, tracemalloc
import numpy  # an import before the node starts: not traced
from bridge.nodes.node import MemoryReport, stop_on_signals
before = tracemalloc.is_tracing()
stop_on_signals()
first = MemoryReport(None).build()
hoard = [bytearray(4096) for _ in range(300)]  # about 1.2 MB kept after the start
print(json.dumps({"before": before, "first": first, "traced_mb": tracemalloc.get_traced_memory()[0] / 2**20}))
"""


def test_a_node_started_with_trace_memory_traces_from_its_start_not_its_imports() -> None:
    """``SCMBRIDGE_TRACE_MEMORY=1``: the node traces what it allocates once started (its memory report names the
    sites that grow while it runs), not the allocations of every module it imported first."""
    import json
    import os
    import subprocess
    import sys

    from bridge.nodes.node import TRACE_MEMORY_ENV

    env = {**os.environ, TRACE_MEMORY_ENV: "1"}
    out = subprocess.run([sys.executable, "-c", _TRACED_FROM_ITS_START], capture_output=True, text=True, timeout=60,
                         env=env)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert res["before"] is False and res["first"]["tracing"] is True and res["first"]["baseline"] is True
    assert 1.0 < res["traced_mb"] < 5.0, res  # the hoard, not numpy's or the project's modules (tens of MB)
    plain = subprocess.run([sys.executable, "-c", _TRACED_FROM_ITS_START], capture_output=True, text=True,
                           timeout=60, env={k: v for k, v in env.items() if k != TRACE_MEMORY_ENV})
    assert json.loads(plain.stdout)["first"]["tracing"] is False, plain.stderr
