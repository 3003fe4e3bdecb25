"""Putting a pose source's stamps on this host's clock (:mod:`bridge.core.clock`): the constructor's refusals, the
sliding window's minimum, a reset, :meth:`ClockOffset.restamp_checked`, an odd run that does not agree, and
:func:`machine`. Pure: every time is an argument.

The behaviour against jitter, a forged stamp, clock steps and late deliveries is tested in
tests/integration/test_mocap.py (beside the driver host's mocap end to end); the gate's use of the offset in
tests/unit/bridge/core/test_gate.py."""

from __future__ import annotations

import re
import socket

import pytest

from bridge.core import clock
from bridge.core.clock import BACK_STEP, CONFIRM, OFFSET_BRACKET_S, STEP, ClockOffset, HeldOffset, wall_offset

AHEAD = 1000.0  # the source's clock runs this far ahead of ours


@pytest.mark.parametrize("kw", [{"window_s": 0.0}, {"window_s": -1.0}, {"step": 0.0}, {"back_step": -0.1},
                                {"confirm": 0}])
def test_a_window_or_step_that_is_not_positive_is_refused(kw: dict) -> None:
    with pytest.raises(ValueError, match="must be positive, confirm at least 1"):
        ClockOffset(**kw)


def test_the_defaults_are_the_documented_ones() -> None:
    c = ClockOffset()
    assert (c.window_s, c.step, c.back_step, c.confirm) == (5.0, STEP, BACK_STEP, CONFIRM) == (5.0, 0.05, 0.2, 3)


def test_no_estimate_before_the_first_sample_and_the_first_sample_is_taken_as_it_is() -> None:
    c = ClockOffset()
    assert c.offset is None
    t, verdict = c.judge(AHEAD + 10.0, 10.004)
    assert verdict == "ok" and t == pytest.approx(10.004)  # nothing to compare with: at its receipt
    assert c.offset == pytest.approx(10.004 - (AHEAD + 10.0))


def test_the_offset_is_the_least_lateness_within_the_window_and_an_old_minimum_leaves_it() -> None:
    c = ClockOffset(window_s=1.0)
    c.restamp(AHEAD + 0.0, 0.001)  # the fastest delivery: 1 ms
    for k in range(1, 10):
        c.restamp(AHEAD + 0.1 * k, 0.1 * k + 0.004)  # later ones take 4 ms
    assert c.offset == pytest.approx(0.001 - AHEAD)
    t = c.restamp(AHEAD + 1.05, 1.05 + 0.004)  # the 1 ms sample (received at 0.001) is now older than the window
    assert c.offset == pytest.approx(0.004 - AHEAD)
    assert t == pytest.approx(1.05 + 0.004)


def test_a_faster_delivery_lowers_the_estimate_at_once_and_each_sample_keeps_its_own_time() -> None:
    c = ClockOffset()
    t1 = c.restamp(AHEAD + 1.0, 1.010)
    t2 = c.restamp(AHEAD + 1.1, 1.102)  # 2 ms: the new minimum
    t3 = c.restamp(AHEAD + 1.2, 1.230)  # 30 ms late: placed at its stamp + the minimum, not at its receipt
    assert t1 == pytest.approx(1.010) and t2 == pytest.approx(1.102) and t3 == pytest.approx(1.202)
    assert t1 < t2 < t3


def test_a_reset_forgets_the_estimate_and_the_odd_run() -> None:
    c = ClockOffset()
    for k in range(10):
        c.judge(AHEAD + 0.02 * k, 0.02 * k + 0.001)
    assert c.judge(AHEAD + 0.2 + 0.4, 0.2 + 0.001) == (None, "dropped")  # one ahead: odd
    c.reset()  # the sender rebooted: a new clock
    assert c.offset is None
    t, verdict = c.judge(5.0, 0.3)  # its new clock is taken as it is
    assert verdict == "ok" and t == pytest.approx(0.3) and c.offset == pytest.approx(-4.7)


def test_odd_samples_that_do_not_agree_never_restart_the_estimate() -> None:
    """A run of odd samples restarts the estimate only when ``confirm`` of them agree (same side, within ``step``):
    alternating forgeries ahead and behind, or ones far apart, are all dropped and shift nothing."""
    c = ClockOffset()
    for k in range(10):
        c.judge(AHEAD + 0.02 * k, 0.02 * k + 0.001)
    off = c.offset
    t0 = 0.2
    for k, shift in enumerate([0.4, -0.5, 0.4, -0.5, 0.4, 0.9, 0.3, 1.5]):  # ahead/behind, or ahead but far apart
        stamp, receipt = AHEAD + t0 + 0.02 * k + shift, t0 + 0.02 * k + 0.001
        assert c.judge(stamp, receipt) == (None, "dropped"), (k, shift)
    assert c.offset == off
    t, verdict = c.judge(AHEAD + 0.5, 0.5 + 0.003)  # a good one: placed by the old estimate
    assert verdict == "ok" and t == pytest.approx(0.501)


