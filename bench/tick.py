"""``scmbridge bench tick``: what one robot's station tick costs in CPU, split by phase (JSON).

One :class:`~bridge.nodes.station_core.StationCore` (the station's whole tick without Zenoh) runs in this process
for ``--ticks`` ticks of simulated time, fed what a station of ``scmbridge bench fleet`` receives per tick from the
wire: the robot's poses at 100 Hz (about 10 ``LearnerState``) and its echoes at 50 Hz plus one per accepted command
(about 6 ``Applied``), as encoded bytes decoded the way the station's adapter decodes them
(:meth:`bridge.nodes.node.Inputs.decode`), and an ok driver status each second. The robot is the fleet bench's own
(:class:`bench.fleet.SimRobot`: the driver host's command gate and an exact unicycle) answering each command at
once; the teacher is the configured default (the real-time-iteration MPC, from compiled code when this machine can
build it: cached in the cache directory); the mission is the fleet bench's (the paper's S-path laid end to end
``--tiles`` times; ``--tiles 1`` is the shipped default mission); the pair store starts empty and fills as it drives.

Every figure is this thread's CPU time (``time.thread_time_ns``), in milliseconds per tick. The robots drive twice, from
empty stores on the same seeds: first as the station ticks them, this thread's clock read only at each tick's start and
end (``cpu_ms_per_tick``: median, p99, mean over the ticks after ``--skip``); then again with a timer around each
phase's calls (``phases_ms``), whose own cost is in that pass's totals (``timed_cpu_ms_per_tick``) and not in the
first's: a thread's CPU clock is a system call, and a tick calls the phases' code some 25 times (``timers_ms_per_tick``:
the difference of the two passes' means). ``passes_agree``: both passes drove alike (their methods and pairs). After
each tick and its command, the work the command left for later (a step of the hole search) is done as the station's loop
does it, off the command's way (:meth:`~bridge.nodes.station_core.StationCore.background`): ``background_ms_per_tick``,
and ``robot_ms_per_tick`` the tick and it together (what a robot costs a period). The phases: ``decode`` (the wire bytes
to messages), ``pairing`` (the pairer's calls), ``store`` (pairs added to the store, the learned limits with them),
``mpc`` (the command source's proposal: references, obstacles, the solve), ``transfer`` (the transfer step's mapping),
``publications`` (status, limits and the store's periodic save), ``encode`` (the outputs to bytes), ``core_rest`` (the
rest of the core's tick: reordering, fitness, mission control, building the messages). ``process_ms_per_tick``: the
whole process's CPU per tick over the first pass, less the simulated robots' share (with the writer threads' saves,
which the station writes off the tick as here; ``saves_written``: how many they wrote). ``reference_ratio``: how long
``bench perf``'s reference workload took right before and right after the run, as a multiple of its time on the machine
its targets were set on (a reader scales the figures by it to compare machines or loads).

What a tick costs depends on how warm the caches are, so the figures of one run are only comparable with another
run of the same options. The start-up heap is frozen before the first tick, as the station freezes its own
(``--no-gc-freeze``: not, so a full collection also scans the numerical stack's start-up objects, a pause the
station does not have). Back to back (the default) every cache is warm; ``--paced`` sleeps to each tick's
deadline in real time, so code and data go cold between ticks as in a station serving a few robots on a busy
machine; ``--count N`` ticks N robots one after the other each period (a many-robot station: code warm, each
robot's data cold); ``--threads`` runs each robot's loop in its own thread on its own deadlines, phases spread over
the period, under ``station --robots``'s switch interval, as that command ran its robots until one thread ticked
them all (the process's CPU per tick only). ``--zenoh``: the
telemetry really crosses a Zenoh session (published by the simulated robot on its keys, drained from Zenoh's ring by
the station's ``Inputs.queue`` as :meth:`bridge.nodes.station.Station.tick` does) and the outputs are put on their
publishers: ``decode`` then includes taking the samples from the ring and ``publish`` the puts. ``--profile N``
prints the N functions of the most own time (cProfile, over the first pass) to stderr.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from bench.common import emit

PHASES = ("decode", "pairing", "store", "mpc", "transfer", "publications", "encode", "publish", "core_rest")
TELEMETRY_HZ = 100.0  # poses (the emulated CAN link's)
APPLIED_EVERY = 2  # an echo every second pose: the driver host's 50 Hz loop


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--ticks", type=int, default=600, help="ticks to run (simulated time, 10 Hz)")
    ap.add_argument("--skip", type=int, default=50, help="first ticks left out of the figures (start-up, cold MPC)")
    ap.add_argument("--count", type=int, default=1, help="robots (cores) ticked one after the other each period, "
                    "as the loops of a many-robot station take turns (their data go cold between two ticks)")
    ap.add_argument("--threads", action="store_true", help="each robot in its own thread on its own 10 Hz deadlines "
                    "(as `station --robots` ran them until one thread ticked them all; with --count): only the CPU per "
                    "tick of the whole process (less the simulated robots' share) and of the ticks themselves, no "
                    "phases")
    ap.add_argument("--switch-interval", type=float, default=None, metavar="S",
                    help="sys.setswitchinterval for --threads (default: the station's FLEET_SWITCH_INTERVAL_S)")
    ap.add_argument("--gc-freeze", action=argparse.BooleanOptionalAction, default=True,
                    help="freeze the start-up heap once the cores are built, as the station does before its loop "
                    "(bridge.nodes.node.freeze_startup_heap; --no-gc-freeze: every full collection also scans "
                    "start-up's objects)")
    ap.add_argument("--tiles", type=int, default=5, help="the mission: the paper's S-path laid end to end this often")
    ap.add_argument("--no-compile", action="store_true", help="the MPC's functions interpreted, not compiled")
    ap.add_argument("--zenoh", action="store_true", help="telemetry and outputs through a real Zenoh session")
    ap.add_argument("--paced", action="store_true", help="sleep to each tick's deadline in real time (caches go cold "
                    "between ticks as in a station; the default runs the ticks back to back)")
    ap.add_argument("--phases", action=argparse.BooleanOptionalAction, default=True,
                    help="drive the robots a second time with a timer around each phase (--no-phases: the first "
                    "pass only, without phases_ms)")
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="print the top N functions (cProfile)")


class _Clock:
    """Per-tick CPU time, by phase when ``phases``: wrappers that charge a callable's time to a phase (without
    phases a callable is left as it is, and a tick reads this thread's clock twice)."""

    def __init__(self, phases: bool = True) -> None:
        self.phases = phases
        self.now: dict[str, int] = defaultdict(int)
        self.ticks: list[dict[str, int]] = []

    def wrap(self, phase: str, fn):
        if not self.phases:
            return fn
        now = self.now

        def timed(*a, **kw):
            t0 = time.thread_time_ns()
            try:
                return fn(*a, **kw)
            finally:
                now[phase] += time.thread_time_ns() - t0

        return timed

    def close_tick(self) -> None:
        self.ticks.append(dict(self.now))
        self.now.clear()


