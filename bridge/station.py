"""``scmbridge station``: the base-station service, the teacher and the transfer policy in a fixed-rate loop.

Each tick (10 Hz default; absolute deadlines, missed ones counted) it takes the latest learner state, forms the
command pairs the driver's applied-command echo and the poses really bracket (:mod:`bridge.pairing`), updates the
pair store (and so the learned limits), runs the teacher MPC bounded by the learned limits, maps its command with
the transfer policy and publishes ``cmd`` (with the method and a validity of three periods) and ``teacher``. At the
goal it publishes stops. The pair store is persisted atomically (write, fsync, rename) every ``persist_every_s``
and at exit, and reloaded at start; ``scm/<robot>/pairs`` answers queries with the refined pairs and limits;
``status`` carries rates, counts and solve times. Callbacks only decode and store; all work is in the loop.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import threading
import time
from pathlib import Path as FsPath
from typing import Any

import numpy as np

from bridge import wire as M
from bridge.cliutil import positive_float
from bridge.config import load_mission, load_station
from bridge.pairing import IntervalPairer
from bridge.wire import Keys, status_key
from bridge.zsession import make_config, open_session
from transfer.domain import Bounds
from transfer.store import PairStore

log = logging.getLogger("scmbridge.station")


def save_atomic(path: FsPath, data: bytes) -> None:
    """Write ``data`` so that ``path`` holds either the old or the new content, never a torn file."""
    path = FsPath(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    dfd = os.open(path.parent, os.O_DIRECTORY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


def load_store(path: FsPath, learner: Bounds, teacher: Bounds, grid, k_min: int) -> tuple[PairStore, str]:
    """The persisted store if there is a valid one, else a new one (a corrupt file is kept aside, not lost)."""
    path = FsPath(path)
    if path.exists():
        try:
            store = PairStore.from_bytes(path.read_bytes())
            if store.learner_bounds != learner or store.teacher_bounds != teacher:
                raise ValueError("its command bounds differ from this configuration")
            return store, f"reloaded {len(store.refined())} refined pairs from {path}"
        except ValueError as exc:
            aside = path.with_name(path.name + f".corrupt-{int(time.time())}")
            os.replace(path, aside)
            log.error("pair store %s unusable (%s); moved to %s, starting empty", path, exc, aside)
    return PairStore(learner, teacher, tuple(grid), k_min), "new pair store"


def pairs_message(store: PairStore, robot: str, now: float) -> M.Pairs:
    recs = [M.PairRecord(id=p.id, version=p.version, count=p.count, teacher_v=float(p.u_T[0]),
                         teacher_omega=float(p.u_T[1]), learner_v=float(p.u_L[0]), learner_omega=float(p.u_L[1]))
            for p in store.refined()]
    return M.Pairs(stamp=now, robot=robot, pairs=recs, limits_box=store.limits.box.as_list(),
                   limits_hull=[[float(a), float(b)] for a, b in store.limits.hull])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scmbridge station", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", help="station TOML (see deploy/station.example.toml)")
    ap.add_argument("--robot", default=None)
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--mode", choices=["peer", "client", "router"], default="peer", help="Zenoh session mode")
    ap.add_argument("--zenoh-config")
    ap.add_argument("--rate", type=positive_float, default=None, help="control tick rate, Hz (overrides the config)")
    ap.add_argument("--mission", default=None, help="mission file (TOML; overrides the config)")
    ap.add_argument("--store", default=None, help="pair store file (persisted atomically, reloaded at start)")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--exit-at-goal", action="store_true", help="stop the service once the goal is reached")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s station %(levelname)s %(message)s")
    cfg = load_station(args.config)
    scfg = cfg.station
    robot = args.robot or cfg.robot
    keys = Keys(robot)
    rate = float(args.rate or scfg.rate_hz)
    period = 1.0 / rate
    dt_pair = scfg.pair_dt
    world = load_mission(args.mission or scfg.mission or None)

    from transfer.policy import TransferPolicy
    from transfer.scm import warmup
    from transfer.teacher.mpc import MpcConfig, MpcTeacher

    TB, LB = cfg.teacher_bounds.bounds(), cfg.learner_bounds.bounds()
    tcfg = cfg.transfer
    store_path = FsPath(args.store) if args.store else cfg.store_file()
    store, how = load_store(store_path, LB, TB, tcfg.grid, tcfg.k_min)
    log.info("%s", how)
    policy = TransferPolicy(store, tcfg.mapper, rng=np.random.default_rng(tcfg.seed))
    mpc = MpcTeacher(MpcConfig(N=scfg.horizon, dt=period))
    warmup()  # compile / load the SC kernels before the first tick
    pairer = IntervalPairer(dt_pair)

    lock = threading.Lock()
    inbox: dict[str, Any] = {"state": None, "applied": [], "malformed": 0}
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())

    def on_state(sample) -> None:
        try:
            st = M.decode(sample.payload.to_bytes(), M.LearnerState)
        except M.MessageError:
            with lock:
                inbox["malformed"] += 1
            return
        with lock:
            inbox["state"] = st
            inbox.setdefault("states", []).append(st)

    def on_applied(sample) -> None:
        try:
            a = M.decode(sample.payload.to_bytes(), M.Applied)
        except M.MessageError:
            with lock:
                inbox["malformed"] += 1
            return
        with lock:
            inbox["applied"].append(a)

    zconf = make_config(mode=args.mode, listen=args.listen, connect=args.connect, config_file=args.zenoh_config)
    counts = {"scm": 0, "direct": 0, "perturb": 0, "affine": 0, "barycentric": 0, "stop": 0}
    t_start = time.monotonic()
    reached = False
    try:
        with open_session(zconf) as session:
            session.declare_subscriber(keys.state, on_state)
            session.declare_subscriber(keys.applied, on_applied)

            def on_query(query) -> None:
                with lock:
                    msg = pairs_message(store, robot, time.monotonic())
                query.reply(keys.pairs, M.encode(msg))

            session.declare_queryable(keys.pairs, on_query)
            pub_cmd = session.declare_publisher(keys.cmd)
            pub_teacher = session.declare_publisher(keys.teacher)
            pub_status = session.declare_publisher(status_key(robot, "station"))
            seq = seq_st = 0
            missed = 0
            solve_ms: list[float] = []
            t_next = time.monotonic()
            t_status = t_persist = t_next
            persist_every = scfg.persist_every_s
            log.info("station for %s at %.0f Hz, world %s", robot, rate, world.name)
            while not stop.is_set():
                now = time.monotonic()
                if args.duration is not None and now - t_start >= args.duration:
                    break
                with lock:
                    applied, inbox["applied"] = inbox["applied"], []
                    states = inbox.pop("states", [])
                    state = inbox["state"]
                events = sorted([(a.stamp, 0, a) for a in applied] + [(st.stamp, 1, st) for st in states],
                                key=lambda e: (e[0], e[1]))
                with lock:  # the queryable reads the store from Zenoh's thread
                    for _, kind, e in events:
                        if kind == 0:
                            pair = pairer.applied(e.stamp, e.v, e.omega, e.reason)
                        else:
                            pair = pairer.state(e.stamp, np.array([e.x, e.y, e.theta]))
                        if pair is not None:
                            store.add(*pair)
                if state is not None and not reached:
                    x = np.array([state.x, state.y, state.theta])
                    if world.reached(x):
                        reached = True
                        t_status = now  # say so at once
                        log.info("goal reached after %.1f s", now - t_start)
                    else:
                        t0 = time.perf_counter()
                        with lock:
                            limits = store.limits.box
                        res = mpc.solve(x, world.path, limits, world.obstacles)
                        solve_ms.append((time.perf_counter() - t0) * 1e3)
                        with lock:
                            m = policy.map(res.u)
                        counts[m.method] = counts.get(m.method, 0) + 1
                        cmd = M.Command(stamp=now, seq=seq, v=float(m.u_L[0]), omega=float(m.u_L[1]),
                                        method=m.method,
                                        valid_ms=int(3000 * period), region=list(m.region)[:8])
                        pub_cmd.put(M.encode(M.validated(cmd)))
                        pred = res.predicted
                        pub_teacher.put(M.encode(M.TeacherCommand(
                            stamp=now, seq=seq, v=float(res.u[0]), omega=float(res.u[1]), solver=res.solver,
                            ok=res.ok, predicted_x=[float(a) for a in pred[:, 0]],
                            predicted_y=[float(a) for a in pred[:, 1]])))
                        seq += 1
                if reached:
                    pub_cmd.put(M.encode(M.Command(stamp=now, seq=seq, v=0.0, omega=0.0, method="stop",
                                                   valid_ms=int(3000 * period))))
                    seq += 1
                    counts["stop"] += 1
                if now >= t_status:
                    sm = np.array(solve_ms[-100:]) if solve_ms else np.zeros(1)
                    with lock:
                        mal = inbox["malformed"]
                        npairs = len(store.refined())
                    pub_status.put(M.encode(M.Status(
                        stamp=now, seq=seq_st, node="station", ok=True, rates_hz={"loop": rate},
                        latencies_ms={"solve_median": float(np.median(sm)), "solve_max": float(sm.max())},
                        counters={**{f"method_{k}": v for k, v in counts.items()}, "missed_deadlines": missed,
                                  "malformed": mal, "refined_pairs": npairs, "raw_pairs": store.raw_count,
                                  "pairs_rejected": pairer.rejected, "pairs_formed": pairer.formed,
                                  "goal_reached": int(reached)},
                        text="goal reached" if reached else "driving")))
                    seq_st += 1
                    t_status = now + 1.0
                if now >= t_persist:
                    with lock:
                        blob = store.to_bytes()
                    save_atomic(store_path, blob)
                    t_persist = now + persist_every
                if reached and args.exit_at_goal:
                    time.sleep(3 * period)
                    break
                t_next += period
                delay = t_next - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                else:
                    missed += 1
                    t_next = time.monotonic()
    finally:
        save_atomic(store_path, store.to_bytes())
        log.info("pair store saved to %s (%d refined pairs)", store_path, len(store.refined()))
    return 0
