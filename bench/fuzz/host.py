"""The Zenoh inputs: ``cmd`` and ``estop`` payloads into a real driver host process, each counted against the wire
contract and the documented estop latch rule, the ``applied`` echoes checked as they arrive."""

from __future__ import annotations

import contextlib
import json
import math
import os
import random
import subprocess
import threading
import time
from collections import Counter
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import msgspec

from bench.fuzz.harness import Crashes, Tally, result, wait_until
from bench.fuzz.messages import COMMAND, ESTOP, CommandStream, MsgMutator, wire_ok
from bridge.core import wire as M
from bridge.core.acts import ActGuard
from bridge.core.gate import DRIVING
from bridge.nodes.driver_config import DEFAULT_HARD_LIMITS
from bridge.nodes.node import rss_mb

#: the driver host runs with no config file: its hard limits are the defaults
HARD_V, HARD_W = DEFAULT_HARD_LIMITS.v, DEFAULT_HARD_LIMITS.w
GATE_VERDICTS = ("accepted", "out_of_order", "old_epoch", "foreign_epoch", "seq_jump", "stamp_jump")


class HostRig:
    """The driver host as its own process (``--link can --emulate``: the emulated controllers inside it), a client
    of a Zenoh router in this process on a free 127.0.0.1 port. Every ``applied`` echo is checked as it arrives;
    the latest ``state`` and ``status`` are kept. ``with HostRig(workdir, robot) as rig:``; the process is always
    stopped and the session closed."""

    def __init__(self, workdir: Path, robot: str, probe: bool = False, shm: bool = True) -> None:
        self.workdir, self.robot, self.probe, self.shm = Path(workdir), robot, probe, shm
        self.keys = M.Keys(robot)
        self.lock = threading.Lock()
        self.status: M.Status | None = None
        self.states: list[tuple[float, float, float]] = []  # (stamp, x, y), the last 2000
        self.applied = Counter()  # n, bad (did not decode), over_limits, nonzero_stop, by reason
        self.last_driving: tuple[float, float, float] | None = None  # (stamp, v, omega) of the last cmd/clamped echo
        self.proc: subprocess.Popen | None = None
        self.stack = ExitStack()

    # ------------------------------------------------------------------------------------------ life cycle
    def __enter__(self) -> HostRig:
        from bridge.nodes.zsession import free_port, make_config, open_session, tcp
        from bridge.tools.procs import Children

        try:
            port = free_port()
            self.endpoint = tcp(port)
            conf = make_config(mode="router", listen=[tcp(port)])
            conf.insert_json5("transport/shared_memory/enabled", json.dumps(self.shm))  # every hop as the host
            self.session = self.stack.enter_context(open_session(conf))
            kids = self.stack.enter_context(Children())
            k = self.keys
            self.session.declare_subscriber(k.applied, self._on_applied)
            self.session.declare_subscriber(k.state, self._on_state)
            self.session.declare_subscriber(M.status_key(self.robot, "driver"), self._on_status)
            self.log_path = self.workdir / f"driver-{self.robot}.log"
            log = self.stack.enter_context(open(self.log_path, "w"))
            client = ["--mode", "client", "--connect", self.endpoint]
            # the host's session with Zenoh's shared-memory transport on (zenoh's default, which scmbridge's
            # configs turn off) or off, through a lab-style file (a file that sets it is obeyed)
            conf = self.workdir / f"zenoh-{self.robot}.json5"
            conf.write_text(json.dumps({"mode": "client", "scouting": {"multicast": {"enabled": False}},
                                        "transport": {"shared_memory": {"enabled": self.shm}}}))
            client += ["--zenoh-config", str(conf)]
            if self.probe:  # a driver-host-like process of this module that also reports its heap
                self.proc = kids.spawn(["bench", "fuzz", "--probe-host", self.robot, *client], subprocess.PIPE,
                                       stdin=subprocess.PIPE, text=True, bufsize=1)
            else:
                self.proc = kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--robot", self.robot,
                                        *client, "--duration", "86400"],
                                       log)
            if not wait_until(lambda: self.status is not None and self.status.ok, 90.0, 0.05):
                raise RuntimeError(f"the driver host did not come up (log: {self.log_path})")
        except BaseException:
            self.stack.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        if self.probe and self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(OSError, ValueError):
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(timeout=10)
        self.stack.close()

    # ----------------------------------------------------------------------------------------- listeners
    def _on_applied(self, sample) -> None:
        try:
            a = M.decode(sample.payload.to_bytes(), M.Applied)
        except M.MessageError:
            with self.lock:
                self.applied["bad"] += 1  # not finite, or outside the wire's ranges
            return
        with self.lock:
            c = self.applied
            c["n"] += 1
            c[f"reason_{a.reason}"] += 1
            if not (HARD_V[0] <= a.v <= HARD_V[1] and HARD_W[0] <= a.omega <= HARD_W[1]):
                c["over_limits"] += 1
            if a.reason not in DRIVING and (a.v != 0.0 or a.omega != 0.0):
                c["nonzero_stop"] += 1
            if a.reason in DRIVING:
                self.last_driving = (a.stamp, a.v, a.omega)

    def _on_state(self, sample) -> None:
        st = M.decode(sample.payload.to_bytes(), M.LearnerState)
        with self.lock:
            self.states.append((st.stamp, st.x, st.y))
            del self.states[:-2000]

    def _on_status(self, sample) -> None:
        st = M.decode(sample.payload.to_bytes(), M.Status)
        with self.lock:
            self.status = st

    # ------------------------------------------------------------------------------------------- queries
    def counters(self) -> dict[str, int]:
        with self.lock:
            return dict(self.status.counters) if self.status else {}

    def status_after(self, t: float, timeout: float = 5.0) -> dict[str, int]:
        """The counters of the first status stamped after ``t`` (the host's clock is this machine's monotonic)."""
        wait_until(lambda: self.status is not None and self.status.stamp > t, timeout, 0.02)
        return self.counters()

    def rss(self) -> float | None:
        return rss_mb(self.proc.pid) if self.proc else None

    def applied_report(self) -> dict:
        with self.lock:
            return dict(self.applied)

    def vehicle_ok(self) -> bool:
        with self.lock:
            c = self.applied
            return c["bad"] == 0 and c["over_limits"] == 0 and c["nonzero_stop"] == 0

    def crashes(self) -> list[str]:
        """The host process gone, or a traceback / panic in its log."""
        out = []
        if self.proc is not None and self.proc.poll() is not None:
            out.append(f"driver host exited with {self.proc.returncode}")
        if not self.probe:
            with contextlib.suppress(OSError), open(self.log_path, errors="replace") as f:
                for line in f:
                    if "Traceback" in line or "panicked" in line:
                        out.append(line.strip()[:200])
        return out

    def publisher(self, key: str):
        import zenoh

        # BLOCK: a full queue holds the publisher instead of dropping the sample (every payload must arrive)
        return self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)

    # -------------------------------------------------------------------------------------------- driving
    def drives(self, v: float = 0.25, seconds: float = 1.2) -> dict:
        """After a silence longer than the deadman (any fuzzed stream goes quiet), a new station run's commands:
        the echo must say they were applied as sent, and the vehicle's state must move."""
        time.sleep(0.45)
        pub = self.publisher(self.keys.cmd)
        epoch = M.new_epoch()
        t0 = time.monotonic()
        seq = 0
        while time.monotonic() - t0 < seconds:
            seq += 1
            pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=v, omega=0.0, method="scm",
                                       sender="bench", epoch=epoch)))
            time.sleep(0.02)
        time.sleep(0.1)
        with self.lock:
            applied = self.last_driving is not None and self.last_driving[0] > t0 and self.last_driving[1:] == (v, 0.0)
            xy = [(x, y) for t, x, y in self.states if t > t0 + 0.3]
        moved = math.hypot(xy[-1][0] - xy[0][0], xy[-1][1] - xy[0][1]) if len(xy) > 1 else 0.0
        pub.undeclare()
        return {"applied_as_sent": bool(applied), "moved_m": round(moved, 3), "ok": bool(applied and moved > 0.02)}


