"""``scmbridge bench estop``: how long an estop takes to reach the vehicle, with the driver host's disk slow (JSON).

A Zenoh router on a free 127.0.0.1 port (this process, standing in for the operator's ``scmbridge estop`` and the
station) and the driver host as its own process (``--link can --emulate --engage``, its state directory a temporary
one, so its estop latch file is its own). Commands stream at 20 Hz; once the host applies them (the vehicle is
driving), each repetition publishes an ``Estop`` (bridge/core/wire.py) and measures the time from that publish to
this process receiving the host's first ``applied`` whose reason is ``estop`` (``CommandGate.decide`` in
bridge/core/gate.py): the stop the link was handed. The receipt is timed, not the ``applied``
stamp: the host stamps a tick when it starts, before the decision that may wait for the latch (both figures are in
the JSON, ``stamp_ms`` is the one the host claims). Between repetitions the estop is released by a configured
release source (``estop_release_sources``, ``operator`` by default) and the bench waits until the host drives again.

The estop latch is kept on the robot's disk (docs/ARCHITECTURE.md, "6. Safety rules": an estop survives a restart),
written with fsyncs. A robot's SD card or a busy disk can take a long time per fsync; ``--fsync-delay S`` measures
that case too: ``strace`` is attached to the host and delays every ``fsync``/``fdatasync`` it makes by S seconds
(``-e inject=fsync:delay_enter=...``; the strace log says how many were delayed). Case ``0`` runs the host as it is,
without strace. Without strace (or where it may not attach) the delayed case is reported as skipped, with why.

Target: an estop reaches the link within 50 ms, whatever the disk does (the vehicle must not drive on while a file is
written).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from bench.common import emit
from bridge.core.gate import DRIVING
from bridge.nodes.driver_config import DriverSection

#: the ``applied`` reason of a tick decided under a latched estop (bridge/core/gate.py, CommandGate.decide)
ESTOP_REASON = "estop"
#: who releases the estop between repetitions: the first source a driver host accepts by default
RELEASE_SOURCE = DriverSection().estop_release_sources[0]
#: publish -> first applied stop, ms
TARGET_MS = 50.0
#: the longest any single wait may take (the host coming up, a stop, driving again), s
WAIT_S = 20.0


class StraceUnavailable(RuntimeError):
    """strace is not installed, or may not attach to the host here (no ptrace permission): the case is skipped."""


class FsyncDelay:
    """``strace -f`` attached to ``pid``, delaying each of its ``fsync``/``fdatasync`` calls by ``delay_s`` until the
    context ends (strace then detaches: the host runs on unaffected). Attached means every thread of the host is
    traced by it (``TracerPid`` in ``/proc``), which is waited for, bounded."""

    def __init__(self, pid: int, delay_s: float, workdir: Path) -> None:
        self.pid, self.delay_s = pid, delay_s
        self.log = Path(workdir) / f"strace-{pid}.log"
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> FsyncDelay:
        exe = shutil.which("strace")
        if exe is None:
            raise StraceUnavailable("strace is not installed (apt-get install strace): the delayed-fsync case needs it")
        us = int(round(self.delay_s * 1e6))
        self.err = tempfile.TemporaryFile()  # noqa: SIM115 (closed in __exit__)
        self.proc = subprocess.Popen(
            [exe, "-f", "-qq", "-o", str(self.log), "-e", "trace=fsync,fdatasync",
             "-e", f"inject=fsync:delay_enter={us}", "-e", f"inject=fdatasync:delay_enter={us}", "-p", str(self.pid)],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self.err, start_new_session=True)
        t_end = time.monotonic() + 10.0
        while not self._attached():
            if self.proc.poll() is not None or time.monotonic() > t_end:
                why = self._said() or f"exit {self.proc.poll()}"
                self.__exit__(None, None, None)
                raise StraceUnavailable(f"strace could not attach to the driver host: {why}")
            time.sleep(0.02)
        return self

    def _attached(self) -> bool:
        assert self.proc is not None
        try:
            tasks = os.listdir(f"/proc/{self.pid}/task")
        except OSError:
            return False
        for tid in tasks:
            try:
                with open(f"/proc/{self.pid}/task/{tid}/status") as f:
                    tracer = next((line.split()[1] for line in f if line.startswith("TracerPid:")), "0")
            except OSError:
                continue  # a thread that ended meanwhile
            if int(tracer) != self.proc.pid:
                return False
        return True

    def _said(self) -> str:
        self.err.seek(0)
        return self.err.read().decode(errors="replace").strip()[-500:]

    def delayed(self) -> int:
        """How many fsync/fdatasync calls strace delayed so far (its log marks each ``(DELAYED)``)."""
        try:
            return self.log.read_text(errors="replace").count("(DELAYED)")
        except OSError:
            return 0

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)  # strace detaches from the host and exits
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self.err.close()


class _Host:
    """What this process sees of the driver host: applied messages (with their receipt time) and status."""

    def __init__(self, session, robot: str) -> None:
        from bridge.core import wire as M

        self.M = M
        self.keys = M.Keys(robot)
        self.lock = threading.Lock()
        self.applied: list[tuple[float, M.Applied]] = []  # (receipt time, message)
        self.subs = [session.declare_subscriber(self.keys.applied, self._on_applied)]
        self.cmd = session.declare_publisher(self.keys.cmd)
        self.estop = session.declare_publisher(self.keys.estop)
        self.session = session
        self.epoch: int | None = None  # the host's start, from its first latch answer (one host process)

    def _on_applied(self, sample) -> None:
        t = time.monotonic()
        a = self.M.decode(sample.payload.to_bytes(), self.M.Applied)
        with self.lock:
            self.applied.append((t, a))

    def first(self, after: float, pred: Callable[[object], bool], timeout: float = WAIT_S) -> tuple[float, object]:
        """The first applied message received after ``after`` for which ``pred`` holds, with its receipt time;
        TimeoutError after ``timeout``."""
        t_end = time.monotonic() + timeout
        while True:
            with self.lock:
                hit = next(((t, a) for t, a in self.applied if t > after and pred(a)), None)
                self.applied = [(t, a) for t, a in self.applied if t > after]  # keep the list short
            if hit is not None:
                return hit
            if time.monotonic() > t_end:
                raise TimeoutError(f"no such applied message within {timeout:g} s")
            time.sleep(0.002)

    def confirm_latch(self, session, timeout: float) -> float:
        """Ask the host for its latch (it answers once what it latched is saved); the time the answer came."""
        for reply in session.get(self.keys.estop, timeout=timeout):
            if reply.ok is not None:
                self.M.decode(reply.ok.payload.to_bytes(), self.M.EstopState)
                return time.monotonic()
        raise TimeoutError(f"the host did not confirm its latch within {timeout:g} s")

    def publish_estop(self, engaged: bool, source: str, reason: str) -> float:
        t = time.monotonic()
        msg = self.M.Estop(stamp=t, engaged=engaged, source=source, reason=reason)
        if not engaged:  # a release is addressed to the host's start (bridge.core.acts)
            from bridge.core.acts import Address, address_of, stamped
            from bridge.tools.estop import latch_states

            if self.epoch is None:  # learned once per host start: its answers are slow while its fsyncs are
                for st in latch_states(self.session, self.keys.estop, 10.0).values():
                    self.epoch = address_of(st).epoch
            if self.epoch is not None:  # the host shares this machine's monotonic clock: echo it as read now
                self.estop.put(self.M.encode(stamped(msg, Address(self.epoch, time.monotonic()))))
            return t
        self.estop.put(self.M.encode(msg))
        return t


def _repetitions(host: _Host, repeat: int) -> dict:
    """``repeat`` estops on a driving vehicle, each released afterwards and driving awaited again."""
    recv, stamp = [], []
    rng = np.random.default_rng(0)
    for i in range(repeat):
        t_rel = host.publish_estop(False, RELEASE_SOURCE, "bench estop: drive again")
        host.first(t_rel, lambda a: a.reason in DRIVING)  # driving (again): the stop below is a real one
        # the estop at a random phase of the host's loop (two 50 Hz periods): right after the applied just seen it
        # would always find the loop just past a tick, waiting out its minimum gap between sends
        time.sleep(rng.uniform(0.0, 0.04))
        t_pub = host.publish_estop(True, "bench", f"bench estop {i}")
        t_recv, a = host.first(t_pub, lambda a: a.reason == ESTOP_REASON)
        recv.append(t_recv - t_pub)
        stamp.append(a.stamp - t_pub)
    ms = np.asarray(recv) * 1e3
    out = {"median_ms": float(np.median(ms)), "max_ms": float(ms.max()), "samples_ms": [round(float(x), 3) for x in ms],
           "stamp_ms": {"median": float(np.median(stamp) * 1e3), "max": float(np.max(stamp) * 1e3)}, "n": int(ms.size)}
    return out


def measure(fsync_delays: Sequence[float], repeat: int) -> dict:
    """The publish -> applied-stop latency over ``repeat`` estops for each fsync delay (0: no strace), one driver
    host for all; ``{"cases": {delay: {...} | {"skipped": why}}, "target_ms", "wall_s"}``."""
    from bridge.nodes.zsession import free_port, make_config, open_session, tcp
    from bridge.tools.procs import Children

    t0 = time.monotonic()
    cases: dict[str, dict] = {}
    robot = f"estop{os.getpid()}"
    stop = threading.Event()
    bound = 30.0 + repeat * sum(2.0 + 4.0 * d for d in fsync_delays) + 5.0 * len(fsync_delays)  # the host's --duration
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="bench-estop-") as tmp, \
            open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        host = _Host(session, robot)
        env = {**os.environ, "SCMBRIDGE_STATE_DIR": str(Path(tmp) / "state"),
               "SCMBRIDGE_RECORD_DIR": str(Path(tmp) / "records")}
        proc = kids.spawn(["driver", "--link", "can", "--emulate", "--x0", "0,0,0", "--engage", "--robot", robot,
                           "--mode", "client", "--connect", tcp(port), "--duration", f"{bound:.0f}"], env=env)

        def drive() -> None:  # the station's stream: a command every 50 ms
            seq = 0
            while not stop.wait(0.05):
                seq += 1
                host.cmd.put(host.M.encode(host.M.Command(stamp=time.monotonic(), seq=seq, v=0.2, omega=0.0,
                                                          method="scm")))

        driver = threading.Thread(target=drive, name="bench-estop-cmd", daemon=True)
        driver.start()
        try:
            try:
                host.first(t0, lambda a: a.reason in DRIVING, timeout=40.0)
            except TimeoutError as exc:
                raise RuntimeError(f"the driver host never drove: {kids.said()}") from exc
            for delay in fsync_delays:
                name = f"{delay:g}"
                try:
                    if delay <= 0:
                        cases[name] = _repetitions(host, repeat)
                        continue
                    with FsyncDelay(proc.pid, delay, Path(tmp)) as slow:
                        case = _repetitions(host, repeat)
                        # the host answers an estop query only once the latch is on disk: the saves (each fsync
                        # delayed) finish under strace, so its log counts them
                        t_q = time.monotonic()
                        case["latch_confirmed_s"] = host.confirm_latch(session, 8.0 * repeat * delay + 10.0)
                        case["latch_confirmed_s"] = round(case["latch_confirmed_s"] - t_q, 3)
                    case["fsyncs_delayed"] = slow.delayed()  # strace has detached: its log is complete
                    cases[name] = case
                except StraceUnavailable as exc:
                    cases[name] = {"skipped": str(exc)}
                except TimeoutError as exc:  # a stop (or driving again) that never came: that case failed
                    cases[name] = {"error": f"{exc}: {kids.said()}"[-3000:]}
        finally:
            stop.set()
            driver.join(timeout=2)
    return {"cases": cases, "fsync_delays_s": list(fsync_delays), "repeat": repeat, "target_ms": TARGET_MS,
            "link": "can", "wall_s": round(time.monotonic() - t0, 1)}


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--fsync-delay", type=float, default=0.5,
                    help="seconds each fsync of the driver host is delayed by in the second case (strace)")
    ap.add_argument("--repeat", type=int, default=5, help="estops per case")


def run(args: argparse.Namespace) -> int:
    if args.repeat < 1 or args.fsync_delay < 0:
        from bridge.core.errors import UsageError

        raise UsageError("--repeat must be at least 1 and --fsync-delay not negative")
    delays = [0.0] if args.fsync_delay == 0 else [0.0, args.fsync_delay]
    out = measure(delays, args.repeat)
    emit(out)
    return 1 if any("error" in c for c in out["cases"].values()) else 0
