"""transfer/teacher/path.py: ``Polyline``, the desired path with arc length (closest point, sampling, distance).

A first check of projection and sampling sits in tests/unit/transfer/teacher/test_mpc.py; here the rest of its
contract: the refusals, the clipping at both ends, ties, a repeated point, the vectorised ``at``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.teacher.path import Polyline

L = Polyline(np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]]))  # 3 m east, 4 m north


@pytest.mark.parametrize("pts", [np.zeros(4), np.zeros((1, 2)), np.zeros((3, 3)), np.zeros((2, 2, 2))])
def test_a_path_needs_at_least_two_planar_points(pts: np.ndarray) -> None:
    with pytest.raises(ValueError, match=r"a path needs an \(M >= 2, 2\) array of points"):
        Polyline(pts)


def test_arc_length_segments_and_headings() -> None:
    assert L.length == 7.0
    np.testing.assert_array_equal(L.s, [0.0, 3.0, 7.0])
    np.testing.assert_array_equal(L.seg_len, [3.0, 4.0])
    np.testing.assert_allclose(L.heading, [0.0, math.pi / 2])
    assert Polyline([[0, 0], [1, 1]]).points.dtype == np.float64  # lists of ints are taken


def test_project_clips_to_the_ends_and_measures_the_distance() -> None:
    assert L.project(np.array([-2.0, 0.0])) == pytest.approx((0.0, 2.0))  # before the start
    assert L.project(np.array([3.0, 6.0])) == pytest.approx((7.0, 2.0))  # beyond the end
    assert L.project(np.array([4.0, 1.0])) == pytest.approx((4.0, 1.0))  # beside the second segment
    assert L.project(np.array([3.0, 0.0])) == pytest.approx((3.0, 0.0))  # on the corner
    assert L.distance([1.5, -0.5]) == pytest.approx(0.5)  # a list is taken


def test_a_tie_goes_to_the_earlier_segment() -> None:
    # a path that comes back over itself: the point is on both legs, the first (smaller arc length) wins
    back = Polyline(np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 0.0]]))
    s, d = back.project(np.array([0.5, 0.0]))
    assert (s, d) == pytest.approx((0.5, 0.0))


def test_at_samples_poses_clipped_to_the_path_with_the_segments_heading() -> None:
    got = L.at(np.array([-1.0, 0.0, 1.5, 3.0, 5.0, 7.0, 9.0]))
    want = [[0, 0, 0], [0, 0, 0], [1.5, 0, 0], [3, 0, math.pi / 2], [3, 2, math.pi / 2], [3, 4, math.pi / 2],
            [3, 4, math.pi / 2]]
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert L.at(2.0).shape == (3,) and L.at(np.zeros((2, 5))).shape == (2, 5, 3)
    # project and at are inverse along the path
    for s in np.linspace(0.0, 7.0, 15):
        assert L.project(L.at(s)[:2]) == pytest.approx((s, 0.0), abs=1e-12)


def test_a_repeated_point_gives_no_nan() -> None:
    p = Polyline(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 1.0]]))
    assert p.length == 2.0
    assert np.all(np.isfinite(p.at(np.linspace(0, 2, 9))))
    assert p.project(np.array([1.2, 0.5])) == pytest.approx((1.5, 0.2))
