"""What every Zenoh node of scmbridge does the same way: decode-and-count subscriptions, a fixed-rate loop with
counted missed deadlines, stop on SIGINT/SIGTERM, a memory report on SIGUSR1, and the Zenoh command-line options.

Callbacks run on Zenoh's threads: they only decode, count and hand the message over; all work is in the node's
loop (docs/ARCHITECTURE.md, "Threads and clocks").
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import queue
import signal
import threading
import tracemalloc
from collections import Counter
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import zenoh
from msgspec import Struct

from bridge.core import lifeline, timebase
from bridge.core import wire as M
from bridge.core.clock import SYSTEM, Clock
from bridge.nodes.zsession import Declared, make_config

log = logging.getLogger("scmbridge.node")
S = TypeVar("S", bound=Struct)
#: samples a queued input holds between two reads (a 10 Hz loop reads ~10 poses and ~5 echoes of a robot each time)
QUEUE_CAPACITY = 1024


def freeze_startup_heap() -> None:
    """Collect once, then move every object alive after a node's start-up (its stores, solvers, sessions, modules)
    out of the garbage collector's reach (``gc.freeze``), so that a full collection scans only what the running
    loop made since. A station of many robots paused in each full collection (docs/BENCHMARKS.md, "Many robots"),
    in whichever thread allocated: the robots queued behind the pause missed their deadlines."""
    gc.collect()
    gc.freeze()


def on_zenoh(fn: Callable[[Any], None]) -> zenoh.handlers.Callback:
    """``fn`` as a Zenoh handler run on Zenoh's own receiving thread, the interpreter lock taken there
    (``zenoh.handlers.Callback(fn, indirect=False)``). A plain function is run by zenoh-python on a Python thread
    started for that one declaration: a many-robot station had several threads per robot, and each thread of a
    process makes every read of its CPU clock slower (the kernel sums over them; the MPC's solver reads it several
    times per solve). Only for a callback that hands over and returns: it never waits on a lock held longer than a
    hand-over, does no I/O and builds nothing big (that goes to an :class:`OffThread`), since every sample Zenoh
    receives waits behind it (docs/ARCHITECTURE.md, "Threads and clocks")."""
    return zenoh.handlers.Callback(fn, indirect=False)


class OffThread:
    """One daemon thread for a process, started by the first job and then kept, running the jobs handed to it in the
    order they were handed: the part of a callback run on Zenoh's thread (:func:`on_zenoh`) that must not run there
    (a store encoded for a query answered while no loop runs, a mission built from its message). A job that raises
    is logged; the thread goes on."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.jobs: queue.SimpleQueue[tuple[Callable[..., None], tuple[Any, ...]]] = queue.SimpleQueue()
        self.lock = threading.Lock()
        self.thread: threading.Thread | None = None

    def __call__(self, fn: Callable[..., None], *args: Any) -> None:
        """Run ``fn(*args)`` on the thread, after the jobs handed before it (returns at once)."""
        self.jobs.put((fn, args))
        if self.thread is None:
            with self.lock:
                if self.thread is None:
                    self.thread = threading.Thread(target=self._run, name=self.name, daemon=True)
                    self.thread.start()

    def _run(self) -> None:
        while True:
            fn, args = self.jobs.get()
            try:
                fn(*args)
            except Exception:
                log.exception("%s: %s failed", self.name, getattr(fn, "__qualname__", fn))


