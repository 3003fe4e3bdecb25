"""The parts of ``scmbridge demo --sitl PATH`` (:func:`bridge.tools.demo_sitl_run.sitl_hil`) that are its own: the
paper's MPC case (Section 5.2) with ArduPilot's real Rover firmware in SITL as the learner, over the MAVLink link
(docs/ARCHITECTURE.md §7).

What a lab would do with a real rover, in order: the autopilot boots (:class:`sim_learner.sitl.Sitl`: own
directory, free instance, fast boot then real time); the learner's command range is read from the vehicle's own
parameters (the speed GUIDED is capped at, ``WP_SPEED``, and the turn-rate limit ``ATC_STR_RAT_MAX``), not the
paper's Jackal's; the mission is placed where the vehicle stands (a robot starts where
it is: the mission's start pose is moved onto the vehicle's pose, path and obstacles with it); the driver host
starts not engaged and the pilot engages it by selecting GUIDED and arming from the ground station; the station
starts from an empty pair store and drives the S-path to the goal. Then, by default, the teacher drives SITL itself
(``--reference auto``) and, with ``--baseline``, the paper's baseline does; one JSON line sums the runs up, its
fields named by role (``learner_*``, ``baseline_*``, ``reference_*``), with one verdict line per claim
(:mod:`bridge.tools.sitl_verdict`).

SITL's body lags its command (the skid rover about 0.3 s to its speed), unlike the paper's learners, which answer
within a tick: a pair formed over the 0.1 s after a command changed says the vehicle reaches less than it does, and
the probe of the learner's top command (whose boundary pair fixes the learned limit) then fixed the top speed at
0.17-0.32 m/s of a true 0.35. So the station here keeps only settled pairs (``[station] pair_settle_s``,
:mod:`bridge.nodes.pairing`), which also holds the probe until the speed has settled. docs/BENCHMARKS.md ("The
transfer on SITL") has the runs.
"""

from __future__ import annotations

import json
import math
import threading
from pathlib import Path
from typing import Any

from bridge.core.errors import UsageError

#: the learner's lowest forward speed, m/s (the paper's learner range starts there too; the MPC plans forward)
V_MIN = 0.05
#: the vehicle parameters the learner's range is read from, and the ones reported beside it
RANGE_PARAMS = ("WP_SPEED", "CRUISE_SPEED", "ATC_STR_RAT_MAX")
REPORTED_PARAMS = (*RANGE_PARAMS, "CRUISE_THROTTLE", "ATC_ACCEL_MAX", "ATC_DECEL_MAX", "FS_ACTION", "FS_TIMEOUT")
#: the station's ``[station] pair_settle_s`` on SITL unless ``--pair-settle`` says otherwise: about twice the skid
#: body's speed lag (0.3 s), so a pair's command had been in force long enough for the speed to follow it
PAIR_SETTLE_S = 0.5
#: the same on the Ackermann body (``--sitl-model rover``), and ``[station] pair_settle_edge_s`` for its commands on
#: an edge of its range: it reaches its top from rest in about 2 s (sitl-weak-ackermann.parm's table: after 2 s of a
#: 4 s hold); with 0.5 or 1 s for every pair its probe of the top speed read 0.12-0.21 m/s of its 0.36 and the
#: teacher, held to that, took twice as long; with 2 s for every pair only 28-55 pairs were kept in a run, too few for
#: a map, and the teacher's commands went to it as they were (docs/BENCHMARKS.md)
PAIR_SETTLE_ACKERMANN_S = 1.0
PAIR_SETTLE_EDGE_ACKERMANN_S = 2.5


def learned_limits(store_path: Path) -> dict[str, list[float]] | None:
    """What the run learned of the learner, on the teacher's domain: the limits' box (``v``, ``w``: [lo, hi]) from
    the saved pair store; None without a store."""
    from bridge.nodes.station_tags import read_store

    try:
        store = read_store(Path(store_path))
    except (OSError, ValueError):
        return None
    box = store.limits.box
    out: dict[str, list[float] | list[float | None]] = {"v": [round(float(x), 4) for x in box.v],
                                                        "w": [round(float(x), 4) for x in box.w]}
    k = store.limits.known_curvature()  # at the full lock (a bound with [transfer] turn = "needs-speed")
    if any(x is not None for x in k):
        out["curvature"] = [None if x is None else round(x, 4) for x in k]
    return out


