"""bridge/nodes/host_loop.py: the driver host's timing, options and echo, pieces of one job each
(docs/ARCHITECTURE.md section 4). The host's loop on them is tested in test_driver_host_timing.py."""

from __future__ import annotations

import threading

from bridge.nodes.host_loop import STALL_REPORT_S, Echo, HostOptions, HostTiming
from bridge.nodes.node import FixedRate
from tests.fakeclock import FakeClock


def test_timing_keeps_the_hosts_clock_and_wait_and_counts_the_schedulers_missed_deadlines() -> None:
    clock = FakeClock()
    t = HostTiming(50.0, 100.0, clock)
    assert t.period == 0.02 and t.max_send_hz == 100.0 and t.missed == 0
    assert t.stall_report_s == STALL_REPORT_S  # two periods at 50 Hz are less than the floor
    assert HostTiming(2.0, 100.0).stall_report_s == 1.0  # two periods at a slow rate
    stop = threading.Event()
    t.ticker = FixedRate(50.0, stop, clock=clock, wait=clock.wait)
    clock.advance(0.1)  # the tick overran its period: a missed deadline, on the host's clock
    assert t.ticker.wait() is True and t.missed == 1


def test_options_and_echo_start_empty_and_are_not_shared_between_hosts() -> None:
    a, b = HostOptions(), HostOptions()
    a.co_located.append("ecus")
    a.fence.append((0.0, 0.0))
    assert b.co_located == [] and b.fence == [] and not b.dry_run and b.latch_path is None
    e = Echo()
    assert (e.seq, e.last.reason, e.last.v, e.last.omega) == (0, "start", 0.0, 0.0)