def _stats(ms: np.ndarray) -> dict[str, float]:
    return {"median": round(float(np.median(ms)), 4), "p99": round(float(np.percentile(ms, 99)), 4),
            "mean": round(float(np.mean(ms)), 4)}


class _Rig:
    """One robot and its station core: the simulated robot's side (poses, echoes, driver status) and the station's
    inputs as they arrive from the wire."""

    def __init__(self, name: str, cfg, mission, tmp: Path, clock: _Clock, fns, session, t0: float) -> None:
        from bench.fleet import SimRobot
        from bridge.core import wire as M
        from bridge.nodes.sources import MpcSource
        from bridge.nodes.station_core import StationCore

        self.M = M
        core = self.core = StationCore(cfg, name, cfg.station.rate_hz, tmp / f"pairs-{name}.bin", mission,
                                       defer=True)
        if fns is not None and isinstance(core.source, MpcSource):
            core.source.teacher.use_compiled(fns)
        self.robot = SimRobot(name, tuple(mission.start), t0)
        core.request(M.MissionRequest(stamp=t0, action="start", source="bench"), t0)
        core.pairer.applied = clock.wrap("pairing", core.pairer.applied)
        core.pairer.state = clock.wrap("pairing", core.pairer.state)
        core.store.add = clock.wrap("store", core.store.add)
        core.source.propose = clock.wrap("mpc", core.source.propose)
        core.transfer.map = clock.wrap("transfer", core.transfer.map)
        for owner, what in ((core, "status"), (core.limits_report, "message"), (core.saves, "save")):
            setattr(owner, what, clock.wrap("publications", getattr(owner, what)))
        # the saves are snapshots taken in the tick, encoded and written by a writer thread, as the station's
        # (bridge.nodes.station.Station): the encoding and the writing are in the process's CPU, not in the tick's
        from bridge.nodes.writer import SaveWriter

        self.writer = core.saves.writer = SaveWriter(name=f"bench-save-{name}")
        self.saved = 0  # saves the writer wrote, as its outcomes came back
        self.wire: list[tuple[bytes, type]] = []  # this period's telemetry as bytes (without --zenoh)
        self.session = session
        self.driver = None
        self.t_status = t0
        self.k_pose = 0
        if session is not None:
            from bridge.nodes.node import Inputs

            keys, inputs = self.robot.keys, Inputs()
            self.queues = [inputs.queue(session, keys.applied, M.Applied, "applied"),
                           inputs.queue(session, keys.state, M.LearnerState, "state")]
            self.pubs = {"state": session.declare_publisher(keys.state),
                         "applied": session.declare_publisher(keys.applied)}
            self.out_pubs = {t: session.declare_publisher(getattr(keys, t)) for t in ("cmd", "limits", "teacher")}
            self.out_pubs["status"] = session.declare_publisher(M.status_key(name, "station"))

    def put(self, topic: str, msg) -> None:
        data = self.M.encode(msg)
        if self.session is not None:
            self.pubs[topic].put(data)
        else:
            self.wire.append((data, self.M.Applied if topic == "applied" else self.M.LearnerState))

    def echo(self, now: float) -> None:
        r = self.robot
        d = r.gate.decide(now)
        r.v, r.w = d.v, d.omega
        self.put("applied", self.M.Applied(stamp=now, seq=r.seq["applied"], v=d.v, omega=d.omega, reason=d.reason,
                                           cmd_seq=d.cmd_seq))
        r.seq["applied"] += 1

    def robot_side(self, now: float, period: float, first: bool) -> None:
        """The last period of the robot's side: poses at 100 Hz, echoes at 50 Hz, a driver status each second."""
        M, r = self.M, self.robot
        step = 1.0 / TELEMETRY_HZ
        if not first:
            for j in range(round(period * TELEMETRY_HZ)):
                t = now - period + (j + 1) * step
                r.integrate(t)
                if self.k_pose % APPLIED_EVERY == 0:
                    self.echo(t)
                self.put("state", M.LearnerState(stamp=t, seq=r.seq["state"], x=r.x, y=r.y, theta=r.th, v=r.v,
                                                 omega=r.w, source="sim", epoch=r.epoch))
                r.seq["state"] += 1
                self.k_pose += 1
        if now >= self.t_status:
            self.driver = (M.decode(M.encode(M.Status(stamp=now, seq=r.seq["status"], node="driver", ok=True,
                                                      text="link sim: driving")), M.Status), now)
            r.seq["status"] += 1
            self.t_status = now + 1.0

    def tick(self, now: float, clock: _Clock, decode, encode):
        """The station's tick: the telemetry decoded (or drained from Zenoh), the core's tick, the outputs encoded
        (and put). Without the clock's phases this thread's clock is read at the tick's start and end only."""
        timed = clock.phases
        c0 = time.thread_time_ns()
        if self.session is not None:
            tel = []
            for q in self.queues:
                tel += q.drain(now)
        else:  # timed as one block: a timer read per message cost more than a message's decoding
            dec = self.M.decode
            tel = [(dec(data, kind), now) for data, kind in self.wire]
            self.wire.clear()
        c1 = time.thread_time_ns() if timed else 0
        self.drain_saves()
        out = self.core.tick(self.inputs(tel), now)
        c2 = time.thread_time_ns() if timed else 0
        self.driver = None
        for topic, msg in (("cmd", out.command), ("teacher", out.teacher), ("limits", out.limits),
                           ("status", out.status)):
            if msg is not None:  # the command as the core checked it, where the core gives it (encoded once)
                data = getattr(out, "command_bytes", None) if topic == "cmd" else None
                data = data or encode(msg)
                if self.session is not None:
                    p0 = time.thread_time_ns() if timed else 0
                    self.out_pubs[topic].put(data)
                    if timed:
                        clock.now["publish"] += time.thread_time_ns() - p0
        clock.now["total"] += time.thread_time_ns() - c0
        if timed:
            clock.now["decode"] += c1 - c0
            inner = sum(clock.now[p] for p in ("pairing", "store", "mpc", "transfer", "publications"))
            clock.now["core_rest"] += (c2 - c1) - inner
        return out

    def drain_saves(self) -> None:
        """The writer's outcomes, taken as the station takes them."""
        for what, error in self.writer.results():
            self.saved += self.core.saves.saved(what, error)

    def inputs(self, tel):
        from bridge.nodes.station_core import TickInputs

        return TickInputs(telemetry=tuple(tel), driver=self.driver)

    def take(self, cmd, now: float) -> None:
        """The robot takes the command at once, as a driver host does."""
        if cmd is not None and self.robot.gate.offer(cmd, now + 1e-3):
            self.robot.integrate(now + 1e-3)
            self.echo(now + 1e-3)


