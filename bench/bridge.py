"""``scmbridge bench bridge``: end-to-end latency and loop timing of the bridge over Zenoh on loopback (JSON).

A Zenoh router on a free 127.0.0.1 port (this process, standing in for the station) and the driver host as its own
process (``--emulate``: the learner's motor controllers on a python-can virtual channel inside it). Commands are
published at 50 Hz; the latency is from the publish to the driver host handing the frames to the bus (its
``applied`` echo carries the command's sequence number and the time, on the same monotonic clock since both run
on this machine). The driver host's loop runs at 50 Hz for the whole run: jitter and missed deadlines come from
its ``status``; memory is the driver host's RSS at the start and the end of the run. Links: ``can`` (controllers
inside the driver host), ``udp`` and ``mavlink`` (the emulated robot / rover as its own process). The time to the
emulated device receiving a command is not measured here (it is another process).

``--beside-station N``: a real ``scmbridge station --robots`` process ticks N robots on the same router and machine
for the whole run, driving the fleet bench's simulated robots (:mod:`bench.fleet`: one process publishing their
poses, echoes and statuses as driver hosts do): the latency and the jitter are then measured beside a station's
ticks (its CPU, its Zenoh traffic through the router), as a one-machine lab runs them. The station's own figures
over the run (missed deadlines, tick p99, CPU) are reported beside the link's.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np

from bench.common import emit
from bridge.nodes.driver_config import DriverSection
from bridge.tools.procs import Children, emulated_link, said

#: the driver host's loop rate (its default): what its missed deadlines are a fraction of
LOOP_HZ = DriverSection().rate_hz


def _rss_kb(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of process ``pid`` so far (0 if it has gone)."""
    from bench.fleet import _cpu_s as cpu

    return cpu(pid)


class BesideStation:
    """A real station process ticking ``robots`` robots (``side1..sideN``) on the router at ``port``, driving the fleet
    bench's simulated robots (one more process), for ``life`` seconds; :meth:`up` waits until every robot drives,
    :meth:`mark` and :meth:`figures` give the station's missed deadlines, tick p99 and CPU between two moments."""

    def __init__(self, kids: Children, session, port: int, robots: int, workdir: Path, life: float) -> None:
        from bench.fleet import STATION_ENV, write_mission
        from bridge.core import wire as M
        from bridge.nodes.zsession import tcp

        self.M = M
        self.robots = [f"side{k + 1}" for k in range(robots)]
        self.status: dict[str, M.Status] = {}
        self.lock = threading.Lock()
        wd = Path(workdir) / f"beside-{port}"
        wd.mkdir(parents=True, exist_ok=True)
        mission = write_mission(wd / "mission.toml")
        session.declare_subscriber(f"{M.PREFIX}/*/status/station", self._on_status)
        names = ",".join(self.robots)
        kids.spawn(["bench", "fleet", "--simulate", names, "--connect", tcp(port), "--mission", str(mission),
                    "--sim-duration", str(life)], subprocess.DEVNULL)
        self.proc = kids.spawn(["station", "--start", "--robots", names, "--mode", "client", "--connect", tcp(port),
                                "--mission", str(mission), "--duration", str(life)], subprocess.DEVNULL,
                               env=dict(os.environ, **STATION_ENV, SCMBRIDGE_STATE_DIR=str(wd)))
        self.t0: tuple[float, float, dict[str, M.Status]] | None = None

    def _on_status(self, sample) -> None:
        robot = str(sample.key_expr).split("/")[1]
        try:
            st = self.M.decode(sample.payload.to_bytes(), self.M.Status)
        except self.M.MessageError:
            return
        with self.lock:
            self.status[robot] = st

    def up(self, timeout: float) -> bool:
        """Wait until every robot's station says it drives (its status reason ``ok``)."""
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end and self.proc.poll() is None:
            with self.lock:
                if all(r in self.status and self.status[r].reason == "ok" for r in self.robots):
                    return True
            time.sleep(0.1)
        return False

    def mark(self) -> None:
        with self.lock:
            self.t0 = (time.monotonic(), _cpu_s(self.proc.pid), dict(self.status))

    def figures(self) -> dict:
        """The station over the run since :meth:`mark`: ticks, missed deadlines (every robot), worst tick p99, CPU."""
        t1, cpu1 = time.monotonic(), _cpu_s(self.proc.pid)
        with self.lock:
            now = dict(self.status)
        assert self.t0 is not None
        t0, cpu0, before = self.t0
        ticks = missed = 0
        p99 = []
        for r in self.robots:
            a, b = before.get(r), now.get(r)
            if a is None or b is None:
                continue
            ticks += b.counters.get("ticks", 0) - a.counters.get("ticks", 0)
            missed += b.counters.get("missed_deadlines", 0) - a.counters.get("missed_deadlines", 0)
            p99.append(b.latencies_ms.get("tick_p99", float("nan")))
        return {"robots": len(self.robots), "ticks": ticks, "missed_deadlines": missed,
                "tick_p99_ms_worst": round(max(p99), 2) if p99 else None,
                "cpu_cores": round((cpu1 - cpu0) / max(t1 - t0, 1e-9), 3),
                "cpu_ms_per_tick": round((cpu1 - cpu0) / max(ticks, 1) * 1e3, 3)}


