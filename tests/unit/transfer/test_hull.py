"""transfer/hull.py: the learned limits' convex hull. Its vertices are qhull's (scipy's ``ConvexHull``, which the
limits used before) on random, rounded (duplicates, points on edges), collinear and repeated point sets, counter-
clockwise; no hull where the points span no area."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial import ConvexHull, QhullError

from transfer.hull import convex_hull


def _qhull(points: np.ndarray) -> set[tuple[float, float]] | None:
    try:
        return set(map(tuple, points[ConvexHull(points).vertices].tolist()))
    except QhullError:
        return None


def _signed_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(x @ np.roll(y, -1) - y @ np.roll(x, -1))


@pytest.mark.parametrize("kind", ["random", "rounded", "collinear", "repeated"])
@pytest.mark.parametrize("seed", range(40))
def test_its_vertices_are_qhulls_counter_clockwise(kind: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 80))
    if kind == "random":
        pts = rng.random((n, 2))
    elif kind == "rounded":  # duplicates and runs of points on one line: only the corners are vertices
        pts = np.round(rng.random((n, 2)) * 5) / 5
    elif kind == "collinear":
        t = rng.random(n)
        pts = np.c_[t, 0.3 * t + 0.1]
    else:
        pts = np.r_[rng.random((n, 2)), np.full((3, 2), 0.5), rng.random((1, 2)).repeat(4, axis=0)]
    ring = convex_hull(pts)
    expected = _qhull(pts)
    if expected is None:
        assert ring is None
        return
    assert ring is not None and set(map(tuple, ring.tolist())) == expected and len(ring) == len(expected)
    assert _signed_area(ring) > 0


@given(st.lists(st.tuples(st.floats(0, 1), st.floats(0, 1)), min_size=0, max_size=40))
def test_every_point_is_inside_or_on_the_hull(points: list[tuple[float, float]]) -> None:
    ring = convex_hull(np.array(points, dtype=float).reshape(-1, 2))
    if ring is None:
        return
    edges = np.roll(ring, -1, axis=0) - ring
    for p in points:
        rel = np.asarray(p) - ring
        assert np.all(edges[:, 0] * rel[:, 1] - edges[:, 1] * rel[:, 0] >= -1e-9)


def test_a_square_with_points_inside_and_on_its_edges_has_its_four_corners() -> None:
    pts = [(0, 0), (1, 0), (1, 1), (0, 1), (0.5, 0), (1, 0.5), (0.5, 0.5), (0.2, 0.7), (0, 0.3)]
    ring = convex_hull(pts)
    assert ring is not None
    assert ring.tolist() == [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]


@pytest.mark.parametrize("pts", [[], [(0.1, 0.2)], [(0, 0), (1, 1)], [(0, 0), (0.5, 0.5), (1, 1)],
                                 [(0.3, 0.3)] * 5])
def test_points_that_span_no_area_have_no_hull(pts) -> None:
    assert convex_hull(np.array(pts, dtype=float).reshape(-1, 2)) is None