class Inputs:
    """Thread-safe counters of a node's inputs (``malformed_<name>``, ...), shared by its callbacks and its loop, and
    what the node declared (:attr:`declared`: its subscribers, and whatever else it keeps there), which the node
    undeclares when it ends. ``clock``: what stamps a sample's receipt (the node's own clock)."""

    def __init__(self, clock: Clock = SYSTEM) -> None:
        self.clock = clock
        self.lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.declared = Declared()

    def count(self, name: str, n: int = 1) -> int:
        """Add ``n`` to counter ``name``; its new value."""
        with self.lock:
            self.counts[name] += n
            return self.counts[name]

    def snapshot(self) -> dict[str, int]:
        with self.lock:
            return dict(self.counts)

    def subscribe(self, session: zenoh.Session, key: str, kind: type[S], name: str,
                  handler: Callable[[S, float], None], remote_only: bool = False, direct: bool = False) -> Any:
        """Declare a subscriber on ``key`` that decodes (and so validates) each sample as ``kind``; a sample that
        does not decode is counted as ``malformed_<name>`` and dropped; ``handler(msg, receive_time)`` gets the rest.
        ``remote_only``: what this session itself publishes on ``key`` is not delivered (Zenoh's
        ``Locality.REMOTE``): a node that listens on a key it publishes on, for other senders only. ``direct``:
        run on Zenoh's receiving thread (:func:`on_zenoh`), for a ``handler`` that only hands over; else on a
        thread of its own.
        """

        clock = self.clock

        def on_sample(sample: zenoh.Sample) -> None:
            now = clock()
            msg = self.decode(sample, kind, name, key)
            if msg is not None:
                handler(msg, now)

        cb = on_zenoh(on_sample) if direct else on_sample
        if remote_only:
            return self.declared.keep(session.declare_subscriber(key, cb, allowed_origin=zenoh.Locality.REMOTE))
        return self.declared.keep(session.declare_subscriber(key, cb))

    def decode(self, sample: zenoh.Sample, kind: type[S], name: str, key: str) -> S | None:
        """``sample`` decoded (and so validated) as ``kind``; None, counted as ``malformed_<name>``, if it is not."""
        try:
            return M.decode(sample.payload.to_bytes(), kind)
        except M.MessageError as exc:
            self.count(f"malformed_{name}")
            log.debug("dropped %s on %s: %s", kind.__name__, key, exc)
            return None

    def answer(self, session: zenoh.Session, key: str, name: str, handler: Callable[[zenoh.Query], None],
               capacity: int = QUEUE_CAPACITY) -> Any:
        """Declare a queryable on ``key`` whose queries wait in Zenoh's own ring buffer and are answered by
        ``handler(query)`` on a thread of this declaration's own (ended when the queryable is undeclared). With a
        plain function zenoh-python runs it on a thread of its own too, but Zenoh's receiving thread takes the
        interpreter lock to hand each query over: under a flood of queries everything behind them on the same link
        (a person's estop, the station's commands) waited until the whole flood had been handed over
        (docs/SECURITY.md, ``acts_flood_one_identity``). A ring takes a query without Python; past ``capacity``
        waiting, the oldest are dropped (Zenoh ends a dropped query without an answer)."""
        queryable = self.declared.keep(session.declare_queryable(key, zenoh.handlers.RingChannel(capacity)))
        queries = queryable.handler  # (read from the handler: a thread blocked on the queryable's own recv would
        # keep it borrowed, and undeclaring it would fail)

        def run() -> None:
            while True:
                try:
                    query = queries.recv()
                except zenoh.ZError:  # undeclared: the channel closed
                    return
                try:
                    handler(query)
                except Exception:
                    log.exception("query on %s failed", key)
                del query  # a query ends (its asker's get returns) when the last reference to it goes, as after a
                # callback; one the handler keeps to answer later it ends itself (``query.drop()``)

        threading.Thread(target=run, name=f"queries-{name}", daemon=True).start()
        return queryable

    def queue(self, session: zenoh.Session, key: str, kind: type[S], name: str,
              capacity: int = QUEUE_CAPACITY) -> Queued[S]:
        """Declare a subscriber on ``key`` whose samples wait in Zenoh's own ring buffer until the node's loop
        takes them (:meth:`Queued.drain`): for a high-rate input (poses at 100 Hz per robot) read once a tick.
        A Python callback per sample costs its thread the GIL each time, several times what draining costs
        (CHANGELOG.md, "many robots"); a ring never blocks Zenoh's receiving thread (a stalled loop loses the
        oldest samples, not the session). Decoded and counted by :meth:`decode`, as :meth:`subscribe`'s."""
        sub = self.declared.keep(session.declare_subscriber(key, zenoh.handlers.RingChannel(capacity)))
        return Queued(self, sub, kind, name, key)


