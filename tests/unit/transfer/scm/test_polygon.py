"""transfer/scm/_polygon.py: the compiled polygon checks (defect codes, segment crossing, point in polygon).

``transfer.scm.geometry`` words the defect codes (tests/unit/transfer/scm/test_geometry.py) and RectangleMap's
refusals go through it (tests/unit/transfer/scm/test_rectmap.py); here the kernels' own answers."""

from __future__ import annotations

import numpy as np
import pytest

from transfer.scm._polygon import points_in_polygon, polygon_defect, segments_cross

SQUARE = np.array([0, 1, 1 + 1j, 1j], dtype=np.complex128)


@pytest.mark.parametrize(
    "p1,p2,q1,q2,want",
    [
        (0, 2 + 2j, 2, 2j, True),  # a proper crossing
        (0, 1, 2, 3, False),  # collinear, apart
        (0, 2, 1, 3, True),  # collinear overlap
        (0, 1, 1, 1 + 1j, True),  # touching at an end
        (0, 1, 1j, 1 + 1j, False),  # parallel
        (0, 1, 0.5 + 1e-3j, 0.5 + 1j, False),  # a T that stops short
        (0, 1, 0.5, 0.5 + 1j, True),  # a T that touches
    ],
)
def test_segments_cross(p1, p2, q1, q2, want: bool) -> None:
    assert segments_cross(complex(p1), complex(p2), complex(q1), complex(q2), 1e-12) is want
    assert segments_cross(complex(q1), complex(q2), complex(p1), complex(p2), 1e-12) is want  # symmetric


@pytest.mark.parametrize(
    "w,want",
    [
        (SQUARE, (0, 0, 0)),
        ([0, 1, complex(np.inf, 0), 1j], (1, 2, 0)),
        ([0, 1, 1 + 1j, 1, 1j], (2, 1, 3)),  # vertices 1 and 3 coincide
        ([0, 1, 1j, 1 + 1j], (3, 1, 3)),  # a bow tie: edge 1-2 meets edge 3-0
        (SQUARE[::-1], (4, 0, 0)),  # clockwise
        ([0, 1, 2], (5, 0, 0)),  # collinear: zero area
        ([0, 2, 1 + 1e-10j, 1 + 1j], (6, 1, 0)),  # vertex 1 folds back onto its edge (a spike, no crossing)
        ([0, 1, 2, 1 + 1j], (0, 0, 0)),  # a straight angle is a valid polygon (RectangleMap refuses it itself)
        ([0, 2, 2 + 1j, 1.999 + 1.001j, 1j], (0, 0, 0)),  # a tiny but real edge is fine
    ],
)
def test_polygon_defect_codes(w, want: tuple[int, int, int]) -> None:
    assert polygon_defect(np.asarray(w, dtype=np.complex128)) == want


def test_points_in_polygon_counts_edges_as_inside_within_tol() -> None:
    # a concave "L": the notch (1.5, 1.5) is outside though inside its bounding box
    ell = np.array([0, 2, 2 + 1j, 1 + 1j, 1 + 2j, 2j], dtype=np.complex128)
    p = np.array([0.5 + 0.5j, 1.5 + 1.5j, 0.5 + 1.5j, 2 + 0.5j, 2 + 1e-12 + 0.5j, 2.1 + 0.5j, 0, -1e-3j])
    got = points_in_polygon(p, ell, 1e-10)
    assert got.tolist() == [True, False, True, True, True, False, True, False]
    assert points_in_polygon(np.zeros(0, dtype=np.complex128), ell, 1e-10).shape == (0,)
