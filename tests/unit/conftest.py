"""Unit tests run on a fake clock (:class:`tests.fakeclock.FakeClock`): time moves only when a test (or a driver's
injected ``sleep``) moves it, so no test sleeps and none depends on how loaded the machine is."""

from __future__ import annotations

import pytest

from tests.fakeclock import FakeClock


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()
