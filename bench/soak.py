"""``scmbridge bench soak``: the hardware-in-the-loop loop driving its mission over and over for ``--minutes``.

The processes ``scmbridge demo`` starts, on a free 127.0.0.1 port: the driver host (with the emulated learner on
``--link``: CAN controllers inside it, the UDP robot or the ArduPilot-like rover as a process of their own, see
:func:`bridge.tools.procs.emulated_link`), the station (MPC teacher + transfer, starting with no pairs) and this
process as
the Zenoh router watching them. Laps: each time the station reports the goal reached, this process publishes the
next lap's :class:`bridge.core.wire.MissionSpec` on ``scm/<robot>/mission`` (the station's goal state resets). The
laps go out and back: the mission's own path, then the same path reversed (same obstacles), and so on. Publishing
the unchanged mission again would end the lap at once: the robot stands at its goal, and the goal rule
(:meth:`transfer.mission.Mission.reached`) counts a robot past the path's end as arrived. The processes run for the
whole soak (no restart per lap), so their memory is measured over all of it.

Every ``--sample-s`` (10 s) each process's RSS (``/proc/<pid>/status`` VmRSS, with its RssAnon and RssShmem parts)
is sampled; the trend is the least-squares slope in MB/min over the samples after ``--warmup-s`` (of VmRSS, and of
RssAnon alone: shared memory mapped once, such as a Zenoh pool, is a step, not a trend). Also reported: the laps,
the missed deadlines of the station and the driver host (their status counters, over the soak and per minute), every
counter of their last status, and any child that exited or logged a traceback. JSON on stdout.

``--trace-memory [station,driver]`` runs those nodes under ``tracemalloc`` and asks each for a memory report
(SIGUSR1, :class:`bridge.nodes.node.MemoryReport`) at the end of warm-up and at the end: ``memory_reports`` lists the
Python allocation sites that grew most in between. Growth of the RSS that no site accounts for is outside Python's
heap (native libraries, the allocator keeping freed memory). Traced nodes are slower, and a report pauses its node
for its snapshot, long enough to trip a driving vehicle's watchdog: so by default only the station is traced.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from bridge.core import wire as M
from bridge.core.errors import UsageError
from bridge.nodes.node import rss_parts
from drivers import link_names


def slope_mb_per_min(times_s: list[float], values: list[float | None], warmup_s: float) -> float | None:
    """Least-squares slope of ``values`` against time, MB/min, over the samples at or after ``warmup_s``."""
    pts = [(t, v) for t, v in zip(times_s, values) if t >= warmup_s and v is not None]
    if len(pts) < 2:
        return None
    t, v = np.array(pts).T
    if np.ptp(t) <= 0:
        return None
    return round(float(np.polyfit(t / 60.0, v, 1)[0]), 3)


def lap_spec(spec: M.MissionSpec, lap: int) -> M.MissionSpec:
    """Lap ``lap`` (0: the mission as it is): odd laps follow the path backwards, to the mission's first point."""
    if lap % 2 == 0:
        return msgspec.structs.replace(spec, name=f"{spec.name[:50]}-lap{lap}", start=None)
    return msgspec.structs.replace(spec, name=f"{spec.name[:50]}-lap{lap}", path=list(reversed(spec.path)),
                                   start=None)


class Watch:
    """The latest status of the station and of the driver host, from Zenoh callbacks."""

    def __init__(self, session, robot: str) -> None:
        self.lock = threading.Lock()
        self.status: dict[str, M.Status] = {}
        self.subs = [session.declare_subscriber(M.status_key(robot, node), self._on_status)
                     for node in ("station", "driver")]

    def _on_status(self, sample) -> None:
        try:
            st = M.decode(sample.payload.to_bytes(), M.Status)
        except M.MessageError:
            return
        with self.lock:
            self.status[st.node] = st

    def get(self, node: str) -> M.Status | None:
        with self.lock:
            return self.status.get(node)


def _status_dict(st: M.Status | None) -> dict | None:
    if st is None:
        return None
    return {"ok": st.ok, "text": st.text, "counters": dict(st.counters), "latencies_ms": dict(st.latencies_ms),
            "rates_hz": dict(st.rates_hz)}


def _tracebacks(path: Path) -> list[str]:
    out = []
    with contextlib.suppress(OSError), open(path, errors="replace") as f:
        for line in f:
            if "Traceback" in line or "panicked" in line or " ERROR " in line:
                out.append(line.strip()[:200])
    return out[:20]


