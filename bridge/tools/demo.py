"""``scmbridge demo``: the hardware-in-the-loop demo over Zenoh on 127.0.0.1, or ``--inprocess`` the SC transfer alone.

A driver host with the emulated learner on the chosen link, a station (teacher MPC + transfer, starting with no
pairs) and this process as the Zenoh hub; the learner drives the mission (the paper's S-path) while a live line
shows progress; at the end a summary, the figures and the logs in ``--out``. ``--count N`` or ``--robots a,b,c``:
several robots, each its own driver host and station, behind the same hub. It ends at the goal, after ``--duration``
or on Ctrl-C, leaving no process behind; exit 1 names any robot that did not reach its goal. ``--drift battery`` (one
robot on CAN): the emulated learner changes mid-run (``sim_learner.can_ecu.Drift``) and the station re-learns the
cells that no longer hold (``[transfer] adapt``); the summary names them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from collections import Counter
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from bridge.core.args import positive_float, robots_arg
from bridge.core.errors import UsageError
from bridge.core.logsink import print_line
from bridge.nodes.node import Inputs
from bridge.nodes.station_status import pairing_figures
from bridge.tools.demo_calibrate import calibrate_first, calibration_budget, check_calibrate, grid, method_shares
from bridge.tools.guard_log import GuardLog
from drivers import link_names

#: ``--transfer``'s station settings (``[transfer]`` mapper, exploration and, by default, limits): on, the SC transfer;
#: off, the paper's baseline learner (Section 5.2), which applies the teacher's commands directly, unaware of its
#: own dynamics: unmapped (identity: only clipped to the learner's range, as ``sim mpc``'s learner clamps them), no
#: exploration, and the MPC bounded by the teacher's own range, ``sim mpc``'s ``teacher_range`` baseline
TRANSFER = {"on": ("scm", "guided", "learned"), "off": ("identity", "off", "teacher")}


def transfer_table(transfer: str, limits: str | None) -> str:
    """The station's ``[transfer]`` lines (its header included) for ``--transfer`` and ``--limits`` (None: the
    transfer's own, :data:`TRANSFER`). ``--transfer off --limits learned`` is the teacher's commands unmapped under
    the MPC bounded by the limits learned from the pairs (what ``--transfer off`` did at first: ``sim mpc``'s
    ``true_range`` baseline with learned limits in place of the true ones; on a vehicle that follows its commands,
    the teacher's reference, docs/BENCHMARKS.md "The transfer on SITL")."""
    mapper, exploration, default_limits = TRANSFER[transfer]
    return (f'[transfer]\nmapper = "{mapper}"\nexploration = "{exploration}"\n'
            f'limits = "{limits or default_limits}"\n')


def teacher_table(args: argparse.Namespace) -> str:
    """The station's ``[teacher]`` lines for ``--curve-margin`` (none without it: the station's default): a margin
    given slows the MPC for bends from the first tick (``slow_for_bends = "always"``)."""
    if args.curve_margin is None:
        return ""
    return f'\n[teacher]\ncurve_margin = {args.curve_margin!r}\nslow_for_bends = "always"\n'


def inprocess(args: argparse.Namespace) -> int:

    from sim_learner.dynamics import MPC_TEACHER_V, MPC_TEACHER_W, mpc_learner
    from transfer.domain import Bounds
    from transfer.pairs import teacher_equivalent
    from transfer.policy import make_policy
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
    policies = {name: make_policy(store, name, seed=args.seed) for name in ("scm", "identity", "barycentric")}
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


#: an echo's driving counts until the next echo, but never for longer than this, s (echoes come at the driver host's
#: loop rate, 50 Hz; a longer gap is a host that stopped echoing, not driving)
ECHO_GAP_S = 0.5


def driving_time(applied: list[tuple[float, str, int | None]], t0: float, t1: float) -> float:
    """Seconds between ``t0`` and ``t1`` during which the vehicle was driven (applied reason ``cmd`` or
    ``clamped``): a run's time apart from its pauses, estops and waits, which can be a large share of a run."""
    echoes = sorted((a[0], a[1] in ("cmd", "clamped")) for a in applied if t0 <= a[0] <= t1)
    return float(sum(min(b[0] - a[0], ECHO_GAP_S) for a, b in zip(echoes, echoes[1:]) if a[1]))


#: the methods the live line always shows (the transfer's, in the order a run uses them), then any other one counted
LINE_METHODS = ("scm", "barycentric", "direct", "perturb", "stop")


def touched_an_obstacle(world, points) -> bool:
    """Whether a disc of the paper's vehicle radius at any of the ``points`` (n x 2, m) touched an obstacle of the
    mission ``world`` (the demo's summary, as ``sim mpc`` judges its runs)."""
    from sim_learner.experiments import VEHICLE_RADIUS

    return bool(any(world.collides(p, VEHICLE_RADIUS) for p in points))


def method_counts(counters: dict[str, int]) -> str:
    """``scm=12 barycentric=230 direct=4 perturb=0 stop=9``: every command the station sent, by method, so the counts
    add up to what it sent."""
    others = sorted(k[7:] for k in counters if k.startswith("method_") and k[7:] not in LINE_METHODS)
    return " ".join(f"{m}={counters.get(f'method_{m}', 0)}" for m in (*LINE_METHODS[:-1], *others, LINE_METHODS[-1]))


class Monitor:
    """The demo's view of the run: the learner's states and each node's latest status, from Zenoh callbacks."""

    def __init__(self, session, robot: str) -> None:
        from bridge.core import wire as M

        self.states: list[tuple[float, float, float, float]] = []
        self.status: dict = {}
        self.applied: list[tuple[float, str, int | None]] = []  # (stamp, reason, cmd_seq): the driver host's clock
        self.cmds: dict[int, str] = {}  # seq -> method (the station's current run)
        # (this process's monotonic time of receipt, box [v_min, v_max, w_min, w_max]) each time the learned limits
        # changed: what the station knew of the learner before and after a change of it (``--param-at``)
        self.limits: list[tuple[float, list[float]]] = []
        self.driving = threading.Event()  # the vehicle has driven a command (applied reason cmd or clamped)
        self.guards = GuardLog()  # when and where the station's guards stopped the run
        self.lock = threading.Lock()
        self.inputs = Inputs()
        keys = M.Keys(robot)
        self.inputs.subscribe(session, keys.state, M.LearnerState, "state", self._state)
        self.inputs.subscribe(session, keys.applied, M.Applied, "applied", self._applied)
        self.inputs.subscribe(session, keys.cmd, M.Command, "cmd", self._cmd)
        self.inputs.subscribe(session, keys.limits, M.Limits, "limits", self._limits)
        for node in ("station", "driver"):
            self.inputs.subscribe(session, M.status_key(robot, node), M.Status, "status", self._status)

    def _state(self, st, now: float) -> None:
        with self.lock:
            self.states.append((st.stamp, st.x, st.y, st.theta))

    def _status(self, st, now: float) -> None:
        with self.lock:
            self.status[st.node] = st
            if st.node == "station":
                self.guards.note(st, self.states[-1] if self.states else None)

    def _applied(self, a, now: float) -> None:
        with self.lock:
            self.applied.append((a.stamp, a.reason, a.cmd_seq))
        if a.reason in ("cmd", "clamped"):
            self.driving.set()

    def _cmd(self, c, now: float) -> None:
        with self.lock:
            self.cmds[c.seq] = c.method

    def _limits(self, lim, now: float) -> None:
        with self.lock:
            box = [float(x) for x in lim.box]
            if not self.limits or self.limits[-1][1] != box:  # published each second: kept when they change
                self.limits.append((now, box))

    def limits_at(self, t: float) -> list[float] | None:
        """The learned limits' box the station last published before ``t`` (this process's monotonic time)."""
        with self.lock:
            before = [box for at, box in self.limits if at < t]
        return before[-1] if before else None

    def line(self, world, t: float) -> str:
        """One line of live progress."""
        with self.lock:
            st = self.status.get("station")
            pos = self.states[-1] if self.states else None
        if st is None or pos is None:
            return f"t={t:5.1f}s waiting for station and driver..."
        c = st.counters
        s_arc, dev = world.path.project(np.array(pos[1:3]))
        return (f"t={t:5.1f}s rate={st.rates_hz.get('loop', 0):.0f}Hz {method_counts(c)} "
                f"pairs={c.get('refined_pairs', 0)} dev={100 * dev:5.1f}cm "
                f"progress={100 * s_arc / world.path.length:5.1f}% [{st.text}]")

    def summary(self, world, corridor_m: float | None = None) -> dict | None:
        """The run's figures over its driving time, or None if it produced no telemetry: from the first command the
        vehicle executed to the goal (the mission's own rule on the poses), or to the last executed command; the
        time parked before and after it is reported apart, and neither its poses nor its stop commands count.
        All times are the driver host's stamps (poses and applied echoes: one clock, whatever the machines).
        ``reached_goal`` is false for a run that left its corridor (any pose of it more than ``corridor_m``, default
        :data:`bridge.tools.sitl_verdict.CORRIDOR_M`, from the path), whatever the goal rule said."""
        from bridge.tools.demo_calibrate import deviations
        from bridge.tools.sitl_verdict import CORRIDOR_M, corridor

        with self.lock:
            states = list(self.states)
            st = self.status.get("station")
            applied, cmds = list(self.applied), dict(self.cmds)
        if not states or st is None:
            return None
        driving = [a for a in applied if a[1] in ("cmd", "clamped")]
        t0 = driving[0][0] if driving else states[0][0]
        goal = next((s[0] for s in states if s[0] >= t0 and world.reached(s[1:3])), None)
        t1 = goal if goal is not None else (driving[-1][0] if driving else states[-1][0])
        run = [s for s in states if t0 <= s[0] <= t1] or states
        traj = np.array([s[1:] for s in run])
        collided = touched_an_obstacle(world, traj[:, :2])
        lane = corridor(world.path.points, traj[:, :2], CORRIDOR_M if corridor_m is None else corridor_m)
        c = st.counters
        seqs = [a[2] for a in applied if a[2] is not None and t0 <= a[0] <= t1]
        if seqs and cmds:  # the commands of the driving time (not the stops parked at the goal)
            lo, hi = min(seqs), max(seqs)
            methods = dict(Counter(m for seq, m in cmds.items() if lo <= seq <= hi))
        else:
            methods = {k[7:]: v for k, v in c.items() if k.startswith("method_")}
        driving_s = driving_time(applied, t0, t1)
        goal_rule = bool(c.get("goal_reached", 0)) or goal is not None
        return {"reached_goal": goal_rule and not lane["left_corridor"], "goal_rule_met": goal_rule, **lane,
                "time_s": round(t1 - t0, 1),
                "driving_s": round(driving_s, 1), "paused_s": round(max(0.0, t1 - t0 - driving_s), 1),
                "parked_before_s": round(max(0.0, t0 - states[0][0]), 1),
                "parked_after_s": round(max(0.0, states[-1][0] - t1), 1),
                **deviations(world.path, traj),  # mean and max over the run, mean over the path's last half
                "collided": collided,  # a disc of the paper's vehicle radius touched an obstacle
                # how far from the goal point it stopped (the station's goal flag alone could be a pose far away)
                "goal_dist_m": round(float(np.hypot(*(traj[-1, :2] - np.asarray(world.goal)))), 3),
                "methods": methods,
                **pairing_figures(c),  # the refined and raw pairs, and why intervals made no pair
                "missed_deadlines": c.get("missed_deadlines"), "solve_ms_median": st.latencies_ms.get("solve_median"),
                "cells_relearned": c.get("cells_relearned"), "changed_cells": list(st.changed_cells),
                "guard_stops": self.guards.summary(t0),
                "_traj": np.array([s[1:] for s in states])}


def _figure(out, world, traj, link: str, mon: Monitor, transfer: str = "on") -> None:
    """The trajectory figure, coloured by each command's method (bridge/tools/demo_view.py), titled by what ran."""
    from bridge.tools.demo_view import methods_along, trajectory_figure

    with mon.lock:
        methods = methods_along(list(mon.states), list(mon.applied), dict(mon.cmds))
    title = "HIL demo: " + ("SC transfer of the teacher MPC" if transfer == "on"
                            else "the paper's baseline (the teacher's commands unmapped)")
    trajectory_figure(out, world, traj, methods, link.upper() if link.islower() else link, title)


def _watch(mon: Monitor, kids, world, timeout: float) -> None:
    """Print progress until the station exits (at the goal), a child dies, a guard of the station's pauses the
    mission (no person is there to resume it), or the timeout."""
    t0 = time.monotonic()
    tty = sys.stdout.isatty()
    last_print = 0.0
    while time.monotonic() - t0 < timeout + 20 and not kids.any_exited() and not mon.guards.stopped:
        time.sleep(0.1)
        now = time.monotonic()
        if now - last_print >= (0.5 if tty else 5.0):
            last_print = now
            line = mon.line(world, now - t0)
            print(("\r" + line.ljust(130)) if tty else line, end="" if tty else "\n", flush=True)
    if tty:
        print()


def hil(args: argparse.Namespace, robot: str) -> int:
    """Three processes over Zenoh on a free loopback port, watched by this one (see the module docstring)."""
    from pathlib import Path

    from bridge.core.config import load_mission
    from bridge.nodes.zsession import free_port, make_config, open_session, tcp
    from bridge.tools.procs import Children, emulated_link

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    store = out / "pairs.bin"
    store.unlink(missing_ok=True)  # the demo starts from scratch
    world = load_mission(args.mission)
    if world.start is None:
        raise SystemExit(f"scmbridge demo: error: mission {world.name!r} has no start pose for the emulated learner")
    port = free_port()
    x0 = ",".join(f"{a:.6f}" for a in world.start)
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    # --transfer off: the paper's baseline; --drift: the learner changes, and the station re-learns what no longer holds
    # by its defaults ([transfer] adapt = true, [teacher] curve_margin once the learner changed)
    (out / "station.toml").write_text(transfer_table(args.transfer, args.limits)
                                      + ('at_limit = "region"\n' if args.calibrate else "") + teacher_table(args))
    station_cfg = ["--config", str(out / "station.toml")]
    mon, cal = None, None
    up = args.duration + 15 + calibration_budget(args.calibrate)  # the driver host and its link outlive the mission
    with ExitStack() as stack:
        logs = {name: stack.enter_context(open(out / f"{name}.log", "w"))
                for name in ("driver", "station", *(["calibrate"] if args.calibrate else []))}
        # this monitor is the hub: a Zenoh router the driver host and the station connect to as clients
        # (peers do not forward between other peers)
        session = stack.enter_context(open_session(make_config(mode="router", listen=[tcp(port)])))
        kids = stack.enter_context(Children())
        try:
            driver_args = emulated_link(kids, args.link, out, x0, up, logs["driver"])
            drift = ["--drift", args.drift] if args.drift else []
            kids.spawn(["driver", "--engage", *driver_args, *drift, *client, "--duration", str(up)], logs["driver"])
            mission = ["--mission", args.mission] if args.mission else []
            mon = Monitor(session, robot)
            if args.calibrate:  # the paper's calibrated start: the mission's figures count from after it, and the
                # mission starts where the calibration left the robot (as the uncalibrated run on its start pose)
                from bridge.tools.demo_calibrate import place_after_calibration, restart_monitor
                cal = calibrate_first(args.calibrate, client, out / "station.toml", store, logs["calibrate"])
                placed = place_after_calibration(mon, args.mission, out, "odometry")
                if placed is not None:
                    world, path = placed
                    mission = ["--mission", path]
                restart_monitor(mon)
            kids.spawn(["station", *client, *station_cfg, "--start", "--store", str(store), "--exit-at-goal",
                        "--duration", str(args.duration), *mission], logs["station"])
            _watch(mon, kids, world, args.duration)
        except KeyboardInterrupt:
            print("\ninterrupted: stopping the demo's processes", file=sys.stderr)
    summary = mon.summary(world, corridor_m=args.corridor) if mon is not None else None
    if summary is None:
        print("the demo produced no telemetry; see the logs in", out, file=sys.stderr)
        return 1
    traj = summary.pop("_traj")
    summary.update(method_shares=method_shares(summary["methods"]), **({"calibration": cal} if cal else {}))
    print_line("summary: " + json.dumps(summary))
    _figure(out, world, traj, args.link, mon, args.transfer)
    from bridge.tools.pairs_cli import pairs_figure

    pairs_figure(store, out / "demo_pairs.png")  # what was learned: command domains, limits, refined pairs
    print(f"figures: {out / 'demo_trajectory.png'}, {out / 'demo_pairs.png'}; pair store: {store}; logs: {out}/*.log")
    return 0 if summary["reached_goal"] else 1


def _wait_state(mon, state: str, timeout: float) -> bool:
    """Wait until the driver host's status says ``state`` (False after ``timeout`` s)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        with mon.lock:
            st = mon.status.get("driver")
        if st is not None and st.state == state:
            return True
        time.sleep(0.05)
    return False


def _robot_summary(mon: Monitor, world, corridor_m: float | None = None) -> dict | None:
    """:meth:`Monitor.summary` of one robot of the fleet: its figures already stop at its goal (its driver host
    keeps publishing poses there while the other robots drive on)."""
    return mon.summary(world, corridor_m=corridor_m)


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--link", choices=link_names(), default=None,
                    help="vehicle link (default: can; mavlink with --sitl)")
    ap.add_argument("--mission", default=None, help="mission file (default: the paper's S-path)")
    ap.add_argument("--out", default="demo_out", help="directory for the figures, the pair stores and the logs")
    ap.add_argument("--duration", type=positive_float, default=None,
                    help="seconds before the demo gives up (default 120; 30 more per extra robot)")
    who = ap.add_mutually_exclusive_group()
    who.add_argument("--robots", type=robots_arg, default=None,
                     help="emulated learners to run at once, comma-separated names, each its own driver host and "
                          "station process (default: one robot, demo)")
    who.add_argument("--count", type=int, default=None, help="N emulated learners demo1..demoN at once")
    ap.add_argument("--sitl", default=None, metavar="PATH",
                    help="ArduPilot's Rover SITL binary (or its directory) as the learner, over --link mavlink")
    ap.add_argument("--sitl-model", default="rover-skid", choices=("rover-skid", "rover", "motorboat"),
                    help="(--sitl) the simulated body")
    ap.add_argument("--sitl-params", default=None, metavar="FILE.parm",
                    help="(--sitl) an extra parameter file (e.g. CRUISE_SPEED, ATC_STR_RAT_MAX: another learner)")
    ap.add_argument("--transfer", choices=("on", "off"), default="on",
                    help="(one robot) off: the paper's baseline learner: the teacher's commands go to the vehicle "
                         "unmapped (identity, clipped to the learner's range), no exploration, the MPC bounded by the "
                         "teacher's own range (sim mpc's teacher_range baseline); pairs are still learned and reported")
    ap.add_argument("--limits", choices=("learned", "teacher"), default=None,
                    help="(one robot) the station's [transfer] limits, what bounds the MPC: learned (default with "
                         "--transfer on) or the teacher's own range (default with off); --transfer off --limits "
                         "learned: the teacher's commands unmapped under the learned limits, how the teacher's "
                         "reference is made on SITL (docs/BENCHMARKS.md)")
    ap.add_argument("--pair-settle", type=float, default=None, metavar="S",
                    help="(--sitl) the station's [station] pair_settle_s: pairs only where the command had been "
                         "steady S seconds (default 0.5 for SITL's lagging skid body; 1 for its Ackermann body, and "
                         "2.5 for its commands on an edge of its range; 0: every pair, as the paper)")
    ap.add_argument("--reference", default=None, metavar="auto|none|SUMMARY.json",
                    help="(--sitl) what the run is judged against: auto (the default) runs the teacher on SITL "
                         "itself after it, the stock rover of the same frame given the range the run learned "
                         "(--transfer off --limits learned); SUMMARY.json, the summary of such a run made before; "
                         "none, no reference (the time and deviation verdicts say n/a)")
    ap.add_argument("--teacher-ref", default=None, metavar="SUMMARY.json", help=argparse.SUPPRESS)
    ap.add_argument("--baseline", action="store_true",
                    help="(--sitl, --transfer on) also run the paper's baseline (--transfer off) on a fresh SITL and "
                         "judge the transfer against it; one figure then shows reference, transfer and baseline")
    ap.add_argument("--identify", action=argparse.BooleanOptionalAction, default=None,
                    help="(--sitl) measure the learner's range before the mission (bounded probes each way and "
                         "straight, by the station's own loop): its top speed and turn rates, whether it turns in "
                         "place, how long it settles, a car's tightest turn (a mission it cannot follow is stopped "
                         "as outside the method's assumption); the vehicle's parameters only bound it, and --turn, "
                         "--start and --pair-settle follow from it unless given. On by default for the transfer "
                         "(--transfer on); --no-identify reads the range from the vehicle's parameters")
    ap.add_argument("--corridor", type=positive_float, default=1.0, metavar="M",
                    help="a run that took any pose more than M metres from the path did not reach its goal, "
                         "whatever the goal rule said (default 1.0)")
    ap.add_argument("--param-at", action="append", default=[], metavar="S:NAME=VALUE",
                    help="(--sitl) set the vehicle's parameter NAME to VALUE S seconds after the vehicle first "
                         "drove a command of the station (PARAM_SET from the ground station, confirmed by its "
                         "PARAM_VALUE: a learner that changes mid-run); repeatable")
    ap.add_argument("--adapt", action="store_true",
                    help="(--sitl) the station's [transfer] adapt = true: re-learn cells whose learner changed")
    ap.add_argument("--drift", default=None, metavar="KIND[:AT[:OVER[:AMOUNT]]]",
                    help="(one robot, --link can) the learner changes mid-run: battery (the motors' top speed falls "
                         "30 %%) or wheel (the left wheel drags), AT s after the wheels first turn, over OVER s "
                         "(default 20:10); the station re-learns the changed cells ([transfer] adapt)")
    ap.add_argument("--turn-probe", choices=("at-command", "at-top-speed"), default="at-command",
                    help="(--sitl) the station's [transfer] turn_probe: probe the yaw-rate limits at the learner's top "
                         "speed instead of at the command's (--turn needs-speed does so whatever this says)")
    ap.add_argument("--turn", choices=("in-place", "needs-speed"), default=None,
                    help="(--sitl) the station's [transfer] turn: needs-speed for a vehicle that cannot turn in place "
                         "(its yaw-rate limits learned as curvatures, the MPC planning within them; default with "
                         "--sitl-model rover), in-place for one that can (the default otherwise)")
    ap.add_argument("--start", choices=("mission", "on-path"), default=None,
                    help="(--sitl) where the vehicle starts relative to the mission: mission, its start pose (the "
                         "paper's: 0.3 m beside the path facing 45 degrees away, a turn on the spot); on-path, on the "
                         "path's first point facing along it, as a car-like vehicle is placed (default with --turn "
                         "needs-speed)")
    ap.add_argument("--curve-margin", type=float, default=None, metavar="SHARE",
                    help="(one robot) the station's [teacher] curve_margin, from the first tick (slow_for_bends = "
                         "always): the MPC slows for a bend the learned yaw-rate limit cannot turn at its top speed, "
                         "using this share of the limit (default: the station's, once the learner changed; 0: the "
                         "paper's MPC always)")
    ap.add_argument("--calibrate", type=grid, default=None, metavar="NVxNW",
                    help="(one robot) the paper's calibrated start: scmbridge calibrate's grid of learner commands "
                         "(e.g. 5x5) on the learner first, then the mission from that pair store")
    ap.add_argument("--inprocess", action="store_true", help="the in-process SC transfer example instead")
    ap.add_argument("--seed", type=int, default=0, help="(--inprocess) random generator seed")
    ap.add_argument("--commands", type=int, default=8, help="(--inprocess) teacher commands to show")


def run(args: argparse.Namespace) -> int:
    if args.count is not None and args.count < 1:
        raise UsageError("--count must be at least 1")
    # the demo's robots keep their estop latches (and the latches' records) under --out, with the demo's other files,
    # never in the lab's state directory: a demo neither reads a lab robot's latch nor leaves one (an explicit
    # SCMBRIDGE_STATE_DIR / SCMBRIDGE_RECORD_DIR is obeyed)
    os.environ.setdefault("SCMBRIDGE_STATE_DIR", str(Path(args.out).resolve() / "state"))
    os.environ.setdefault("SCMBRIDGE_RECORD_DIR", str(Path(args.out).resolve() / "records"))
    robots = args.robots or ([f"demo{k + 1}" for k in range(args.count)] if args.count else ["demo"])
    if args.duration is None:
        args.duration = 120.0 + 30.0 * (len(robots) - 1)
    if args.drift is not None:
        from sim_learner.can_ecu import Drift

        if args.link not in (None, "can") or len(robots) != 1 or args.count or args.inprocess or args.sitl is not None:
            raise UsageError("--drift changes one emulated CAN robot: --link can, one robot")
        try:
            Drift.parse(args.drift)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    if args.curve_margin is not None and not 0.0 <= args.curve_margin <= 1.0:
        raise UsageError(f"--curve-margin must be in [0, 1], got {args.curve_margin}")
    if args.curve_margin is not None and (len(robots) != 1 or args.count or args.inprocess):
        raise UsageError("--curve-margin sets one robot's station: not with --robots, --count or --inprocess")
    if (args.transfer != "on" or args.limits is not None) and (len(robots) != 1 or args.count or args.inprocess):
        raise UsageError("--transfer and --limits set one robot's station: not with --robots, --count or --inprocess")
    if args.sitl is None and (args.turn is not None or args.start is not None):
        raise UsageError("--turn and --start set the SITL demo's station and mission: they take --sitl")
    check_calibrate(args, robots)
    if args.sitl is None and (args.baseline or args.reference is not None or args.teacher_ref is not None):
        raise UsageError("--baseline and --reference add runs on SITL: they take --sitl")
    if args.inprocess:
        return inprocess(args)
    if args.sitl is not None:
        from bridge.tools.demo_sitl_run import sitl_hil

        return sitl_hil(args, sys.modules[__name__])
    if args.link is None:
        args.link = "can"
    if len(robots) == 1 and not args.count:
        return hil(args, robots[0])
    from bridge.tools.demo_fleet import fleet

    return fleet(args, robots, sys.modules[__name__])
