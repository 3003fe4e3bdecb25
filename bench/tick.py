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

Every figure is this thread's CPU time (``time.thread_time_ns``), in milliseconds per tick: ``total`` (median, p99,
mean over the ticks after ``--skip``) and the phases: ``decode`` (the wire bytes to messages), ``pairing`` (the
pairer's calls), ``store`` (pairs added to the store, the learned limits with them), ``mpc`` (the command source's
proposal: references, obstacles, the solve), ``transfer`` (the transfer step's mapping), ``publications`` (status,
limits and the store's periodic save), ``encode`` (the outputs to bytes), ``core_rest`` (the rest of the core's
tick: reordering, fitness, mission control, building the messages). With ``--zenoh`` the telemetry really crosses a
Zenoh session (published by the simulated robot on its keys, drained from Zenoh's ring by the station's
``Inputs.queue`` as in :meth:`bridge.nodes.station.Station.tick`) and the outputs are put on their publishers:
``decode`` then includes taking the samples from the ring and ``publish`` the puts; ``process_ms`` is the whole
process's CPU per tick (Zenoh's own threads too, the simulated robot included). ``--profile N`` prints the N
functions of the most own time (cProfile) to stderr.
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
    ap.add_argument("--tiles", type=int, default=5, help="the mission: the paper's S-path laid end to end this often")
    ap.add_argument("--no-compile", action="store_true", help="the MPC's functions interpreted, not compiled")
    ap.add_argument("--zenoh", action="store_true", help="telemetry and outputs through a real Zenoh session")
    ap.add_argument("--paced", action="store_true", help="sleep to each tick's deadline in real time (caches go cold "
                    "between ticks as in a station; the default runs the ticks back to back)")
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="print the top N functions (cProfile)")


class _Clock:
    """Per-tick CPU time by phase, and wrappers that charge a callable's time to a phase."""

    def __init__(self) -> None:
        self.now: dict[str, int] = defaultdict(int)
        self.ticks: list[dict[str, int]] = []

    def wrap(self, phase: str, fn):
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


