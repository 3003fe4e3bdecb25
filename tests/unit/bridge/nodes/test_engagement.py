"""The driver host's engagement, pure (bridge/nodes/engagement.py): a person engages, the operator's transitions,
the refusals, and the last word on a tick's decision. Times are arguments (a fake clock); no Zenoh, no link."""

from __future__ import annotations

import math

import pytest

from bridge.core.gate import Decision
from bridge.nodes.engagement import Engagement, OperatorEvent, Outcome, Ruling, blocked_reason, overrule
from drivers.base import LinkHealth

FIT = LinkHealth(connected=True, ok=True, text="ok", reason="ok")
OPERATOR = LinkHealth(connected=True, ok=False, text="operator took control: mode HOLD", reason="operator")
FAULT = LinkHealth(connected=True, ok=False, text="axis error", reason="fault")
DOWN = LinkHealth(connected=False, ok=False, text="no link", reason="link_down")


def test_a_host_starts_not_engaged_and_a_person_engages_it_once_the_link_took_it() -> None:
    e = Engagement()
    assert not e.engaged and e.since == -math.inf
    ruling = e.request(True, 1.0, estopped=False)
    assert ruling == Ruling(Outcome.PROCEED) and not e.engaged  # not engaged before the link took it
    assert e.confirm(1.5) is Outcome.ENGAGED and e.engaged and e.since == 1.5
    assert e.request(True, 2.0, estopped=False).outcome is Outcome.ALREADY_ENGAGED and e.since == 1.5


def test_a_hand_back_is_always_taken_and_says_whether_it_was_engaged() -> None:
    e = Engagement()
    assert e.request(False, 1.0, estopped=True, unsaved="anything").outcome is Outcome.NOT_ENGAGED
    e.confirm(2.0)
    assert e.request(False, 3.0, estopped=True).outcome is Outcome.DISENGAGED
    assert not e.engaged and e.since == 3.0
    assert Outcome.DISENGAGED.accepted and Outcome.NOT_ENGAGED.accepted


def test_an_engage_is_refused_while_the_latch_is_not_on_disk_then_while_it_is_latched() -> None:
    e = Engagement()
    unsaved = "estop latched but NOT saved to /x: No space left on device; engage refused until it is saved"
    r = e.request(True, 1.0, estopped=True, estop_source="operator", unsaved=unsaved)
    assert r.outcome is Outcome.REFUSED_UNSAVED and r.text == f"refused: {unsaved}" and not r.outcome.accepted
    r = e.request(True, 1.0, estopped=False, unsaved=unsaved)  # a release in memory that is not on disk
    assert r.outcome is Outcome.REFUSED_UNSAVED
    r = e.request(True, 1.0, estopped=True, estop_source="operator")
    assert r.outcome is Outcome.REFUSED_ESTOP and r.text == "refused: estop latched by operator"
    assert e.request(True, 1.0, estopped=True).text == "refused: estop latched by unknown"
    assert not e.engaged


def test_the_operator_engages_only_by_a_transition_while_the_host_runs() -> None:
    """A vehicle found GUIDED and armed at start is not engaged (a restart never takes a vehicle back); the operator
    arming it while the host runs (connected and not fit, then fit) is."""
    e = Engagement(follows_operator=True)
    assert e.follow(FIT, 1.0) is OperatorEvent.NONE and not e.engaged  # found fit at start
    e = Engagement(follows_operator=True)
    assert e.follow(DOWN, 1.0) is OperatorEvent.NONE
    assert e.follow(FIT, 1.1) is OperatorEvent.NONE and not e.engaged  # the link came up fit: not a person's act
    assert e.follow(OPERATOR, 1.2) is OperatorEvent.NONE
    assert e.follow(FIT, 1.3) is OperatorEvent.GAVE and e.engaged and e.since == 1.3
    assert e.follow(FIT, 1.4) is OperatorEvent.NONE
    assert e.follow(FAULT, 1.5) is OperatorEvent.NONE and e.engaged  # a fault is not the operator: still engaged
    assert e.follow(OPERATOR, 1.6) is OperatorEvent.TOOK and not e.engaged and e.since == 1.6


@pytest.mark.parametrize("text", ["operator took control: mode HOLD", "", "driving", "estop latched by operator"])
def test_the_operator_is_read_from_the_typed_reason_never_the_words(text: str) -> None:
    e = Engagement(follows_operator=True, engaged=True)
    assert e.follow(LinkHealth(connected=True, ok=False, text=text, reason="fault"), 1.0) is OperatorEvent.NONE
    assert e.follow(LinkHealth(connected=True, ok=False, text=text, reason="operator"), 1.1) is OperatorEvent.TOOK


def test_a_link_whose_operator_does_not_engage_is_never_followed() -> None:
    e = Engagement(follows_operator=False, engaged=True)
    for k, h in enumerate([OPERATOR, FIT, OPERATOR]):
        assert e.follow(h, float(k)) is OperatorEvent.NONE and e.engaged
    e = Engagement(follows_operator=False)
    for k, h in enumerate([OPERATOR, FIT]):
        assert e.follow(h, float(k)) is OperatorEvent.NONE and not e.engaged


def _overrule(d: Decision, now: float = 10.0, **kw) -> Decision:
    args = dict(engaged=True, unsaved=False, health=FIT, dry_run=False, last_pose=now, max_telemetry_age=0.5)
    args.update(kw)
    return overrule(d, now, **args)


def test_a_driving_decision_is_overruled_in_order_and_a_stop_stays_the_gates() -> None:
    drive = Decision(0.2, 0.1, "cmd", 7)
    assert _overrule(drive) is drive
    assert _overrule(drive, unsaved=True, engaged=False, health=DOWN) == Decision(0.0, 0.0, "estop", 7)
    assert _overrule(drive, engaged=False, health=DOWN) == Decision(0.0, 0.0, "disengaged", 7)
    assert _overrule(drive, health=OPERATOR) == Decision(0.0, 0.0, "operator", 7)
    assert _overrule(drive, health=FAULT).reason == "fault"
    assert _overrule(drive, health=DOWN).reason == "link_down"
    assert _overrule(drive, health=FAULT, dry_run=True) is drive  # a dry run sends nothing: the link's health aside
    assert _overrule(drive, last_pose=9.49).reason == "no_telemetry"
    assert _overrule(drive, last_pose=9.5) is drive
    assert _overrule(drive, last_pose=-math.inf).reason == "no_telemetry"
    stop = Decision(0.0, 0.0, "deadman", 7)
    assert _overrule(stop, unsaved=True, engaged=False, health=DOWN, last_pose=-math.inf) is stop


def test_the_applied_reason_of_a_link_not_fit_comes_from_its_typed_reason() -> None:
    for reason in ("rebooted", "disarmed", "no_telemetry", "fault", "no_heartbeat", "odometry", "arming"):
        assert blocked_reason(LinkHealth(connected=True, ok=False, text="operator", reason=reason)) == "fault"
    assert blocked_reason(OPERATOR) == "operator"
    assert blocked_reason(LinkHealth(connected=False, ok=False, text="", reason="operator")) == "link_down"