def _memory_env(trace: bool, workdir: Path, name: str) -> dict[str, Any]:
    """Spawn keywords for a node whose Python heap is traced (:class:`bridge.nodes.node.MemoryReport`), or none."""
    if not trace:
        return {}
    from bridge.nodes.node import MEMORY_REPORT_ENV, TRACE_MEMORY_ENV

    return {"env": {**os.environ, TRACE_MEMORY_ENV: "1", MEMORY_REPORT_ENV: str(workdir / f"memory-{name}.jsonl")}}


def _ask_memory_reports(procs: dict[str, Any], names: tuple[str, ...]) -> None:
    for name in names:
        with contextlib.suppress(OSError):
            os.kill(procs[name].pid, signal.SIGUSR1)


def _memory_reports(workdir: Path, names: tuple[str, ...]) -> dict[str, list[dict]]:
    """Every traced node's reports so far (an empty list for one that wrote none: it never answered)."""
    out: dict[str, list[dict]] = {name: [] for name in names}
    for name in names:
        with contextlib.suppress(OSError):
            out[name] = [json.loads(line) for line in (workdir / f"memory-{name}.jsonl").read_text().splitlines()]
    return out


def soak(minutes: float, link: str, workdir: Path, sample_s: float = 10.0, warmup_s: float = 60.0,
        mission: str = "paper-s-path", startup_timeout: float = 180.0, trace_memory: tuple[str, ...] = ()) -> dict:
    """The soak (see the module docstring); returns the JSON-ready result."""
    from bridge.core.config import load_mission_spec
    from bridge.nodes.zsession import free_port, make_config, open_session, tcp
    from bridge.tools.procs import Children, emulated_link

    spec = load_mission_spec(mission)
    if spec.start is None:
        raise SystemExit(f"scmbridge bench soak: error: mission {spec.name!r} has no start pose for the learner")
    seconds = minutes * 60.0
    robot, port = "soak", free_port()
    keys = M.Keys(robot)
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    x0 = ",".join(f"{a:.6f}" for a in spec.start)
    life = seconds + startup_timeout + 60
    procs: dict[str, Any] = {}
    samples: dict[str, list[dict | None]] = {}
    times: list[float] = []
    laps: list[dict] = []
    alive = True
    with ExitStack() as stack:
        logs = {name: stack.enter_context(open(workdir / f"{name}.log", "w")) for name in ("driver", "station",
                                                                                             "learner")}
        session = stack.enter_context(open_session(make_config(mode="router", listen=[tcp(port)])))
        watch = Watch(session, robot)
        kids = stack.enter_context(Children())
        driver_args = emulated_link(kids, link, workdir, x0, life, logs["learner"])
        if link != "can":
            procs["learner"] = kids.procs[-1]
        procs["driver"] = kids.spawn(["driver", "--engage", *driver_args, *client, "--duration", str(life)],
                                     logs["driver"], **_memory_env("driver" in trace_memory, workdir, "driver"))
        procs["station"] = kids.spawn(["station", *client, "--start", "--store", str(workdir / "pairs.bin"),
                                       "--mission", mission, "--duration", str(life)], logs["station"],
                                      **_memory_env("station" in trace_memory, workdir, "station"))
        traced = tuple(n for n in ("station", "driver") if n in trace_memory)
        t_up = time.monotonic() + startup_timeout
        while time.monotonic() < t_up and not kids.any_exited():
            st = watch.get("station")
            if st is not None and watch.get("driver") is not None and st.counters.get("method_scm", 0) + \
                    st.counters.get("method_direct", 0) + st.counters.get("method_perturb", 0) > 0:
                break  # both up, and the station is driving
            time.sleep(0.2)
        startup = round(time.monotonic() - (t_up - startup_timeout), 1)
        st = watch.get("station")
        up = st is not None and watch.get("driver") is not None
        if not up:  # a node that has not spoken may not have its SIGUSR1 handler yet: the signal would kill it
            traced_up: tuple[str, ...] = ()
        else:
            traced_up = traced
        first = {n: _status_dict(watch.get(n)) for n in ("station", "driver")}
        pub = session.declare_publisher(keys.mission)
        t0 = time.monotonic()
        t_sample = t0
        lap, lap_t0, published_missions = 0, t0, None
        warm = min(warmup_s, 0.5 * seconds)
        baseline_due = t0 + warm if traced_up else math.inf
        while time.monotonic() - t0 < seconds:
            now = time.monotonic()
            if kids.any_exited():
                alive = False
                break
            if now >= baseline_due:  # the heap after warm-up is the baseline the last report compares with
                _ask_memory_reports(procs, traced_up)
                baseline_due = math.inf
            if now >= t_sample:
                times.append(round(now - t0, 1))
                for name, p in [*procs.items(), ("bench", None)]:
                    samples.setdefault(name, []).append(rss_parts(p.pid if p is not None else None) or None)
                t_sample += sample_s
            st = watch.get("station")
            if st is not None:
                c = st.counters
                if published_missions is not None and c.get("missions", 0) > published_missions:
                    published_missions = None  # the station took the new lap: its goal state was reset
                if published_missions is None and c.get("goal_reached", 0) == 1:
                    laps.append({"lap": lap, "seconds": round(now - lap_t0, 1), "reversed": lap % 2 == 1})
                    lap += 1
                    lap_t0 = now
                    published_missions = c.get("missions", 0)
                    pub.put(M.encode(M.validated(lap_spec(spec, lap))))
            time.sleep(0.2)
        elapsed = time.monotonic() - t0
        last = {n: watch.get(n) for n in ("station", "driver")}
        pub.undeclare()
        if traced_up and alive:
            _ask_memory_reports(procs, traced_up)
            t_end = time.monotonic() + 120.0  # a snapshot of a large traced heap takes a while
            while time.monotonic() < t_end and any(len(r) < 2 for r in _memory_reports(workdir, traced).values()):
                time.sleep(0.5)
    crashes = {name: _tracebacks(workdir / f"{name}.log") for name in ("driver", "station", "learner")}
    exits = {name: p.returncode for name, p in procs.items()}
    rss = {}
    for name, rows in samples.items():
        vals = [r["rss"] if r else None for r in rows]
        good = [v for v in vals if v is not None]
        part = {k: [r.get(k) if r else None for r in rows] for k in ("anon", "shmem")}
        rss[name] = {"first_mb": good[0] if good else None, "last_mb": good[-1] if good else None,
                     "max_mb": max(good) if good else None,
                     "slope_mb_per_min": slope_mb_per_min(times, vals, warm),
                     "anon_slope_mb_per_min": slope_mb_per_min(times, part["anon"], warm),
                     "shmem_last_mb": part["shmem"][-1] if part["shmem"] else None,
                     "samples_mb": vals, "anon_mb": part["anon"], "shmem_mb": part["shmem"]}
    missed = {}
    for node in ("station", "driver"):
        c0 = (first[node] or {}).get("counters", {})
        c1 = dict(last[node].counters) if last[node] is not None else {}
        n = c1.get("missed_deadlines", 0) - c0.get("missed_deadlines", 0)
        missed[node] = {"over_soak": n, "per_min": round(n / max(elapsed / 60.0, 1e-9), 2),
                        "total": c1.get("missed_deadlines")}
    return {
        "link": link, "minutes": round(elapsed / 60.0, 2), "sample_s": sample_s,
        "warmup_s": min(warmup_s, 0.5 * seconds), "startup_s": startup,
        "laps": {"completed": len(laps), "laps": laps, "mission": spec.name,
                 "how": "out and back: the mission's path, then the same path reversed, alternately; published on "
                        "scm/<robot>/mission when the station reports the goal reached; processes not restarted"},
        "times_s": times, "rss": rss, "missed_deadlines": missed,
        "last_status": {n: _status_dict(last[n]) for n in ("station", "driver")},
        "processes_alive": alive, "exit_codes": exits, "log_errors": crashes, "nodes_up": up,
        **({"memory_reports": _memory_reports(workdir, traced)} if traced else {}),
    }


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--duration", type=float, default=600.0, help="seconds to drive (after start-up)")
    ap.add_argument("--link", choices=link_names(), default="can")
    ap.add_argument("--sample-every", type=float, default=10.0, help="RSS sampling period, seconds")
    ap.add_argument("--warmup", type=float, default=60.0, help="seconds of samples left out of the slope")
    ap.add_argument("--mission", default="paper-s-path", help="mission file or shipped mission name")
    ap.add_argument("--trace-memory", nargs="?", const="station", default="", metavar="NODES",
                    help="run these nodes (comma-separated: station, driver; default station) under tracemalloc and "
                         "report where their Python heap grew between the end of warm-up and the end. A report "
                         "pauses the node while it snapshots its heap (seconds): a driver host on CAN misses its "
                         "controllers' watchdog, and they stop until the operator releases them")


def run(args: argparse.Namespace) -> int:
    if not (args.duration > 0 and args.sample_every > 0 and args.warmup >= 0):
        raise UsageError("--duration and --sample-every must be > 0, --warmup >= 0")
    traced = tuple(n for n in args.trace_memory.split(",") if n)
    if not set(traced) <= {"station", "driver"}:
        raise UsageError(f"--trace-memory: station and/or driver, not {args.trace_memory!r}")
    from bench.common import emit

    with tempfile.TemporaryDirectory(prefix="scm-soak-") as tmp:
        out = soak(args.duration / 60.0, args.link, Path(tmp), args.sample_every, args.warmup, args.mission,
                  trace_memory=traced)
    emit(out)
    return 0 if out["processes_alive"] else 1
