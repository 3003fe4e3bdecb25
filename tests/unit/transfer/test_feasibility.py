"""transfer/feasibility.py: whether a path bends more than a measured car can follow within the corridor."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.core.config import load_mission
from transfer.feasibility import CORRIDOR_SHARE, Reach, outside_assumption, path_bends


def _arc(radius: float, turn: float, n: int = 400, left: bool = True) -> np.ndarray:
    th = np.linspace(0.0, turn, n)
    y = radius * (1 - np.cos(th))
    return np.c_[radius * np.sin(th), y if left else -y]


def test_the_curvature_of_an_arc_is_one_over_its_radius_and_its_sign_says_the_side() -> None:
    s, k = path_bends(_arc(2.0, np.pi))
    assert np.median(k[20:-20]) == pytest.approx(0.5, rel=1e-3) and s[-1] == pytest.approx(2 * np.pi, rel=1e-3)
    _, k = path_bends(_arc(2.0, np.pi, left=False))
    assert np.median(k[20:-20]) == pytest.approx(-0.5, rel=1e-3)
    _, k = path_bends(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [2.0, 0.0]]))  # a repeated point turns nothing
    assert np.allclose(k, 0.0)


def test_the_s_path_bends_at_about_three_quarters_of_a_radian_per_metre_each_way() -> None:
    _, k = path_bends(load_mission(None).path.points)
    assert 0.70 < k.max() < 0.76 and -0.76 < k.min() < -0.70


def test_a_car_that_turns_less_than_the_bend_within_its_corridor_allowance_is_outside() -> None:
    path = load_mission(None).path.points
    # the cars measured on the held-out Ackermann profiles that left the corridor turned 0.29-0.58 rad/m
    for kappa in (0.29, 0.37, 0.58):
        out = outside_assumption(path, Reach(kappa, kappa, 0.33), corridor_m=1.0)
        assert out is not None and out.vehicle_kappa == kappa and 0.70 < out.path_kappa < 0.76
        assert "0.73 rad/m" in out.text() and f"{kappa:.2f} rad/m at 0.33 m/s" in out.text(), out.text()
    # those that followed it turned 0.67 rad/m and more; a skid-steer (nothing measured) is never outside
    for kappa in (0.67, 0.73, 0.96):
        assert outside_assumption(path, Reach(kappa, kappa, 0.3), corridor_m=1.0) is None
    # one side only: the side that falls short is named
    out = outside_assumption(path, Reach(right=0.9, left=0.4, speed=0.3), corridor_m=1.0)
    assert out is not None and out.side == "left"
    assert outside_assumption(path, Reach(right=None, left=None, speed=0.3), corridor_m=1.0) is None


def test_the_allowance_is_a_share_of_the_corridor_and_only_the_path_ahead_counts() -> None:
    arc = _arc(2.0, np.pi / 2)  # 0.5 rad/m: a car turning 0.45 drives 0.22 m wide of its arc
    straight = np.c_[np.linspace(-5.0, -0.01, 100), np.zeros(100)]
    path = np.vstack([straight, arc])
    assert CORRIDOR_SHARE * 1.0 > 1.0 / 0.45 - 2.0
    assert outside_assumption(path, Reach(0.45, 0.45, 0.3), corridor_m=1.0) is None
    assert outside_assumption(path, Reach(0.45, 0.45, 0.3), corridor_m=0.5) is not None  # a narrower corridor
    assert outside_assumption(path, Reach(0.3, 0.3, 0.3), corridor_m=1.0) is not None
    assert outside_assumption(path, Reach(0.3, 0.3, 0.3), corridor_m=1.0, from_s=100.0) is None  # past the bend
