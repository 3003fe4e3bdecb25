"""sim_learner/device.py: the life cycle every emulated device shares (open, serve from one thread, close)."""

from __future__ import annotations

import threading
import time

import pytest

from sim_learner.device import ThreadedDevice


class Probe(ThreadedDevice):
    """Records the life cycle; its loop ends when told to stop (or, for ``stubborn``, only at the test's end)."""

    thread_name = "probe-device"

    def __init__(self, stubborn: bool = False) -> None:
        super().__init__()
        self.calls: list[str] = []
        self.running = threading.Event()
        self.release = threading.Event()
        self.stubborn = stubborn
        self.ran_in: str | None = None

    def _open(self) -> None:
        self.calls.append("open")

    def _run(self) -> None:
        self.ran_in = threading.current_thread().name
        self.calls.append("run")
        self.running.set()
        (self.release if self.stubborn else self._stop).wait(10.0)

    def _close(self) -> None:
        self.calls.append("close")


def test_start_opens_then_serves_from_its_own_named_daemon_thread_and_stop_closes() -> None:
    d = Probe()
    assert d.start() is d
    assert d.running.wait(5.0)
    assert d.ran_in == "probe-device" and d._thread is not None and d._thread.daemon
    d.stop()
    assert d.calls == ["open", "run", "close"] and not d._thread.is_alive()


def test_the_context_manager_starts_and_stops() -> None:
    with Probe() as d:
        assert d.running.wait(5.0) and d.calls == ["open", "run"]
    assert d.calls == ["open", "run", "close"] and d._thread is not None and not d._thread.is_alive()


def test_a_failed_open_starts_no_thread() -> None:
    class Broken(Probe):
        def _open(self) -> None:
            raise OSError("address in use")

    d = Broken()
    with pytest.raises(OSError, match="address in use"):
        d.start()
    assert d._thread is None and d.calls == []


def test_stop_without_start_still_closes() -> None:
    d = Probe()
    d.stop()
    assert d.calls == ["close"] and d._stop.is_set()


def test_stop_waits_at_most_two_seconds_for_a_loop_that_does_not_end() -> None:
    d = Probe(stubborn=True).start()
    assert d.running.wait(5.0)
    t0 = time.monotonic()
    d.stop()
    took = time.monotonic() - t0
    try:
        assert 1.9 <= took < 4.0 and d.calls[-1] == "close" and d._thread is not None and d._thread.is_alive()
    finally:
        d.release.set()
        d._thread.join(5.0)
