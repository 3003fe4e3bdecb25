"""``scmbridge demo --calibrate NVxNW``: the paper's calibrated start (its Jackal MPC run: command pairs constructed
at the learner's limits before the mission), on the demo's link.

Before the station starts, ``scmbridge calibrate`` runs against the same driver host, over the same hub, with the
station's configuration and store (docs/OPERATING.md, calibration): the grid of learner commands, extremes included,
each held ``[calibration] hold_s``, driving back toward the start between them and stopping at the distance or time
bound. The station then starts its mission from that store: calibrated pairs and measured limits. The summary gives
each method's share of the mission's driving commands (:func:`method_shares`) and what the calibration left.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path
from typing import Any

import msgspec

from bridge.core.errors import UsageError
from bridge.tools.procs import spawn, stop_group

#: seconds the calibration stage may take, per command of its grid (held, then driving back toward the start)
CAL_S_PER_COMMAND = 4.0


def grid(text: str) -> tuple[int, int]:
    """``--calibrate``'s argument, as ``scmbridge calibrate --grid`` reads it (imported only when given)."""
    from bridge.tools.calibrate import grid_arg

    return grid_arg(text)


def check_calibrate(args: Any, robots: list[str]) -> None:
    """``--calibrate`` calibrates one robot on its link before its mission (not a fleet, not in-process): an
    emulated one, or with ``--sitl`` the SITL rover of the run it calibrates (not its baseline or reference)."""
    if args.calibrate is not None and (len(robots) != 1 or args.count or args.inprocess):
        raise UsageError("--calibrate calibrates one robot on its link: not with --robots, --count or --inprocess")


#: (--sitl) seconds each calibration command is held beyond the station's pair settling time: a few control
#: intervals' pairs of every command count (a cell needs k_min of them), not only the first after it settled
SITL_HOLD_AFTER_SETTLE_S = 1.0
#: (--sitl) the calibration's distance bounds on SITL's open field: it drives at the vehicle's full range, and the
#: mission is placed where it stopped
SITL_MAX_DISTANCE_M, SITL_RETURN_RADIUS_M = 10.0, 3.0


def calibration_budget(grid: tuple[int, int] | None, hold_s: float = 1.0) -> float:
    """The calibration stage's bound on time for ``grid`` with each command held ``hold_s`` (0 without a grid)."""
    return 0.0 if grid is None else 20.0 + (CAL_S_PER_COMMAND + max(0.0, hold_s - 1.0)) * grid[0] * grid[1]


def sitl_calibration_table(settle_s: float) -> str:
    """(--sitl) the station's ``[calibration]`` lines: each command held the pair settling time and
    :data:`SITL_HOLD_AFTER_SETTLE_S` more (the default hold of one second leaves a command on a real firmware one
    settled pair or none), within SITL's open field's bounds."""
    return (f"\n[calibration]\nhold_s = {settle_s + SITL_HOLD_AFTER_SETTLE_S:.3f}\n"
            f"max_distance_m = {SITL_MAX_DISTANCE_M}\nreturn_radius_m = {SITL_RETURN_RADIUS_M}\n")


def calibrate_first(grid: tuple[int, int], client: list[str], config: Path, store: Path, log: Any,
                    hold_s: float = 1.0) -> dict:
    """Run ``scmbridge calibrate`` to its end (bounded by :func:`calibration_budget`, then stopped) and return what
    it reports: ``ok`` (it drove every command of its grid), ``line`` (its summary line), ``wall_s``. The caller's
    driver host must be running and engaged; no station may drive the robot meanwhile. ``hold_s``: the hold the
    station's ``[calibration]`` gives each command (the default's unless the caller wrote another)."""
    budget = calibration_budget(grid, hold_s)
    t0 = time.monotonic()
    proc = spawn(["calibrate", *client, "--config", str(config), "--store", str(store), "--grid",
                  f"{grid[0]}x{grid[1]}", "--duration", f"{budget:g}"], log)
    try:
        code = proc.wait(timeout=budget + 60.0)
    except subprocess.TimeoutExpired:
        code = None
    finally:
        stop_group(proc)  # ended already, or past its bound: nothing of it may outlive the stage
    line = ""
    path = Path(getattr(log, "name", ""))
    if path.is_file():
        lines = [x for x in path.read_text(errors="replace").splitlines() if x.startswith("calibration:")]
        line = lines[-1] if lines else ""
    wall = round(time.monotonic() - t0, 1)
    print(f"calibration ({wall} s): {line or 'no summary line; see calibrate.log'}", flush=True)
    return {"ok": code == 0 and " commands driven" in line and line.startswith("calibration: all "), "line": line,
            "wall_s": wall}


def restart_monitor(mon: Any) -> None:
    """Forget what the demo's monitor (:class:`bridge.tools.demo.Monitor`) saw before the mission (an identification
    or a calibration on the same vehicle): the run's figures are the mission's."""
    with mon.lock:
        mon.states.clear()
        mon.applied.clear()
        mon.cmds.clear()
        mon.status.pop("station", None)
    mon.driving.clear()


def place_after_calibration(mon: Any, mission: str | None, out: Path, frame: str) -> tuple[Any, str] | None:
    """The mission moved rigidly onto the pose the robot stands at after its calibration (the demo's monitor's last
    state), written to ``out/mission.toml``: the mission starts where the calibration left the robot, as a lab's
    ``scmbridge mission place`` would put it (docs/OPERATING.md), and as the uncalibrated run starts on its start
    pose. Returns the placed mission (:class:`transfer.mission.Mission`) and the file, or None without a pose."""
    from bridge.core.config import load_mission_spec, mission_from_spec
    from bridge.tools.demo_sitl import mission_toml, place_mission

    with mon.lock:
        last = mon.states[-1] if mon.states else None
    if last is None:
        return None
    spec = load_mission_spec(mission)
    placed = msgspec.structs.replace(place_mission(spec, (last[1], last[2], last[3])), name=f"{spec.name}@calibrated",
                                     frame=frame)
    path = out / "mission.toml"
    path.write_text(mission_toml(placed))
    return mission_from_spec(placed), str(path)


def deviations(path: Any, traj: Any) -> dict[str, float | None]:
    """The run's distance from the path (``path``: :class:`transfer.teacher.path.Polyline`; ``traj``: poses
    ``(n, >= 2)``): its mean and maximum over the run (``mean_dev_m``, ``max_dev_m``: with the approach from the start
    pose, beside the path, in both), and the mean over the last half of the path (``dev_last_half_m``: the paper's
    reading, as ``sim mpc`` and the SITL verdicts measure it; docs/PAPER.md), None before the robot got there."""
    import numpy as np

    proj = np.array([path.project(p[:2]) for p in traj])  # (along the path, distance from it) per pose
    devs, half = proj[:, 1], proj[:, 0] >= 0.5 * path.length
    return {"mean_dev_m": round(float(devs.mean()), 4), "max_dev_m": round(float(devs.max()), 4),
            "dev_last_half_m": round(float(devs[half].mean()), 4) if half.any() else None}


def method_shares(methods: dict[str, int]) -> dict[str, float]:
    """Each method's share of the driving commands (``stop`` left out: it drives nothing), rounded to 0.001."""
    driving = {m: n for m, n in methods.items() if m != "stop"}
    total = sum(driving.values())
    return {m: round(n / total, 3) for m, n in sorted(driving.items(), key=lambda e: -e[1])} if total else {}