def _settle(rig: HostRig, total: Callable[[dict], int], target: int, timeout: float) -> dict:
    """Wait until the host's status shows ``total(counters) >= target`` (or the timeout), then one more status."""
    wait_until(lambda: total(rig.counters()) >= target, timeout, 0.05)
    return rig.status_after(time.monotonic(), 3.0)


def _delta(after: dict, before: dict, keys) -> int:
    return sum(after.get(k, 0) - before.get(k, 0) for k in keys)


def fuzz_cmd_payloads(rig: HostRig, n: int, rng: random.Random) -> dict:
    """``n`` payloads on ``cmd``; every one must be counted once: malformed, or one gate verdict."""
    before = rig.counters()
    tally = Tally()
    mut = MsgMutator(rng, COMMAND, CommandStream(rng))
    pub = rig.publisher(rig.keys.cmd)
    bad = 0
    for _ in range(n):
        kind, data = mut.next()
        refused = not wire_ok(data, M.Command)
        tally.add(kind, refused)
        bad += refused
        pub.put(data)
    pub.undeclare()
    keys = ("malformed_cmd", *GATE_VERDICTS)
    after = _settle(rig, lambda c: _delta(c, before, keys), n, 30.0 + n / 2000)
    malformed = _delta(after, before, ("malformed_cmd",))
    verdicts = {k: _delta(after, before, (k,)) for k in GATE_VERDICTS}
    return {"sent": n, "counted": malformed, "expected": bad,
            "exact": malformed == bad and sum(verdicts.values()) == n - bad,
            "decoded": n - bad, "gate_verdicts": verdicts, "contract_violations": tally.contract_violations(),
            "kinds_sent_refused": tally.report()}


