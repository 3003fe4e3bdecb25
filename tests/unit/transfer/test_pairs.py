"""transfer/pairs.py: f_T^-1, the teacher command that reproduces an observed learner move (paper Eq. commandPairs).

Its exact recovery of teacher-made motion and the sideways least-squares case are tested in
tests/unit/transfer/test_step.py; here: the batch form, reversing, headings across the wrap, and the refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.pairs import teacher_equivalent
from transfer.teacher.unicycle import step


def test_the_batch_form_equals_the_one_pair_form_pair_by_pair() -> None:
    rng = np.random.default_rng(4)
    x0 = np.c_[rng.uniform(-5, 5, (20, 2)), rng.uniform(-4, 4, 20)]
    x1 = x0 + rng.normal(0, 0.05, (20, 3))
    batch = teacher_equivalent(x0, x1, 0.1)
    assert batch.shape == (20, 2)
    for a, b, u in zip(x0, x1, batch):
        np.testing.assert_allclose(teacher_equivalent(a, b, 0.1), u, rtol=0, atol=1e-12)  # the scalar path
        np.testing.assert_allclose(teacher_equivalent(list(a), list(b), 0.1), u, rtol=0, atol=1e-12)
    # leading axes are kept
    assert teacher_equivalent(x0.reshape(4, 5, 3), x1.reshape(4, 5, 3), 0.1).shape == (4, 5, 2)


def test_a_backward_move_is_a_negative_speed() -> None:
    x0 = np.array([1.0, 2.0, math.pi / 3])
    x1 = step(x0, [-0.4, 0.0], 0.5)
    np.testing.assert_allclose(teacher_equivalent(x0, x1, 0.5), [-0.4, 0.0], atol=1e-12)


def test_the_heading_rate_is_taken_across_the_wrap_the_short_way() -> None:
    # from just below +pi to just above -pi is a small left turn, not almost a full turn right
    x0 = np.array([0.0, 0.0, math.pi - 0.01])
    x1 = np.array([0.0, 0.0, -math.pi + 0.01])
    v, w = teacher_equivalent(x0, x1, 0.1)
    assert v == 0.0 and w == pytest.approx(0.2, abs=1e-9)
    # the same through the batch path
    np.testing.assert_allclose(teacher_equivalent(x0[None], x1[None], 0.1), [[0.0, 0.2]], atol=1e-9)


@pytest.mark.parametrize("dt", [0.0, -0.1, math.inf, math.nan])
def test_a_time_step_that_is_not_positive_and_finite_is_refused(dt: float) -> None:
    with pytest.raises(ValueError, match="dt must be a positive finite number"):
        teacher_equivalent(np.zeros(3), np.ones(3), dt)


def test_malformed_poses_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"poses must be \(\.\.\., 3\) arrays"):
        teacher_equivalent([0.0, 0.0], [1.0, 0.0], 0.1)
    with pytest.raises(ValueError, match="poses must be finite"):
        teacher_equivalent(np.array([0.0, 0.0, 0.0]), np.array([np.inf, 0.0, 0.0]), 0.1)  # the one-pair path
    with pytest.raises(ValueError, match="poses must be finite"):
        teacher_equivalent(np.zeros((2, 3)), np.array([[0.0, 0.0, 0.0], [0.0, np.nan, 0.0]]), 0.1)