def run(args: argparse.Namespace) -> int:
    """The bench (module docstring); the pair stores and the mission in a temporary directory, removed after."""
    from bench.perf import REFERENCE_S, reference_seconds
    from bridge.teacher.codegen import native_stdout_to_stderr

    before = reference_seconds() / REFERENCE_S
    # qpOASES prints its banner on file descriptor 1 when a solver's memory is made: kept off the JSON
    with tempfile.TemporaryDirectory(prefix="scmbridge-bench-tick-") as tmp, native_stdout_to_stderr():
        res = _run(args, Path(tmp))
    res["reference_ratio"] = [round(before, 2), round(reference_seconds() / REFERENCE_S, 2)]
    emit(res)
    return 0


def _run(args: argparse.Namespace, tmp: Path) -> dict:
    """Two passes over the same robots (module docstring): the ticks as the station runs them, then the same ticks
    again with the phases' timers (``--threads``: one pass, without them)."""
    from bench.fleet import write_mission
    from bridge.core.config import StationConfig, load_mission
    from transfer.scm import warmup

    warmup()
    cfg = StationConfig()
    mission = load_mission(str(write_mission(tmp / "mission.toml", args.tiles)))
    fns = None
    if cfg.teacher.kind == "mpc" and not args.no_compile:
        from bridge.teacher.codegen import build_mpc, compile_functions
        from transfer.teacher.mpc import MpcConfig

        probe = build_mpc(MpcConfig(N=cfg.station.horizon, dt=1.0 / cfg.station.rate_hz,
                                    max_obstacles=cfg.teacher.obstacle_slots, solver=cfg.teacher.mpc_solver))
        fns = compile_functions(probe.kernels()) if probe.kernels() else None
    if args.threads:
        return _pass(args, tmp / "threads", cfg, mission, fns, phases=False)
    plain = _pass(args, tmp / "plain", cfg, mission, fns, phases=False)
    res: dict = {"bench": "tick", "robots": args.count, "ticks": plain["ticks"], "paced": bool(args.paced),
                 "compiled_mpc": fns is not None, "zenoh": bool(args.zenoh), "mission": mission.name,
                 "solver": cfg.teacher.mpc_solver, "cpu_ms_per_tick": plain["total"],
                 "background_ms_per_tick": plain["background"], "robot_ms_per_tick": plain["robot"]}
    if args.phases:
        timed = _pass(args, tmp / "timed", cfg, mission, fns, phases=True)
        res.update({"phases_ms": timed["phases"], "timed_cpu_ms_per_tick": timed["total"],
                    "timers_ms_per_tick": round(timed["total"]["mean"] - plain["total"]["mean"], 4),
                    # the same robots on the same seeds: a pass that drove otherwise would not be comparable
                    "passes_agree": all(plain[k] == timed[k] for k in ("methods", "raw_pairs", "refined_pairs"))})
    res.update({k: plain[k] for k in ("methods", "refined_pairs", "raw_pairs", "why", "saves_written")})
    res["process_ms_per_tick"] = plain["process_ms"]
    return res