def _estop_dict(rng: random.Random, epoch: int = 0) -> dict:
    """A valid estop payload before mutation; half are acts addressed to the host's start ``epoch`` (most of them
    fresh on its clock, some 30 s old or ahead, some for another start: bridge.core.acts). A fresh echo is 1 s old,
    never "now": the rule and the host read the clock a few ms apart, and an echo between the two would be "not made
    yet" for one and fresh for the other."""
    msg = {"stamp": time.monotonic(), "seq": rng.randrange(1000), "engaged": rng.random() < 0.5,
           "source": rng.choice(["operator", "operator", "fuzzer", "", "station", "Operator", "operator "]),
           "reason": rng.choice(["", "test", "x" * 100])}
    if rng.random() < 0.5:  # a release is taken only addressed, fresh and once: half are
        msg.update(wall_time=time.time(), nonce=M.new_nonce(),
                   target=rng.choice([epoch, epoch, epoch, NOT_THE_HOST]),
                   echo=max(0.0, time.monotonic() - rng.choice([1.0, 1.0, 30.0, -30.0])))
    return msg


#: the model's epoch: no 62-bit epoch a host picks (bridge.core.wire.new_epoch) is this
NOT_THE_HOST = 2**63 - 1


class LatchModel:
    """The documented estop rule (docs/ARCHITECTURE.md section 6), counted as the driver host counts it: anyone
    engages; only a configured source releases, and only fresh and once (``bridge.core.acts``); ``estops`` counts
    engagements of an unlatched host, ``estop_releases`` and ``estop_release_refused`` (a source not configured) or
    ``estop_release_refused_<kind>`` (stale, replayed, not stamped) the releases of a latched one."""

    def __init__(self, release_sources: tuple[str, ...] = ("operator",), epoch: int = NOT_THE_HOST) -> None:
        self.sources = release_sources
        self.latched = False
        self.counts = Counter()
        self.guard = ActGuard(epoch)  # the host's start (its answers name it), so the rule's releases are taken

    def offer(self, e: M.Estop) -> None:
        if e.engaged:
            self.counts["estops"] += not self.latched
            self.latched = True
        elif self.latched:
            why = self.guard.check(e.target, e.echo, e.nonce, e.source, time.monotonic())
            if why is not None:
                self.counts[f"estop_release_refused_{why.kind}"] += 1
            elif e.source in self.sources:
                self.counts["estop_releases"] += 1
                self.latched = False
            else:
                self.counts["estop_release_refused"] += 1


