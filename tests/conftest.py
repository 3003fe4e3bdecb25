"""Suite-wide settings. Property tests draw the same examples on every run and machine (a failure is then a
regression, never the luck of a seed); HYPOTHESIS_PROFILE=explore searches with fresh random seeds instead, which
is how new counterexamples are found (each one becomes an @example of its test)."""

from __future__ import annotations

import os

import pytest
from hypothesis import settings

settings.register_profile("suite", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "suite"))


@pytest.fixture(autouse=True)
def _own_state_and_cache(tmp_path_factory, monkeypatch) -> None:
    """Each test (and every process it starts) keeps its state (estop latch, pair store, mission) in a directory of
    its own, so a latch one test leaves never stops another; the compiled-code cache is shared by the session. The
    stations the suite starts run the MPC's functions interpreted (same results; the compiled path has its own tests
    in test_codegen.py): a build per worker would cost each a core for tens of seconds beside timed tests."""
    monkeypatch.setenv("SCMBRIDGE_STATE_DIR", str(tmp_path_factory.mktemp("state")))
    monkeypatch.setenv("SCMBRIDGE_RECORD_DIR", str(tmp_path_factory.mktemp("record")))  # the latch's record
    monkeypatch.setenv("SCMBRIDGE_NO_COMPILE", "1")
    if "SCMBRIDGE_CACHE_DIR" not in os.environ:
        monkeypatch.setenv("SCMBRIDGE_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "cache"))


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The longest tests (``slow``: whole HIL loops, demos, soaks) spread evenly through the run: xdist hands each
    worker a contiguous share of the tests to start with (``--dist worksteal`` then rebalances what is left), so
    slow tests that sit together in one file's or one directory's stretch would run one after another on one worker
    while the others finish early."""
    slow = [it for it in items if it.get_closest_marker("slow") is not None]
    if not slow:
        return
    rest = [it for it in items if it.get_closest_marker("slow") is None]
    step = max(1, len(rest) // len(slow))
    out: list[pytest.Item] = []
    for i, it in enumerate(rest):
        if i % step == 0 and slow:
            out.append(slow.pop(0))
        out.append(it)
    items[:] = out + slow
