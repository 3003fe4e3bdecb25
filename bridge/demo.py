"""``scmbridge demo``: the hardware-in-the-loop demo over Zenoh, or ``--inprocess`` the SC transfer alone.

Default: three separate processes on 127.0.0.1 (free port, no multicast scouting): the driver host with the
learner's emulated CAN motor controllers on a python-can ``virtual`` channel inside it, the station (teacher MPC +
transfer policy, starting with no command pairs) and this monitor. The learner drives the MPC S-path; a live
one-line status shows rate, method counts, deviation and progress; at the end a summary and a figure
(``--out``, default ``demo_out/``). It ends on its own at the goal or at ``--timeout``, and on Ctrl-C, leaving no
process behind.

``--inprocess``: learn pairs from the paper's nonlinear learner, map teacher commands with SCM, the identity
baseline and the barycentric alternative, drive the learner 0.1 s with each and print how far each lands.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np


def inprocess(args: argparse.Namespace) -> int:

    from sim_learner.dynamics import MPC_TEACHER_V, MPC_TEACHER_W, mpc_learner
    from transfer.domain import Bounds
    from transfer.pairs import teacher_equivalent
    from transfer.policy import TransferPolicy
    from transfer.scm import warmup
    from transfer.store import PairStore
    from transfer.teacher.unicycle import step

    t0 = time.perf_counter()
    warmup()
    rng = np.random.default_rng(args.seed)
    learner = mpc_learner()
    LB = Bounds(learner.v_range, learner.w_range)
    TB = Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
    store = PairStore(LB, TB, k_min=5)
    dt = 0.1
    x0 = np.array([0.0, 0.0, 0.0])
    g = (np.arange(11) + 0.5) / 11
    for _ in range(5):  # five noisy visits of every cell: k_min = 5 makes each a refined pair
        for a in g:
            for b in g:
                u = LB.clip(LB.denormalise([a, b] + 0.02 * rng.standard_normal(2)))
                store.add(teacher_equivalent(x0, learner.step(x0, u, dt), dt), u)
    for u in LB.corners():  # the learner's extremes mark its limits on the teacher domain
        store.add(teacher_equivalent(x0, learner.step(x0, u, dt), dt), u)
    box = store.limits.box
    print(f"learned {len(store.refined())} refined pairs from {store.raw_count} raw pairs")
    print(f"learner limits on the teacher domain: v in [{box.v[0]:.3f}, {box.v[1]:.3f}] m/s, "
          f"omega in [{box.w[0]:.3f}, {box.w[1]:.3f}] rad/s (true: v [0.050, 0.300], omega "
          f"[{-math.pi / 16:.3f}, {math.pi / 12:.3f}])")
    policies = {name: TransferPolicy(store, name, seed=args.seed) for name in ("scm", "identity", "barycentric")}
    ids, _, T, _ = store.refined_arrays()
    lo, hi = T.min(axis=0), T.max(axis=0)
    print(f"\n{'teacher (v, w)':>18} | {'SCM learner cmd':>18} {'err mm':>7} | {'baseline err mm':>15} | "
          f"{'barycentric err mm':>18}")
    errs: dict[str, list[float]] = {k: [] for k in policies}
    for _ in range(args.commands):
        uT = TB.denormalise(lo + (hi - lo) * (0.1 + 0.8 * rng.random(2)))
        target = step(x0, uT, dt)
        row = {}
        for name, pol in policies.items():
            m = pol.map(uT)
            reached = learner.step(x0, m.u_L, dt)
            e = float(np.hypot(*(reached[:2] - target[:2]))) * 1e3
            errs[name].append(e)
            row[name] = (m, e)
        m, e = row["scm"]
        print(f"({uT[0]:6.3f}, {uT[1]:+6.3f}) | ({m.u_L[0]:6.3f}, {m.u_L[1]:+6.3f}) {e:7.3f} | "
              f"{row['identity'][1]:15.3f} | {row['barycentric'][1]:18.3f}")
    print("\nmedian position error after 0.1 s (mm): " + ", ".join(
        f"{k} {np.median(v):.3f}" for k, v in errs.items()))
    print(f"done in {time.perf_counter() - t0:.1f} s")
    sys.stdout.flush()
    return 0


def hil(args: argparse.Namespace) -> int:
    import subprocess
    import threading
    from pathlib import Path

    from bridge import wire as M
    from bridge.procs import stop_group
    from bridge.wire import Keys, status_key
    from bridge.zsession import free_port, make_config, open_session, tcp
    from sim_learner.worlds import mpc_world

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    store = out / "pairs.bin"
    if store.exists():
        store.unlink()  # the demo starts from scratch
    world = mpc_world()
    robot = "demo"
    port = free_port()
    x0 = ",".join(f"{a:.6f}" for a in world.start)
    py = [sys.executable, "-m", "bridge.cli"]
    logs = {name: open(out / f"{name}.log", "w") for name in ("driver", "station")}  # noqa: SIM115
    procs = []
    states: list = []
    status: dict = {}
    lock = threading.Lock()
    t0 = time.monotonic()
    keys = Keys(robot)
    try:
        # this monitor is the hub: a Zenoh router on 127.0.0.1 that the driver host and the station connect to
        # (peers do not forward between other peers, so a station-to-monitor path needs a router in between)
        with open_session(make_config(mode="router", listen=[tcp(port)])) as session:
            def on_state(sample) -> None:
                st = M.decode(sample.payload.to_bytes(), M.LearnerState)
                with lock:
                    states.append((st.stamp, st.x, st.y, st.theta))

            def on_status(sample) -> None:
                st = M.decode(sample.payload.to_bytes(), M.Status)
                with lock:
                    status[st.node] = st

            if args.link == "can":  # the emulated motor controllers live inside the driver host
                driver_args = ["--link", "can", "--emulate", "--x0", x0]
            else:  # the UDP robot / the rover is its own process, like the device it stands in for
                import socket

                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                    s.bind(("127.0.0.1", 0))
                    dev_port = s.getsockname()[1]
                cfg = out / f"driver-{args.link}.toml"
                if args.link == "udp":
                    cfg.write_text(f"[link.udp]\nrobot_host = \"127.0.0.1\"\nrobot_port = {dev_port}\n")
                else:
                    cfg.write_text(f"[link.mavlink]\nurl = \"udpout:127.0.0.1:{dev_port}\"\nrate_hz = 20\n")
                procs.append(subprocess.Popen(py + ["learner", "--link", args.link, "--port", str(dev_port),
                                                    "--x0", x0, "--duration", str(args.timeout + 15)],
                                              stdout=logs["driver"], stderr=subprocess.STDOUT,
                                              start_new_session=True))
                driver_args = ["--link", args.link, "--config", str(cfg)]
            procs.append(subprocess.Popen(py + ["driver", *driver_args, "--robot", robot, "--mode", "client",
                                                "--connect", tcp(port), "--duration", str(args.timeout + 15)],
                                          stdout=logs["driver"], stderr=subprocess.STDOUT, start_new_session=True))
            procs.append(subprocess.Popen(py + ["station", "--robot", robot, "--mode", "client", "--connect", tcp(port),
                                                "--store", str(store), "--exit-at-goal",
                                                "--duration", str(args.timeout)],
                                          stdout=logs["station"], stderr=subprocess.STDOUT, start_new_session=True))
            session.declare_subscriber(keys.state, on_state)
            session.declare_subscriber(status_key(robot, "station"), on_status)
            session.declare_subscriber(status_key(robot, "driver"), on_status)
            tty = sys.stdout.isatty()
            last_print = 0.0
            while time.monotonic() - t0 < args.timeout + 20:
                if procs[-1].poll() is not None:
                    break
                if any(p.poll() is not None for p in procs):
                    break
                time.sleep(0.1)
                now = time.monotonic()
                if now - last_print >= (0.5 if tty else 5.0):
                    last_print = now
                    with lock:
                        st = status.get("station")
                        pos = states[-1] if states else None
                    if st is None or pos is None:
                        line = f"t={now - t0:5.1f}s waiting for station and driver..."
                    else:
                        c = st.counters
                        s_arc, dev = world.path.project(np.array(pos[1:3]))
                        line = (f"t={now - t0:5.1f}s rate={st.rates_hz.get('loop', 0):.0f}Hz "
                                f"scm={c.get('method_scm', 0)} direct={c.get('method_direct', 0)} "
                                f"perturb={c.get('method_perturb', 0)} pairs={c.get('refined_pairs', 0)} "
                                f"dev={100 * dev:5.1f}cm progress={100 * s_arc / world.path.length:5.1f}%")
                    print(("\r" + line.ljust(110)) if tty else line, end="" if tty else "\n", flush=True)
            if tty:
                print()
    except KeyboardInterrupt:
        print("\ninterrupted: stopping the demo's processes", file=sys.stderr)
    finally:
        for p in reversed(procs):
            stop_group(p)
        for f in logs.values():
            f.close()
    with lock:
        traj = np.array([s[1:] for s in states]) if states else np.zeros((0, 3))
        st = status.get("station")
    if traj.shape[0] == 0 or st is None:
        print("the demo produced no telemetry; see the logs in", out, file=sys.stderr)
        return 1
    devs = np.array([world.path.project(p[:2])[1] for p in traj])
    c = st.counters
    reached = bool(c.get("goal_reached", 0))
    elapsed = states[-1][0] - states[0][0]
    summary = {"reached_goal": reached, "time_s": round(elapsed, 1), "mean_dev_m": round(float(devs.mean()), 4),
               "max_dev_m": round(float(devs.max()), 4),
               "methods": {k[7:]: v for k, v in c.items() if k.startswith("method_")},
               "refined_pairs": c.get("refined_pairs"), "raw_pairs": c.get("raw_pairs"),
               "missed_deadlines": c.get("missed_deadlines"), "solve_ms_median": st.latencies_ms.get("solve_median")}
    print("summary:", json.dumps(summary))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim_learner.figures import _world

    fig, ax = plt.subplots(figsize=(9, 4))
    _world(ax, world)
    ax.plot(traj[:, 0], traj[:, 1], color="tab:blue", label=f"learner over Zenoh + {args.link.upper()}")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("HIL demo: SCM transfer of the teacher MPC")
    fig.tight_layout()
    fig.savefig(out / "demo_trajectory.png", dpi=120)
    plt.close(fig)
    print(f"figure: {out / 'demo_trajectory.png'}; pair store: {store}; logs: {out}/*.log")
    return 0 if reached else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scmbridge demo", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--link", choices=["can", "udp", "mavlink"], default="can", help="vehicle link")
    ap.add_argument("--out", default="demo_out")
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds before the demo gives up")
    ap.add_argument("--inprocess", action="store_true", help="the in-process SC transfer example instead")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--commands", type=int, default=8, help="(--inprocess) teacher commands to show")
    args = ap.parse_args(argv)
    return inprocess(args) if args.inprocess else hil(args)