class Queued(Generic[S]):
    """A queued input (:meth:`Inputs.queue`)."""

    def __init__(self, inputs: Inputs, subscriber: Any, kind: type[S], name: str, key: str) -> None:
        self.inputs, self.subscriber, self.kind, self.name, self.key = inputs, subscriber, kind, name, key

    def drain(self, now: float) -> list[tuple[S, float]]:
        """Every sample waiting, decoded, in arrival order, each with ``now`` as its receipt time (the samples
        arrived since the last read, at most one loop period ago); the malformed ones counted and dropped (by
        :meth:`Inputs.decode`, as a subscription's). The valid ones go through the message's decoder directly: a
        station drains about 15 samples per robot and tick."""
        out: list[tuple[S, float]] = []
        recv, dec = self.subscriber.try_recv, M.decoder(self.kind).decode
        while (sample := recv()) is not None:
            try:
                out.append((dec(sample.payload.to_bytes()), now))
            except M.DECODE_ERRORS:
                self.inputs.decode(sample, self.kind, self.name, self.key)  # counts it, says why, drops it
        return out


class StatusOut:
    """A node's status key (``scm/<robot>/status/<node>``): a publisher, and a queryable that answers with the last
    status put, so that ``scmbridge status`` asks and has every node's answer in one round trip instead of waiting
    up to a second for the next periodic one. :meth:`put` takes the encoded status, as a publisher's does."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.key = key
        self.last: bytes | None = None
        self.lock = threading.Lock()
        self.publisher = session.declare_publisher(key)
        self.queryable = session.declare_queryable(key, on_zenoh(self._on_query))  # a copy under a lock, a reply

    def put(self, payload: bytes) -> None:
        with self.lock:
            self.last = payload
        self.publisher.put(payload)

    def _on_query(self, query: zenoh.Query) -> None:  # Zenoh's thread: the last status as it was sent
        with self.lock:
            last = self.last
        if last is not None:
            query.reply(self.key, last)

    def undeclare(self) -> None:
        self.queryable.undeclare()
        self.publisher.undeclare()


class SendBudget:
    """A token bucket: ``burst`` ticks may follow each other at once, ``rate_hz`` a second on average; over any
    window of T seconds at most ``burst + rate_hz * T`` ticks pass. The driver host's link budget (``max_send_hz``):
    a command that arrives just after a periodic tick is sent at once instead of waiting out a minimum gap
    (docs/ARCHITECTURE.md, "Threads and clocks")."""

    #: tokens short of a whole one that still count as one (rounding of the refill)
    EPS = 1e-9

    def __init__(self, rate_hz: float, burst: int, now: float) -> None:
        self.interval = 1.0 / float(rate_hz)
        self.burst = float(burst)
        self.tokens = self.burst
        self.t = now

    def _refill(self, now: float) -> None:
        if now > self.t:
            self.tokens = min(self.burst, self.tokens + (now - self.t) / self.interval)
            self.t = now

    def ready_at(self, now: float) -> float:
        """The earliest moment from ``now`` at which a tick may pass."""
        self._refill(now)
        short = 1.0 - self.EPS - self.tokens
        return now if short <= 0 else now + short * self.interval

    def take(self, now: float) -> None:
        """A tick passes at ``now``."""
        self._refill(now)
        self.tokens -= 1.0


class FixedRate:
    """The one scheduler of the nodes' loops (the station's, the driver host's): deadlines at ``rate_hz``, an input
    that should be handled now (``wake``), and optionally a budget of ticks (``max_hz``: :class:`SendBudget`).

    The caller ticks once when it builds the scheduler, then calls :meth:`wait` after each tick: it returns True
    when the next deadline is reached (a periodic tick; ``late`` says by how much it was passed) and False when
    ``wake`` was set first. Woken, the deadline stays where it is (the next wait keeps it), or, with ``rephase``,
    the woken tick restarts the period: the next deadline is one period after it (the driver host: a command just
    sent makes the periodic re-send due a period later, not at once). A periodic tick that itself ends past the next
    deadline is counted in ``missed`` and the schedule restarts from now; one late because a woken tick ran over its
    deadline is given at once and keeps the schedule (counted only when a whole period late). With a budget no tick,
    periodic or woken, passes while it is spent: :meth:`wait` returns when one may. ``clock``: the time and the
    waits (its ``wait``); every reading and every wait of the scheduler is the clock's."""

    def __init__(self, rate_hz: float, stop: threading.Event, *, wake: threading.Event | None = None,
                 max_hz: float | None = None, burst: int = 2, rephase: bool = False, clock: Clock = SYSTEM,
                 wait: timebase.Wait | None = None) -> None:
        """``clock``: the loop's own (a test's fake clock); ``wait``: its waits, the clock's own when not given (a
        driver host's plain clock function comes with :mod:`bridge.core.timebase`'s wait)."""
        self.period = 1.0 / float(rate_hz)
        self.stop = stop
        self.wake = wake
        self.rephase = rephase
        self.clock = clock
        self._wait: timebase.Wait = wait if wait is not None else clock.wait
        self.t_next = clock()
        self.missed = 0
        self.late = 0.0  # s the last periodic tick came after its deadline
        self.pending = False  # woken before the deadline: the next wait keeps the same deadline
        self.budget = SendBudget(max_hz, burst, self.t_next) if max_hz is not None else None
        if self.budget is not None:
            self.budget.take(self.t_next)  # the caller's first tick, now

    def wait(self, wake: threading.Event | None = None) -> bool:
        """Sleep to the next deadline, or until ``wake`` (this call's, else the scheduler's) is set; then, with a
        budget, until it allows a tick. True: the tick is periodic; False: woken (handle the input, call again)."""
        wake = wake if wake is not None else self.wake
        was_pending, self.pending = self.pending, False
        if not was_pending:
            self.t_next += self.period
        deadline = self.t_next
        clock, wait = self.clock, self._wait
        now = clock()
        delay = deadline - now
        if delay <= 0:
            if not was_pending or -delay >= self.period:
                self.missed += 1
                self.t_next = now
            periodic = True
        elif wake is not None:
            periodic = not wait(wake, delay)
            now = clock()
        else:
            wait(self.stop, delay)
            periodic = True
            now = clock()
        if self.budget is not None:
            ready = self.budget.ready_at(now)
            while ready > now and not self.stop.is_set():
                wait(self.stop, ready - now)
                now = clock()
                ready = self.budget.ready_at(now)
            self.budget.take(now)
            periodic = periodic or now >= deadline  # the deadline came while the budget was spent: this is it
        if wake is not None:
            wake.clear()  # the tick that follows reads every input handed over until now
        if periodic:
            self.late = max(0.0, now - deadline)
        elif self.rephase:
            self.t_next = now
        else:
            self.pending = True
        return periodic


