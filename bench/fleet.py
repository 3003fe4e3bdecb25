"""``scmbridge bench fleet``: how many robots one base station holds at 10 Hz (JSON).

For each fleet size N of a sweep (1, 2, 4, 8, 12, 16, 20, 24, ... up to ``--max-robots``): this process is the Zenoh
router (a free 127.0.0.1 port), N real ``scmbridge station`` processes (MPC N = 20, transfer, pairing; one per
robot ``fleet1..fleetN``, each from an empty pair store, one BLAS thread each as the shipped units run them) are
its clients, and one lightweight process
(``--simulate``, this module) stands in for all N robots' driver hosts: a unicycle per robot integrating the
commands it accepts (through the driver host's own :class:`bridge.core.gate.CommandGate`: its (epoch, seq) stream,
freshness, the deadman, the hard limits), publishing per robot at the driver host's cadence with the emulated CAN
link: ``state`` at 100 Hz, ``applied`` at 50 Hz and at once for each accepted command, an ok ``status/driver``
each second, all as :mod:`bridge.core.wire` messages. It holds the robots with a truthful not-ok status until every
station is up, then lets them all drive at once, so every station plans (the MPC runs) for the whole window; the
mission is the paper's S-path laid end to end five times (40 m), which no robot finishes within a run.

After ``--warmup`` seconds of driving, each station's ``status`` is collected for ``--duration``: missed deadlines
over the window's ticks (every periodic tick publishes one ``cmd``, counted at the hub), the station's own tick
p99 (its last 600 ticks: the window when ``--duration`` >= 60), and, at the hub, the command latency from the
tick's start (the command's stamp) to its arrival. N is held when **every** station missed fewer than 1 % of its
deadlines and its tick p99 is under the period. CPU seconds of the stations, the simulator and this process over
the window give the ticks per core-second; the machine's load and busy cores show what else was running. After each
fleet size, ``bench tick`` runs as many robots as one station process serves, in one process without Zenoh
(``tick_alone``, ``--tick-ticks``), and ``fleet_over_tick`` is the stations' CPU per robot-tick over that process's:
what the fleet costs around its ticks (Zenoh, the loop, the callbacks); then once more paced in real time as a
station's ticks are, their caches cold between periods (``tick_alone_paced``, ``fleet_over_paced_tick``). The
sweep stops at the first N not held (``--keep-going`` runs them all). ``robots_held``: the largest N held with
every smaller N of the sweep held too.

``--layout two-hosts`` (root only): docs/FLEET.md's several base stations on one machine, two ``station --shard``
hosts of N/2 robots each in network namespaces of their own (:mod:`bench.netns`), clients of this process's router
over their own links; after the window ``status --all`` at the router says how many stations answered
(``status_all``). ``estop --all`` needs driver hosts to confirm, which the simulated robots are not:
``tests/integration/test_shards_netns.py`` runs it across both hosts with real driver hosts.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench import netns
from bench.common import emit
from bridge.core.config import StationSection
from bridge.core.errors import UsageError
from bridge.nodes.driver_config import DEFAULT_HARD_LIMITS, DriverSection
from bridge.tools.cli import ONE_BLAS_THREAD

PERIOD_S = 1.0 / StationSection().rate_hz  # the station's default tick
STATE_HZ = 100.0  # the emulated CAN link's poses: each wheel's encoder estimate every 10 ms
APPLIED_HZ = DriverSection().rate_hz  # the driver host's loop
TILES = 5  # the paper's 8 m S-path laid end to end: 40 m, more than a robot drives in one run
#: What the shipped station units (deploy/systemd/scmbridge-station*.service) set: one BLAS / OpenMP thread per
#: station, so that OpenBLAS's spinning workers do not take the cores other stations need (docs/BENCHMARKS.md,
#: "Many robots", has the figures; ``--blas-threads inherit`` measures the default).
STATION_ENV = ONE_BLAS_THREAD


# ------------------------------------------------------------------------------------------- the robots
class SimRobot:
    """One robot as its driver host shows it on the wire: the gate, a unicycle, its keys and sequence numbers."""

    def __init__(self, name: str, x0: tuple[float, float, float], now: float) -> None:
        from bridge.core import wire as M
        from bridge.core.gate import CommandGate

        self.name, self.keys = name, M.Keys(name)
        self.gate = CommandGate(DEFAULT_HARD_LIMITS.bounds(), DriverSection().cmd_timeout)
        self.x, self.y, self.th = (float(a) for a in x0)
        self.v = self.w = 0.0
        self.t = now
        self.epoch = M.new_epoch()
        self.seq = {"state": 0, "applied": 0, "status": 0}
        self.new_cmd = False
        self.pubs: dict = {}

    def integrate(self, now: float) -> None:
        """The unicycle under the command in force since the last call (exact arcs, no drift)."""
        dt = now - self.t
        self.t = now
        if dt <= 0:
            return
        if abs(self.w) < 1e-9:
            self.x += self.v * dt * math.cos(self.th)
            self.y += self.v * dt * math.sin(self.th)
        else:
            th1 = self.th + self.w * dt
            self.x += self.v / self.w * (math.sin(th1) - math.sin(self.th))
            self.y -= self.v / self.w * (math.cos(th1) - math.cos(self.th))
            self.th = th1


class SimFleet:
    """All robots of the bench in one process and one loop (see the module docstring)."""

    def __init__(self, robots: list[str], x0: tuple[float, float, float]) -> None:
        now = time.monotonic()
        self.robots = {r: SimRobot(r, x0, now) for r in robots}
        self.lock = threading.Lock()
        self.wake = threading.Event()
        self.stations_seen: set[str] = set()
        self.released = False

    def on_cmd(self, robot: SimRobot):
        def handler(cmd, now: float) -> None:
            with self.lock:
                if robot.gate.offer(cmd, now):
                    robot.new_cmd = True
            self.wake.set()

        return handler

    def on_station_status(self, sample) -> None:
        robot = str(sample.key_expr).split("/")[1]
        with self.lock:
            self.stations_seen.add(robot)

    def apply(self, r: SimRobot, now: float) -> None:
        """A driver host tick for ``r``: integrate, decide, echo what the vehicle got."""
        from bridge.core import wire as M
        from bridge.core.gate import Decision

        r.integrate(now)
        with self.lock:
            d = r.gate.decide(now)
            r.new_cmd = False
        if not self.released and d.driving:  # held until every station is up (its status says so): no motion
            d = Decision(0.0, 0.0, "operator", d.cmd_seq)
        r.v, r.w = d.v, d.omega
        r.pubs["applied"].put(M.encode(M.Applied(stamp=now, seq=r.seq["applied"], v=d.v, omega=d.omega,
                                                 reason=d.reason, cmd_seq=d.cmd_seq)))
        r.seq["applied"] += 1

    def publish_state(self, r: SimRobot, now: float) -> None:
        from bridge.core import wire as M

        r.integrate(now)
        r.pubs["state"].put(M.encode(M.LearnerState(stamp=now, seq=r.seq["state"], x=r.x, y=r.y, theta=r.th, v=r.v,
                                                    omega=r.w, source="sim", epoch=r.epoch)))
        r.seq["state"] += 1

    def publish_status(self, r: SimRobot, now: float, waiting: int) -> None:
        from bridge.core import wire as M

        with self.lock:
            counters = dict(r.gate.counters)
        text = "link sim: driving" if self.released else f"link sim: waiting for {waiting} more station(s)"
        r.pubs["status"].put(M.encode(M.Status(stamp=now, seq=r.seq["status"], node="driver", ok=self.released,
                                               state="driving" if self.released else "waiting",
                                               reason="ok" if self.released else "not_engaged",
                                               rates_hz={"loop": APPLIED_HZ}, counters=counters, text=text)))
        r.seq["status"] += 1

    def serve(self, session, stop: threading.Event, duration: float) -> None:
        from bridge.core import wire as M
        from bridge.nodes.node import Inputs

        inputs = Inputs()
        for r in self.robots.values():
            inputs.subscribe(session, r.keys.cmd, M.Command, "cmd", self.on_cmd(r))
            r.pubs = {"state": session.declare_publisher(r.keys.state),
                      "applied": session.declare_publisher(r.keys.applied),
                      "status": session.declare_publisher(M.status_key(r.name, "driver"))}
        session.declare_subscriber(f"{M.PREFIX}/*/status/station", self.on_station_status)
        t0 = t_next = time.monotonic()
        t_status = t0
        k = 0
        step = 1.0 / STATE_HZ
        every = max(1, round(STATE_HZ / APPLIED_HZ))
        while not stop.is_set() and time.monotonic() - t0 < duration:
            delay = t_next - time.monotonic()
            if delay > 0 and self.wake.wait(delay):  # a command arrived: apply it now, as the driver host does
                self.wake.clear()
                now = time.monotonic()
                for r in self.robots.values():
                    if r.new_cmd:
                        self.apply(r, now)
                continue
            now = time.monotonic()
            if not self.released:
                with self.lock:
                    waiting = len(set(self.robots) - self.stations_seen)
                if waiting == 0:
                    self.released = True
                    logging.info("every station is up: the %d robots drive", len(self.robots))
            for r in self.robots.values():
                if k % every == 0:
                    self.apply(r, now)
                self.publish_state(r, now)
            if now >= t_status:
                with self.lock:
                    waiting = len(set(self.robots) - self.stations_seen)
                for r in self.robots.values():
                    self.publish_status(r, now, waiting)
                t_status = now + 1.0
            k += 1
            t_next += step
            if t_next < time.monotonic():  # behind: do not burst to catch up
                t_next = time.monotonic() + step


def simulate(args: argparse.Namespace) -> int:
    """``--simulate fleet1,fleet2,...``: the robots' side of the bench as one client process."""
    from bridge.core.config import load_mission
    from bridge.nodes.node import stop_on_signals
    from bridge.nodes.zsession import make_config, open_session

    logging.basicConfig(level=logging.INFO, format="%(asctime)s fleet-sim %(levelname)s %(message)s")
    world = load_mission(args.mission)
    fleet = SimFleet(args.simulate.split(","), tuple(world.start))
    stop = stop_on_signals()
    with open_session(make_config(mode="client", connect=args.connect)) as session:
        fleet.serve(session, stop, args.sim_duration)
    return 0


