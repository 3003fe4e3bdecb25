"""bridge/tools/demo_identify.py: the station's settings that follow from the measured range (the identification's
run through the station on SITL: tests/integration/test_sitl_profiles.py, marked ``sitl``)."""

from __future__ import annotations

import argparse

from bridge.tools.demo_identify import settings
from transfer.identify import Identified


def args(**kw: object) -> argparse.Namespace:
    return argparse.Namespace(**{"turn": None, "start": None, "pair_settle": None, **kw})


def test_a_car_like_slow_vehicle_gets_curvature_limits_an_on_path_start_and_long_settling() -> None:
    car = Identified(v_max=1.0, w_range=(-0.52, 0.52), turns_in_place=False, settle_s=0.9, settle_top_s=1.9)
    got = settings(car, args(), 0.05)
    assert (got["turn"], got["start"]) == ("needs-speed", "on-path")
    assert got["settle"] == 1.1 and got["settle_edge"] == 2.6  # as the hand-set Ackermann demo: 1 s, 2.5 s
    assert got["v_range"] == (0.05, 1.0) and got["w_range"] == (-0.52, 0.52)


def test_a_quick_vehicle_that_turns_in_place_keeps_the_papers_start_and_short_settling() -> None:
    skid = Identified(v_max=0.6, w_range=(-0.9, 0.8), turns_in_place=True, settle_s=0.3, settle_top_s=0.7)
    got = settings(skid, args(), 0.05)
    assert (got["turn"], got["start"], got["settle"], got["settle_edge"]) == ("in-place", "mission", 0.5, 0.0)


def test_what_the_person_said_wins_over_what_was_measured() -> None:
    car = Identified(v_max=1.0, w_range=(-0.52, 0.52), turns_in_place=False, settle_s=0.9, settle_top_s=1.9)
    got = settings(car, args(turn="in-place", start="on-path", pair_settle=0.0), 0.05)
    assert (got["turn"], got["start"], got["settle"], got["settle_edge"]) == ("in-place", "on-path", 0.0, 0.0)
    tiny = Identified(v_max=0.04, w_range=(-0.5, 0.5), turns_in_place=True, settle_s=0.3, settle_top_s=0.5)
    assert settings(tiny, args(), 0.05)["v_range"] == (0.05, 0.1)  # never an empty range
