"""``scmbridge station``: the base-station service, the teacher and the transfer policy in a fixed-rate loop.

Each tick (10 Hz default; absolute deadlines, missed ones counted) it takes the learner states and applied-command
echoes that arrived, forms the command pairs they really bracket (:mod:`bridge.nodes.pairing`), updates the pair store
(and so the learned limits), and then either drives or says why not:

- it drives only while a person has started the mission (:mod:`bridge.nodes.mission_control`: it starts idle;
  ``scmbridge mission start``, or ``--start``; requests are answered on ``scm/<robot>/control``) and the robot is
  fit: the driver host's status is fresh and ``ok`` (link up, engaged, no fault, no estop), and the latest pose
  arrived less than ``max_pose_age_s`` ago; a robot that stops being fit while driving pauses the mission until a
  person resumes it;
- otherwise, and at the goal, it publishes stops and its status says why (``idle: ...``, ``paused: estop latched by
  operator``, ``waiting for the robot: ...``, ``goal reached``).

Driving: the teacher MPC, bounded by the learned limits and given the obstacles that matter, proposes a command;
the transfer policy maps it; ``cmd`` carries it (with the method, a validity of three periods, this run's sender
name and epoch) and ``teacher`` the teacher's own command and plan. ``limits`` is published when the learned
limits change and each second; ``pairs`` answers queries; ``mission`` takes a new mission (the goal state resets).
The pair store is persisted atomically every ``persist_every_s`` and at exit, and reloaded at start; a failed save
(a full disk) is logged, reported on status and retried, and never stops the loop. Callbacks only decode and
store; all work is in the loop (docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg
from bridge.core.config import RATE_HZ_RANGE, StationConfig, load_mission_spec, load_station, mission_from_spec
from bridge.core.errors import UsageError
from bridge.core.paths import save_atomic, state_dir
from bridge.nodes import systemd
from bridge.nodes.mission_control import Fitness, MissionControl, Saved, spec_of
from bridge.nodes.node import FixedRate, Inputs, add_zenoh_args, stop_on_signals, zenoh_config
from bridge.nodes.pairing import IntervalPairer
from bridge.nodes.zsession import open_session
from transfer.calibration import CalibrationPlan
from transfer.domain import Bounds
from transfer.mission import Mission
from transfer.policy import make_policy
from transfer.step import TransferStep
from transfer.store import PairStore
from transfer.teacher.primitives import PrimitiveFollower, PrimitiveLibrary, PrimitivePlanner

log = logging.getLogger("scmbridge.station")

#: a driver host publishes status each second: after this long without one, the robot is not known to be fit
DRIVER_STATUS_MAX_AGE = 3.0
#: an integrity problem (another sender, implausible telemetry) keeps the status not ok this long, s
INTEGRITY_WINDOW_S = 5.0
#: what the learner can really do is its box (or the teacher's) times this; beyond it a pose or pair is implausible
PLAUSIBLE = 1.5


def load_store(path: Path, learner: Bounds, teacher: Bounds, grid, k_min: int) -> tuple[PairStore, str]:
    """The persisted store if there is a valid one, else a new one. A file that is corrupt, made for other bounds,
    holds a pair no vehicle could have produced, or would break the wire contract when served (``pairs``) is
    quarantined: kept aside, not lost, and not served."""
    path = Path(path)
    if path.exists():
        try:
            store = PairStore.from_bytes(path.read_bytes())
            if store.learner_bounds != learner or store.teacher_bounds != teacher:
                raise ValueError("its command bounds differ from this configuration")
            top_v = PLAUSIBLE * max(abs(x) for x in (*learner.v, *teacher.v))
            top_w = PLAUSIBLE * max(abs(x) for x in (*learner.w, *teacher.w))
            for p in store.refined():
                if not all(abs(float(u[0])) <= top_v and abs(float(u[1])) <= top_w for u in (p.u_T, p.u_L)):
                    raise ValueError(f"pair {p.id} (teacher {p.u_T[0]:.3g}, {p.u_T[1]:.3g}; learner "
                                     f"{p.u_L[0]:.3g}, {p.u_L[1]:.3g}) is beyond what the vehicle can do")
            M.validated(pairs_message(store, "learner", 0.0))  # what the pairs queryable would serve
            return store, f"reloaded {len(store.refined())} refined pairs from {path}"
        except ValueError as exc:
            aside = path.with_name(path.name + f".corrupt-{int(time.time())}")
            os.replace(path, aside)
            log.error("pair store %s unusable (%s); quarantined as %s, starting empty", path, exc, aside)
    return PairStore(learner, teacher, tuple(grid), k_min), "new pair store"


def pairs_message(store: PairStore, robot: str, now: float) -> M.Pairs:
    recs = [M.PairRecord(id=p.id, version=p.version, count=p.count, teacher_v=float(p.u_T[0]),
                         teacher_omega=float(p.u_T[1]), learner_v=float(p.u_L[0]), learner_omega=float(p.u_L[1]))
            for p in store.refined()]
    return M.Pairs(stamp=now, robot=robot, pairs=recs, limits_box=store.limits.box.as_list(),
                   limits_hull=[[float(a), float(b)] for a, b in store.limits.hull],
                   teacher_bounds=store.teacher_bounds.as_list(), learner_bounds=store.learner_bounds.as_list(),
                   grid=[int(store.grid[0]), int(store.grid[1])])


class Station:
    """One robot's station: pairing, the teacher, the policy, persistence and the Zenoh side."""

    def __init__(self, cfg: StationConfig, robot: str, rate_hz: float, store_path: Path, mission: Mission,
                 control: MissionControl | None = None, control_path: Path | None = None) -> None:
        """``control``: the mission's phase machine (default: ``mission``, idle); ``control_path``: where it is
        kept across restarts (None: not kept)."""
        from transfer.teacher.mpc import MpcConfig, MpcTeacher

        scfg, tcfg = cfg.station, cfg.transfer
        self.robot, self.keys = robot, M.Keys(robot)
        self.period = 1.0 / rate_hz
        self.store_path = store_path
        self.persist_every = scfg.persist_every_s
        self.max_pose_age = scfg.max_pose_age_s
        self.store, how = load_store(store_path, cfg.learner_bounds.bounds(), cfg.teacher_bounds.bounds(),
                                     tcfg.grid, tcfg.k_min)
        log.info("%s", how)
        policy = make_policy(self.store, tcfg.mapper, np.random.default_rng(tcfg.seed),
                             exploration="paper" if tcfg.exploration == "paper" else "guided")
        self.transfer = TransferStep(policy, dt=self.period, explore=tcfg.exploration != "off",
                                     clearance=tcfg.explore_clearance_m)
        self.mpc = MpcTeacher(MpcConfig(N=scfg.horizon, dt=self.period)) if cfg.teacher.kind == "mpc" else None
        learner, teacher = cfg.learner_bounds.bounds(), cfg.teacher_bounds.bounds()
        top_v = float(max(abs(x) for x in (*learner.v, *teacher.v)))
        top_w = float(max(abs(x) for x in (*learner.w, *teacher.w)))
        self.pairer = IntervalPairer(scfg.pair_dt, max_speed=PLAUSIBLE * top_v + 0.1, max_turn=PLAUSIBLE * top_w + 0.2,
                                     command_bounds=learner, teacher_bounds=Bounds((-top_v, top_v), (-top_w, top_w)),
                                     margin=PLAUSIBLE)
        self.control = control or MissionControl(robot, spec_of(mission))
        self.control_path = control_path
        self.fitness = Fitness()
        self.driver_seq = -1  # the driver host's last status seq: a lower one means it restarted
        self.foreign_cmd_at, self.foreign_epoch = -np.inf, 0  # the last command of another sender on our key
        self.implausible_seen: tuple[int, float] = (0, -np.inf)  # (count, when it last grew)
        self.teacher_kind = cfg.teacher.kind
        self.teacher_timeout = cfg.teacher.timeout_s
        self.calibration: CalibrationPlan | None = None
        self.primitives: PrimitiveFollower | None = None
        if self.teacher_kind == "primitives":
            lib = PrimitiveLibrary(cfg.teacher_bounds.bounds(), cfg.teacher.primitives_grid,
                                   duration=cfg.teacher.primitive_s, dt=self.period)
            self.primitives = PrimitiveFollower(PrimitivePlanner(lib, k_d=1.0, k_theta=2.0, horizon=2))
        self.wake = threading.Event()  # an external teacher's command is mapped as it arrives
        self.inputs = Inputs()
        self.lock = threading.Lock()  # the inbox, the store (read by the pairs queryable) and the mission
        self.inbox: dict[str, Any] = {"state": None, "state_at": -np.inf, "events": [], "driver": None,
                                      "driver_at": -np.inf, "mission": None, "teacher": None, "teacher_at": -np.inf,
                                      "teacher_new": False, "driver_restarted": False}
        self.epoch = M.new_epoch()
        self.seq = {"cmd": 0, "status": 0}
        self.counts: dict[str, int] = {"scm": 0, "direct": 0, "perturb": 0, "affine": 0, "barycentric": 0, "stop": 0}
        self.calib_progress: tuple[int, int, str] | None = None
        self.extra = {"obstacles_dropped": 0, "persist_failures": 0, "missions": 0, "explore_vetoed": 0}
        self.mission_version = self.control.version
        self.why = "starting"
        self.persist_error = ""
        self.limits_sent: tuple[list[float], int] | None = None
        self.limits_version = 0
        self.solve_ms: list[float] = []
        self.tick_ms: deque[float] = deque(maxlen=600)  # the last minute of periodic ticks' durations
        self.ticks = 0
        self.pubs: dict[str, zenoh.Publisher] = {}
        self.ticker: FixedRate | None = None

    # ---------------------------------------------------------------------------------------------- inputs
    @property
    def mission(self) -> Mission:
        return self.control.mission

    def on_state(self, st: M.LearnerState, now: float) -> None:
        with self.lock:
            self.inbox["state"], self.inbox["state_at"] = st, now
            self.inbox["events"].append((st.stamp, 1, st, now))

    def on_applied(self, a: M.Applied, now: float) -> None:
        with self.lock:
            self.inbox["events"].append((a.stamp, 0, a, now))

    def on_own_cmd(self, cmd: M.Command, now: float) -> None:
        """Commands on this robot's key that this station did not send: another station (or a forger)."""
        if cmd.epoch != self.epoch:
            with self.lock:
                self.foreign_cmd_at, self.foreign_epoch = now, cmd.epoch
            self.inputs.count("foreign_commands")

    def on_driver_status(self, st: M.Status, now: float) -> None:
        with self.lock:
            if st.seq < self.driver_seq:
                self.inbox["driver_restarted"] = True  # a new driver host process: it counts from 0 again
            self.driver_seq = st.seq
            self.inbox["driver"], self.inbox["driver_at"] = st, now

    def on_control_query(self, query: zenoh.Query) -> None:
        """A person's request (``scmbridge mission ...``): done or refused under the lock, answered at once."""
        now = time.monotonic()
        try:
            payload = query.payload
            req = M.decode(payload.to_bytes() if payload is not None else b"", M.MissionRequest)
        except M.MessageError as exc:
            self.inputs.count("malformed_control")
            with self.lock:
                ans = self.control.answer(now, False, f"malformed request: {exc}")
        else:
            with self.lock:
                ans = self.control.request(req, self.fitness, now)
            if req.action != "status":
                log.info("mission %s%s: %s", req.action, f" by {req.source}" if req.source else "", ans.text)
        query.reply(self.keys.control, M.encode(ans))

    def on_mission(self, spec: M.MissionSpec, now: float) -> None:
        try:
            mission = mission_from_spec(spec)
        except ValueError as exc:
            self.inputs.count("malformed_mission")
            log.warning("mission %r refused: %s", spec.name, exc)
            return
        with self.lock:
            self.inbox["mission"] = (spec, mission)

    def on_teacher(self, t: M.TeacherCommand, now: float) -> None:
        with self.lock:
            self.inbox["teacher"], self.inbox["teacher_at"], self.inbox["teacher_new"] = t, now, True
        self.wake.set()

    def on_pairs_query(self, query: zenoh.Query) -> None:
        with self.lock:
            msg = pairs_message(self.store, self.robot, time.monotonic())
        query.reply(self.keys.pairs, M.encode(msg))

    # ------------------------------------------------------------------------------------------------ tick
    def ingest(self) -> tuple[M.LearnerState | None, float, M.Status | None, float]:
        """Pairs from the echoes and poses that arrived (time order), a new mission if one came; returns the
        latest state and driver status with their receipt times."""
        with self.lock:
            events, self.inbox["events"] = self.inbox["events"], []
            mission, self.inbox["mission"] = self.inbox["mission"], None
            for _, kind, e, received in sorted(events, key=lambda e: (e[0], e[1])):
                if kind == 0:
                    pair = self.pairer.applied(e.stamp, e.v, e.omega, e.reason, received)
                else:
                    pair = self.pairer.state(e.stamp, np.array([e.x, e.y, e.theta]), received)
                if pair is not None:
                    self.store.add(*pair)
            inbox = dict(self.inbox)
            self.inbox["driver_restarted"] = False
            if mission is not None:
                self.control.replace(*mission)
            if inbox["driver_restarted"]:
                log.warning("the driver host restarted")
                self.control.driver_restarted()
            new_mission = self.control.version != self.mission_version
            self.mission_version = self.control.version
        if new_mission:  # from the mission topic or a person's send
            mission = self.mission
            if self.mpc is not None:
                self.mpc.reset()
            if self.primitives is not None:
                self.primitives.reset()
            self.extra["missions"] += 1
            log.info("new mission %r: %d waypoints, %.1f m, %d obstacles", mission.name, len(mission.path.points),
                     mission.path.length, len(mission.obstacles))
        return inbox["state"], inbox["state_at"], inbox["driver"], inbox["driver_at"]

    def fit_to_drive(self, now: float, state, state_at: float, driver, driver_at: float) -> str:
        """Empty if the station may drive the robot now, else why not (for status and the log)."""
        if driver is None or now - driver_at > DRIVER_STATUS_MAX_AGE:
            return "robot not ready: no driver host status"
        if not driver.ok:
            return f"robot not ready: {driver.text}"
        if state is None:
            return "no pose yet"
        if now - state_at > self.max_pose_age:
            return f"no pose for {now - state_at:.1f} s"
        return ""

    def drive(self, now: float, state: M.LearnerState) -> str:
        """Drive by the configured teacher; returns why it did not, or an empty string."""
        if self.calibration is not None:
            return self.calibrate(now, state)
        if self.teacher_kind == "external":
            return self.map_external(now, state)
        if self.primitives is not None:
            return self.drive_primitives(now, state)
        self.drive_mpc(now, state)
        return ""

    def drive_primitives(self, now: float, state: M.LearnerState) -> str:
        """The paper's motion-primitive teacher: only the primitives inside the learned limits (hull) are planned
        with, so it needs calibrated pairs first; each tick's command is the current primitive's, mapped."""
        lib = self.primitives.planner.lib
        with self.lock:
            allowed = np.asarray(self.store.limits.contains(lib.commands, use_hull=True, tol=1e-6))
        if not allowed.any():
            return "no primitive within the learned limits: calibrate first (scmbridge calibrate)"
        x = np.array([state.x, state.y, state.theta])
        u_T = self.primitives.step(x, self.mission.path, allowed, self.mission.obstacles)
        self.extra["primitive_replans"] = self.primitives.replans
        self.extra["primitives_allowed"] = int(allowed.sum())
        self.map_and_send(now, u_T, x)
        return ""

    def map_external(self, now: float, state: M.LearnerState) -> str:
        """Transfer-only service: map the external teacher's latest command once, as it arrives. A teacher that
        says stop (``ok`` false or an exact zero) or falls silent for ``timeout_s`` gets the robot stopped."""
        with self.lock:
            t, t_at, new = self.inbox["teacher"], self.inbox["teacher_at"], self.inbox["teacher_new"]
            self.inbox["teacher_new"] = False
        if t is None:
            return "waiting for the external teacher"
        if now - t_at > self.teacher_timeout:
            return f"no teacher command for {now - t_at:.1f} s"
        if not t.ok or (t.v == 0.0 and t.omega == 0.0):
            return "the teacher says stop"
        if new:
            self.map_and_send(now, np.array([t.v, t.omega]), np.array([state.x, state.y]))
        return ""

    def calibrate(self, now: float, state: M.LearnerState) -> str:
        """The calibration stage: the plan's learner commands go out as they are (method ``calibrate``)."""
        step = self.calibration.step(now, [state.x, state.y, state.theta])
        if step.done:
            if self.why != f"calibration: {step.reason}":
                log.info("calibration finished: %s; %d refined pairs", step.reason, len(self.store.refined()))
            return f"calibration: {step.reason}"
        self.counts["calibrate"] = self.counts.get("calibrate", 0) + 1
        self._command(now, float(step.u_L[0]), float(step.u_L[1]), "calibrate")
        if self.calib_progress is None or self.calib_progress[:1] + self.calib_progress[2:] != (step.index,
                                                                                                step.phase):
            dist = float(np.hypot(state.x - self.calibration.start[0], state.y - self.calibration.start[1]))
            log.info("calibration %d/%d %s (v %.3f, omega %.3f): %d raw / %d refined pairs, %.2f m from the start",
                     step.index + 1, step.total, step.phase, step.u_L[0], step.u_L[1], self.store.raw_count,
                     len(self.store.refined()), dist)
        self.calib_progress = (step.index, step.total, step.phase)
        return ""

    def map_and_send(self, now: float, u_T, x=None, predicted=None) -> None:
        """Map a teacher command and publish it. Exploration is allowed only if configured and, when the pose is
        known, at least ``explore_clearance_m`` from every obstacle; ``predicted`` (the teacher's plan) steers
        which missing pair guided exploration fills."""
        with self.lock:
            m = self.transfer.map(u_T, x, self.mission, predicted)
        if m.vetoed:
            self.extra["explore_vetoed"] += 1
        self.counts[m.method] = self.counts.get(m.method, 0) + 1
        self._command(now, float(m.u_L[0]), float(m.u_L[1]), m.method, list(m.region)[:8])

    def drive_mpc(self, now: float, state: M.LearnerState) -> None:
        """One teacher command of the built-in MPC, mapped and published."""
        x = np.array([state.x, state.y, state.theta])
        t0 = time.perf_counter()
        with self.lock:
            limits = self.store.limits.box
        res = self.mpc.solve(x, self.mission.path, limits, self.mission.obstacles)
        self.solve_ms.append((time.perf_counter() - t0) * 1e3)
        del self.solve_ms[:-100]
        self.extra["obstacles_dropped"] += res.obstacles_dropped
        self.map_and_send(now, res.u, x, res.predicted)
        pred = res.predicted
        self._put("teacher", M.TeacherCommand(
            stamp=now, seq=self.seq["cmd"] - 1, v=float(res.u[0]), omega=float(res.u[1]), solver=res.solver,
            ok=res.ok, predicted_x=[float(a) for a in pred[:, 0]], predicted_y=[float(a) for a in pred[:, 1]],
            sender="station", epoch=self.epoch))

    def _command(self, now: float, v: float, omega: float, method: str, region: list[int] | None = None) -> None:
        cmd = M.Command(stamp=now, seq=self.seq["cmd"], v=v, omega=omega, method=method,
                        valid_ms=int(3000 * self.period), region=region or [], sender="station", epoch=self.epoch)
        self._put("cmd", M.validated(cmd))
        self.seq["cmd"] += 1

    def tick(self, now: float) -> None:
        state, state_at, driver, driver_at = self.ingest()
        fit = self.fit_to_drive(now, state, state_at, driver, driver_at)
        estop = driver is not None and (driver.state == "estop" or "estop latched" in driver.text)
        late = driver is None or now - driver_at > DRIVER_STATUS_MAX_AGE or driver.ok  # a pose or a status late
        follows_mission = self.teacher_kind != "external" and self.calibration is None
        with self.lock:
            self.fitness = Fitness(fit, estop, immediate=not late)
            c = self.control
            if follows_mission and not fit and c.phase == "running":
                c.progress = max(c.progress, self.mission.progress([state.x, state.y]))
                if self.mission.reached([state.x, state.y]):
                    c.reached()
            drive = c.may_drive(self.fitness, now)
            why = "" if drive else self.not_driving(fit)
        if drive:
            why = self.drive(now, state)
        if why:
            if why != self.why:
                log.info("not driving: %s", why)
            self._command(now, 0.0, 0.0, "stop")
            self.counts["stop"] += 1
        elif self.why != "driving":
            log.info("driving (mission %r)", self.mission.name)
        self.why = why or "driving"
        if self.control.changed:
            self.save_control()

    def not_driving(self, fit: str) -> str:
        """The one reason the robot is not driven this tick (for the status line and the log)."""
        c = self.control
        if c.phase == "idle":
            return f"idle: waiting for a person (scmbridge mission start --robot {self.robot})"
        if c.phase == "finished":
            return "goal reached"
        if c.phase == "running":
            return f"waiting for the robot: {fit}"
        return c.reason  # paused: why; aborted: by whom

    def save_control(self) -> None:
        """Keep the mission and its phase on disk (a restart comes back to it, never running)."""
        with self.lock:
            blob = M.encode(self.control.saved()) if self.control_path is not None else b""
        if self.control_path is None:
            return
        try:
            save_atomic(self.control_path, blob)
        except OSError as exc:
            self.extra["persist_failures"] += 1
            self.control.changed = True  # retried next tick
            self.persist_error = f"mission state not saved: {exc.strerror or exc}"

    # ---------------------------------------------------------------------------------------- publications
    def publish_limits(self, now: float, force: bool) -> None:
        with self.lock:
            box = self.store.limits.box.as_list()
            hull = [[float(a), float(b)] for a, b in self.store.limits.hull]
        key = (box, len(hull))
        if self.limits_sent is None or self.limits_sent != key:
            self.limits_version += 1
        elif not force:
            return
        self.limits_sent = key
        self._put("limits", M.Limits(stamp=now, robot=self.robot, version=self.limits_version, box=box, hull=hull))

    def status(self, now: float) -> M.Status:
        sm = np.array(self.solve_ms) if self.solve_ms else np.zeros(1)
        with self.lock:
            npairs = len(self.store.refined())
        counters = {**{f"method_{k}": v for k, v in self.counts.items()}, **self.extra, **self.inputs.snapshot(),
                    "missed_deadlines": self.ticker.missed if self.ticker else 0, "refined_pairs": npairs,
                    "raw_pairs": self.store.raw_count,
                    "pairs_rejected": self.pairer.rejected, "pairs_formed": self.pairer.formed,
                    "pairs_out_of_order": self.pairer.out_of_order,
                    "implausible_stamps": self.pairer.implausible_stamp,
                    "implausible_poses": self.pairer.implausible_pose,
                    "implausible_pairs": self.pairer.implausible_pair, "pairer_resyncs": self.pairer.resyncs,
                    "goal_reached": int(self.control.phase == "finished")}
        if self.calib_progress is not None:
            i, n, phase = self.calib_progress
            counters.update({"calibration_index": i, "calibration_total": n})
        problems = self.integrity(now)
        ok = ((self.why in ("driving", "goal reached") or self.why.startswith("calibration:"))
              and not self.persist_error and not problems)
        text = "; ".join([self.why, *([self.persist_error] if self.persist_error else []), *problems])
        phase = self.control.phase
        state = "driving" if self.why == "driving" else ("waiting" if phase == "running" else phase)
        tk = np.array(self.tick_ms) if self.tick_ms else np.zeros(1)
        counters["ticks"] = self.ticks
        msg = M.Status(stamp=now, seq=self.seq["status"], node="station", ok=ok, state=state,
                       progress=min(1.0, max(0.0, self.control.progress)), rates_hz={"loop": 1 / self.period},
                       latencies_ms={"solve_median": float(np.median(sm)), "solve_max": float(sm.max()),
                                     "tick_p50": float(np.percentile(tk, 50)), "tick_p99": float(np.percentile(tk, 99)),
                                     "tick_max": float(tk.max())},
                       counters=counters, text=text[:1024])
        self.seq["status"] += 1
        return msg

    def integrity(self, now: float) -> list[str]:
        """What makes this station's work untrustworthy right now (its status is then not ok): another sender's
        commands on this robot's key, telemetry dropped as implausible before pairing, in the last few seconds."""
        out = []
        with self.lock:
            foreign_at, foreign_epoch = self.foreign_cmd_at, self.foreign_epoch
        if now - foreign_at < INTEGRITY_WINDOW_S:
            out.append(f"another sender publishes commands for this robot (epoch {foreign_epoch:x}): a second "
                       "station or a forger")
        p = self.pairer
        bad = p.implausible_stamp + p.implausible_pose + p.implausible_pair
        if bad > self.implausible_seen[0]:
            self.implausible_seen = (bad, now)
        if now - self.implausible_seen[1] < INTEGRITY_WINDOW_S:
            out.append(f"implausible telemetry dropped before pairing ({p.implausible_stamp} stamps, "
                       f"{p.implausible_pose} poses, {p.implausible_pair} pairs so far)")
        return out

    def persist(self) -> bool:
        """Save the store; a failure (disk full, permissions) is reported and retried at the next period."""
        with self.lock:
            blob = self.store.to_bytes()
        try:
            save_atomic(self.store_path, blob)
        except OSError as exc:
            self.extra["persist_failures"] += 1
            self.persist_error = f"pair store not saved: {exc.strerror or exc}"
            log.error("%s (%s); driving on, retrying in %.0f s", self.persist_error, self.store_path,
                      self.persist_every)
            return False
        if self.persist_error:
            log.info("pair store saved again to %s", self.store_path)
        self.persist_error = ""
        return True

    def _put(self, topic: str, msg: Any) -> None:
        self.pubs[topic].put(M.encode(msg))

    # ------------------------------------------------------------------------------------------------- run
    def serve(self, session: zenoh.Session, stop: threading.Event, duration: float | None,
              exit_at_goal: bool) -> None:
        k = self.keys
        self.inputs.subscribe(session, k.state, M.LearnerState, "state", self.on_state)
        self.inputs.subscribe(session, k.applied, M.Applied, "applied", self.on_applied)
        self.inputs.subscribe(session, M.status_key(self.robot, "driver"), M.Status, "driver_status",
                              self.on_driver_status)
        self.inputs.subscribe(session, k.mission, M.MissionSpec, "mission", self.on_mission)
        self.inputs.subscribe(session, k.cmd, M.Command, "own_cmd", self.on_own_cmd)
        if self.teacher_kind == "external":
            self.inputs.subscribe(session, k.teacher, M.TeacherCommand, "teacher", self.on_teacher)
        session.declare_queryable(k.pairs, self.on_pairs_query)
        session.declare_queryable(k.control, self.on_control_query)
        self.pubs = {t: session.declare_publisher(getattr(k, t)) for t in ("cmd", "limits")}
        if self.teacher_kind != "external":
            self.pubs["teacher"] = session.declare_publisher(k.teacher)
        self.pubs["status"] = session.declare_publisher(M.status_key(self.robot, "station"))
        what = "calibration" if self.calibration else (
            "external teacher" if self.teacher_kind == "external" else f"mission {self.mission.name}")
        log.info("station for %s at %.0f Hz, %s, %s (epoch %x)", self.robot, 1 / self.period, what,
                 self.control.phase, self.epoch)
        systemd.ready(f"{self.robot}: {what}, mission {self.control.phase}")
        self.ticker = FixedRate(1 / self.period, stop)
        t_start = time.monotonic()
        t_status = t_persist = t_start
        periodic = True
        while not stop.is_set():
            now = time.monotonic()
            if duration is not None and now - t_start >= duration:
                break
            if not periodic:  # woken by an external teacher's command: map it now, nothing else
                self.tick(now)
                periodic = self.ticker.wait(self.wake)
                continue
            self.tick(now)
            self.tick_ms.append((time.monotonic() - now) * 1e3)
            self.ticks += 1
            if now >= t_status:
                self._put("status", self.status(now))
                self.publish_limits(now, force=True)
                t_status = now + 1.0
            else:
                self.publish_limits(now, force=False)
            if now >= t_persist:
                self.persist()
                t_persist = now + self.persist_every
            if exit_at_goal and (self.control.phase in ("finished", "aborted")
                                 or (self.calibration is not None and self.calibration.finished)):
                self._put("status", self.status(now))
                time.sleep(3 * self.period)
                break
            periodic = self.ticker.wait(self.wake if self.teacher_kind == "external" else None)


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--config", help="station TOML (scmbridge config show --kind station)")
    ap.add_argument("--robot", type=robot_arg, default=None, help="robot name (overrides the config)")
    ap.add_argument("--mission", default=None, help="mission file (TOML; overrides the config)")
    add_zenoh_args(ap)
    ap.add_argument("--rate", type=positive_float, default=None, help="control tick rate, Hz (overrides the config)")
    ap.add_argument("--store", default=None, help="pair store file (persisted atomically, reloaded at start)")
    ap.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    ap.add_argument("--exit-at-goal", action="store_true", help="stop the service once the goal is reached")
    ap.add_argument("--start", action="store_true",
                    help="start the mission at once (a person's act: never in a service unit that restarts)")