def teacher_reference(path: str | Path) -> dict[str, Any]:
    """The teacher's figures from the summary (``summary.json``, or a file whose last ``summary:`` line is one) of
    a run of the teacher on SITL itself: the stock rover given the learner's range, ``--transfer off --limits
    learned`` (the teacher's commands, under the MPC bounded by what the vehicle was seen to reach, applied to a
    vehicle that follows them: the paper's ideal teacher; a summary from before ``--limits`` existed says
    ``transfer off`` and was made so too). SITL's own deviation floor (an EKF position, a 10 Hz loop over MAVLink,
    the body's lag) is several millimetres, the simulated teacher's 1.1 mm: the paper's deviation claim compares
    like with like only against a run on SITL."""
    text = Path(path).read_text()
    lines = [ln[len("summary: "):] for ln in text.splitlines() if ln.startswith("summary: ")]
    try:
        ref = json.loads(lines[-1] if lines else text)
    except json.JSONDecodeError as exc:
        raise UsageError(f"--teacher-ref {path}: not a demo summary ({exc})") from None
    role = ref.get("role", "learner" if ref.get("transfer") == "on" else "reference")
    pre = role if f"{role}_time_s" in ref else "scm"  # a summary from before the fields were named by role
    t, d = ref.get(f"{pre}_time_s"), ref.get(f"{pre}_dev_last_half_m")
    if not ref.get("reached_goal") or t is None or d is None:
        raise UsageError(f"--reference {path}: that run did not reach the goal, it is no teacher's reference")
    collided = ref.get(f"{pre}_collided", ref.get("collisions", {}).get("scm"))
    params = ref.get("vehicle_params", {})
    return {"time_s": t, "dev_last_half_m": d, "collided": bool(collided),
            "source": f"SITL {ref.get('model')} (WP_SPEED {params.get('WP_SPEED')}, ATC_STR_RAT_MAX "
                      f"{params.get('ATC_STR_RAT_MAX')}), transfer {ref.get('transfer')}, limits "
                      f"{ref.get('limits', 'learned')}: {Path(path).name}"}


def learner_range(params: dict[str, float]) -> tuple[tuple[float, float], tuple[float, float]]:
    """The learner's command box from the vehicle's parameters: v in [V_MIN, WP_SPEED] m/s (GUIDED caps a velocity
    target at WP_SPEED; 0 there means CRUISE_SPEED, as in Rover), omega in +-ATC_STR_RAT_MAX (deg/s on the vehicle,
    rad/s here). CRUISE_SPEED is not a limit: with CRUISE_THROTTLE it is the point the speed controller's throttle
    feed-forward is tuned on (throttle = CRUISE_THROTTLE * v / CRUISE_SPEED). So a CRUISE_SPEED far below the speed its
    CRUISE_THROTTLE was tuned at asks a large throttle for a small speed, and the rover drives far faster than
    commanded."""
    v_max = params["WP_SPEED"] if params["WP_SPEED"] > 0 else params["CRUISE_SPEED"]
    w_max = math.radians(params["ATC_STR_RAT_MAX"])
    if not (v_max > V_MIN and w_max > 0):
        raise UsageError(f"the vehicle's parameters give no usable command range: {params}")
    return (V_MIN, float(v_max)), (-float(w_max), float(w_max))


def place_mission(spec, pose: tuple[float, float, float]):
    """``spec`` moved rigidly so that its start pose lands on ``pose`` (x, y, theta; ENU): path, obstacles, start."""
    from bridge.core import wire as M

    sx, sy, sth = spec.start if spec.start is not None else (spec.path[0][0], spec.path[0][1], 0.0)
    px, py, pth = pose
    c, s = math.cos(pth - sth), math.sin(pth - sth)

    def move(x: float, y: float) -> list[float]:
        dx, dy = x - sx, y - sy
        return [px + c * dx - s * dy, py + s * dx + c * dy]

    return M.MissionSpec(name=f"{spec.name}@sitl", frame="sitl-local", path=[move(x, y) for x, y in spec.path],
                         goal_tolerance=spec.goal_tolerance, obstacles=[[*move(x, y), r] for x, y, r in spec.obstacles],
                         start=[px, py, pth])


