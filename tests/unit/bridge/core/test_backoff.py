"""The one backoff every retry uses (router, vehicle, CAN bus, MAVLink connection)."""

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