# ------------------------------------------------------------------------------------------- the mission
def write_mission(path: Path, tiles: int = TILES) -> Path:
    """The paper's S-path (and its obstacles) laid end to end ``tiles`` times along x, as a mission file."""
    from bridge.core.config import load_mission_spec

    spec = load_mission_spec(None)
    x_end = spec.path[-1][0] - spec.path[0][0]
    pts, obs = [], []
    for i in range(tiles):
        off = i * x_end
        pts += [[x + off, y] for x, y in (spec.path if i == 0 else spec.path[1:])]
        obs += [[x + off, y, r] for x, y, r in spec.obstacles]

    def fmt(rows) -> str:
        return "[\n" + "".join("  [" + ", ".join(repr(float(a)) for a in row) + "],\n" for row in rows) + "]"

    path.write_text(f'name = "fleet-bench-s-path-x{tiles}"\nframe = "{spec.frame}"\n'
                    f"goal_tolerance = {spec.goal_tolerance!r}\nstart = [{', '.join(repr(a) for a in spec.start)}]\n"
                    f"obstacles = {fmt(obs)}\npath = {fmt(pts)}\n")
    return path


# ------------------------------------------------------------------------------------------- measuring
_CLK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of process ``pid`` so far (0 if it has gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / _CLK
    except (OSError, IndexError, ValueError):
        return 0.0


def _rss_mb(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def _machine_busy() -> tuple[float, float]:
    """(busy, total) jiffies of all CPUs from /proc/stat."""
    with open("/proc/stat") as f:
        vals = [int(a) for a in f.readline().split()[1:]]
    idle = vals[3] + (vals[4] if len(vals) > 4 else 0)
    total = sum(vals[:8])
    return total - idle, total


def _load() -> list[float]:
    return [round(a, 2) for a in os.getloadavg()]


def run_level(n: int, seconds: float, warmup: float, mission: Path, workdir: Path, log,
              env: dict[str, str] | None = None, layout: str = "processes", shards: int = 2,
              loop_threads: int | None = None) -> dict:
    """N stations and the simulated robots behind one router; the window's figures (see the module docstring).
    ``layout``: ``processes``, a station process per robot; ``one``, every robot in one ``station --robots``;
    ``shards``, the robots split over ``shards`` such processes (as station hosts of a sharded lab would be);
    ``two-hosts``, over two ``station --shard`` hosts each in a network namespace of its own (:mod:`bench.netns`),
    reaching the router over their own links, and ``status --all`` asked at the router after the window."""
    from bridge.core import wire as M
    from bridge.nodes.zsession import free_port, make_config, open_session, tcp
    from bridge.tools.procs import Children

    robots = [f"fleet{k + 1}" for k in range(n)]
    port = free_port()
    status: dict[str, list] = {r: [] for r in robots}
    cmds: dict[str, list[tuple[float, float]]] = {r: [] for r in robots}
    lock = threading.Lock()
    startup_limit = 60.0 + 10.0 * n
    life = startup_limit + warmup + seconds + 30.0
    res: dict = {"robots": n, "held": False, "load_before": _load()}

    def on_status(sample) -> None:
        robot = str(sample.key_expr).split("/")[1]
        try:
            st = M.decode(sample.payload.to_bytes(), M.Status)
        except M.MessageError:
            return
        with lock:
            if robot in status:
                status[robot].append((time.monotonic(), st))

    def on_cmd(sample) -> None:
        now = time.monotonic()
        robot = str(sample.key_expr).split("/")[1]
        try:
            c = M.decode(sample.payload.to_bytes(), M.Command)
        except M.MessageError:
            return
        with lock:
            if robot in cmds:
                cmds[robot].append((c.stamp, now))

    def latest(robot: str):
        with lock:
            return status[robot][-1][1] if status[robot] else None

    t_start = time.monotonic()
    with contextlib.ExitStack() as stack:
        hosts = stack.enter_context(netns.hosts(2)) if layout == "two-hosts" else []
        listen = [tcp(port), *(tcp(port, h.router_addr) for h in hosts)]
        session = stack.enter_context(open_session(make_config(mode="router", listen=listen)))
        kids = stack.enter_context(Children())
        session.declare_subscriber(f"{M.PREFIX}/*/status/station", on_status)
        session.declare_subscriber(f"{M.PREFIX}/*/cmd", on_cmd)
        sim = kids.spawn(["bench", "fleet", "--simulate", ",".join(robots), "--connect", tcp(port), "--mission",
                          str(mission), "--sim-duration", str(life)], log)
        if layout == "two-hosts":  # two station hosts, each in a network namespace of its own (bench/netns.py)
            shards = {f"host{k}": robots[k::2] for k in range(min(2, n))}
            cfg = workdir / "fleet.toml"
            cfg.write_text("[fleet.shards]\n" + "".join(f"{h} = {list(rs)}\n".replace("'", '"')
                                                        for h, rs in shards.items()))
            stations = {h: kids.spawn(["station", "--config", str(cfg), "--shard", h, "--start", "--mode", "client",
                                       "--connect", tcp(port, host.router_addr), "--mission", str(mission),
                                       "--duration", str(life)], log, prefix=host.prefix,
                                      env=dict(env or os.environ, SCMBRIDGE_STATE_DIR=str(workdir / h)))
                        for (h, _), host in zip(shards.items(), hosts)}
        elif layout in ("one", "shards"):  # the pair stores and missions in the state directory (workdir)
            groups = [robots] if layout == "one" else [robots[k::shards] for k in range(min(shards, n))]
            threads = ["--loop-threads", str(loop_threads)] if loop_threads is not None else []
            stations = {f"shard{k}": kids.spawn(["station", "--start", "--robots", ",".join(g), "--mode", "client",
                                                 "--connect", tcp(port), "--mission", str(mission), "--duration",
                                                 str(life), *threads], log,
                                                env=dict(env or os.environ, SCMBRIDGE_STATE_DIR=str(workdir)))
                        for k, g in enumerate(groups)}
        else:
            stations = {r: kids.spawn(["station", "--start", "--robot", r, "--mode", "client", "--connect", tcp(port),
                                       "--store", str(workdir / f"pairs-{r}.bin"), "--mission", str(mission),
                                       "--duration", str(life)], log, env=env) for r in robots}
        # up: every station publishes status and says it is driving (the robots are released together)
        while time.monotonic() - t_start < startup_limit:
            sts = [latest(r) for r in robots]
            if all(s is not None and s.reason == "ok" for s in sts):
                break
            if kids.any_exited():
                break
            time.sleep(0.2)
        else:
            sts = [latest(r) for r in robots]
        up = sum(1 for s in sts if s is not None and s.reason == "ok")
        res["startup_s"] = round(time.monotonic() - t_start, 1)
        if up < n:
            res["failed"] = f"{up} of {n} stations driving after {res['startup_s']} s" + (
                "; a process exited" if kids.any_exited() else "")
            res["exited"] = {name: p.returncode for name, p in {"sim": sim, **stations}.items()
                             if p.poll() is not None}
            return res
        time.sleep(warmup)
        pids = {"stations": [p.pid for p in stations.values()], "sim": [sim.pid], "hub": [os.getpid()]}
        cpu0 = {k: sum(_cpu_s(p) for p in v) for k, v in pids.items()}
        busy0, total0 = _machine_busy()
        t_w0 = time.monotonic()
        time.sleep(seconds)
        t_w1 = time.monotonic()
        cpu1 = {k: sum(_cpu_s(p) for p in v) for k, v in pids.items()}
        busy1, total1 = _machine_busy()
        rss = [_rss_mb(p) for p in pids["stations"]]
        if layout == "two-hosts":  # an operator at the router: every robot of both hosts answers status --all
            res["status_all"] = _status_all(port, robots)
        exited = [r for r, p in stations.items() if p.poll() is not None] + (["sim"] if sim.poll() is not None else [])
    with lock:
        status_c = {r: list(v) for r, v in status.items()}
        cmds_c = {r: list(v) for r, v in cmds.items()}
    per: dict[str, dict] = {}
    for r in robots:
        before = [st for t, st in status_c[r] if t <= t_w0]
        inside = [st for t, st in status_c[r] if t_w0 < t <= t_w1]
        if not inside:
            per[r] = {"failed": "no status in the window"}
            continue
        s0 = before[-1] if before else inside[0]
        s1 = inside[-1]
        ticks = sum(1 for stamp, _ in cmds_c[r] if s0.stamp < stamp <= s1.stamp)
        missed = s1.counters.get("missed_deadlines", 0) - s0.counters.get("missed_deadlines", 0)
        lat = np.array([(t - stamp) * 1e3 for stamp, t in cmds_c[r] if t_w0 < t <= t_w1])
        per[r] = {"ticks": ticks, "missed": missed, "missed_fraction": missed / max(ticks, 1),
                  "tick_p50_ms": s1.latencies_ms.get("tick_p50"), "tick_p99_ms": s1.latencies_ms.get("tick_p99"),
                  "tick_max_ms": s1.latencies_ms.get("tick_max"),
                  "solve_ms_median": s1.latencies_ms.get("solve_median"),
                  "cmd_latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
                  "driving": s1.reason == "ok", "refined_pairs": s1.counters.get("refined_pairs"),
                  # why a robot was not driving at the window's end (its station's own words), else None
                  "not_driving": None if s1.reason == "ok" else f"{s1.reason}: {s1.text}"}
    good = [v for v in per.values() if "failed" not in v]
    window = t_w1 - t_w0
    ticks = sum(v["ticks"] for v in good)
    cpu = {k: (cpu1[k] - cpu0[k]) for k in cpu0}
    busy = (busy1 - busy0) / max(total1 - total0, 1) * (os.cpu_count() or 1)
    res.update({
        "window_s": round(window, 1),
        "stations_reporting": len(good), "stations_driving": sum(1 for v in good if v["driving"]),
        "ticks": ticks, "missed": sum(v["missed"] for v in good),
        "missed_fraction_fleet": round(sum(v["missed"] for v in good) / max(ticks, 1), 4),
        "missed_fraction_worst": round(max((v["missed_fraction"] for v in good), default=1.0), 4),
        "tick_p50_ms_median": _r(np.median([v["tick_p50_ms"] for v in good])) if good else None,
        "tick_p99_ms_worst": _r(max((v["tick_p99_ms"] for v in good), default=math.inf)),
        "tick_max_ms_worst": _r(max((v["tick_max_ms"] for v in good), default=math.inf)),
        "cmd_latency_p99_ms_worst": _r(max((v["cmd_latency_p99_ms"] or math.inf for v in good), default=math.inf)),
        "solve_ms_median": _r(np.median([v["solve_ms_median"] for v in good])) if good else None,
        "cpu_cores": {"stations": _r(cpu["stations"] / window, 3), "sim_robots": _r(cpu["sim"] / window, 3),
                      "hub_router": _r(cpu["hub"] / window, 3), "machine_busy": _r(busy, 3),
                      "others": _r(busy - sum(cpu.values()) / window, 3)},
        "station_cpu_ms_per_tick": _r(cpu["stations"] / max(ticks, 1) * 1e3, 2),
        "ticks_per_core_s": _r(ticks / cpu["stations"], 1) if cpu["stations"] > 0 else None,
        "station_rss_mb_median": _r(np.median([a for a in rss if a is not None])) if any(rss) else None,
        "station_rss_mb_total": _r(sum(a for a in rss if a is not None)) if any(rss) else None,
        "layout": layout,
        "load_after": _load(),
    })
    if exited:
        res["exited"] = exited
    res["held"] = bool(len(good) == n and not exited and res["stations_driving"] == n
                       and res["missed_fraction_worst"] < 0.01 and res["tick_p99_ms_worst"] < PERIOD_S * 1e3)
    res["per_robot"] = per
    return res


def _status_all(port: int, robots: list[str]) -> dict:
    """``scmbridge status --all`` at the router: how many of ``robots`` have their station's row, and how long it
    took."""
    import subprocess

    from bridge.nodes.zsession import tcp

    t0 = time.monotonic()
    try:
        out = subprocess.run([sys.executable, "-m", "bridge", "status", "--all", "--mode", "client", "--connect",
                              tcp(port)], capture_output=True, text=True, timeout=120)
    except subprocess.SubprocessError as exc:
        return {"failed": str(exc)[:300]}
    rows = {tuple(line.split()[:2]) for line in out.stdout.splitlines()}
    return {"exit": out.returncode, "robots": len(robots), "stations_seen": sum((r, "station") in rows for r in robots),
            "seconds": round(time.monotonic() - t0, 1)}


def tick_alone(count: int, ticks: int, level: dict, env: dict[str, str] | None, options: tuple[str, ...] = ()) -> dict:
    """What the fleet's ticks cost alone: ``scmbridge bench tick --count`` (the station's whole tick in one process
    for ``count`` robots, one after the other each period, no Zenoh) run right after the level on the same machine,
    and the fleet's station CPU per robot-tick over it (``fleet_over_tick``: what serving them over Zenoh, the loop
    and the status cost on top of the ticks), with ``bench tick``'s ``reference_ratio`` (the machine's speed before and
    after it, as a multiple of its quiet value: the load the tick alone was measured at). Then the same ticks paced as
    a station's are, each period's at its deadline in real time with the thread asleep between them
    (``tick_alone_paced``, ``bench tick --paced``): their code and data go cold between periods as a station's do, so
    ``fleet_over_paced_tick`` is what the fleet costs around ticks that cost what a station's cost. ``options``: more
    of ``bench tick``'s options."""
    alone = _bench_tick(count, ticks, env, options)
    if "failed" in alone:
        return {"tick_alone": alone}
    paced = _bench_tick(count, ticks, env, (*options, "--paced"))
    fleet = level.get("station_cpu_ms_per_tick")

    def over(tick: dict) -> float | None:
        ms = tick.get("process_ms_per_tick") or 0
        return _r(fleet / ms) if fleet and ms > 0 else None

    return {"tick_alone": alone, "fleet_over_tick": over(alone), "tick_alone_paced": paced,
            "fleet_over_paced_tick": over(paced)}


def _bench_tick(count: int, ticks: int, env: dict[str, str] | None, options: tuple[str, ...]) -> dict:
    """One ``bench tick`` run of ``count`` robots for ``ticks`` ticks after 50 skipped: its CPU per tick and the
    machine's speed around it, or ``{"failed": why}``."""
    import json
    import subprocess

    cmd = [sys.executable, "-m", "bridge", "bench", "tick", "--count", str(count), "--ticks", str(ticks + 50),
           "--skip", "50", "--no-phases", *options]
    paced_s = (ticks + 50) * PERIOD_S if "--paced" in options else 0.0
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=120 + 0.05 * count * ticks + paced_s,
                             env=env, check=True)
        res = json.loads(out.stdout[out.stdout.index("{\n"):])  # past qpOASES's banner (printed on stdout)
    except (subprocess.SubprocessError, ValueError) as exc:
        return {"failed": str(exc)[:300]}
    return {"robots": count, "ticks": res["ticks"], "process_ms_per_tick": res["process_ms_per_tick"],
            **{f"tick_{k}_ms": v for k, v in res["cpu_ms_per_tick"].items()},
            "reference_ratio": res.get("reference_ratio")}


def _r(x, nd: int = 2):
    return None if x is None or not math.isfinite(float(x)) else round(float(x), nd)


def sweep(limit: int) -> list[int]:
    """1, 2, 4, 8, 12, 16, 20, 24, ... up to ``limit`` (and ``limit`` itself)."""
    out = [n for n in (1, 2, 4, 8) if n <= limit]
    n = 12
    while n <= limit:
        out.append(n)
        n += 4
    if limit not in out:
        out.append(limit)
    return out


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--max-robots", type=int, default=24, help="the largest fleet of the sweep")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of the measurement window per fleet size")
    ap.add_argument("--warmup", type=float, default=10.0, help="seconds of driving before the window")
    ap.add_argument("--sizes", default=None, help="fleet sizes to run, comma-separated (default: the sweep)")
    ap.add_argument("--keep-going", action="store_true", help="run every size even after one is not held")
    ap.add_argument("--layout", choices=["processes", "one", "shards", "two-hosts"], default="processes",
                    help="processes: a station process per robot; one: every robot in one `station --robots` process; "
                         "shards: the robots split over --shards such processes; two-hosts: over two `station --shard` "
                         "hosts, each in a network namespace of its own behind the router (needs root)")
    ap.add_argument("--shards", type=int, default=os.cpu_count() or 1, help="station processes of --layout shards "
                    "(default: one per core)")
    ap.add_argument("--loop-threads", type=int, default=None, metavar="N",
                    help="the station processes' `--loop-threads` (layouts one and shards; default: the station's)")
    ap.add_argument("--blas-threads", choices=["1", "inherit"], default="1",
                    help="1: the stations run as the shipped units run them (OPENBLAS_NUM_THREADS=1, "
                         "OMP_NUM_THREADS=1); inherit: OpenBLAS's default, one thread per core")
    ap.add_argument("--tick-ticks", type=int, default=200, metavar="N",
                    help="after each fleet size, `bench tick` of as many robots as one station process serves, for N "
                         "ticks, back to back and then paced: the tick alone, and the fleet's cost over it (0: not "
                         "measured)")
    ap.add_argument("--simulate", default=None, help=argparse.SUPPRESS)  # the robots' process: fleet1,fleet2,...
    ap.add_argument("--connect", action="append", default=[], help=argparse.SUPPRESS)
    ap.add_argument("--mission", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--sim-duration", type=float, default=600.0, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    if args.simulate:
        return simulate(args)
    if args.max_robots < 1:
        raise UsageError("--max-robots must be at least 1")
    if args.layout == "two-hosts" and (why := netns.unavailable()):
        raise UsageError(f"--layout two-hosts: network namespaces cannot be made here: {why}")
    sizes = [int(a) for a in args.sizes.split(",")] if args.sizes else sweep(args.max_robots)
    # `scmbridge` sets one BLAS thread for every command it runs (bridge/cli.py) unless the environment says
    # otherwise; "inherit" asks for OpenBLAS's own default, a thread per core, explicitly
    cores = str(os.cpu_count() or 1)
    env = dict(os.environ, **(STATION_ENV if args.blas_threads == "1" else
                               {"OPENBLAS_NUM_THREADS": cores, "OMP_NUM_THREADS": cores}))
    out: dict = {"rate_hz": 1 / PERIOD_S, "period_ms": PERIOD_S * 1e3, "mpc_horizon": StationSection().horizon,
                 "criterion": {"missed_fraction_every_station": "< 0.01", "tick_p99_ms_every_station": "< 100"},
                 "duration_s": args.duration, "warmup_s": args.warmup, "cpus": os.cpu_count(), "load_start": _load(),
                 "station_env": {k: env[k] for k in STATION_ENV},
                 "levels": []}
    held = 0
    with tempfile.TemporaryDirectory(prefix="scm-fleet-") as tmp:
        mission = write_mission(Path(tmp) / "fleet_mission.toml")
        with open(Path(tmp) / "fleet.log", "w") as log:
            for n in sizes:
                wd = Path(tmp) / f"n{n}"
                wd.mkdir()
                t0 = time.monotonic()
                level = run_level(n, args.duration, args.warmup, mission, wd, log, env, args.layout, args.shards,
                                  args.loop_threads)
                level["wall_s"] = round(time.monotonic() - t0, 1)
                if args.tick_ticks > 0 and "failed" not in level:
                    per_process = {"one": n, "shards": math.ceil(n / max(1, min(args.shards, n))),
                                   "two-hosts": math.ceil(n / 2)}.get(args.layout, 1)
                    level.update(tick_alone(per_process, args.tick_ticks, level, env))
                out["levels"].append(level)
                brief = {k: level.get(k) for k in ("robots", "held", "missed_fraction_worst", "tick_p99_ms_worst",
                                                   "ticks_per_core_s", "station_cpu_ms_per_tick", "tick_alone",
                                                   "fleet_over_tick", "fleet_over_paced_tick", "cpu_cores",
                                                   "failed")}
                print(f"fleet of {n}: {brief}", file=sys.stderr, flush=True)
                if level["held"] and held == sizes.index(n):
                    held = sizes.index(n) + 1
                if not level["held"] and not args.keep_going:
                    break
            if not out["levels"] or any(lv.get("exited") for lv in out["levels"]) or "failed" in out["levels"][0]:
                log.flush()
                text = (Path(tmp) / "fleet.log").read_text()
                crash = text.find("Fatal Python error")  # a crashed process's stack (faulthandler), else the end
                print(text[crash:crash + 60000] if crash >= 0 else text[-3000:], file=sys.stderr)
    out["robots_held"] = sizes[held - 1] if held else 0
    out["layout"] = args.layout if args.layout != "shards" else f"shards ({args.shards} processes)"
    one = [lv for lv in out["levels"] if lv.get("station_rss_mb_total") is not None]
    if args.layout == "one" and len(one) >= 2:  # what each added robot costs the one process
        a, b = one[0], one[-1]
        out["rss_mb_per_added_robot"] = _r((b["station_rss_mb_total"] - a["station_rss_mb_total"])
                                           / max(b["robots"] - a["robots"], 1))
    tpc = [lv["ticks_per_core_s"] for lv in out["levels"] if lv.get("ticks_per_core_s")]
    if tpc:
        best = float(np.median(tpc))
        out["scaling"] = {"ticks_per_core_s_median": round(best, 1),
                          "robots_per_core_at_10hz": round(best * PERIOD_S, 1),
                          "note": "a station's CPU per tick (MPC solve, transfer, pairing, Zenoh, status); "
                                  "a machine's robots at 10 Hz ~ free cores x robots_per_core, before the deadline "
                                  "tail (p99) binds"}
    out["load_end"] = _load()
    emit(out)
    return 0


