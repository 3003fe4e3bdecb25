"""``scmbridge demo --sitl``'s runs (:mod:`bridge.tools.demo_sitl` says what each does, as a lab would with its own
rover): one run of the chosen role, then, by default, the reference made on SITL itself (``--reference auto``: the
teacher on the stock rover of the same frame, bounded by the range the first run learned), and, with
``--baseline``, the paper's baseline; one summary whose fields are named by role, one verdict line per claim
(:mod:`bridge.tools.sitl_verdict`), a figure per run titled by what ran and one with all of them together.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from contextlib import ExitStack
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from bridge.core.errors import UsageError
from bridge.core.logsink import print_line
from bridge.tools import sitl_verdict as V

#: the longest the identification may take before the mission (``--identify``), s
IDENTIFY_S = 90.0
#: the longest the station's start-up may take (a first start compiles the MPC's kernels: over a minute on a
#: loaded machine) before the run's ``--duration`` begins, s
STARTUP_S = 90.0
#: the teacher's own range (paper Table 2): what an automatic reference is never given more of, m/s and deg/s
TEACHER_V_MAX = 0.6
TEACHER_W_MAX_DEG = 45.0


def reference_parm(model: str, learned: dict[str, Any] | None, params: dict[str, float]) -> str:
    """The parameter file of the automatic reference (``--reference auto``): the stock rover of the same frame given
    the range the run before it learned of the learner (what the paper's ideal teacher is bounded by: the learner's
    true range), never more than the learner's own caps nor the teacher's range. As deploy/examples/
    sitl-teacher.parm (skid) and sitl-teacher-ackermann.parm (Ackermann: the stock loop with its turn-rate
    feed-forward raised, which at these speeds turns too little otherwise) are made by hand."""
    from bridge.tools.demo_sitl import learner_range

    (_, v_cap), (_, w_cap) = learner_range(params)
    v_cap, w_cap_deg = min(v_cap, TEACHER_V_MAX), min(math.degrees(w_cap), TEACHER_W_MAX_DEG)
    v, w_deg = v_cap, w_cap_deg
    if learned and learned.get("v") and learned["v"][1] > 0.1:
        v = min(v_cap, float(learned["v"][1]))
    if model != "rover" and learned and learned.get("w"):
        w_seen = min(abs(float(learned["w"][0])), abs(float(learned["w"][1])))
        if w_seen > 0.05:
            w_deg = min(w_cap_deg, math.degrees(w_seen))
    lines = ["# the automatic reference: the stock rover given the learner's range (scmbridge demo --reference auto)",
             f"WP_SPEED {v:.3f}", f"ATC_STR_RAT_MAX {w_deg:.1f}"]
    if model == "rover":
        lines.append("ATC_STR_RAT_FF 1.5")
    return "\n".join(lines) + "\n"


def sitl_hil(args: argparse.Namespace, demo: ModuleType) -> int:
    """``--sitl``: the run of the role ``--transfer``/``--limits`` say, then the baseline (``--baseline``) and the
    reference (``--reference``), then the verdict. Exit 0 only if the first run reached its goal. ``demo`` is
    :mod:`bridge.tools.demo` (its monitor and watch), handed in by it rather than imported: it imports this module."""
    from bridge.tools.demo_sitl import learned_limits, teacher_reference

    if args.link not in (None, "mavlink"):
        raise UsageError("--sitl is ArduPilot's Rover: it takes --link mavlink")
    binary = Path(args.sitl)
    binary = binary / "ardurover" if binary.is_dir() else binary
    if not binary.is_file():
        raise UsageError(f"--sitl {args.sitl}: no ArduPilot SITL binary there")
    reference = args.teacher_ref or args.reference or "auto"
    ref_file = None if reference in ("auto", "none") else teacher_reference(reference)
    out = Path(args.out)
    role = V.role_of(args.transfer, args.limits)
    if getattr(args, "identify", None) is None:  # measured, not read, for the transfer (the baseline reads it)
        args = argparse.Namespace(**{**vars(args), "identify": role == "learner"})
    runs: dict[str, dict[str, Any]] = {}
    first = sitl_once(demo, args, binary, out, role)
    if first is None:
        return 1
    runs[role] = first
    if first["interrupted"]:  # Ctrl-C (or SIGTERM) ends the demo, not only its first run
        args = argparse.Namespace(**{**vars(args), "baseline": False})
        reference = "none"
    if args.baseline and role == "learner":
        # the paper's baseline: the teacher's commands within what the vehicle accepts, nothing measured first
        b_args = argparse.Namespace(**{**vars(args), "transfer": "off", "limits": None, "identify": False,
                                       "calibrate": None})
        b = sitl_once(demo, b_args, binary, out / "baseline", "baseline")
        if b is not None:
            runs["baseline"] = b
            if b["interrupted"]:
                reference = "none"
    if reference == "auto" and role != "reference":
        ref_out = out / "reference"
        ref_out.mkdir(parents=True, exist_ok=True)
        parm = ref_out / "teacher.parm"
        parm.write_text(reference_parm(args.sitl_model, learned_limits(out / "pairs.bin"), first["vehicle_params"]))
        ackermann = args.sitl_model == "rover"
        r_args = argparse.Namespace(**{**vars(args), "transfer": "off", "limits": "learned", "sitl_params": str(parm),
                                       "param_at": [], "adapt": False, "identify": False, "calibrate": None,
                                       "turn": "in-place" if ackermann else args.turn,
                                       "start": first["start"], "pair_settle": first["summary"]["pair_settle_s"]
                                       if getattr(args, "identify", False) else args.pair_settle})
        r = sitl_once(demo, r_args, binary, ref_out, "reference")
        if r is not None:
            runs["reference"] = r
    summary = dict(first["summary"])
    if ref_file is not None:
        summary.update({"reference_reached_goal": True, "reference_time_s": ref_file["time_s"],
                        "reference_dev_last_half_m": ref_file["dev_last_half_m"],
                        "reference_collided": ref_file["collided"]})
        summary["reference_source"] = ref_file["source"]
    for other in ("baseline", "reference"):
        if other in runs and other != role:
            summary.update(V.role_fields(other, runs[other]["figures"]))
            summary[f"{other}_source"] = f"SITL {args.sitl_model}, run in {runs[other]['out']}"
    if reference == "none" and role != "reference":
        summary["reference_source"] = None
    if "reference_time_s" in summary and not summary.get("reference_reached_goal"):
        summary["reference_time_s"] = None  # a reference that did not finish is no reference
    for subject in ("learner", "baseline"):
        if f"{subject}_reached_goal" in summary:
            summary[f"{subject}_time_ratio"] = _ratio(summary.get(f"{subject}_time_s"), summary.get("reference_time_s"))
            summary[f"{subject}_dev_ratio"] = _ratio(summary.get(f"{subject}_dev_last_half_m"),
                                                     summary.get("reference_dev_last_half_m"))
    vs = V.verdicts(summary) if role != "reference" else []
    summary["verdicts"] = {v["claim"]: v["ok"] for v in vs}
    summary["worked"] = V.worked(vs)
    summary["wall_s"] = round(sum(r["summary"]["wall_s"] for r in runs.values()), 1)
    for v in vs:
        print(V.verdict_text(v))
    print_line("summary: " + json.dumps(summary))
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")  # what --reference FILE reads
    pose0 = first["pose"]
    trajs = {r: V.into_frame(run["traj"], run["pose"], pose0) for r, run in runs.items()}
    figures = [first["figure"]]
    if len(trajs) > 1:
        V.compare_figure(out / "demo_compare.png", first["world"], trajs, args.sitl_model)
        figures.append(out / "demo_compare.png")
    print(f"figures: {', '.join(str(f) for f in figures)}; pair store: {out / 'pairs.bin'}; logs: {out}/*.log")
    return 0 if first["figures"]["reached_goal"] else 1


def started(mon: Any, kids: Any, timeout: float) -> bool:
    """Wait until the station's first command was driven, a guard of its stopped the mission before any, or one of
    the demo's processes ended (bounded by ``timeout`` s): whether it drove."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and not (mon.guards.stopped or kids.any_exited()):
        if mon.driving.wait(0.2):
            return True
    return mon.driving.is_set()


