"""The station's guards (bridge.nodes.station_guards) in the real station core, without Zenoh: the corridor, the fence
and the pose jump each pause a running mission with their typed reason; only a person resumes, and not while the robot
is still out unless told to override; a pose that jumps onto the goal does not finish the mission."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission_spec, mission_from_spec
from bridge.nodes.mission_control import MissionControl
from bridge.nodes.sources import Proposal
from bridge.nodes.station_core import StationCore, TickInputs
from bridge.nodes.station_guards import Guards, inside, outside_by
from bridge.tools.mission import reversed_spec

SQUARE = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]


def test_inside_and_how_far_outside_a_polygon() -> None:
    assert inside(1.0, 1.0, SQUARE) and inside(2.0, 1.0, SQUARE) and not inside(3.0, 1.0, SQUARE)
    assert outside_by(1.0, 1.0, SQUARE) == 0.0
    assert outside_by(3.0, 1.0, SQUARE) == pytest.approx(1.0)
    assert outside_by(3.0, 3.0, SQUARE) == pytest.approx(math.sqrt(2.0))


class Ahead:
    """A command source that follows the mission and always asks for the same slow command (the poses are the
    test's: these tests are about where the robot is, not how it got there)."""

    what, follows_mission, external = "ahead", True, False

    def propose(self, now, pose, ctx):
        return Proposal(np.array([0.2, 0.0]), np.array([pose.x, pose.y]))

    def reset(self) -> None:
        pass

    def done(self) -> bool:
        return False


def _driver(seq: int = 1) -> M.Status:
    return M.Status(stamp=0.0, seq=seq, node="driver", ok=True, text="driving", reason="ok")


class Run:
    """A station core fed poses at 50 Hz and ticked at 10 Hz, with a driver host status each tick."""

    def __init__(self, tmp_path, spec: M.MissionSpec | None = None, cfg: StationConfig | None = None) -> None:
        spec = spec or load_mission_spec()
        self.core = StationCore(cfg or StationConfig(), "r1", 10.0, tmp_path / "p.bin", mission_from_spec(spec),
                                control=MissionControl("r1", spec), source=Ahead())
        self.t, self.seq, self.driver_seq = 1.0, 0, 1

    def poses(self, points, epoch: int = 1) -> M.Status | None:
        """Each point a pose 20 ms after the last; a tick each 100 ms; the last status."""
        status = None
        for x, y in points:
            self.t += 0.02
            self.seq += 1
            st = M.LearnerState(stamp=self.t, seq=self.seq, x=float(x), y=float(y), theta=0.0, epoch=epoch)
            out = self.core.tick(TickInputs(telemetry=((st, self.t),), driver=(_driver(self.driver_seq), self.t)),
                                 self.t)
            status = out.status or status
        return status

    def ask(self, action: str, override: bool = False) -> M.MissionState:
        return self.core.request(M.MissionRequest(stamp=0.0, action=action, source="test", override=override), self.t)

    def status(self) -> M.Status:
        return self.core.status(self.t)


def _cfg(**station) -> StationConfig:
    return msgspec.convert({"station": station}, StationConfig)


def _line(a, b, step: float = 0.01):
    n = max(1, int(math.dist(a, b) / step))
    return [(a[0] + (b[0] - a[0]) * k / n, a[1] + (b[1] - a[1]) * k / n) for k in range(1, n + 1)]


def test_leaving_the_corridor_stops_the_robot_pauses_the_mission_and_says_how_far(tmp_path) -> None:
    run = Run(tmp_path)
    run.poses([(0.0, 0.0)])
    assert run.ask("start").accepted
    run.poses(_line((0.0, 0.0), (0.5, -0.5), 0.002))  # drifting off the S-path slowly (it heads north-east first)
    assert run.core.control.phase == "running"
    run.poses(_line((0.5, -0.5), (0.8, -1.0), 0.002))
    st = run.status()
    assert run.core.control.phase == "paused" and st.reason == "left_corridor" and not st.ok
    assert st.off_path_m is not None and st.off_path_m > 1.0  # the distance now, on the status
    assert run.core.counters.corridor_trips == 1 and "the corridor" in st.text
    trip = run.core.guards.trips[-1]  # where it left: as it reached 1 m (at 0.1 m/s, a tenth of a second ahead)
    assert trip.reason == "left_corridor" and 0.85 < trip.distance < 1.02 and trip.y < -0.5
    out = run.core.tick(TickInputs(driver=(_driver(), run.t)), run.t)
    assert out.command is not None and out.command.method == "stop" and (out.command.v, out.command.omega) == (0, 0)
    # only a person resumes, and not while the robot is still out ...
    ans = run.ask("resume")
    assert not ans.accepted and "from the path" in ans.text and "--override" in ans.text
    assert run.core.control.phase == "paused"
    # ... unless told to override: the station drives it back, the guard re-arms once it is inside
    assert run.ask("resume", override=True).accepted and run.core.control.phase == "running"
    run.poses(_line((0.8, -1.0), (0.5, -0.5), 0.002))
    assert run.core.control.phase == "running" and run.core.guards.corridor_override is None
    run.poses(_line((0.5, -0.5), (0.8, -1.0), 0.002))  # out again: paused again
    assert run.core.control.phase == "paused" and run.status().reason == "left_corridor"


def test_a_mission_files_corridor_wins_over_the_stations(tmp_path) -> None:
    spec = msgspec.structs.replace(load_mission_spec(), corridor_m=3.0)
    run = Run(tmp_path, spec, _cfg(corridor_m=0.5))
    run.poses([(0.0, 0.0)])
    assert run.ask("start").accepted
    run.poses(_line((0.0, 0.0), (0.8, -1.0)))
    assert run.core.control.phase == "running"  # 1.6 m out: inside the mission's 3 m
    run2 = Run(tmp_path / "b", None, _cfg(corridor_m=0.5))
    run2.poses([(0.0, 0.0)])
    assert run2.ask("start").accepted
    run2.poses(_line((0.0, 0.0), (0.8, -1.0)))
    assert run2.core.control.phase == "paused" and run2.status().reason == "left_corridor"


def test_a_start_with_the_robot_far_from_the_path_is_refused_unless_overridden(tmp_path) -> None:
    run = Run(tmp_path)
    run.poses([(0.0, -2.0)])
    ans = run.ask("start")
    assert not ans.accepted and "2.00 m from the path" in ans.text and run.core.control.phase == "idle"
    assert run.ask("start", override=True).accepted


def test_the_fence_pauses_the_mission_when_the_robot_leaves_it(tmp_path) -> None:
    fence = [(-1.0, -1.5), (3.0, -1.5), (3.0, 3.0), (-1.0, 3.0)]
    run = Run(tmp_path, msgspec.structs.replace(load_mission_spec(), corridor_m=5.0),
              _cfg(fence=[list(p) for p in fence]))
    run.poses([(0.0, 0.0)])
    assert run.ask("start").accepted
    run.poses(_line((0.0, 0.0), (0.5, -1.4)))
    assert run.core.control.phase == "running"
    run.poses(_line((0.5, -1.4), (0.5, -1.6)))
    st = run.status()
    assert run.core.control.phase == "paused" and st.reason == "fence" and run.core.counters.fence_trips == 1
    assert not run.ask("resume").accepted  # still outside
    run.poses(_line((0.5, -1.6), (0.5, -1.2)))  # driven back in by a person
    assert run.ask("resume").accepted


def test_a_pose_jump_pauses_the_mission_and_is_not_progress(tmp_path) -> None:
    run = Run(tmp_path)
    run.poses([(0.0, 0.0)])
    assert run.ask("start").accepted
    run.poses(_line((0.0, 0.0), (0.3, 0.28)))
    before = run.core.control.progress
    path = load_mission_spec().path
    run.poses([path[100]])  # on the path, 2 m ahead in 20 ms
    st = run.status()
    assert run.core.control.phase == "paused" and st.reason == "pose_jump" and run.core.counters.pose_jumps == 1
    assert run.core.control.progress == before
    assert run.ask("resume").accepted  # a person looked: the track goes on from the new pose
    run.poses(_line(path[100], path[103], 0.005))
    assert run.core.control.phase == "running"


def test_a_driver_host_restart_whose_pose_jumps_onto_the_goal_does_not_finish_the_mission(tmp_path) -> None:
    """As a new user found it: the mission sent reversed (its goal is the origin), driven a little, the driver host
    restarts and its emulated pose starts again at (0, 0): the goal. A person resumes; the mission must go on, not
    end as "goal reached" at once."""
    spec = reversed_spec(load_mission_spec())
    start = spec.path[0]
    run = Run(tmp_path, spec)
    run.poses([start])
    assert run.ask("start").accepted
    run.poses(_line(start, spec.path[40]))
    progress = run.core.control.progress
    assert run.core.control.phase == "running" and 0.0 < progress < 0.2
    run.driver_seq = 0  # the driver host restarted: its status counts from 0 again
    run.poses([spec.path[40]] * 3)
    assert run.core.control.phase == "paused"
    run.t += 2.0  # the restart took 2 s; the new host's pose is the origin, the mission's goal
    run.driver_seq = 1
    run.poses([(0.0, 0.0)] * 5, epoch=2)
    assert run.core.counters.pose_jumps == 1
    assert run.ask("resume").accepted
    run.poses([(0.0, 0.0)] * 10, epoch=2)
    assert run.core.control.phase == "running", run.core.control.reason  # not "goal reached"
    assert run.core.control.progress < 0.3


def test_the_jump_bound_is_the_learned_top_speed_with_a_margin() -> None:
    g = Guards()
    a = M.LearnerState(stamp=1.0, seq=1, x=0.0, y=0.0, theta=0.0)
    assert g.pose(a, 1.0, top_speed=1.0) is None
    # 1 s later, 1.7 m away: within 1.5 * 1 m/s * 1 s + 0.3 m
    assert g.pose(M.LearnerState(stamp=2.0, seq=2, x=1.7, y=0.0, theta=0.0), 2.0, top_speed=1.0) is None
    # a batch: received together, but the stamps say 1 s apart
    assert g.pose(M.LearnerState(stamp=3.0, seq=3, x=3.4, y=0.0, theta=0.0), 2.0, top_speed=1.0) is None
    assert g.pose(M.LearnerState(stamp=3.1, seq=4, x=4.0, y=0.0, theta=0.0), 2.1, top_speed=1.0) == pytest.approx(0.6)
    assert g.odometer == pytest.approx(3.4)  # the jump is not track


def test_a_robot_started_part_way_along_the_path_finishes_at_the_goal(tmp_path) -> None:
    """The track begins where the robot is when a person starts the mission: progress from there, not from 0."""
    spec = load_mission_spec()
    k = int(0.8 * len(spec.path))
    run = Run(tmp_path, spec)
    run.poses([spec.path[k]])
    assert run.ask("start").accepted
    for a, b in zip(spec.path[k:], spec.path[k + 1:]):
        run.poses(_line(a, b, 0.005))
        if run.core.control.phase != "running":
            break
    assert run.core.control.phase == "finished", run.core.control.reason


def test_a_robot_running_away_fast_is_stopped_before_the_line(tmp_path) -> None:
    """At 1 m/s straight away from the path the stop is given a second ahead of the line (STOP_LOOKAHEAD_S), so that a
    fast vehicle's braking ends near it, not a metre past it."""
    run = Run(tmp_path)
    run.poses([(0.0, 0.0)])
    assert run.ask("start").accepted
    run.poses(_line((0.0, 0.0), (0.7, -0.7), 0.02))  # 1 m/s, straight off the path's start
    st = run.status()
    trip = run.core.guards.trips[-1]
    assert run.core.control.phase == "paused" and st.reason == "left_corridor", st
    assert trip.distance < 0.3 and "leaving the corridor" in trip.text and "moving away at" in trip.text, trip
