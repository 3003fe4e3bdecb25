"""transfer/teacher/_refs.py: the compiled closest point of a polyline and the MPC's references along it.

tests/unit/transfer/teacher/test_mpc.py checks on random poses that they equal ``Polyline.project`` and ``at``
through the MPC; here the functions' own contract on cases with known answers: the first segment wins a tie, the
references are clipped at the path's end, and the headings are unwrapped next to the vehicle's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.teacher._refs import closest, references
from transfer.teacher.path import Polyline


def _args(p: Polyline) -> tuple:
    return p.points, p.s, p.seg_len


def test_closest_point_and_the_first_segment_winning_a_tie() -> None:
    p = Polyline(np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0]]))
    assert closest(*_args(p), 2.0, 1.0) == pytest.approx((2.0, 1.0))
    assert closest(*_args(p), 6.0, 6.0) == pytest.approx((8.0, math.hypot(2.0, 2.0)))
    assert closest(*_args(p), -1.0, 0.0) == pytest.approx((0.0, 1.0))
    back = Polyline(np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 0.0]]))  # both legs hold (1, 0)
    assert closest(*_args(back), 1.0, 0.0) == pytest.approx((1.0, 0.0))
    # a point equidistant from the ends of two legs of a V: the earlier one
    v = Polyline(np.array([[-1.0, 1.0], [0.0, 0.0], [1.0, 1.0]]))
    s, d = closest(*_args(v), 0.0, 1.0)
    assert s == pytest.approx(math.sqrt(2) / 2) and d == pytest.approx(math.sqrt(2) / 2)


def test_references_are_spaced_along_the_path_and_stop_at_its_end() -> None:
    p = Polyline(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]))
    r = references(p.points, p.s, p.seg_len, p.heading, 0.5, -0.2, 0.0, 0.5, 6)
    assert r.shape == (6, 3)
    want = [[0.5, 0.0, 0.0], [1.0, 0.0, math.pi / 2], [1.0, 0.5, math.pi / 2], [1.0, 1.0, math.pi / 2],
            [1.0, 1.0, math.pi / 2], [1.0, 1.0, math.pi / 2]]
    np.testing.assert_allclose(r, want, atol=1e-12)


def test_reference_headings_are_unwrapped_next_to_the_vehicles() -> None:
    # a path heading west (pi); a vehicle whose heading has been counted up to 3 turns: references follow it
    p = Polyline(np.array([[0.0, 0.0], [-5.0, 0.0]]))
    theta = math.pi + 6 * math.pi - 0.1
    r = references(p.points, p.s, p.seg_len, p.heading, -1.0, 0.0, theta, 0.2, 4)
    np.testing.assert_allclose(r[:, 2], 7 * math.pi, atol=1e-12)
    assert abs(r[0, 2] - theta) <= math.pi
    # a path that turns a full circle: each next heading within pi of the one before (no jump of 2 pi)
    ang = np.linspace(0.0, 2 * math.pi, 33)
    circle = Polyline(np.c_[np.cos(ang), np.sin(ang)])
    r = references(circle.points, circle.s, circle.seg_len, circle.heading, 1.0, 0.0, math.pi / 2, 0.1, 60)
    assert np.all(np.abs(np.diff(r[:, 2])) < math.pi)
    assert r[-1, 2] - r[0, 2] > math.pi  # it kept counting up instead of wrapping back
