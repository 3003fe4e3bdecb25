"""The driver host's status, pure (bridge/nodes/host_status.py): the problems in words, the state and typed reason
from typed values only, when a status is due, and the message built. Times are arguments (a fake clock)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest

from bridge.core import wire as M
from bridge.nodes.host_status import (
    STATUS_EVERY_S,
    STATUS_MAX_HZ,
    UNAUTHENTICATED,
    HostFacts,
    HostStatus,
    host_counters,
    node_state,
)
from drivers.base import FailsafeReport, LinkHealth

FIT = LinkHealth(connected=True, ok=True, text="ok", reason="ok")
OPERATOR = LinkHealth(connected=True, ok=False, text="operator took control: mode HOLD", reason="operator")
FAULT = LinkHealth(connected=True, ok=False, text="left axis error", reason="fault")
DOWN = LinkHealth(connected=False, ok=False, text="no link", reason="link_down")
NOW = 100.0


def _host(**kw) -> HostStatus:
    return HostStatus("r1", "can", period=0.02, max_telemetry_age=0.5, **kw)


def _facts(**kw) -> HostFacts:
    args = dict(health=FIT, engaged=True, last_pose=NOW)
    args.update(kw)
    return HostFacts(**args)


def test_a_fit_engaged_host_with_fresh_poses_is_driving_and_ok() -> None:
    a = _host().assess(_facts(), NOW)
    assert (a.problems, a.state, a.reason, a.ok, a.pose_age) == ((), "driving", "ok", True, 0.0)


def test_the_problems_come_most_important_first() -> None:
    unsaved = "estop latched but NOT saved to /x: No space left on device; engage refused until it is saved"
    a = _host().assess(_facts(health=FAULT, last_pose=NOW - 2.0, estopped=True, estop_source="operator",
                              unsaved=unsaved, conflict="two senders on epoch 7"), NOW)
    assert a.problems == (unsaved, "estop latched by operator", "left axis error", "no telemetry for 2.0 s",
                          "two senders on epoch 7")
    assert (a.state, a.reason, a.ok) == ("estop", "latch_unsaved", False)
    a = _host().assess(_facts(last_pose=-math.inf, estopped=True), NOW)
    assert a.problems == ("estop latched by unknown", "no telemetry yet") and (a.state, a.reason) == ("estop", "estop")


def test_a_host_not_engaged_says_what_it_waits_for() -> None:
    a = _host().assess(_facts(engaged=False), NOW)
    assert a.problems == ("waiting for engage (scmbridge engage --robot r1)",)
    assert (a.state, a.reason) == ("waiting", "not_engaged")
    a = _host(operator_engages=True).assess(_facts(engaged=False, health=OPERATOR), NOW)
    assert a.problems[0] == "waiting for the operator: mode HOLD (or scmbridge engage --robot r1)", a.problems
    a = _host(operator_engages=True).assess(_facts(engaged=False, estopped=True), NOW)
    assert a.problems == ("estop latched by unknown",)  # the estop first, nothing about engaging


@pytest.mark.parametrize("text", ["operator took control: mode HOLD", "", "estop latched by operator", "driving"])
def test_the_state_and_reason_come_from_typed_values_whatever_the_words(text: str) -> None:
    def state(estop=False, h=FIT, pose_age=0.0, problems=(), unsaved=False, engaged=True, dry_run=False):
        return node_state(estop, h, pose_age, list(problems), unsaved, engaged=engaged, dry_run=dry_run,
                          max_telemetry_age=0.5)

    op = LinkHealth(connected=True, ok=False, text=text, reason="operator")
    fault = LinkHealth(connected=True, ok=False, text=text, reason="fault")
    assert state(h=op, problems=[text]) == ("operator", "operator")
    assert state(h=fault, problems=[text]) == ("fault", "fault")
    assert state(h=op, engaged=False) == ("waiting", "not_engaged")
    assert state(h=DOWN, engaged=False) == ("link_down", "link_down")
    assert state(pose_age=0.6) == ("no_pose", "no_telemetry")
    assert state(problems=[text]) == ("fault", "conflict")
    assert state(estop=True, h=DOWN) == ("estop", "estop")
    assert state(estop=True, unsaved=True) == ("estop", "latch_unsaved")
    assert state(estop=True, dry_run=True) == ("dry_run", "estop")  # a latched estop is said also in a dry run
    assert state(estop=True, unsaved=True, dry_run=True) == ("dry_run", "latch_unsaved")
    assert state(dry_run=True) == ("dry_run", "dry_run")


def test_a_status_is_due_each_second_and_at_once_on_a_change_at_most_twenty_a_second() -> None:
    s = _host()
    driving = s.assess(_facts(), NOW)
    estop = s.assess(_facts(estopped=True), NOW)
    assert s.due(driving, NOW)  # the first one
    s.build(NOW, driving, counters={})
    assert not s.due(driving, NOW + 0.5)  # nothing changed, not a second yet
    gap = 1.0 / STATUS_MAX_HZ
    assert not s.due(estop, NOW + gap / 2)  # changed, but too soon after the last one
    assert s.due(estop, NOW + gap + 1e-9)
    s.build(NOW + gap + 1e-9, estop, counters={})
    assert not s.due(estop, NOW + 0.9)
    assert s.due(estop, NOW + STATUS_EVERY_S)  # the periodic grid, whatever went out between
    assert not s.due(estop, NOW + STATUS_EVERY_S + 0.5)


@dataclass(frozen=True)
class _Detail:
    resyncs: int = 3

    def status_counters(self) -> dict[str, int]:
        return {"resyncs": self.resyncs}


def test_the_status_counts_the_gate_the_inputs_the_link_and_the_loop() -> None:
    h = LinkHealth(connected=True, ok=True, text="ok", reason="ok", frames_sent=5, frames_received=6, malformed=1,
                   errors=2, detail=_Detail())
    c = host_counters({"deadman_trips": 4}, {"decoded_cmd": 9}, h, unauthenticated=True, missed=7, stalls=8,
                      ticks=10)
    assert c == {"deadman_trips": 4, "decoded_cmd": 9, "unauthenticated_link": 1, "link_malformed": 1,
                 "link_errors": 2, "missed_deadlines": 7, "loop_stalls": 8, "frames_sent": 5, "frames_received": 6,
                 "ticks": 10, "link_resyncs": 3}


def test_the_status_message_says_it_in_words_and_numbers_its_own_stream() -> None:
    s = _host(unauthenticated="insecure = true", max_drive_on=1.0)
    start = s.starting(NOW, "starting", "link can: opening (vehicle not yet ready)")
    assert (start.seq, start.state, start.reason, start.ok) == (0, "starting", "starting", False)
    a = s.assess(_facts(last_pose=NOW - 0.1), NOW)
    st = M.validated(s.build(NOW, a, counters={"ticks": 1}, late=[0.001, 0.002, 0.003, 0.004],
                             failsafe=FailsafeReport(drive_on_s=3.0, text="3 s"), driving_reason="clamped"))
    assert (st.seq, st.ok, st.state, st.reason, st.node) == (1, True, "driving", "ok", "driver")
    assert st.text == ("link can: applying the station's commands, clamped to the hard limits (clamped)"
                       + UNAUTHENTICATED)
    assert st.latencies_ms["telemetry_age"] == pytest.approx(100.0)
    assert st.latencies_ms["jitter_max"] == pytest.approx(4.0) and st.latencies_ms["failsafe_drive_on"] == 3000.0
    assert st.rates_hz == {"loop": 50.0} and st.counters == {"ticks": 1}
    dry = s.assess(_facts(dry_run=True, health=LinkHealth(connected=True, ok=False, text="x" * 2000)), NOW)
    st = s.build(NOW, dry, counters={})
    assert not st.ok and st.text.startswith("DRY RUN (nothing is sent to the vehicle): link can: x")
    assert st.text.endswith(UNAUTHENTICATED) and len(st.text) == 1024  # said whatever else is cut
    assert "jitter_p50" not in st.latencies_ms  # (fewer than three ticks measured)


def test_an_engaged_fit_host_holding_a_stop_says_so_with_its_measured_speed_never_driving() -> None:
    """Finding: after the station died the host's line read `driving (deadman)`, and `driving (stop)` while paused:
    engaged and fit, but a lab reads it as moving. The words say what the vehicle is given; the status carries the
    measured speeds (``scmbridge status`` says moving or stopped from them) and whether a person engaged it."""
    s = _host()
    for reason, words in (("deadman", "holding a stop: no fresh command (deadman)"),
                          ("stop", "holding the station's stop (stop)")):
        a = s.assess(_facts(last_pose=NOW - 0.1, measured=(0.0, 0.0)), NOW)
        st = M.validated(s.build(NOW, a, counters={}, driving_reason=reason))
        assert st.text == f"link can: {words}" and "driving" not in st.text, st.text
        assert st.measured == [0.0, 0.0] and st.engaged is True
    stale = s.assess(_facts(last_pose=NOW - 5.0, measured=(0.3, 0.0)), NOW)  # an old speed is no measurement now
    assert s.build(NOW, stale, counters={}).measured is None
    idle = s.assess(_facts(engaged=False, last_pose=NOW - 0.1, measured=(0.0, 0.0)), NOW)
    assert s.build(NOW, idle, counters={}).engaged is False