class StopEvent(threading.Event):
    """The stop of a service: set by a signal (:attr:`why` names it) or by the service itself."""

    why = ""


#: the signals that stop a service (:func:`stop_on_signals`)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_signal_stops: list[StopEvent] = []  # every stop :func:`stop_on_signals` gave in this process
_signal_lock = threading.Lock()  # (taken by callers and the watcher only, never in a signal handler)
_signal_fd: int | None = None  # the pipe's read end the watcher reads; None until the first call


def stop_on_signals() -> StopEvent:
    """An Event set by SIGINT, SIGTERM or SIGHUP (the loop polls it; Zenoh's ``recv`` would ignore SIGINT), the
    signal's name in its ``why`` (the service's last line says it, :func:`stopped_because`). SIGUSR1 writes a memory
    report (:class:`MemoryReport`).

    The handler takes no lock. Python runs it in the main thread between two bytecodes, and that thread may be inside
    ``stop.wait`` holding the event's own lock: a handler that set the event there waited for that lock forever (a
    driver host outlived its killed demo that way, asleep on a futex, seen beside load). So the signal's number goes
    through the interpreter's wake-up pipe (``signal.set_wakeup_fd``, written by its C handler) to a watcher thread,
    which sets every stop of the process from its own thread. A process forked from this one does not inherit it.
    A process tied to its parent (:mod:`bridge.core.lifeline`) whose parent died while it started gets its stop set
    at once: the SIGTERM the kernel sent it then went to the start-up's handler, which may not have stopped it."""
    global _signal_fd
    stop = StopEvent()
    with _signal_lock:
        _signal_stops.append(stop)
        if _signal_fd is None:
            r, w = os.pipe()
            os.set_blocking(w, False)  # the C handler's write never blocks (a full pipe drops the byte, not the signal)
            signal.set_wakeup_fd(w, warn_on_full_buffer=False)
            _signal_fd = r
            threading.Thread(target=_watch_signals, args=(r,), name="signals", daemon=True).start()
            os.register_at_fork(after_in_child=_forget_signals)
    for sig in STOP_SIGNALS:
        signal.signal(sig, _on_stop_signal)
    report = MemoryReport(os.environ.get(MEMORY_REPORT_ENV))
    if os.environ.get(TRACE_MEMORY_ENV) and not tracemalloc.is_tracing():
        tracemalloc.start()  # from here: the node's own allocations, not every import's (MemoryReport)
    signal.signal(signal.SIGUSR1, lambda *_: report.write())
    if lifeline.orphaned():  # the parent died while this process started: its SIGTERM may have been lost meanwhile
        stop.why = stop.why or "SIGTERM (its parent had died)"
        stop.set()
    return stop


