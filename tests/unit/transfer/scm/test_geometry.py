"""transfer/scm/geometry.py: what a valid polygon is, in words (one place for the SC maps and the region choice).

RectangleMap's refusals, which go through :func:`check_polygon` and :func:`check_corners`, are tested in
tests/unit/transfer/scm/test_rectmap.py; here the functions themselves."""

from __future__ import annotations

import numpy as np
import pytest

from transfer.scm.geometry import as_complex, check_corners, check_polygon, is_simple_ccw, turning_exponents

SQUARE = [0, 1, 1 + 1j, 1j]


def test_as_complex_reads_complex_numbers_and_xy_pairs() -> None:
    xy = np.array([[0.0, 1.0], [2.0, 3.0]])
    np.testing.assert_array_equal(as_complex(xy), [1j, 2 + 3j])
    np.testing.assert_array_equal(as_complex(np.array([1 + 2j, 3j])), [1 + 2j, 3j])
    assert as_complex(np.zeros((4, 5, 2))).shape == (4, 5)
    assert as_complex(2.5) == 2.5 + 0j and as_complex([1.0, 2.0, 3.0]).tolist() == [1, 2, 3]  # real numbers
    assert as_complex(xy).dtype == np.complex128


def test_turning_exponents_of_convex_polygons_sum_to_minus_two() -> None:
    np.testing.assert_allclose(turning_exponents(np.array(SQUARE, dtype=complex)), [-0.5] * 4)
    hexagon = np.exp(2j * np.pi * np.arange(6) / 6)
    np.testing.assert_allclose(turning_exponents(hexagon), [-1 / 3] * 6)
    # a concave vertex has a positive exponent (interior angle above pi)
    arrow = np.array([0, 2, 2 + 2j, 1 + 1j, 2j])
    beta = turning_exponents(arrow)
    assert beta[3] == pytest.approx(0.5) and beta.sum() == pytest.approx(-2.0)


@pytest.mark.parametrize(
    "v,match",
    [
        ([0, 1, 1 + 1j], "at least 4 vertices, got 3"),
        ([0, 1, 1 + 1j, complex(np.nan, 0)], "non-finite"),
        ([0, 1, 1 + 1j, 1, 1j], "repeated vertices: vertex 1 and vertex 3 coincide"),
        ([0, 1, 1j, 1 + 1j], "self-crossing polygon: edge 1-2 meets edge 3-0"),
        ([0, 1, 2], "degenerate polygon with zero area"),
        (SQUARE[::-1], "clockwise order; give them counter-clockwise"),
        ([0, 2, 1 + 1e-10j, 1 + 1j], "vertex 1 has a zero or full interior angle"),
    ],
)
def test_check_polygon_names_the_problem(v, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        check_polygon(v, min_vertices=3 if "zero area" in match else 4)
    assert is_simple_ccw(v) is False


def test_check_polygon_returns_the_vertices_and_takes_xy_pairs() -> None:
    w = check_polygon(np.array([[0, 0], [1, 0], [1, 1], [0, 1]]))
    np.testing.assert_array_equal(w, SQUARE)
    assert check_polygon([0, 1, 1j], min_vertices=3).size == 3  # a triangle, when asked for
    assert is_simple_ccw(SQUARE) and is_simple_ccw(np.array([[0, 0], [1, 0], [1, 1], [0, 1]]))
    assert not is_simple_ccw([0, 1, 1j])  # fewer than 4
    assert not is_simple_ccw("not a polygon") and not is_simple_ccw([[0, 0, 0]])


@pytest.mark.parametrize(
    "corners,n,match",
    [
        ((0, 1, 2), 4, "4 vertex indices, got 3"),
        (("a", 1, 2, 3), 4, "4 integer vertex indices"),
        ((0, 1.5, 2, 3), 4, "must be integers"),
        ((0, 1, 2, 4), 4, r"vertex indices in \[0, 4\)"),
        ((-1, 1, 2, 3), 4, r"in \[0, 4\)"),
        ((0, 2, 1, 3), 5, "distinct increasing"),
    ],
)
def test_check_corners_refuses_by_name(corners, n: int, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        check_corners(corners, n)


def test_check_corners_returns_ints() -> None:
    got = check_corners([np.int64(0), 2.0, 3, 5], 6)
    assert got == (0, 2, 3, 5) and all(type(c) is int for c in got)
