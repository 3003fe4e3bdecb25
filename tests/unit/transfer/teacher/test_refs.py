"""transfer/teacher/_refs.py: the compiled closest point of a polyline and the MPC's references along it.

tests/unit/transfer/teacher/test_mpc.py checks on random poses that they equal ``Polyline.project`` and ``at``
through the MPC; here the functions' own contract on cases with known answers: the first segment wins a tie, the
references are clipped at the path's end, and the headings are unwrapped next to the vehicle's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.teacher._refs import closest, closest_near, curve_speed, curve_speed_from, references, references_from
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


def test_closest_near_a_hint_is_closest_bit_for_bit_whatever_the_hint() -> None:
    """Started from any segment (the last answer, a wrong one, one out of range), the same point and distance, the
    earlier leg still winning a tie; and the references and the bend's speed from that point are the ones found
    from the pose."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 6 * math.pi, 700)
    p = Polyline(np.stack([t, np.sin(t)], axis=1))  # a wave: far legs nearly as close as the nearest
    back = Polyline(np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 0.0]]))
    for poly in (p, back):
        n, hint = len(poly.points) - 1, 0
        for _ in range(400):
            x, y = rng.uniform(-1.0, 20.0), rng.normal(0.0, 1.5)
            want = closest(*_args(poly), x, y)
            for h in (hint, int(rng.integers(-3, n + 3)), 0, n - 1):
                s, d, hint = closest_near(*_args(poly), x, y, h)
                assert (s, d) == want  # exactly: the same segment, the same arithmetic
    assert closest_near(*_args(back), 1.0, 0.0, 1)[:2] == (1.0, 0.0)  # the first leg, from a hint on the second
    s0, _ = closest(*_args(p), 5.0, 0.3)
    np.testing.assert_array_equal(references_from(*_args(p), p.heading, s0, 0.2, 0.05, 21),
                                  references(*_args(p), p.heading, 5.0, 0.3, 0.2, 0.05, 21))
    assert curve_speed_from(p.s, p.curvature, s0, 1.0, 0.1, -2.0, 2.0, 0.9, 2.0) == \
        curve_speed(*_args(p), p.curvature, 5.0, 0.3, 1.0, 0.1, -2.0, 2.0, 0.9, 2.0)


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


def _arc(radius: float, sweep: float, n: int = 200, left: bool = True) -> Polyline:
    """A straight 2 m lead-in, then an arc of ``radius`` turning ``sweep`` rad to the left (or right)."""
    a = np.linspace(0.0, sweep, n)
    sign = 1.0 if left else -1.0
    arc = np.stack([2.0 + radius * np.sin(a), sign * radius * (1.0 - np.cos(a))], axis=1)
    return Polyline(np.vstack([[[0.0, 0.0]], arc]))


def test_the_curvature_of_an_arc_is_one_over_its_radius_signed_by_its_side() -> None:
    left, right = _arc(2.0, math.pi / 2), _arc(2.0, math.pi / 2, left=False)
    np.testing.assert_allclose(left.curvature[2:-1], 0.5, rtol=1e-3)
    np.testing.assert_allclose(right.curvature[2:-1], -0.5, rtol=1e-3)
    assert left.curvature[0] == 0.0 and left.curvature[-1] == 0.0
    # a coarse polyline's corner: the turn over the mean of its two segments, wrapped (a left turn of pi/2)
    sq = Polyline(np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]]))
    assert sq.curvature[1] == pytest.approx((math.pi / 2) / 2.0)


def test_the_speed_for_a_bend_uses_the_yaw_rate_bound_on_its_side() -> None:
    p = _arc(2.0, math.pi / 2)  # curvature 0.5 to the left from s = 2 m
    args = (p.points, p.s, p.seg_len, p.curvature)
    # far from the bend (the horizon reaches 1 m of path at 0.5 m/s over 2 s): the top speed
    assert curve_speed(*args, 0.0, 0.0, 0.5, 0.05, -0.3, 0.2, 0.9, 2.0) == pytest.approx(0.5)
    # in reach of it: 0.9 of the left bound over the curvature, whatever the right bound
    assert curve_speed(*args, 1.5, 0.0, 0.5, 0.05, -0.3, 0.2, 0.9, 2.0) == pytest.approx(0.9 * 0.2 / 0.5, rel=1e-3)
    assert curve_speed(*args, 1.5, 0.0, 0.5, 0.05, -0.01, 0.2, 0.9, 2.0) == pytest.approx(0.36, rel=1e-3)
    # a bend the bound turns at the top speed: no change; one it cannot turn at all: the floor
    assert curve_speed(*args, 1.5, 0.0, 0.5, 0.05, -0.3, 0.4, 0.9, 2.0) == pytest.approx(0.5)
    assert curve_speed(*args, 1.5, 0.0, 0.5, 0.05, -0.3, -0.1, 0.9, 2.0) == pytest.approx(0.05)
    r = _arc(2.0, math.pi / 2, left=False)
    assert curve_speed(r.points, r.s, r.seg_len, r.curvature, 1.5, 0.0, 0.5, 0.05, -0.1, 0.8, 0.9, 2.0) == \
        pytest.approx(0.9 * 0.1 / 0.5, rel=1e-3)
