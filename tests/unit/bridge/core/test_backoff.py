"""The one backoff every retry uses (router, vehicle, CAN bus, MAVLink connection). bridge.core.backoff.Backoff is
pure, so its whole behaviour is a sequence of waits (no clock at all)."""

from __future__ import annotations

import pytest

from bridge.core.backoff import Backoff


def test_the_wait_doubles_up_to_its_maximum_and_a_success_resets_it() -> None:
    b = Backoff(0.25, 2.0)
    assert [b.delay, b.grow(), b.grow(), b.grow(), b.grow()] == [0.25, 0.5, 1.0, 2.0, 2.0]
    b.reset()
    assert b.delay == 0.25
    with pytest.raises(ValueError, match="initial <= maximum"):
        Backoff(1.0, 0.5)


def test_the_wait_starts_at_initial_and_doubles_to_its_bound() -> None:
    b = Backoff(0.05, 0.2)
    assert b.delay == 0.05
    assert [b.grow() for _ in range(5)] == [0.1, 0.2, 0.2, 0.2, 0.2]


def test_a_success_resets_the_wait_to_the_first() -> None:
    b = Backoff(0.25, 5.0)
    b.grow()
    b.grow()
    b.reset()
    assert b.delay == 0.25 and b.grow() == 0.5


def test_a_factor_stretches_each_wait_and_one_keeps_it_constant() -> None:
    b = Backoff(1.0, 100.0, factor=3.0)
    assert [b.grow(), b.grow(), b.grow(), b.grow(), b.grow()] == [3.0, 9.0, 27.0, 81.0, 100.0]
    flat = Backoff(0.5, 0.5, factor=1.0)
    assert [flat.grow() for _ in range(3)] == [0.5, 0.5, 0.5]


@pytest.mark.parametrize("initial,maximum,factor", [(0.0, 1.0, 2.0), (-1.0, 1.0, 2.0), (2.0, 1.0, 2.0),
                                                    (0.1, 1.0, 0.5)])
def test_a_backoff_that_could_not_wait_or_would_shrink_is_refused(initial: float, maximum: float,
                                                                  factor: float) -> None:
    with pytest.raises(ValueError, match="need 0 < initial <= maximum and factor >= 1"):
        Backoff(initial, maximum, factor)
