"""``scmbridge demo --robots A,B,... | --count N``: several robots, each a driver host and a station process, behind one
router hub (this process), with one line for the whole fleet and one figure; each robot's summary, then the fleet's.
The one-robot demo and what both read of a robot (:class:`bridge.tools.demo.Monitor`) are in :mod:`bridge.tools.demo`,
which hands itself to :func:`fleet` (as to its SITL runs: no module imports the other back).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import types
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from bridge.core.logsink import print_line


def _fleet_line(mons: dict, world, t: float) -> str:
    """One line for the whole fleet: how many are at the goal, each robot's progress (or the spread of them)."""
    parts, at_goal, missed, pairs = [], 0, 0, 0
    progress = []
    for robot, mon in mons.items():
        with mon.lock:
            st = mon.status.get("station")
            pos = mon.states[-1] if mon.states else None
        if st is None or pos is None:
            parts.append(f"{robot} --")
            continue
        c = st.counters
        at_goal += int(bool(c.get("goal_reached", 0)))
        missed += c.get("missed_deadlines", 0)
        pairs += c.get("refined_pairs", 0)
        s_arc, dev = world.path.project(np.array(pos[1:3]))
        pct = 100 * s_arc / world.path.length
        progress.append(pct)
        parts.append(f"{robot} {pct:3.0f}% {100 * dev:4.1f}cm")
    head = f"t={t:5.1f}s at goal {at_goal}/{len(mons)} pairs={pairs} missed={missed}"
    if len(mons) <= 6:
        return head + " | " + " | ".join(parts)
    if not progress:
        return head + " | waiting for stations and drivers..."
    return head + (f" | progress min {min(progress):.0f}% median {float(np.median(progress)):.0f}% "
                   f"max {max(progress):.0f}% ({len(progress)}/{len(mons)} reporting)")


def _fleet_figure(out, world, trajs: dict[str, np.ndarray], link: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim_learner.figures import draw_mission

    fig, ax = plt.subplots(figsize=(9, 4))
    draw_mission(ax, world)
    colors = plt.cm.tab10(np.arange(len(trajs)) % 10)
    for (robot, traj), color in zip(trajs.items(), colors):
        if traj.shape[0]:
            ax.plot(traj[:, 0], traj[:, 1], color=color, lw=1.2, label=robot)
    ax.legend(loc="upper right", fontsize=7, ncol=max(1, len(trajs) // 6))
    ax.set_title(f"HIL demo: {len(trajs)} learners over Zenoh + {link.upper()}, one base station")
    fig.tight_layout()
    fig.savefig(out / "demo_fleet.png", dpi=120)
    plt.close(fig)


def fleet(args: argparse.Namespace, robots: list[str], demo: types.ModuleType) -> int:
    """Several robots, each a driver host and a station process, behind this one router hub; ``demo``: the
    :mod:`bridge.tools.demo` module (its ``Monitor`` reads each robot)."""

    from bridge.core.config import load_mission
    from bridge.nodes.zsession import free_port, make_config, open_session, tcp
    from bridge.tools.procs import Children, emulated_link

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    world = load_mission(args.mission)
    if world.start is None:
        raise SystemExit(f"scmbridge demo: error: mission {world.name!r} has no start pose for the emulated learner")
    timeout = args.duration
    port = free_port()
    x0 = ",".join(f"{a:.6f}" for a in world.start)  # every robot in its own namespace: the same start for all
    mons: dict = {}
    stations: dict[str, object] = {}
    stores = {r: out / f"pairs-{r}.bin" for r in robots}
    for store in stores.values():
        store.unlink(missing_ok=True)  # the demo starts from scratch
    from bridge.tools.cli import ONE_BLAS_THREAD

    # the stations share the cores: one BLAS thread each, as the units run them
    env = dict(os.environ, **ONE_BLAS_THREAD)
    interrupted = False
    t0 = time.monotonic()
    with ExitStack() as stack:
        session = stack.enter_context(open_session(make_config(mode="router", listen=[tcp(port)])))
        kids = stack.enter_context(Children())
        try:
            for robot in robots:
                logs = {n: stack.enter_context(open(out / f"{robot}-{n}.log", "w")) for n in ("driver", "station")}
                mons[robot] = demo.Monitor(session, robot)
                client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
                wd = out / robot
                wd.mkdir(exist_ok=True)
                driver_args = emulated_link(kids, args.link, wd, x0, timeout + 15, logs["driver"])
                kids.spawn(["driver", "--engage", *driver_args, *client, "--duration", str(timeout + 15)],
                           logs["driver"])
                stations[robot] = kids.spawn(
                    ["station", *client, "--start", "--store", str(stores[robot]), "--exit-at-goal", "--duration",
                     str(timeout), *(["--mission", args.mission] if args.mission else [])], logs["station"], env=env)
            tty = sys.stdout.isatty()
            last_print = 0.0
            others = [p for p in kids.procs if p not in stations.values()]
            # until every station has ended (each exits at its goal) or a driver host or learner died, or the timeout
            while time.monotonic() - t0 < timeout + 20:
                if all(p.poll() is not None for p in stations.values()) or any(p.poll() is not None for p in others):
                    break
                time.sleep(0.1)
                now = time.monotonic()
                if now - last_print >= (0.5 if tty else 5.0):
                    last_print = now
                    line = _fleet_line(mons, world, now - t0)
                    print(("\r" + line.ljust(150)) if tty else line, end="" if tty else "\n", flush=True)
            if tty:
                print()
        except KeyboardInterrupt:
            interrupted = True
            print("\ninterrupted: stopping the demo's processes", file=sys.stderr)
    summaries: dict[str, dict | None] = {r: demo._robot_summary(mons[r], world, args.corridor) if r in mons else None
                                        for r in robots}
    trajs = {}
    for robot in robots:
        s = summaries[robot]
        if s is None:
            print(f"summary {robot}: no telemetry; see {out}/{robot}-*.log")
            continue
        trajs[robot] = s.pop("_traj")
        print_line(f"summary {robot}: " + json.dumps(s))
    reached = [r for r in robots if summaries[r] is not None and summaries[r]["reached_goal"]]
    missing = [r for r in robots if r not in reached]
    times = [summaries[r]["time_s"] for r in reached]
    fleet_summary = {"robots": len(robots), "reached_goal": reached, "not_at_goal": missing,
                     "wall_s": round(time.monotonic() - t0, 1),
                     "time_s_max": max(times) if times else None,
                     "missed_deadlines": {r: summaries[r]["missed_deadlines"] for r in robots if summaries[r]},
                     "interrupted": interrupted}
    print_line("fleet: " + json.dumps(fleet_summary))
    for r in reached:
        if summaries[r]["goal_dist_m"] is not None and summaries[r]["goal_dist_m"] > world.goal_tolerance:
            print(f"note: {r} met the mission's goal rule {summaries[r]['goal_dist_m']:.2f} m from the goal point "
                  f"(past the path's end; max deviation {summaries[r]['max_dev_m']:.2f} m)")
    if trajs:
        _fleet_figure(out, world, trajs, args.link)
        print(f"figure: {out / 'demo_fleet.png'}; pair stores: {out}/pairs-*.bin; logs: {out}/*-driver.log, "
              f"{out}/*-station.log")
    if missing:
        print(f"not at the goal: {', '.join(missing)}", file=sys.stderr)
        return 1
    return 0
