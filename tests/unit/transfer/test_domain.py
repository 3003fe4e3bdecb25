"""transfer/domain.py: the command box (``Bounds``) and its normalisation onto [0, 1]^2.

Every map of the transfer works in these normalised coordinates (docs/ARCHITECTURE.md section 2), so the round trip
and the refusals of a malformed box are what the rest of ``transfer/`` relies on."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from transfer.domain import Bounds

B = Bounds((0.05, 0.3), (-math.pi / 16, math.pi / 12))


@pytest.mark.parametrize(
    "v,w,match",
    [
        ((0.3, 0.05), (-1.0, 1.0), r"v=\(0.3, 0.05\) must have min < max"),
        ((0.1, 0.1), (-1.0, 1.0), "min < max"),
        ((0.0, 1.0), (1.0, -1.0), r"w=\(1.0, -1.0\) must have min < max"),
        ((0.0, math.inf), (-1.0, 1.0), "must be finite"),
        ((0.0, 1.0), (math.nan, 1.0), r"bounds w=\(nan, 1.0\) must be finite"),
    ],
)
def test_a_malformed_box_is_refused_by_name(v, w, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        Bounds(v, w)


def test_the_box_stores_floats_and_is_read_only() -> None:
    b = Bounds((0, 2), (-1, 1))
    assert b.v == (0.0, 2.0) and all(type(x) is float for x in (*b.v, *b.w))
    np.testing.assert_array_equal(b.lo, [0.0, -1.0])
    np.testing.assert_array_equal(b.hi, [2.0, 1.0])
    np.testing.assert_array_equal(b.span, [2.0, 2.0])
    with pytest.raises(ValueError):  # numpy refuses writes to the cached arrays
        b.lo[0] = 5.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        b.v = (0.0, 3.0)  # type: ignore[misc]
    assert b == Bounds((0.0, 2.0), (-1.0, 1.0)) and b != Bounds((0.0, 2.0), (-1.0, 1.5))


def test_normalise_maps_the_box_onto_the_unit_square_and_denormalise_inverts_it() -> None:
    np.testing.assert_allclose(B.normalise(B.lo), [0.0, 0.0])
    np.testing.assert_allclose(B.normalise(B.hi), [1.0, 1.0])
    rng = np.random.default_rng(0)
    u = B.denormalise(rng.uniform(-0.5, 1.5, (7, 5, 2)))  # any leading shape, inside the box or out of it
    n = B.normalise(u)
    assert n.shape == (7, 5, 2)
    np.testing.assert_allclose(B.denormalise(n), u, rtol=0, atol=1e-15)
    # outside the box maps outside [0, 1] (normalise does not clip)
    assert B.normalise([B.v[1] + B.span[0], B.w[0]])[0] == pytest.approx(2.0)


def test_clip_and_contains_agree_with_the_box() -> None:
    inside, outside = [0.1, 0.0], [0.5, -1.0]
    np.testing.assert_array_equal(B.clip(inside), inside)
    np.testing.assert_allclose(B.clip(outside), [B.v[1], B.w[0]])
    assert B.contains(inside) is True and B.contains(outside) is False
    assert B.contains(B.clip(outside)) is True  # a clipped command is always accepted
    got = B.contains(np.array([inside, outside, B.hi, B.lo]))
    assert isinstance(got, np.ndarray) and got.tolist() == [True, False, True, True]
    # the tolerance is relative to the box's span: a hair outside passes only with a larger tol
    hair = B.hi + 1e-9 * B.span
    assert not B.contains(hair) and B.contains(hair, tol=1e-8)


def test_corners_are_counter_clockwise_from_the_lower_left() -> None:
    c = B.corners()
    np.testing.assert_array_equal(c[0], B.lo)
    np.testing.assert_array_equal(c[2], B.hi)
    area2 = sum(c[i, 0] * c[(i + 1) % 4, 1] - c[(i + 1) % 4, 0] * c[i, 1] for i in range(4))
    assert area2 == pytest.approx(2 * B.span[0] * B.span[1])  # positive: counter-clockwise


def test_the_list_form_round_trips_and_needs_four_numbers() -> None:
    assert B.as_list() == [B.v[0], B.v[1], B.w[0], B.w[1]]
    assert Bounds.from_list(B.as_list()) == B
    assert Bounds.from_list(np.array([[0, 1], [2, 3]])) == Bounds((0.0, 1.0), (2.0, 3.0))
    with pytest.raises(ValueError, match="bounds need 4 numbers .* got 3"):
        Bounds.from_list([0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="min < max"):
        Bounds.from_list([1.0, 0.0, 0.0, 1.0])