def start_on_path(spec):
    """``spec`` with its start on the path's first point, facing along the path's first segment: where a car-like
    vehicle is placed. From the paper's start (0.3 m beside the path facing 45 degrees away: a turn on the spot) a
    vehicle that cannot turn in place joins the path only after a loop, and even the ideal teacher, bounded by the
    weak Ackermann rover's curvature, then deviates 0.39 m over the last half and touches an obstacle
    (docs/BENCHMARKS.md, "The transfer on SITL")."""
    import msgspec

    (x0, y0), (x1, y1) = spec.path[0], spec.path[1]
    return msgspec.structs.replace(spec, start=[float(x0), float(y0), math.atan2(y1 - y0, x1 - x0)])


def mission_toml(spec) -> str:
    """A mission file for ``spec`` (what ``scmbridge station --mission`` reads)."""
    def num(x: float) -> str:
        return repr(float(x))

    rows = ",\n".join(f"  [{num(x)}, {num(y)}]" for x, y in spec.path)
    obs = ",\n".join(f"  [{num(x)}, {num(y)}, {num(r)}]" for x, y, r in spec.obstacles)
    start = "" if spec.start is None else f"start = [{', '.join(num(a) for a in spec.start)}]\n"  # a start is optional
    return (f'name = "{spec.name}"\nframe = "{spec.frame}"\ngoal_tolerance = {num(spec.goal_tolerance)}\n'
            f"{start}obstacles = [\n{obs}\n]\npath = [\n{rows}\n]\n")


def param_change(text: str) -> tuple[float, str, float]:
    """``--param-at S:NAME=VALUE``: the vehicle's parameter NAME set to VALUE S seconds after the vehicle first
    drove a command of the station (a learner that changes under the transfer, through the autopilot's own
    parameters)."""
    try:
        at, rest = text.split(":", 1)
        name, value = rest.split("=", 1)
        s, v = float(at), float(value)
    except ValueError:
        raise UsageError(f"--param-at {text!r}: expected SECONDS:NAME=VALUE, e.g. 30:CRUISE_THROTTLE=45") from None
    if not (s >= 0 and math.isfinite(s) and math.isfinite(v) and name.strip().isidentifier()):
        raise UsageError(f"--param-at {text!r}: expected SECONDS:NAME=VALUE with SECONDS >= 0")
    return s, name.strip().upper(), v


class ParamChanges:
    """Sets the vehicle's parameters at their times through the pilot's link (PARAM_SET, done when the vehicle's
    PARAM_VALUE says so), as a person at the ground station would mid-run; ``done`` holds (monotonic time, name,
    value, error or "") for each, and ``read_back`` the value the vehicle's PARAM_VALUE then said for each name (the
    vehicle acknowledged the change; absent where it did not). A thread of its own, waiting on an event (``stop``
    ends it at once)."""

    def __init__(self, pilot: Any, changes: list[tuple[float, str, float]]) -> None:
        self.pilot = pilot
        self.changes = sorted(changes)
        self.done: list[tuple[float, str, float, str]] = []
        self.read_back: dict[str, float] = {}
        self._stop = threading.Event()
        self.finished = threading.Event()  # every change made (or stopped before)
        self._thread = threading.Thread(target=self._run, name="param-changes", daemon=True)
        self.t0 = math.nan
        self._after: threading.Event | None = None

    def start(self, t0: float | None, after: threading.Event | None = None) -> None:
        """Make the changes at their times from ``t0`` (monotonic), or, with ``after``, from when that event is set
        (the vehicle's first driven command: a change counted from the station's start would land before any
        driving whenever the station is slow to come up, 2-20 s depending on the machine's load)."""
        self.t0 = math.nan if t0 is None else t0
        self._after = after
        if self.changes:
            self._thread.start()
        else:
            self.finished.set()

    def _run(self) -> None:
        import time

        try:
            if self._after is not None:
                while not self._after.wait(0.1):
                    if self._stop.is_set():
                        return
                self.t0 = time.monotonic()
            self._changes()
        finally:
            self.finished.set()

    def _changes(self) -> None:
        import time

        for at, name, value in self.changes:
            if self._stop.wait(max(0.0, self.t0 + at - time.monotonic())):
                return
            err = ""
            try:
                self.pilot.set_param(name, value)  # returns once the vehicle's PARAM_VALUE says the new value
                with self.pilot.cond:
                    got = self.pilot.s.params.get(name)
                if got is not None:
                    self.read_back[name] = float(got)
            except Exception as exc:  # noqa: BLE001  (reported in the summary, never fatal to the run)
                err = str(exc)
            self.done.append((time.monotonic(), name, value, err))
            print(f"PARAM_SET {name} = {value:g} at {time.monotonic() - self.t0:.1f} s"
                  + (f": {err}" if err else ""), flush=True)

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
