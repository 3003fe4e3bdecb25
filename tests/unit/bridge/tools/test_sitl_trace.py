"""bridge/tools/sitl_trace.py: a SITL run's trace and where its last half's deviation came from."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bridge.core.config import load_mission_spec, mission_from_spec
from bridge.tools.sitl_trace import BEND_RAD_PER_M, curvature_at, deviation_sources, write_trace


def test_the_last_halfs_deviation_splits_into_bends_and_straights_and_by_the_method_driving(tmp_path) -> None:
    world = mission_from_spec(load_mission_spec(None))  # the paper's S-path: bends and straights
    path = world.path
    s = np.linspace(0.0, path.length, 200)
    poses = path.at(s)
    kappa = np.array([curvature_at(path, float(x)) for x in s])
    assert (kappa > BEND_RAD_PER_M).any() and (kappa <= BEND_RAD_PER_M).any()
    # off the path to its left: 3 cm on the bends, 1 cm on the straights (exact where the offset is small)
    off = np.where(kappa > BEND_RAD_PER_M, 0.03, 0.01)
    xy = poses[:, :2] + off[:, None] * np.stack([-np.sin(poses[:, 2]), np.cos(poses[:, 2])], axis=1)
    states = [(0.1 * i, float(x), float(y), float(th)) for i, ((x, y), th) in enumerate(zip(xy, poses[:, 2]))]
    # the first 150 poses' time driven by a "direct" command, the rest by "scm"
    applied = [(0.0, "cmd", 1), (15.0, "cmd", 2), (15.0, "stop", None)]
    trace = write_trace(tmp_path / "trace.json", states, applied, {1: "direct", 2: "scm"}, world)
    assert json.loads((tmp_path / "trace.json").read_text()) == trace
    got = deviation_sources(trace, 0.0, 20.0)
    half = [(o, k) for o, k, q in zip(off, kappa, s) if q / path.length >= 0.5]
    assert got["poses"] == len(half) and got["bend"]["mean_dev_m"] == pytest.approx(0.03, abs=2e-3)
    assert got["straight"]["mean_dev_m"] == pytest.approx(0.01, abs=2e-3)
    parts = [got["bend"], got["straight"]]
    assert sum(p["share"] * p["mean_dev_m"] for p in parts) == pytest.approx(got["mean_dev_m"], abs=1e-3)
    assert set(got["by_method"]) == {"direct", "scm"}
    assert got["by_method"]["direct"]["poses"] + got["by_method"]["scm"]["poses"] == got["poses"]
    assert deviation_sources(trace, 100.0, 120.0) == {"poses": 0}  # nothing in the window
