"""Fixtures of the simulations' unit tests (sim_learner/)."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def _close_figures() -> Iterator[None]:
    """Every matplotlib figure a test opened is closed after it (pyplot keeps each one open until closed, and warns
    past twenty): test_figures.py and test_plots.py draw many. A test that never imported pyplot costs nothing."""
    yield
    plt = sys.modules.get("matplotlib.pyplot")
    if plt is not None:
        plt.close("all")
