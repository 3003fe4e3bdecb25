"""bridge/tools/demo_sitl.py: the SITL demo's pure parts (docs/ARCHITECTURE.md section 7, the paper's Section 5.2
case): the learner's range from the vehicle's parameters, the mission moved rigidly onto the vehicle's pose, and the
mission file written for the station. The shipped S-path placed and read back, and the run against ArduPilot's SITL,
are in tests/integration/test_demo_sitl.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import MissionSpec, decode_toml, mission_from_spec
from bridge.core.errors import UsageError
from bridge.tools.demo_sitl import RANGE_PARAMS, REPORTED_PARAMS, V_MIN, learner_range, mission_toml, place_mission

SPEC = M.MissionSpec(name="ell", path=[[0.0, 0.0], [2.0, 0.0], [2.0, 1.0]], goal_tolerance=0.2,
                     obstacles=[[1.0, 0.5, 0.25]], start=[0.0, -0.3, 0.0])


def test_the_range_params_are_reported_with_the_others() -> None:
    assert set(RANGE_PARAMS) <= set(REPORTED_PARAMS) and len(set(REPORTED_PARAMS)) == len(REPORTED_PARAMS)


def test_the_turn_rate_limit_is_read_in_degrees_and_given_in_radians_both_ways() -> None:
    v, w = learner_range({"WP_SPEED": 1.0, "CRUISE_SPEED": 2.0, "ATC_STR_RAT_MAX": 90.0})
    assert v == (V_MIN, 1.0) and w == pytest.approx((-math.pi / 2, math.pi / 2))
    assert all(isinstance(a, float) for a in (*v, *w))


@pytest.mark.parametrize("params", [
    {"WP_SPEED": V_MIN, "CRUISE_SPEED": 3.0, "ATC_STR_RAT_MAX": 90.0},  # no speed above the floor
    {"WP_SPEED": 1.0, "CRUISE_SPEED": 3.0, "ATC_STR_RAT_MAX": 0.0},  # no turning
    {"WP_SPEED": 1.0, "CRUISE_SPEED": 3.0, "ATC_STR_RAT_MAX": -10.0},
])
def test_a_vehicle_without_a_usable_range_is_refused_with_its_parameters(params: dict[str, float]) -> None:
    with pytest.raises(UsageError, match="no usable command range") as err:
        learner_range(params)
    assert "ATC_STR_RAT_MAX" in str(err.value)


def test_a_missing_parameter_is_not_guessed() -> None:
    with pytest.raises(KeyError):
        learner_range({"WP_SPEED": 1.0})


def test_placing_onto_the_start_pose_itself_changes_nothing_but_the_name_and_frame() -> None:
    placed = place_mission(SPEC, tuple(SPEC.start))
    assert np.allclose(placed.path, SPEC.path) and placed.start == pytest.approx(SPEC.start)
    assert np.allclose(placed.obstacles, SPEC.obstacles) and placed.goal_tolerance == SPEC.goal_tolerance
    assert (placed.name, placed.frame) == ("ell@sitl", "sitl-local")


def test_placing_turns_about_the_start_and_moves_onto_the_pose() -> None:
    placed = place_mission(SPEC, (10.0, 20.0, math.pi / 2))  # a quarter turn left
    # (0, 0) is 0.3 m left of the start (0, -0.3) facing +x: after the turn it is 0.3 m in -x of (10, 20)
    assert placed.path[0] == pytest.approx([9.7, 20.0])
    assert placed.path[1] == pytest.approx([9.7, 22.0]) and placed.path[2] == pytest.approx([8.7, 22.0])
    assert placed.obstacles[0] == pytest.approx([9.2, 21.0, 0.25])  # the radius is kept
    assert placed.start == [10.0, 20.0, math.pi / 2]


def test_a_mission_without_a_start_is_placed_from_its_first_waypoint_facing_x() -> None:
    spec = M.MissionSpec(name="line", path=[[1.0, 1.0], [2.0, 1.0]])
    placed = place_mission(spec, (0.0, 0.0, math.pi))
    assert placed.path[0] == pytest.approx([0.0, 0.0]) and placed.path[1] == pytest.approx([-1.0, 0.0])


def test_the_mission_file_reads_back_as_the_same_mission() -> None:
    placed = place_mission(SPEC, (1.25, -3.5, 0.7))
    back = decode_toml(mission_toml(placed), MissionSpec, "mission.toml")
    assert (back.name, back.frame, back.goal_tolerance) == (placed.name, placed.frame, placed.goal_tolerance)
    assert back.path == placed.path and back.obstacles == placed.obstacles and back.start == placed.start  # exact
    assert mission_from_spec(back).path.length == pytest.approx(mission_from_spec(SPEC).path.length)


def test_a_mission_without_obstacles_or_start_still_makes_a_file() -> None:
    spec = M.MissionSpec(name="bare", path=[[0.0, 0.0], [1.0, 0.0]])
    back = decode_toml(mission_toml(spec), MissionSpec, "mission.toml")
    assert back.path == spec.path and back.obstacles == [] and back.start is None


class _Autopilot:
    """The vehicle's parameter table as a pilot's link sees it (``set_param`` returns once the vehicle's
    PARAM_VALUE says the new value, as :meth:`sim_learner.sitl.Pilot.set_param` does)."""

    def __init__(self) -> None:
        import threading
        from types import SimpleNamespace

        self.cond = threading.Condition()
        self.s = SimpleNamespace(params={"CRUISE_THROTTLE": 65.0})

    def set_param(self, name: str, value: float) -> None:
        with self.cond:
            self.s.params[name] = float(value)


def test_a_parameter_change_counts_from_the_first_driven_command_and_says_what_the_vehicle_read_back() -> None:
    """``--param-at``: S seconds after the vehicle first drove (the event), not after the station started, which
    takes 2-20 s to come up; the vehicle's PARAM_VALUE is kept beside the change; stopped before the vehicle drove,
    nothing changes."""
    import threading
    import time

    from bridge.tools.demo_sitl import ParamChanges, param_change

    pilot, driving = _Autopilot(), threading.Event()
    changes = ParamChanges(pilot, [param_change("0.2:CRUISE_THROTTLE=45")])
    changes.start(None, after=driving)
    assert not changes.finished.wait(0.3) and changes.done == []  # the vehicle has not driven yet
    t_drove = time.monotonic()
    driving.set()
    assert changes.finished.wait(10.0)
    (at, name, value, err), = changes.done
    assert (name, value, err) == ("CRUISE_THROTTLE", 45.0, "") and at >= t_drove + 0.2
    assert changes.read_back == {"CRUISE_THROTTLE": 45.0}
    never = ParamChanges(_Autopilot(), [param_change("0:CRUISE_THROTTLE=45")])
    never.start(None, after=threading.Event())
    never.stop()
    assert never.finished.wait(5.0) and never.done == [] and never.read_back == {}