#: ``--speed-limiter``: the acceleration and jerk limits the driver host applies to every command (a vehicle's)
LIMITER_KEYS = "v_accel = 1.0\nomega_accel = 2.0\nv_jerk = 10.0\nomega_jerk = 20.0\n"


def run_link(link: str, seconds: float, workdir: str, random_phase: bool = False, beside: int = 0,
             limiter: bool = False, min_latencies: int = 0, min_beside_ticks: int = 0, overtime: float = 60.0) -> dict:
    """Commands at 50 Hz for ``seconds`` through the driver host on ``link``; latency, loop timing, memory.

    The host's loop ticks at 50 Hz too, and it sends at most ``max_send_hz`` (100 Hz): a command that arrives less
    than 10 ms after the last tick waits for the rest of that gap. Commands sent on a steady 50 Hz clock keep one
    phase to the host's ticks for the whole run, so the median is that phase's wait: 0.3 ms in one run, 5 ms in
    the next. ``random_phase`` sends each command at a random point of its 20 ms slot instead (50 Hz on average),
    so every phase is sampled in every run: what ``bench perf`` judges, where a figure must not be a lottery.
    ``beside``: that many robots ticked by a real station process on the same router for the whole run
    (:class:`BesideStation`), which is up and driving before the first command is measured. ``limiter``: the
    driver host limits acceleration and jerk (:data:`LIMITER_KEYS`, CAN only: its ``[driver.hard_limits]``).
    ``min_latencies`` / ``min_beside_ticks``: the commands go on past ``seconds`` (for at most ``overtime`` s more)
    until that many latencies were measured and the station beside ticked that often, so a machine that stalls the
    processes makes the run longer instead of its figures fewer (what a test that needs a count asks for)."""
    rng = np.random.default_rng(0)

    from bridge.core import wire as M
    from bridge.core.wire import Keys, status_key
    from bridge.nodes.zsession import free_port, make_config, open_session, tcp

    port = free_port()
    life = seconds + (overtime if min_latencies or min_beside_ticks else 0.0)  # the longest the commands may go on
    robot = f"bench{link}"
    keys = Keys(robot)
    sent: dict[int, float] = {}
    lat: list[float] = []
    reasons: dict[str, int] = {}  # the echoes by reason: why no latency was measured, when none was
    status: list = []
    lock = threading.Lock()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        def on_applied(sample) -> None:
            a = M.decode(sample.payload.to_bytes(), M.Applied)
            with lock:
                reasons[a.reason] = reasons.get(a.reason, 0) + 1
                if a.cmd_seq is not None and a.reason in ("cmd", "clamped"):
                    t = sent.pop(a.cmd_seq, None)
                    if t is not None:
                        lat.append(a.stamp - t)

        def on_status(sample) -> None:
            st = M.decode(sample.payload.to_bytes(), M.Status)
            with lock:
                status.append(st)

        session.declare_subscriber(keys.applied, on_applied)
        session.declare_subscriber(status_key(robot, "driver"), on_status)
        station = None
        if beside > 0:
            station = BesideStation(kids, session, port, beside, Path(workdir), life + 120 + 10 * beside)
            if not station.up(60.0 + 10.0 * beside):
                raise RuntimeError(f"the station beside the link did not drive its {beside} robot(s) in time")
        driver_args = emulated_link(kids, link, Path(workdir), "0,0,0", life + 40, rate_hz=50)
        if limiter:
            if link != "can":
                raise ValueError("--speed-limiter is measured on the CAN link (its host takes a --config of its own)")
            cfg = Path(workdir) / "driver-limiter.toml"
            cfg.write_text(f"[driver.hard_limits]\nv = [-0.5, 0.5]\nw = [-1.0, 1.0]\n{LIMITER_KEYS}")
            driver_args += ["--config", str(cfg)]
        # its own state and record directories: a bench never reads (nor leaves) a latch of another run
        env = dict(os.environ, SCMBRIDGE_STATE_DIR=str(Path(workdir) / "state"),
                   SCMBRIDGE_RECORD_DIR=str(Path(workdir) / "records"))
        driver = kids.spawn(["driver", "--engage", *driver_args, "--robot", robot, "--mode", "client", "--connect",
                             tcp(port), "--rate", "50", "--duration", str(life + 30)], env=env)
        t_end = time.monotonic() + 30
        while time.monotonic() < t_end:
            with lock:
                if status:
                    break
            time.sleep(0.05)
        rss0 = _rss_kb(driver.pid)
        if station is not None:
            station.mark()
        pub = session.declare_publisher(keys.cmd)
        seq = 0
        t0 = time.monotonic()
        t_next = t0

        def enough() -> bool:
            with lock:
                n = len(lat)
            return n >= min_latencies and (station is None or station.figures()["ticks"] >= min_beside_ticks)

        while time.monotonic() - t0 < seconds or (time.monotonic() - t0 < life and not enough()):
            seq += 1
            now = time.monotonic()
            with lock:
                sent[seq] = now
            w = float(0.05 * np.sin(seq / 50))
            pub.put(M.encode(M.Command(stamp=now, seq=seq, v=0.2, omega=w, method="scm")))
            t_next += 0.02
            jitter = float(rng.uniform(0.0, 0.02)) if random_phase else 0.0
            time.sleep(max(0.0, t_next + jitter - time.monotonic()))
        span = time.monotonic() - t0
        time.sleep(1.2)  # the last commands' echoes (a bench's settling, not a test's wait)
        rss1 = _rss_kb(driver.pid)
        beside_figures = station.figures() if station is not None else None
        driver_said = said(driver, 2000)
    with lock:
        ms = np.array(lat) * 1e3
        last = status[-1] if status else None
    c = last.counters if last else {}
    return {
        "publish_to_driver_send_ms": {"median": float(np.median(ms)), "p99": float(np.percentile(ms, 99)),
                                      "max": float(ms.max()), "n": int(ms.size)} if ms.size else None,
        "commands_sent": seq,
        "loop_50hz": {"jitter_ms": dict(last.latencies_ms) if last else None,
                      "missed_deadlines": c.get("missed_deadlines"),
                      "missed_fraction": c.get("missed_deadlines", 0) / (LOOP_HZ * (span + 1))},
        "driver_rss_kb": {"start": rss0, "end": rss1},
        **({"beside_station": beside_figures} if beside_figures is not None else {}),
        # what a run that measured fewer latencies than asked needs to say why: the echoes' reasons, the host's last
        # word, counters and log
        **({} if ms.size >= max(1, min_latencies) else {"echo_reasons": dict(reasons), "driver_status": last and {
            "state": last.state, "reason": last.reason, "text": last.text, "engaged": last.engaged, "counters": c},
            "driver_said": driver_said}),
    }


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of the CAN run (loop timing and memory)")
    ap.add_argument("--link-duration", type=float, default=15.0, help="seconds of the udp and mavlink runs")
    ap.add_argument("--links", default="can,udp,mavlink")
    ap.add_argument("--beside-station", type=int, default=0, metavar="N",
                    help="a real station process ticks N robots (the fleet bench's simulated ones) on the same "
                         "router for the whole run: the figures beside a station's ticks (default 0: none)")
    ap.add_argument("--speed-limiter", action="store_true",
                    help="the driver host limits acceleration and jerk ([driver.hard_limits] v_accel, omega_accel, "
                         "v_jerk, omega_jerk; CAN link only): what the limiter costs the loop")


def run(args: argparse.Namespace) -> int:
    import tempfile

    out: dict = {"links": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for link in args.links.split(","):
            out["links"][link] = run_link(link, args.duration if link == "can" else args.link_duration, tmp,
                                          beside=args.beside_station, limiter=args.speed_limiter)
    out["beside_station_robots"] = args.beside_station
    out["speed_limiter"] = args.speed_limiter
    out["load"] = [round(a, 2) for a in os.getloadavg()]
    out["targets"] = {"median_ms": 1.0, "p99_ms": 5.0, "jitter_p99_ms": 2.0, "missed_deadlines_fraction": 0.01,
                      "memory": "no growth"}
    emit(out)
    return 0