def _on_stop_signal(_sig: int, _frame: object) -> None:
    """Nothing here (:func:`stop_on_signals`): the wake-up pipe carries the signal to the watcher. Installed so that
    the signal's default action (ending the process at once, or KeyboardInterrupt) is not taken."""


def _watch_signals(fd: int) -> None:
    """The watcher thread: each stop signal read from the wake-up pipe sets every stop (the first signal names it)."""
    while True:
        try:
            data = os.read(fd, 64)
        except OSError:
            return
        if not data:
            return
        for sig in data:
            if sig not in STOP_SIGNALS:  # (SIGUSR1's report and other handlers' signals come this way too)
                continue
            with _signal_lock:
                stops = list(_signal_stops)
            for stop in stops:
                if not stop.is_set():
                    stop.why = stop.why or signal.Signals(sig).name
                    stop.set()


def _forget_signals() -> None:
    """In a child forked from a process with stops: its signals are its own (the parent's pipe and stops are not)."""
    global _signal_fd, _signal_lock
    signal.set_wakeup_fd(-1)
    _signal_fd, _signal_lock = None, threading.Lock()  # (a thread of the parent may have held it at the fork)
    _signal_stops.clear()
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)


def stopped_because(stop: threading.Event) -> str:
    """Why a service stopped, for its last log line: the signal, or its own end (``--duration``, its work done, a
    failure logged before)."""
    why = getattr(stop, "why", "")
    return f"on {why}" if why else "at its own end (--duration, work done, or the failure logged above)"


MEMORY_REPORT_ENV = "SCMBRIDGE_MEMORY_REPORT"
#: set (to anything): a node traces its allocations from its start, once its modules are imported (MemoryReport)
TRACE_MEMORY_ENV = "SCMBRIDGE_TRACE_MEMORY"


