"""A person is in charge of the vehicle: the driver host's engagement, pure (docs/ARCHITECTURE.md, "A person is in
charge"; times and the link's health are arguments, no Zenoh, no I/O, no clock, no logging).

A driver host starts *not engaged* and its vehicle gets only stops (``applied`` reason ``disengaged``) until a person
engages it: ``scmbridge engage`` (a query the host hands to :meth:`Engagement.request`), ``engage_on_start``, or, on
a link whose operator engages (MAVLink), the operator putting the vehicle in GUIDED and arming it while the host
runs: a *transition* seen by :meth:`Engagement.follow`, never a state found at start. The operator taking the
vehicle disengages. An engage is refused while the estop latch is not on disk (``latch_unsaved``) or is latched; a
hand-back is always taken.

The answers are typed (:class:`Outcome`, as MAVSDK-Python's result enums): the host decides on them and words them;
an engage that nothing refuses is :attr:`Outcome.PROCEED`: the host engages the link (its I/O), then
:meth:`Engagement.confirm` (or says the link's refusal). :func:`overrule` is the last word on a tick's gate decision
(a small pure piece, as ros2_control's diff_drive_controller keeps its limits and timeouts): not engaged, a latch not
on disk, a link not fit or telemetry too old each turn it into a stop with its own typed reason.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from bridge.core.gate import Decision
from drivers.base import LinkHealth


class Outcome(enum.Enum):
    """What a person's request came to (:meth:`Engagement.request`, :meth:`Engagement.confirm`)."""

    PROCEED = "proceed"  # nothing refuses it: engage the link, then confirm()
    ENGAGED = "engaged"
    ALREADY_ENGAGED = "already engaged"
    DISENGAGED = "disengaged"
    NOT_ENGAGED = "not engaged"  # a hand-back of a vehicle that was not engaged
    REFUSED_UNSAVED = "latch_unsaved"  # the estop latch is not on disk (latched, or a release not saved)
    REFUSED_ESTOP = "estop"

    @property
    def accepted(self) -> bool:
        return self not in (Outcome.REFUSED_UNSAVED, Outcome.REFUSED_ESTOP)


class OperatorEvent(enum.Enum):
    """What :meth:`Engagement.follow` saw the operator do this tick."""

    NONE = "none"
    TOOK = "took"  # the operator took the vehicle (left GUIDED): disengaged
    GAVE = "gave"  # the operator put it in GUIDED and armed it while the host ran: engaged


@dataclass(frozen=True, slots=True)
class Ruling:
    """:meth:`Engagement.request`'s answer: the outcome and, for a refusal, why in words (for people only)."""

    outcome: Outcome
    text: str = ""


@dataclass
class Engagement:
    """The engagement's state machine (see the module docstring). ``follows_operator``: the link's operator engages
    and disengages it (MAVLink; never in a dry run). ``since``: when the engagement last changed (the caller's
    clock, -inf before any change). Used by the driver host's loop thread only (no lock)."""

    follows_operator: bool = False
    engaged: bool = False
    #: the link's health at the last :meth:`follow` (an operator's GUIDED + arming is a transition from not ok)
    was_ok: bool = False
    was_connected: bool = False
    since: float = -math.inf

    def request(self, engage: bool, now: float, *, estopped: bool, estop_source: str = "",
                unsaved: str = "") -> Ruling:
        """A person's engage (``engage``) or hand-back. A hand-back always disengages; an engage of an engaged
        vehicle changes nothing; otherwise refused while the latch is not on disk (``unsaved``: why, in words) or an
        estop is latched (by ``estop_source``), else :attr:`Outcome.PROCEED` (the caller engages the link, then
        :meth:`confirm`)."""
        if not engage:
            was = self.engaged
            self._set(False, now)
            return Ruling(Outcome.DISENGAGED if was else Outcome.NOT_ENGAGED)
        if self.engaged:
            return Ruling(Outcome.ALREADY_ENGAGED)
        if unsaved:
            return Ruling(Outcome.REFUSED_UNSAVED, f"refused: {unsaved}")
        if estopped:
            return Ruling(Outcome.REFUSED_ESTOP, f"refused: estop latched by {estop_source or 'unknown'}")
        return Ruling(Outcome.PROCEED)

    def confirm(self, now: float) -> Outcome:
        """The link took the engage that :meth:`request` let :attr:`Outcome.PROCEED`: engaged."""
        self._set(True, now)
        return Outcome.ENGAGED

    def follow(self, health: LinkHealth, now: float) -> OperatorEvent:
        """Follow the operator on this tick's link health (a link whose operator engages only): the operator taking
        the vehicle (the link not fit for reason ``operator``) disengages; the link becoming fit after a tick in which
        it was connected and not fit (GUIDED and armed while the host runs) engages. The health is remembered for
        the next tick either way."""
        event = OperatorEvent.NONE
        if self.follows_operator:
            operator = health.connected and not health.ok and health.reason == "operator"
            if self.engaged and operator:
                self._set(False, now)
                event = OperatorEvent.TOOK
            elif not self.engaged and health.ok and not self.was_ok and self.was_connected:
                self._set(True, now)
                event = OperatorEvent.GAVE
        self.was_ok, self.was_connected = health.ok, health.connected
        return event

    def _set(self, engaged: bool, now: float) -> None:
        if engaged != self.engaged:
            self.engaged, self.since = engaged, now


def blocked_reason(health: LinkHealth) -> str:
    """The ``applied`` reason for a vehicle the link says is not fit to drive (from its typed reason, never its
    words)."""
    if not health.connected:
        return "link_down"
    return "operator" if health.reason == "operator" else "fault"


def overrule(d: Decision, now: float, *, engaged: bool, unsaved: bool, health: LinkHealth, dry_run: bool,
             last_pose: float, max_telemetry_age: float) -> Decision:
    """The gate's decision ``d``, overruled (in this order) by a latch not on disk (``estop``: released in memory
    but not on disk yet, a stop until the release is saved), not engaged (``disengaged``), a link not fit to drive
    (its :func:`blocked_reason`; not in a dry run) and telemetry older than ``max_telemetry_age`` at ``now``
    (``no_telemetry``). Only a driving decision is overruled: a stop stays the gate's."""
    if d.driving and unsaved:
        return Decision(0.0, 0.0, "estop", d.cmd_seq)
    if d.driving and not engaged:
        return Decision(0.0, 0.0, "disengaged", d.cmd_seq)
    if d.driving and not health.ok and not dry_run:
        return Decision(0.0, 0.0, blocked_reason(health), d.cmd_seq)
    if d.driving and now - last_pose > max_telemetry_age:
        return Decision(0.0, 0.0, "no_telemetry", d.cmd_seq)
    return d
