"""The order the suite's tests are handed to pytest-xdist in (tests/conftest.py calls :func:`order`).

``--dist worksteal`` first gives each of the N workers a contiguous share of the collected tests, in order, then a
worker whose share ran out takes the later half of the longest remaining share. Where a long test sits decides the
wall time: one that starts late (near the end of its share, or stolen at the end) ends the run alone while the
other workers wait. So the long tests are dealt out first: the longest to the share with the least long-test time so
far (longest processing time first), and in each share they start early, each followed by a stretch of quick tests
(not one long test after another on one worker: most of them are whole loops of processes on real time, and the
quick tests between them leave the cores to the loops). The quick tests keep their collected order (a file's tests
stay together), so the late halves the stealing moves are quick tests.

The long tests and their seconds are :data:`LONGEST` (``pytest --durations`` of a fresh clone's ``make test``, four
workers on two cores); a test marked ``slow`` that is not listed counts :data:`SLOW_DEFAULT_S`. A name that no longer
matches a collected test is simply not found: the order stays valid, only less balanced. How long the suite takes:
docs/BENCHMARKS.md, "The test suite"."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

T = TypeVar("T")

#: node id -> seconds, for the tests that take longer than a few seconds (the measure is only for their order)
LONGEST: dict[str, float] = {
    "tests/integration/test_can_drift.py::test_the_hil_loop_relearns_the_cells_a_dragging_wheel_changed_in_the_"
    "direction_of_the_drag": 51.0,
    "tests/integration/test_can_drift.py::test_the_hil_loop_relearns_the_cells_a_sagging_battery_changed_and_reaches_"
    "the_goal": 45.0,
    "tests/integration/test_record.py::test_a_recorded_demo_reports_the_live_demos_figures": 40.0,
    "tests/integration/test_fleet.py::test_the_fleet_demo_brings_three_robots_to_their_goals_and_leaves_no_process":
        35.0,
    "tests/integration/test_reliability.py::test_a_short_soak_runs_and_reports": 32.0,
    "tests/integration/test_demo_calibrate.py::test_the_demo_calibrates_then_drives_its_mission_from_the_calibrated_"
    "store": 31.0,
    "tests/integration/test_fleet.py::test_the_fleet_bench_measures_one_station_and_says_how_many_it_held": 30.0,
    "tests/integration/test_mission_control.py::test_a_station_drives_only_after_a_person_and_an_estop_release_or_a_"
    "driver_restart_leaves_it_paused": 30.0,
    "tests/repo/test_install.py::test_a_robot_installs_from_its_lock_and_the_project_offline": 27.0,
    "tests/integration/test_calibrate.py::test_the_motion_primitive_teacher_drives_from_calibrated_pairs": 24.0,
    "tests/integration/test_corridor.py::test_a_robot_that_runs_away_stops_within_the_corridor_and_waits_for_a_person":
        24.0,
    "tests/integration/test_lab_in_a_box.py::test_a_secure_lab_on_loopback_is_driven_and_stopped_by_its_operator": 22.0,
    "tests/integration/test_external_teacher.py::test_the_example_external_teacher_drives_the_robot_through_the_"
    "transfer_service": 20.0,
    "tests/repo/test_docs_commands.py::test_the_documented_offline_commands_run": 20.0,
    "tests/integration/test_tool_signals.py::test_a_tool_told_to_stop_leaves_no_process_behind[demo-SIGTERM]": 17.0,
    "tests/integration/test_lab_in_a_box.py::test_the_operators_documented_commands_run_as_written_in_the_lab": 16.0,
    "tests/integration/test_tool_signals.py::test_a_tool_told_to_stop_leaves_no_process_behind[demo --robots-SIGTERM]":
        16.0,
    "tests/unit/sim_learner/test_experiments.py::test_cli_grid_over_seeds_runs_each_seeds_mpc_and_summarises": 15.0,
    "tests/unit/sim_learner/test_experiments.py::test_primitives_scm_learner_reaches_the_goal_and_the_baseline_"
    "deviates_3x_more": 14.0,
}
#: the seconds counted for a test marked ``slow`` that :data:`LONGEST` does not list
SLOW_DEFAULT_S = 10.0
#: the long tests of a share start within this part of it (the rest, quick tests only, is what stealing moves)
LONG_SPAN = 0.4


def shares(n_items: int, workers: int) -> list[int]:
    """The sizes of the contiguous shares ``--dist worksteal`` first hands the workers (xdist's own arithmetic: each
    idle worker in turn gets the remaining tests divided by the workers still to serve)."""
    out, left = [], n_items
    for i in range(workers):
        out.append(left // (workers - i))
        left -= out[-1]
    return out


def order(items: Sequence[T], workers: int, seconds: Callable[[T], float | None],
          group: Callable[[T], str] | None = None) -> list[T]:
    """``items`` reordered for ``workers`` xdist workers (see the module docstring); ``seconds(item)`` is an item's
    expected time if it is a long test, else None. A long test goes in only between two quick tests of different
    ``group`` (tests/conftest.py: the module, for a module with a module- or class-scoped fixture): one inside such a
    module's run of tests would end its fixtures there, and pytest would set them up again after it; and the long
    tests of one such group go one after another to one share (dealt apart, each worker would set up the fixture they
    share). Every item is kept, once."""
    quick = [it for it in items if seconds(it) is None]
    units: dict[object, list[T]] = {}  # a module's long tests that share its fixtures go together, in their order
    for i, it in enumerate(items):
        if seconds(it) is not None:
            units.setdefault(group(it) if group is not None else i, []).append(it)
    if not units:
        return list(items)

    def unit_s(unit: list[T]) -> float:
        return sum(seconds(it) or 0.0 for it in unit)

    workers = max(1, workers)
    sizes = shares(len(items), workers)
    bins: list[list[list[T]]] = [[] for _ in range(workers)]
    load = [0.0] * workers
    counts = [0] * workers
    for unit in sorted(units.values(), key=lambda u: -unit_s(u)):  # the longest first, each to the share with the
        k = min(range(workers), key=lambda i: (load[i], counts[i] - sizes[i]))  # least long-test time (ties: larger)
        bins[k].append(unit)
        load[k] += unit_s(unit)
        counts[k] += len(unit)
    out: list[T] = []
    q = 0
    for k in range(workers):
        n_quick = max(0, sizes[k] - counts[k])
        mine, q = quick[q:q + n_quick], q + n_quick
        gap = int(len(mine) * LONG_SPAN) // max(1, len(bins[k]))  # quick tests after each long one
        cut = 0
        for j, unit in enumerate(bins[k]):
            out.extend(unit)
            end = max(cut, min(len(mine), (j + 1) * gap))
            while group is not None and 0 < end < len(mine) and group(mine[end]) == group(mine[end - 1]):
                end += 1  # to the end of that module's run
            out.extend(mine[cut:end])
            cut = end
        out.extend(mine[cut:])
    out.extend(quick[q:])  # only when the long tests outnumber a share's size
    return out