def _pass(args: argparse.Namespace, tmp: Path, cfg, mission, fns, phases: bool) -> dict:
    """``--count`` robots from empty stores, ticked ``--ticks`` times: each tick's CPU (by phase when ``phases``),
    the process's, what they drove; ``--profile`` on the pass without phases (no timer in its frames)."""
    from bridge.core import wire as M

    tmp.mkdir()
    session = None
    if args.zenoh:
        from bridge.nodes.zsession import free_port, make_config, open_session, tcp

        session = open_session(make_config(listen=[tcp(free_port())]))
    t0 = 1000.0  # a monotonic clock's value
    clock = _Clock(phases)
    rigs = [_Rig(f"tick{i + 1}", cfg, mission, tmp, clock, fns, session, t0) for i in range(args.count)]
    period = rigs[0].core.time.period
    if args.gc_freeze:  # as the station before its loop: start-up's objects out of every later collection
        from bridge.nodes.node import freeze_startup_heap

        freeze_startup_heap()
    decode = clock.wrap("decode", M.decode)
    encode = clock.wrap("encode", M.encode)
    if args.threads:
        return _threaded(args, rigs, period, t0, decode, encode, clock, session)
    prof = cProfile.Profile() if args.profile and not phases else None
    proc0 = sim_cpu = 0
    methods: dict[str, int] = defaultdict(int)
    wall0 = time.monotonic()
    for k in range(args.ticks + 1):
        now = t0 + k * period
        if args.paced:
            time.sleep(max(0.0, wall0 + k * period - time.monotonic()))
        if k == args.skip:
            proc0, sim_cpu = time.process_time_ns(), 0
            if prof is not None:
                prof.enable()
        for rig in rigs:  # one after the other, as a many-robot station's loops take turns
            s0 = time.thread_time_ns()
            rig.robot_side(now, period, k == 0)
            sim_cpu += time.thread_time_ns() - s0
            out = rig.tick(now, clock, decode, encode)
            s0 = time.thread_time_ns()
            if out.command is not None:
                methods[out.command.method] += 1
            rig.take(out.command, now)
            s1 = time.thread_time_ns()
            sim_cpu += s1 - s0
            rig.core.background()  # as the station's loop, once the command is out
            clock.now["background"] += time.thread_time_ns() - s1
            clock.close_tick()
    for rig in rigs:  # what the writers still hold is written before the process's CPU is read
        rig.writer.close()
        rig.drain_saves()
    if prof is not None:
        prof.disable()
    proc_ms = (time.process_time_ns() - proc0 - sim_cpu) / 1e6 / max(1, (args.ticks - args.skip) * len(rigs))
    if session is not None:
        session.close()
    ticks = clock.ticks[(args.skip + 1) * len(rigs):]
    core = rigs[0].core
    if prof is not None:
        for key in ("tottime", "cumulative"):
            s = io.StringIO()
            pstats.Stats(prof, stream=s).sort_stats(key).print_stats(args.profile)
            sys.stderr.write(s.getvalue())
    total = np.array([t.get("total", 0) for t in ticks]) / 1e6
    background = np.array([t.get("background", 0) for t in ticks]) / 1e6
    return {"ticks": len(ticks), "total": _stats(total), "background": _stats(background),
            "robot": _stats(total + background),
            "phases": {p: _stats(np.array([t.get(p, 0) for t in ticks]) / 1e6) for p in PHASES
                       if any(p in t for t in ticks)},
            "process_ms": round(proc_ms, 4), "methods": dict(methods), "refined_pairs": len(core.store.refined()),
            "raw_pairs": core.store.raw_count, "why": core.verdict.why,
            "saves_written": sum(rig.saved for rig in rigs)}


