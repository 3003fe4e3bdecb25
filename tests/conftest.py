"""Suite-wide settings. Property tests draw the same examples on every run and machine (a failure is then a
regression, never the luck of a seed); HYPOTHESIS_PROFILE=explore searches with fresh random seeds instead, which
is how new counterexamples are found (each one becomes an @example of its test)."""

from __future__ import annotations

import os

import pytest
from hypothesis import settings

from tests.rewrite_share import share_rewriting
from tests.schedule import LONGEST, SLOW_DEFAULT_S, order

settings.register_profile("suite", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "suite"))


def pytest_configure(config: pytest.Config) -> None:
    """An xdist worker writes its part of the suite's rewritten test modules before it collects, and loads the
    others' (tests/rewrite_share.py): the suite is rewritten about once, not once per worker."""
    share_rewriting(config)


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


@pytest.hookimpl(trylast=True)  # after ``-m``/``-k`` deselected theirs: the shares are of the tests that run
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The long tests (tests/schedule.py: the listed ones and those marked ``slow``: whole HIL loops, demos, soaks)
    start first, dealt out evenly over the xdist workers' first shares, so none starts late and ends the run alone
    while the other workers wait; the quick tests keep their order around them."""
    workers = int(getattr(config, "workerinput", {}).get("workercount", 1))

    def seconds(it: pytest.Item) -> float | None:
        if it.nodeid in LONGEST:
            return LONGEST[it.nodeid]
        return SLOW_DEFAULT_S if it.get_closest_marker("slow") is not None else None

    def module(it: pytest.Item) -> str:
        return it.nodeid.split("::", 1)[0]

    def shares_a_fixture(it: pytest.Item) -> bool:  # one set up once for a module's (or a class's) tests
        info = getattr(it, "_fixtureinfo", None)
        defs = info.name2fixturedefs.values() if info is not None else ()
        return any(str(d.scope).rsplit(".", 1)[-1].lower() in ("module", "class", "package") for ds in defs for d in ds)

    kept = {module(it) for it in items if shares_a_fixture(it)}  # their runs of tests are not split
    items[:] = order(items, workers, seconds, group=lambda it: module(it) if module(it) in kept else it.nodeid)