def control_file(robot: str) -> Path:
    """Where a station keeps its mission and phase across restarts."""
    return state_dir() / f"mission-{robot}.bin"


def restore_control(robot: str, mission_arg: str | None, default_mission: str | None) -> MissionControl:
    """The mission a station starts with: ``--mission`` (a new one: idle), else the saved one (never running),
    else the configured or shipped one (idle). An unreadable saved file is kept aside, not lost."""
    path = control_file(robot)
    if mission_arg:
        return MissionControl(robot, load_mission_spec(mission_arg))
    if path.exists():
        try:
            return MissionControl.restored(robot, M.decode(path.read_bytes(), Saved))
        except (OSError, M.MessageError, ValueError) as exc:
            aside = path.with_name(path.name + f".corrupt-{int(time.time())}")
            os.replace(path, aside)
            log.error("mission state %s unusable (%s); moved to %s, starting idle", path, exc, aside)
    return MissionControl(robot, load_mission_spec(default_mission))


def run(args: argparse.Namespace) -> int:
    cfg = load_station(args.config)  # mistakes end here, before any session opens
    robot = M.check_robot(args.robot or cfg.robot)
    rate = cfg.station.rate_hz if args.rate is None else args.rate
    if not RATE_HZ_RANGE[0] <= rate <= RATE_HZ_RANGE[1]:
        raise UsageError(f"--rate {rate:g}: must be within {RATE_HZ_RANGE[0]:g}..{RATE_HZ_RANGE[1]:g} Hz")
    store_path = Path(args.store) if args.store else cfg.store_file(robot)
    if store_path.is_dir():
        raise UsageError(f"pair store {store_path} is a directory; name a file")
    control = restore_control(robot, args.mission, cfg.station.mission or None)
    if args.start:
        control.request(M.MissionRequest(stamp=0.0, action="start", source="command line"),
                        Fitness("not checked yet"), 0.0)

    from transfer.scm import warmup

    station = Station(cfg, robot, rate, store_path, control.mission, control, control_file(robot))
    warmup()  # compile / load the SC kernels before the first tick
    stop = stop_on_signals()
    try:
        with open_session(zenoh_config(args), wait=stop, what="station") as session:
            station.serve(session, stop, args.duration, args.exit_at_goal)
    finally:
        saved = station.persist()
        station.save_control()
        if saved:
            log.info("pair store saved to %s (%d refined pairs)", store_path, len(station.store.refined()))
        else:
            log.error("pair store NOT saved to %s: %s (%d refined pairs lost at this exit)", store_path,
                      station.persist_error, len(station.store.refined()))
    return 0 if saved else 1
