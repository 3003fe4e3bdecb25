"""sim_learner/sitl_profiles.py: the seeded family of ArduPilot Rover profiles (``scmbridge bench sitl``)."""

from __future__ import annotations

import pytest

from sim_learner.sitl_profiles import COUNT, FRAMES, RANGES, SEED, family, select

DRAWN = ("CRUISE_SPEED", "CRUISE_THROTTLE", "ATC_SPEED_P", "ATC_SPEED_I", "ATC_SPEED_FF", "ATC_ACCEL_MAX",
         "ATC_DECEL_MAX", "ATC_STR_RAT_MAX", "ATC_STR_RAT_P", "ATC_STR_RAT_I", "ATC_STR_RAT_FF", "MOT_THST_EXPO")


@pytest.mark.parametrize("frame", list(FRAMES))
def test_each_frame_has_its_family_half_held_out_every_parameter_inside_ardupilots_range(frame: str) -> None:
    fam = family(frame)
    assert len(fam) == COUNT >= 24 and len({p.name for p in fam}) == COUNT
    assert sum(p.split == "heldout" for p in fam) == sum(p.split == "dev" for p in fam) == COUNT // 2
    for p in fam:
        assert set(DRAWN) <= set(p.params) <= set(RANGES)
        for name, value in p.params.items():
            lo, hi = RANGES[name]
            assert lo <= value <= hi, (p.name, name, value)
        assert p.params["ATC_STR_RAT_MAX"] <= 45.0  # at most the teacher's turn rate
    with_wp = sum("WP_SPEED" in p.params for p in fam)
    assert 0 < with_wp < COUNT  # WP_SPEED set in some, left at the frame's default in others
    assert all(0.3 <= p.params["WP_SPEED"] <= 0.6 for p in fam if "WP_SPEED" in p.params)


def test_the_family_and_its_split_are_fixed_by_the_seed() -> None:
    assert family("skid") == family("skid") and family("skid", seed=SEED + 1) != family("skid")
    longer = family("skid", count=30)
    assert [p.params for p in longer[:COUNT]] == [p.params for p in family("skid")]  # profile k is profile k
    assert [p.params for p in family("skid")] != [p.params for p in family("ackermann")]


def test_a_profile_is_a_parameter_file_sitl_reads() -> None:
    p = family("ackermann")[3]
    lines = [ln for ln in p.parm().splitlines() if ln and not ln.startswith("#")]
    assert {ln.split()[0]: float(ln.split()[1]) for ln in lines} == pytest.approx(p.params)
    assert p.model == "rover" and p.name == "ackermann-03"


def test_profiles_are_selected_by_half_or_index() -> None:
    assert [p.split for p in select("skid", "heldout")] == ["heldout"] * (COUNT // 2)
    assert [p.index for p in select("skid", "2..4")] == [2, 3, 4] and len(select("skid", "all")) == COUNT
    assert [p.index for p in select("ackermann", "7")] == [7]
    for bad in ("5..2", "x", f"0..{COUNT}"):
        with pytest.raises(ValueError):
            select("skid", bad)