def _cmd_on(rig: HostRig, n: int, rng: random.Random) -> dict:
    t0 = time.monotonic()
    crashes = Crashes()
    rss0 = rig.rss()
    res = fuzz_cmd_payloads(rig, n, rng)
    rss1 = rig.rss()
    drive = rig.drives()
    crashes.events += rig.crashes()
    return result(res.pop("sent"), res.pop("counted"), res.pop("expected"), res.pop("exact"), crashes, t0,
                   (rss0, rss1), "driver host", **res,
                   vehicle={"applied_echoes": rig.applied_report(), "ok": rig.vehicle_ok()}, drives_after=drive)


def _estop_on(rig: HostRig, n: int, rng: random.Random) -> dict:
    """``n`` payloads on ``estop`` (and a station's commands between them): malformed ones counted, the valid ones'
    latch counters as the rule gives them; the operator releases the estop at the end and driving resumes."""
    t0 = time.monotonic()
    crashes = Crashes()
    rss0 = rig.rss()
    before = rig.counters()
    tally = Tally()
    from bridge.tools.estop import latch_states

    answers = latch_states(rig.session, rig.keys.estop, 5.0)
    epoch = next(iter(answers.values())).epoch if answers else NOT_THE_HOST  # the host's start, from its answer
    mut = MsgMutator(rng, ESTOP, lambda: _estop_dict(rng, epoch))
    model = LatchModel(epoch=epoch)
    epub, cpub = rig.publisher(rig.keys.estop), rig.publisher(rig.keys.cmd)
    stream = CommandStream(rng)
    bad = 0
    for _ in range(n):
        kind, data = mut.next()
        try:
            model.offer(M.decode(data, M.Estop))
            refused = False
        except M.MessageError:
            refused = True
        tally.add(kind, refused)
        bad += refused
        epub.put(data)
        if rng.random() < 0.05:
            cpub.put(msgspec.msgpack.encode(stream()))
    latch_keys = ("estops", "estop_releases", "estop_release_refused",
                  *(f"estop_release_refused_{k}" for k in ActGuard(NOT_THE_HOST).refused))
    want = sum(model.counts.values())
    after = _settle(rig, lambda c: _delta(c, before, ("malformed_estop", *latch_keys)), bad + want,
                    30.0 + n / 2000)
    malformed = _delta(after, before, ("malformed_estop",))
    latch = {k: _delta(after, before, (k,)) for k in latch_keys}
    rss1 = rig.rss()
    # the operator releases (a configured source), and a new station run drives
    from bridge.core.acts import address_of, stamped

    for st in latch_states(rig.session, rig.keys.estop, 5.0).values():  # addressed to the host's start
        epub.put(M.encode(stamped(M.Estop(stamp=time.monotonic(), engaged=False, source="operator",
                                          reason="bench"), address_of(st))))
    epub.undeclare()
    cpub.undeclare()
    drive = rig.drives()
    crashes.events += rig.crashes()
    rule = {k: model.counts[k] for k in latch_keys}
    return result(n, malformed, bad, malformed == bad and latch == rule, crashes, t0, (rss0, rss1), "driver host",
                   decoded=n - bad, latch_counters={"host": latch, "rule": rule},
                   contract_violations=tally.contract_violations(), kinds_sent_refused=tally.report(),
                   vehicle={"applied_echoes": rig.applied_report(), "ok": rig.vehicle_ok()}, drives_after=drive)


def fuzz_zenoh(n: int, seed: int, workdir: Path, inputs=("zenoh_cmd", "zenoh_estop")) -> dict:
    """The Zenoh inputs, one after the other into one driver host process (the applied echoes are checked over
    the whole run, so each input's ``vehicle`` covers the ones before it too)."""
    out = {}
    with HostRig(workdir, f"fuzz{os.getpid()}") as rig:
        if "zenoh_cmd" in inputs:
            out["zenoh_cmd"] = _cmd_on(rig, n, random.Random(seed))
        if "zenoh_estop" in inputs:
            out["zenoh_estop"] = _estop_on(rig, n, random.Random(seed + 1))
    return out