def _threaded(args, rigs, period: float, t0: float, decode, encode, clock: _Clock, session) -> dict:
    """--threads: every robot's loop in its own thread, ticking at the period from a phase spread over it, as
    ``station --robots`` ran them before one thread ticked them all (:class:`bridge.nodes.fleet_loop.FleetLoop`); the
    CPU of the process per tick less the simulated robots'."""
    import threading

    from bridge.nodes.fleet_loop import FLEET_SWITCH_INTERVAL_S

    sys.setswitchinterval(FLEET_SWITCH_INTERVAL_S if args.switch_interval is None else args.switch_interval)
    counts = [[0, 0, 0] for _ in rigs]  # per robot: ticks measured, tick CPU ns, simulated robot CPU ns
    start = threading.Barrier(len(rigs) + 1)
    measuring = threading.Event()

    def loop(i: int) -> None:
        rig, c = rigs[i], counts[i]
        start.wait()
        wall0 = time.monotonic() + i * period / len(rigs)
        for k in range(args.ticks + 1):
            time.sleep(max(0.0, wall0 + k * period - time.monotonic()))
            now = t0 + k * period
            s0 = time.thread_time_ns()
            rig.robot_side(now, period, k == 0)
            s1 = time.thread_time_ns()
            out = rig.tick(now, _Clock(phases=False), decode, encode)
            s2 = time.thread_time_ns()
            rig.take(out.command, now)
            s3 = time.thread_time_ns()
            rig.core.background()
            s4 = time.thread_time_ns()
            if measuring.is_set():
                c[0] += 1
                c[1] += (s2 - s1) + (s4 - s3)
                c[2] += (s1 - s0) + (s3 - s2)

    threads = [threading.Thread(target=loop, args=(i,), daemon=True) for i in range(len(rigs))]
    for t in threads:
        t.start()
    start.wait()
    time.sleep(args.skip * period)
    p0, w0 = time.process_time_ns(), time.monotonic()
    measuring.set()
    time.sleep((args.ticks - 2 * args.skip) * period)
    measuring.clear()
    p1, w1 = time.process_time_ns(), time.monotonic()
    sim = sum(c[2] for c in counts)
    n = sum(c[0] for c in counts)
    for t in threads:
        t.join()
    for rig in rigs:
        rig.writer.close()
    if session is not None:
        session.close()
    return {"bench": "tick", "robots": len(rigs), "threads": True, "switch_interval_s": sys.getswitchinterval(),
          "window_s": round(w1 - w0, 2), "ticks": n,
          "process_ms_per_tick": round((p1 - p0 - sim) / 1e6 / max(n, 1), 4),
          "tick_thread_ms_per_tick": round(sum(c[1] for c in counts) / 1e6 / max(n, 1), 4),
          "sim_ms_per_tick": round(sim / 1e6 / max(n, 1), 4)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scmbridge bench tick", description=__doc__.splitlines()[0])
    arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