def _ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 4) if a is not None and b else None


def sitl_once(demo: ModuleType, args: argparse.Namespace, binary: Path, out: Path, role: str,
              robot: str = "sitl") -> dict | None:
    """One run on a freshly booted SITL: boot, engage as the pilot, the station and the driver host on MAVLink,
    watched to the goal. Its summary (fields named by ``role``, written to ``out``/summary.json and printed as
    ``run ROLE: {...}``), its figures (``time_s`` etc., :func:`sitl_verdict.role_fields`'s input), its poses and
    the pose its mission was placed at; None if it produced no telemetry."""
    from bridge.core.config import load_mission_spec, load_station, mission_from_spec
    from bridge.nodes.zsession import free_port, make_config, open_session, tcp
    TRANSFER, Monitor, teacher_table, touched_an_obstacle = (demo.TRANSFER, demo.Monitor, demo.teacher_table,
                                                            demo.touched_an_obstacle)
    _wait_state, _watch, transfer_lines = demo._wait_state, demo._watch, demo.transfer_table
    from bridge.tools.demo_calibrate import (
        SITL_HOLD_AFTER_SETTLE_S,
        calibrate_first,
        calibration_budget,
        method_shares,
        restart_monitor,
        sitl_calibration_table,
    )
    from bridge.tools.demo_sitl import (
        PAIR_SETTLE_ACKERMANN_S,
        PAIR_SETTLE_EDGE_ACKERMANN_S,
        PAIR_SETTLE_S,
        REPORTED_PARAMS,
        ParamChanges,
        learned_limits,
        learner_range,
        mission_toml,
        param_change,
        place_mission,
        start_on_path,
    )
    from bridge.tools.procs import Children
    from sim_learner.sitl import Sitl, SitlError

    out.mkdir(parents=True, exist_ok=True)
    store = out / "pairs.bin"
    store.unlink(missing_ok=True)  # from no pairs at all, as the paper's case
    spec = load_mission_spec(args.mission)
    ackermann = args.sitl_model == "rover"
    settle = ((PAIR_SETTLE_ACKERMANN_S if ackermann else PAIR_SETTLE_S) if args.pair_settle is None
              else float(args.pair_settle))
    settle_edge = PAIR_SETTLE_EDGE_ACKERMANN_S if ackermann and args.pair_settle is None and settle > 0 else 0.0
    if not 0.0 <= settle <= 5.0:
        raise UsageError(f"--pair-settle {settle}: between 0 and 5 s")
    changes = [param_change(x) for x in args.param_at]
    calibrate = getattr(args, "calibrate", None)  # the paper's calibrated start before the mission (--calibrate)
    # an Ackermann rover cannot turn in place: its yaw-rate limits are curvatures (docs/BENCHMARKS.md)
    turn = args.turn or ("needs-speed" if ackermann else "in-place")
    start = args.start or ("on-path" if turn == "needs-speed" else "mission")
    base_spec = spec
    if start == "on-path":
        spec = start_on_path(spec)
    t_wall = time.monotonic()
    print(f"run {role}: booting SITL {args.sitl_model}" + (f" with {args.sitl_params}" if args.sitl_params else ""),
          flush=True)
    try:
        sitl = Sitl(binary, model=args.sitl_model, parm_files=[args.sitl_params] if args.sitl_params else ())
    except SitlError as exc:
        raise UsageError(str(exc)) from None
    mon = None
    interrupted = False
    ident = None
    cal: dict[str, Any] | None = None
    accepted = None
    reach = None  # a car's tightest turn, measured (the station checks the mission's path against it)
    with ExitStack() as stack:
        try:
            stack.enter_context(sitl)
        except SitlError as exc:
            print(f"scmbridge demo: SITL did not boot: {exc}", file=sys.stderr)
            return None
        pilot = sitl.pilot
        assert pilot is not None
        changer = ParamChanges(pilot, changes)
        params = {n: pilot.param(n) for n in REPORTED_PARAMS}
        v_range, w_range = learner_range(params)
        with pilot.cond:
            p, att = pilot.s.position, pilot.s.attitude
        pose = (float(p.y), float(p.x), math.pi / 2 - float(att.yaw))  # NED -> ENU, as the MAVLink driver does
        placed = place_mission(spec, pose)
        world = mission_from_spec(placed)
        accepted = (v_range, w_range)  # what the vehicle accepts: the driver host's hard limits

        def write_station() -> None:
            (out / "mission.toml").write_text(mission_toml(placed))
            (out / "station.toml").write_text(
                f'robot = "{robot}"\n\n[learner_bounds]\nv = [{v_range[0]!r}, {v_range[1]!r}]\n'
                f"w = [{w_range[0]!r}, {w_range[1]!r}]\n\n[station]\npair_settle_s = {settle!r}\n"
                + (f"pair_settle_edge_s = {settle_edge!r}\n" if settle_edge > settle else "") + "\n"
                + transfer_lines(args.transfer, args.limits)
                + ("adapt = true\n" if args.adapt else "")
                + (f'turn_probe = "{args.turn_probe}"\n' if args.turn_probe != "at-command" else "")
                + (f'turn = "{turn}"\n' if turn != "in-place" else "")
                + ('at_limit = "region"\n' if calibrate else "")
                + (f"turn_reach = [{reach.right:.4f}, {reach.left:.4f}, {reach.speed:.4f}]\n"
                   if reach is not None and reach.right is not None and reach.left is not None
                   and turn == "needs-speed" else "")
                + teacher_table(args)
                + (sitl_calibration_table(max(settle, settle_edge)) if calibrate else ""))

        write_station()
        (out / "driver.toml").write_text(
            f'robot = "{robot}"\n\n[driver.hard_limits]\nv = [{-accepted[0][1]!r}, {accepted[0][1]!r}]\n'
            f"w = [{accepted[1][0]!r}, {accepted[1][1]!r}]\n\n[link.mavlink]\nurl = \"{sitl.driver_url}\"\n"
            "rate_hz = 20\n")
        print(f"SITL {args.sitl_model} instance {sitl.instance} booted in {sitl.boot_s:.1f} s; vehicle {params}; "
              f"learner v {v_range} m/s, omega ({w_range[0]:.3f}, {w_range[1]:.3f}) rad/s; mission placed at "
              f"({pose[0]:.2f}, {pose[1]:.2f}, {pose[2]:.2f})", flush=True)
        port = free_port()
        client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
        logs = {name: stack.enter_context(open(out / f"{name}.log", "w"))
                for name in ("driver", "station", *(["calibrate"] if calibrate else []))}
        session = stack.enter_context(open_session(make_config(mode="router", listen=[tcp(port)])))
        kids = stack.enter_context(Children())
        mon = Monitor(session, robot)
        try:
            # the driver host outlives the identification (up to IDENTIFY_S) and the station's start-up too
            extra = (IDENTIFY_S if getattr(args, "identify", False) else 0.0) + calibration_budget(calibrate, 3.0)
            kids.spawn(["driver", "--link", "mavlink", "--config", str(out / "driver.toml"), *client, "--duration",
                        str(args.duration + 30 + extra + STARTUP_S)], logs["driver"])
            if not _wait_state(mon, "waiting", 60):
                print(f"scmbridge demo: the driver host did not come up; see {out}/driver.log", file=sys.stderr)
                return None
            pilot.set_mode("GUIDED")  # the person engages: GUIDED and armed from the ground station
            pilot.arm(True)
            if not _wait_state(mon, "driving", 10):
                print("scmbridge demo: the driver host did not take the pilot's engage", file=sys.stderr)
                return None
            if getattr(args, "identify", False):
                from bridge.tools.demo_identify import identify, settings

                ident = identify(out / "station.toml", robot, port, world, timeout_s=IDENTIFY_S)
                if ident is None:
                    print("scmbridge demo: the identification did not finish", file=sys.stderr)
                    return None
                got = settings(ident, args, v_range[0])
                turn, start, settle, settle_edge = got["turn"], got["start"], got["settle"], got["settle_edge"]
                v_range, w_range = got["v_range"], got["w_range"]
                reach = ident.reach()
                with pilot.cond:  # the mission is placed where the vehicle stands now
                    p, att = pilot.s.position, pilot.s.attitude
                pose = (float(p.y), float(p.x), math.pi / 2 - float(att.yaw))
                placed = place_mission(start_on_path(base_spec) if start == "on-path" else base_spec, pose)
                world = mission_from_spec(placed)
                write_station()
                print(f"identified: {ident.as_dict()}; learner v ({v_range[0]:.3f}, {v_range[1]:.3f}) m/s, omega "
                      f"({w_range[0]:.3f}, {w_range[1]:.3f}) rad/s, turn {turn}, start {start}, pairs settle "
                      f"{settle} s (edges {max(settle, settle_edge)} s)", flush=True)
                restart_monitor(mon)  # the run starts after the identification: its figures are the mission's
            if calibrate:  # the paper's calibrated start, on the firmware: then the mission from where it stopped
                cal = calibrate_first(calibrate, client, out / "station.toml", store, logs["calibrate"],
                                      hold_s=max(settle, settle_edge) + SITL_HOLD_AFTER_SETTLE_S)
                with pilot.cond:
                    p, att = pilot.s.position, pilot.s.attitude
                pose = (float(p.y), float(p.x), math.pi / 2 - float(att.yaw))
                placed = place_mission(start_on_path(base_spec) if start == "on-path" else base_spec, pose)
                world = mission_from_spec(placed)
                write_station()
                restart_monitor(mon)
            kids.spawn(["station", *client, "--config", str(out / "station.toml"), "--start", "--store", str(store),
                        "--exit-at-goal", "--duration", str(args.duration + STARTUP_S), "--mission",
                        str(out / "mission.toml")], logs["station"])
            changer.start(None, after=mon.driving)  # --param-at counts from the first command driven
            started(mon, kids, STARTUP_S)  # the run's --duration counts from its first command, not the start-up
            _watch(mon, kids, world, args.duration)
        except KeyboardInterrupt:
            print("\ninterrupted: stopping the demo's processes", file=sys.stderr)
            interrupted = True
        except SitlError as exc:
            print(f"scmbridge demo: the pilot could not engage: {exc}", file=sys.stderr)
            return None
        finally:
            changer.stop()
    # the processes are gone (the driver host stopped and disarmed the vehicle), and so is SITL
    run = mon.summary(world, corridor_m=args.corridor) if mon is not None else None
    if run is None:
        print("the demo produced no telemetry; see the logs in", out, file=sys.stderr)
        return None
    traj = run.pop("_traj")
    with mon.lock:
        states = list(mon.states)
        applied = list(mon.applied)
        cmds = dict(mon.cmds)
    from bridge.tools.sitl_trace import deviation_sources, write_trace

    trace = write_trace(out / "trace.json", states, applied, cmds, world)
    driving = [a[0] for a in applied if a[1] in ("cmd", "clamped")]
    t0 = driving[0] if driving else states[0][0]
    in_run = [s for s in states if t0 <= s[0] <= t0 + run["time_s"] + 1e-6]
    poses = np.array([s[1:3] for s in in_run]) if in_run else None
    dev_last_half = collided = None
    devs_at: list[tuple[float, float]] = []  # (stamp, deviation) of the driving time
    if poses is not None and len(poses):
        prog = np.array([world.path.project(q)[0] / world.path.length for q in poses])
        dev = np.array([world.path.project(q)[1] for q in poses])
        devs_at = list(zip([s[0] for s in in_run], dev.tolist()))
        dev_last_half = float(dev[prog >= 0.5].mean()) if (prog >= 0.5).any() else None
        collided = touched_an_obstacle(world, poses)
    with mon.lock:
        st = mon.status.get("station")
    relearned = st.counters.get("cells_relearned") if st is not None else None
    edges = st.counters.get("limits_relearned", 0) if st is not None else None
    changed = []
    for at, name, value, err in changer.done:  # the learner changed mid-run: the deviation before and after
        before = [d for t, d in devs_at if at - 20.0 <= t < at]
        after = [d for t, d in devs_at if t >= at + 15.0]
        box = mon.limits_at(at)  # what the station had learned of the vehicle before it changed
        changed.append({"at_s": round(at - t0, 1), "name": name, "value": value, "error": err or None,
                        "read_back": changer.read_back.get(name),
                        "dev_before_m": round(float(np.mean(before)), 4) if before else None,
                        "dev_after_m": round(float(np.mean(after)), 4) if after else None,
                        "limits_before": None if box is None else
                        {"v": [round(x, 4) for x in box[:2]], "w": [round(x, 4) for x in box[2:]]}})
    from sim_learner.experiments import reference_figures

    sim = reference_figures(False)["teacher"]  # the ideal teacher on the same path, simulated (sim mpc's)
    figures = {"reached_goal": run["reached_goal"], "time_s": run["time_s"] if run["reached_goal"] else None,
               "dev_last_half_m": dev_last_half, "collided": collided, "max_dev_m": run["max_path_dist_m"],
               "left_corridor": run["left_corridor"]}
    summary = {
        "experiment": "mpc-sitl", "model": args.sitl_model, "role": role, "transfer": args.transfer,
        "limits": args.limits or TRANSFER[args.transfer][2],
        "reached_goal": run["reached_goal"], "goal_rule_met": run["goal_rule_met"],
        "corridor_m": run["corridor_m"], "max_path_dist_m": run["max_path_dist_m"],
        **V.role_fields(role, figures),
        "sim_teacher_time_s": sim["time_s"], "sim_teacher_dev_last_half_m": sim["dev_last_half_m"],
        "method_counts": run["methods"], "method_shares": method_shares(run["methods"]), "calibration": cal,
        "refined_pairs": run["refined_pairs"], "raw_pairs": run["raw_pairs"], "pairing": run["pairing"],
        "pair_settle_s": settle, "pair_settle_edge_s": max(settle_edge, settle),
        "learned_limits": learned_limits(store),
        "adapt": load_station(out / "station.toml").transfer.adapt,  # what the station does (true by default)
        "curve_margin": load_station(out / "station.toml").teacher.curve_margin, "turn": turn, "start": start,
        "turn_probe": load_station(out / "station.toml").transfer.probe_turns(),  # what the station does
        "cells_relearned": relearned, "limits_relearned": edges, "param_changes": changed,
        "dev_sources": deviation_sources(trace, t0, t0 + run["time_s"] + 1e-6),
        "goal_dist_m": run["goal_dist_m"], "driving_s": run["driving_s"], "guard_stops": run["guard_stops"],
        "learner_bounds": [list(v_range), list(w_range)], "accepted_bounds": [list(accepted[0]), list(accepted[1])],
        "range": "measured" if ident is not None else "parameters",
        "assumption_checked": load_station(out / "station.toml").transfer.turn_reach != [],
        "outside_assumption": next((g["text"].removeprefix("paused: ").split("; the robot")[0]
                                    for g in run["guard_stops"] if g["reason"] == "outside_assumption"), None),
        "identified": ident.as_dict() if ident is not None else None, "vehicle_params": params,
        "missed_deadlines": run["missed_deadlines"], "boot_s": round(sitl.boot_s, 1),
        "wall_s": round(time.monotonic() - t_wall, 1)}
    print_line(f"run {role}: " + json.dumps(summary))
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    figure = out / "demo_trajectory.png"
    V.run_figure(figure, world, traj, role, args.sitl_model)
    from bridge.tools.pairs_cli import pairs_figure

    pairs_figure(store, out / "demo_pairs.png")  # what was learned on ArduPilot's own firmware, as the demo's
    return {"summary": summary, "figures": figures, "traj": traj, "pose": pose, "world": world, "out": out,
            "figure": figure, "vehicle_params": params, "start": start, "interrupted": interrupted}