def run(args: argparse.Namespace) -> int:
    from bench.fleet import SimRobot, write_mission
    from bridge.core import wire as M
    from bridge.core.config import StationConfig, load_mission
    from bridge.nodes.sources import MpcSource
    from bridge.nodes.station_core import StationCore, TickInputs
    from transfer.scm import warmup

    warmup()
    cfg = StationConfig()
    tmp = Path(tempfile.mkdtemp(prefix="scmbridge-bench-tick-"))
    mission = load_mission(str(write_mission(tmp / "mission.toml", args.tiles)))
    core = StationCore(cfg, "tick1", cfg.station.rate_hz, tmp / "pairs.bin", mission)
    compiled = False
    if isinstance(core.source, MpcSource) and not args.no_compile:
        from bridge.core.codegen import compile_functions

        fns = compile_functions(core.source.teacher.kernels())
        if fns is not None:
            core.source.teacher.use_compiled(fns)
            compiled = True
    period = core.period
    t0 = 1000.0  # a monotonic clock's value
    robot = SimRobot("tick1", tuple(mission.start), t0)
    core.request(M.MissionRequest(stamp=t0, action="start", source="bench"), t0)

    clock = _Clock()
    core.pairer.applied = clock.wrap("pairing", core.pairer.applied)
    core.pairer.state = clock.wrap("pairing", core.pairer.state)
    core.store.add = clock.wrap("store", core.store.add)
    core.source.propose = clock.wrap("mpc", core.source.propose)
    core.transfer.map = clock.wrap("transfer", core.transfer.map)
    for name in ("status", "limits", "persist"):
        setattr(core, name, clock.wrap("publications", getattr(core, name)))

    session = None
    wire: list[tuple[bytes, type]] = []  # the telemetry of this tick, as bytes (without --zenoh)
    if args.zenoh:
        from bridge.nodes.node import Inputs
        from bridge.nodes.zsession import free_port, make_config, open_session, tcp

        session = open_session(make_config(listen=[tcp(free_port())]))
        inputs = Inputs()
        queues = [inputs.queue(session, robot.keys.applied, M.Applied, "applied"),
                  inputs.queue(session, robot.keys.state, M.LearnerState, "state")]
        pubs = {"state": session.declare_publisher(robot.keys.state),
                "applied": session.declare_publisher(robot.keys.applied)}
        out_pubs = {t: session.declare_publisher(getattr(M.Keys("tick1"), t)) for t in ("cmd", "limits", "teacher")}
        out_pubs["status"] = session.declare_publisher(M.status_key("tick1", "station"))

    def put(topic: str, msg) -> None:
        data = M.encode(msg)
        if session is not None:
            pubs[topic].put(data)
        else:
            wire.append((data, M.Applied if topic == "applied" else M.LearnerState))

    def echo(now: float) -> None:
        d = robot.gate.decide(now)
        robot.v, robot.w = d.v, d.omega
        put("applied", M.Applied(stamp=now, seq=robot.seq["applied"], v=d.v, omega=d.omega, reason=d.reason,
                                 cmd_seq=d.cmd_seq))
        robot.seq["applied"] += 1

    step, k_pose = 1.0 / TELEMETRY_HZ, 0
    per_tick = round(period * TELEMETRY_HZ)
    driver = None
    t_status = t0
    decode = clock.wrap("decode", M.decode)
    encode = clock.wrap("encode", M.encode)
    prof = cProfile.Profile() if args.profile else None
    proc0 = sim_cpu = 0
    methods: dict[str, int] = defaultdict(int)
    wall0 = time.monotonic()
    for k in range(args.ticks + 1):
        now = t0 + k * period
        if args.paced:
            time.sleep(max(0.0, wall0 + k * period - time.monotonic()))
        s0 = time.thread_time_ns()
        if k > 0:  # the robot's side of the last period: poses, echoes, a driver status each second
            for j in range(per_tick):
                t = now - period + (j + 1) * step
                robot.integrate(t)
                if k_pose % APPLIED_EVERY == 0:
                    echo(t)
                put("state", M.LearnerState(stamp=t, seq=robot.seq["state"], x=robot.x, y=robot.y, theta=robot.th,
                                            v=robot.v, omega=robot.w, source="sim", epoch=robot.epoch))
                robot.seq["state"] += 1
                k_pose += 1
        if now >= t_status:
            driver = (M.decode(M.encode(M.Status(stamp=now, seq=robot.seq["status"], node="driver", ok=True,
                                                 text="link sim: driving")), M.Status), now)
            robot.seq["status"] += 1
            t_status = now + 1.0
        sim_cpu += time.thread_time_ns() - s0
        if k == args.skip:
            proc0, sim_cpu = time.process_time_ns(), 0
        if prof is not None and k == args.skip:
            prof.enable()
        # ---------------------------------------------------------------- the station's tick
        c0 = time.thread_time_ns()
        if session is not None:
            tel = []
            d0 = time.thread_time_ns()
            for q in queues:
                tel += q.drain(now)
            clock.now["decode"] += time.thread_time_ns() - d0
        else:
            tel = [(decode(data, kind), now) for data, kind in wire]
            wire.clear()
        c1 = time.thread_time_ns()
        out = core.tick(TickInputs(telemetry=tuple(tel), driver=driver), now)
        c2 = time.thread_time_ns()
        driver = None
        for topic, msg in (("cmd", out.command), ("teacher", out.teacher), ("limits", out.limits),
                           ("status", out.status)):
            if msg is not None:
                data = encode(msg)
                if session is not None:
                    p0 = time.thread_time_ns()
                    out_pubs[topic].put(data)
                    clock.now["publish"] += time.thread_time_ns() - p0
        clock.now["total"] += time.thread_time_ns() - c0
        inner = sum(clock.now[p] for p in ("pairing", "store", "mpc", "transfer", "publications"))
        clock.now["core_rest"] += (c2 - c1) - inner
        clock.close_tick()
        # ---------------------------------------------------------------- the robot takes the command at once
        s0 = time.thread_time_ns()
        if out.command is not None:
            methods[out.command.method] += 1
            if robot.gate.offer(out.command, now + 1e-3):
                robot.integrate(now + 1e-3)
                echo(now + 1e-3)
        sim_cpu += time.thread_time_ns() - s0
    if prof is not None:
        prof.disable()
    if session is not None:
        session.close()
    ticks = clock.ticks[args.skip + 1:]
    res: dict = {"bench": "tick", "ticks": len(ticks), "compiled_mpc": compiled, "zenoh": bool(args.zenoh),
                 "mission": mission.name, "solver": cfg.teacher.mpc_solver,
                 "cpu_ms_per_tick": _stats(np.array([t.get("total", 0) for t in ticks]) / 1e6),
                 "phases_ms": {p: _stats(np.array([t.get(p, 0) for t in ticks]) / 1e6) for p in PHASES
                               if any(p in t for t in ticks)},
                 "process_ms_per_tick": round((time.process_time_ns() - proc0 - sim_cpu) / 1e6
                                              / max(1, args.ticks - args.skip), 4),
                 "methods": dict(methods), "refined_pairs": len(core.store.refined()),
                 "raw_pairs": core.store.raw_count, "why": core.why}
    emit(res)
    if prof is not None:
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(args.profile)
        sys.stderr.write(s.getvalue())
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("cumulative").print_stats(args.profile)
        sys.stderr.write(s.getvalue())
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scmbridge bench tick", description=__doc__.splitlines()[0])
    arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