class MemoryReport:
    """``kill -USR1 <pid>`` on a node: where its Python heap grew. The first report is the baseline; each later one
    lists the allocation sites (file:line) that grew most since it, after a garbage collection. It needs
    ``tracemalloc`` on: start the node with ``SCMBRIDGE_TRACE_MEMORY=1`` (tracing from the node's start, once its
    modules are imported: what grows while it runs, at a fraction of the cost and with snapshots of its own heap only)
    or ``PYTHONTRACEMALLOC=1`` (from the interpreter's first import on); without it the report says so and gives the
    RSS only. A report is one JSON line in the log (WARNING: it is asked for), and appended to the file named by
    ``$SCMBRIDGE_MEMORY_REPORT`` when set (``scmbridge bench soak --trace-memory`` reads it).

    The snapshot runs in the node's main thread and pauses its loop for as long as it takes (seconds for a station's
    heap). Ask a station or a tool, not the driver host of a robot that is driving: its link's own watchdogs (an
    ODrive's, 0.5 s) stop the vehicle, and the stop waits for the operator."""

    def __init__(self, path: str | None, top: int = 12) -> None:
        self.path, self.top = path, top
        self.first: tracemalloc.Snapshot | None = None

    def build(self) -> dict[str, Any]:
        out: dict[str, Any] = {"pid": os.getpid(), "rss_mb": rss_mb(), "tracing": tracemalloc.is_tracing()}
        if not tracemalloc.is_tracing():
            out["note"] = (f"start the node with {TRACE_MEMORY_ENV}=1 (or PYTHONTRACEMALLOC=1) to see allocation "
                           "sites")
            return out
        gc.collect()
        snap = tracemalloc.take_snapshot().filter_traces((tracemalloc.Filter(False, tracemalloc.__file__),))
        out["traced_mb"] = round(tracemalloc.get_traced_memory()[0] / 2**20, 2)
        if self.first is None:
            self.first = snap
            out["baseline"] = True
            return out
        diffs = [d for d in snap.compare_to(self.first, "lineno") if d.size_diff > 0][: self.top]
        out["growth"] = [{"site": f"{d.traceback[0].filename}:{d.traceback[0].lineno}",
                          "kb": round(d.size_diff / 1024, 1), "blocks": d.count_diff} for d in diffs]
        return out

    def write(self) -> None:
        try:
            rep = self.build()
            line = json.dumps(rep)
            log.warning("memory report: %s", line)
            if self.path:
                with open(self.path, "a") as f:
                    f.write(line + "\n")
        except Exception:  # a diagnostic must never take the node down
            log.exception("memory report failed")


def rss_mb(pid: int | None = None) -> float | None:
    """VmRSS of ``pid`` (this process by default) in MB, or None if it is gone."""
    return rss_parts(pid).get("rss")


def rss_parts(pid: int | None = None) -> dict[str, float]:
    """VmRSS and its parts (RssAnon: private heap and stacks; RssFile: mapped files and code; RssShmem: shared
    memory, such as Zenoh's shared-memory pools), MB; empty if the process is gone."""
    out: dict[str, float] = {}
    names = {"VmRSS:": "rss", "RssAnon:": "anon", "RssFile:": "file", "RssShmem:": "shmem"}
    try:
        with open(f"/proc/{pid or 'self'}/status") as f:
            for line in f:
                key = line.split(maxsplit=1)[0] if line.strip() else ""
                if key in names:
                    out[names[key]] = round(int(line.split()[1]) / 1024, 1)
    except OSError:
        return {}
    return out


def add_zenoh_args(ap: argparse.ArgumentParser) -> None:
    """The Zenoh options every node takes."""
    ap.add_argument("--listen", action="append", default=[], help="Zenoh endpoint to listen on (repeatable)")
    ap.add_argument("--connect", action="append", default=[], help="Zenoh endpoint to connect to (repeatable)")
    ap.add_argument("--mode", choices=["peer", "client", "router"], default="peer", help="Zenoh session mode")
    ap.add_argument("--zenoh-config", help="a Zenoh JSON5 config file (deploy/zenoh/); the endpoints above override it")


def zenoh_config(args: argparse.Namespace) -> zenoh.Config:
    return make_config(mode=args.mode, listen=args.listen, connect=args.connect, config_file=args.zenoh_config)


def endpoints_tried(args: argparse.Namespace) -> str:
    """The endpoints a session made from ``args`` tries, in words (for the no-station error)."""
    eps = [*args.connect, *(f"listening on {e}" for e in args.listen)]
    if args.zenoh_config:
        eps.insert(0, f"the endpoints of {args.zenoh_config}")
    if not eps:
        return "no endpoint (multicast scouting is off: give --connect tcp/HOST:PORT)"
    return ", ".join(eps)


__all__ = ["FixedRate", "Inputs", "MemoryReport", "SendBudget", "StatusOut", "StopEvent", "add_zenoh_args",
           "endpoints_tried", "rss_mb", "rss_parts", "stop_on_signals", "stopped_because", "zenoh_config"]