def test_restamp_checked_places_every_sample_and_says_which_were_odd() -> None:
    c = ClockOffset()
    for k in range(10):
        assert c.restamp_checked(AHEAD + 0.02 * k, 0.02 * k + 0.001) == pytest.approx((0.02 * k + 0.001, True))
    t, ok = c.restamp_checked(AHEAD + 0.2 + 0.4, 0.2 + 0.001)  # stamped 0.4 s ahead: dropped
    assert (t, ok) == (0.201, False)  # put at its receipt, for the caller to count
    for k in range(CONFIRM - 1):  # the clock really stepped: the run's last (the CONFIRM-th) restarts the estimate
        t, ok = c.restamp_checked(AHEAD + 0.22 + 0.02 * k + 0.4, 0.22 + 0.02 * k + 0.001)
        assert not ok and t == pytest.approx(0.22 + 0.02 * k + 0.001)
    assert c.offset == pytest.approx(0.001 - 0.4 - AHEAD)  # restarted from the run's last sample
    t, ok = c.restamp_checked(AHEAD + 0.3 + 0.4, 0.3 + 0.001)
    assert ok and t == pytest.approx(0.301)  # on the new estimate


def test_machine_names_this_host_and_its_boot() -> None:
    name = clock.machine()
    host, _, boot = name.rpartition("/")
    assert host == socket.gethostname()[:55]
    assert re.fullmatch(r"[0-9a-f]{8}|noboot", boot)
    assert clock.machine() is name  # read once: the same for the whole boot
    assert len(name) <= 64  # fits Status.host (a Name)


def test_the_wall_offset_is_read_in_a_bracket_a_preemption_cannot_widen_unseen() -> None:
    """A read preempted between the monotonic and the wall clock's (80 ms) is off by the preemption; the bracket
    says so, and the next, tight one is taken."""
    t = [100.0]
    gaps = [0.08]  # the thread loses the core once, between the first bracket's two wall reads

    def mono() -> float:
        return t[0]

    def wall() -> float:
        if gaps and reads[0] == 1:  # preempted just before this read
            t[0] += gaps.pop()
        reads[0] += 1
        return t[0] + 1.7e9

    reads = [0]
    off, bracket = wall_offset(mono, wall)
    assert off == pytest.approx(1.7e9, abs=1e-6) and bracket < OFFSET_BRACKET_S and reads[0] == 4

    def slow_wall() -> float:  # every bracket wide: the tightest is taken, and said
        t[0] += 0.01
        return t[0] + 1.7e9

    off, bracket = wall_offset(mono, slow_wall)
    assert bracket == pytest.approx(0.01, abs=1e-6) and off == pytest.approx(1.7e9, abs=0.006)


def test_a_held_offset_keeps_its_tight_read_through_reads_that_stayed_wide() -> None:
    """Reads whose every try was preempted at the second wall read (30 ms) are off by half of it: a held offset
    keeps the tight read it had instead, follows a step of the wall clock at the next tight read, and before any
    tight read holds the narrowest so far."""
    t, step, wide = [100.0], [0.0], [0.0]

    def mono() -> float:
        return t[0]

    def wall() -> float:
        reads[0] += 1
        if wide[0] and reads[0] % 2 == 0:  # the second read of each bracket comes after a preemption
            t[0] += wide[0]
        return t[0] + 1.7e9 + step[0]

    reads = [0]
    held = HeldOffset()
    wide[0] = 0.04
    assert held.read(mono, wall) == pytest.approx(1.7e9 + 0.02, abs=1e-6) and held.bracket == pytest.approx(0.04)
    wide[0] = 0.03  # still wide, but narrower: better than what it holds
    assert held.read(mono, wall) == pytest.approx(1.7e9 + 0.015, abs=1e-6)
    wide[0] = 0.0
    assert held.read(mono, wall) == pytest.approx(1.7e9, abs=1e-6) and held.bracket < OFFSET_BRACKET_S
    wide[0] = 0.03
    assert wall_offset(mono, wall)[0] == pytest.approx(1.7e9 + 0.015, abs=1e-6)  # what a read alone would say
    assert held.read(mono, wall) == pytest.approx(1.7e9, abs=1e-6)
    wide[0], step[0] = 0.0, 2.5  # the wall clock stepped (NTP): a tight read follows it
    assert held.read(mono, wall) == pytest.approx(1.7e9 + 2.5, abs=1e-6)
