"""Missions the tests drive when the paper's whole S-path is not what they are about: a shorter run of the same
kind, so a test that checks a demo's plumbing (its recording, its fleet) pays for its claims and not for 8 m of path."""

from __future__ import annotations

from pathlib import Path

from bridge.core.config import load_mission_spec
from bridge.core.wire import MissionSpec
from bridge.tools.mission_place import mission_toml


def first_bend() -> MissionSpec:
    """The S-path's first bend (x <= 4 m: 4.8 m of arc, its start pose and the two obstacles beside that bend)."""
    spec = load_mission_spec(None)
    return MissionSpec(name="s-path-first-bend", frame=spec.frame, goal_tolerance=spec.goal_tolerance,
                       start=spec.start, path=[p for p in spec.path if p[0] <= 4.0],
                       obstacles=[o for o in spec.obstacles if o[0] <= 4.0])


def first_bend_file(directory: Path) -> Path:
    """:func:`first_bend` as a mission file in ``directory`` (``scmbridge demo --mission``)."""
    path = directory / "first-bend.toml"
    path.write_text(mission_toml(first_bend()))
    return path
