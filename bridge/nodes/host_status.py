"""What the driver host says about itself on ``scm/<robot>/status/driver``, pure (times and facts are arguments; no
Zenoh, no lock, no clock; docs/ARCHITECTURE.md section 3, "Reasons are typed, words are for people", and section 6).

Health is truthful: the host is ``ok`` only if the link is fit, the telemetry fresh, no estop is latched (and the
latch is on disk), the vehicle is engaged, no two senders share the station's epoch, and it is not a dry run. The one
word (``state``) and the typed ``reason`` come from typed values only, never from a text: the station decides on the
reason (``estop``: a start or resume is refused). :class:`HostStatus` turns the :class:`HostFacts` the host gathers
each tick into an :class:`Assessment` (the problems in words, most important first, and the state and reason they
give), says when a status is due (each second, and at once on a change of ok, state or reason, at most
``STATUS_MAX_HZ`` a second) and builds the :class:`bridge.core.wire.Status` with its counters and latencies.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from bridge.core import wire as M
from bridge.core.clock import machine
from drivers.base import FailsafeReport, LinkHealth

#: the end of the status text of a host whose link does not authenticate (drivers.base.link_unauthenticated)
UNAUTHENTICATED = " (link unauthenticated: anyone on the network can drive it)"
#: a status goes out each this many seconds, and at once on a change of ok, state or reason, but at most
#: STATUS_MAX_HZ a second (a flapping link cannot flood the station)
STATUS_EVERY_S = 1.0
STATUS_MAX_HZ = 20.0


@dataclass(frozen=True, slots=True)
class HostFacts:
    """What the host knows at one instant: the link's ``health`` (as read this tick), whether a person engaged the
    vehicle, when a pose was last published (``last_pose``, the host's clock), the estop latch (``estopped``, by
    ``estop_source``; ``unsaved``: why the latch on disk is not the gate's, "" when it is), two senders on one epoch
    (``conflict``: the gate's words, None when there are not), whether this is a dry run and the vehicle's measured
    body speeds (``measured``: v, omega from its poses, :class:`bridge.nodes.pose_feed.PoseFeed`; None before any)."""

    health: LinkHealth
    engaged: bool
    last_pose: float = -math.inf
    estopped: bool = False
    estop_source: str = ""
    unsaved: str = ""
    conflict: str | None = None
    dry_run: bool = False
    measured: tuple[float, float] | None = None


@dataclass(frozen=True, slots=True)
class Assessment:
    """What stands in the way of driving (``problems``, in words, most important first), the state and typed reason
    they give, and the pose's age (s)."""

    problems: tuple[str, ...]
    state: M.NodeState
    reason: M.Reason
    pose_age: float
    dry_run: bool = False
    engaged: bool = False
    measured: tuple[float, float] | None = None  # None too when the poses are not fresh: not measured now

    @property
    def ok(self) -> bool:
        return not self.problems and not self.dry_run

    @property
    def key(self) -> tuple[bool, str, str]:
        """What a change of sends a status at once."""
        return self.ok, self.state, self.reason


#: what the vehicle is given, in words, by the last decision's reason (``Applied.reason``) of an engaged, fit host: it
#: says what is applied, never "driving" (a robot held at a stop is engaged and fit, and stands still)
APPLYING = {
    "cmd": "applying the station's commands",
    "clamped": "applying the station's commands, clamped to the hard limits",
    "stop": "holding the station's stop",
    "deadman": "holding a stop: no fresh command",
    "stale": "holding a stop: the last command is stale",
    "start": "holding a stop: no command yet",
    "refused": "holding a stop: the command is outside what the vehicle can do",
}


def applying(reason: str) -> str:
    """An engaged, fit host's words for what its vehicle is given (:data:`APPLYING`), ending in the reason."""
    return f"{APPLYING.get(reason, 'applying')} ({reason})" if reason else "engaged"


def _bounded(x: float) -> float:
    """A measured speed within what the wire carries (a glitching link's jump says "moving", not a dropped status)."""
    return max(-100.0, min(100.0, float(x)))


def node_state(estop: bool, h: LinkHealth, pose_age: float, problems: Sequence[str], unsaved: bool = False, *,
               engaged: bool, dry_run: bool, max_telemetry_age: float) -> tuple[M.NodeState, M.Reason]:
    """The one word ``scmbridge status`` shows for a host, and its typed reason (what the station decides on: a
    latched estop is ``estop`` also in a dry run, ``latch_unsaved`` when it is not on disk); from typed values only,
    never from a text."""
    latched: M.Reason = "latch_unsaved" if unsaved else "estop"
    if dry_run:
        return "dry_run", latched if estop else "dry_run"
    if estop:
        return "estop", latched
    if not h.connected:
        return "link_down", "link_down"
    if not engaged:
        return "waiting", "not_engaged"
    if not h.ok:
        return ("operator", "operator") if h.reason == "operator" else ("fault", "fault")
    if pose_age > max_telemetry_age:
        return "no_pose", "no_telemetry"
    return ("driving", "ok") if not problems else ("fault", "conflict")  # (the one problem left: two senders)


def host_counters(gate: Mapping[str, int], inputs: Mapping[str, int], h: LinkHealth, *, unauthenticated: bool,
                  missed: int, stalls: int, ticks: int) -> dict[str, int]:
    """The status's counters: the gate's, the inputs' (decoded, malformed, refused), the link's and the loop's.
    (``unauthenticated_link`` is 1 for a link anyone on the network can drive; not ``link_unauthenticated``: that is
    the UDP link's count of datagrams dropped for a bad tag.)"""
    counters = dict(gate)
    counters.update(inputs)
    counters["unauthenticated_link"] = int(unauthenticated)
    counters.update({"link_malformed": h.malformed, "link_errors": h.errors, "missed_deadlines": missed,
                     "loop_stalls": stalls, "frames_sent": h.frames_sent, "frames_received": h.frames_received,
                     "ticks": ticks})
    if h.detail is not None:
        counters.update({f"link_{k}": v for k, v in h.detail.status_counters().items()})
    return counters


class HostStatus:
    """One host's status: its assessment, its schedule and its messages (see the module docstring). ``robot`` and
    ``link`` name it in the words; ``period``: the loop's (its rate is on the status); ``unauthenticated``: why
    anyone on the network can drive the link ("" when it authenticates); ``operator_engages``: the link's operator
    engages (the words say to wait for the operator); ``max_drive_on``: s a vehicle may drive on alone after the
    link is lost, beyond which its failsafe is on the status. Used by the host's loop thread."""

    def __init__(self, robot: str, link: str, *, period: float, max_telemetry_age: float,
                 operator_engages: bool = False, unauthenticated: str = "", max_drive_on: float = math.inf) -> None:
        self.robot, self.link, self.period = robot, link, period
        self.max_telemetry_age, self.max_drive_on = max_telemetry_age, max_drive_on
        self.operator_engages, self.unauthenticated = operator_engages, unauthenticated
        self.failsafe: FailsafeReport | None = None  # what the vehicle does if the host dies, read once the link opens
        self.logged_state = ""  # the state the host's log last named
        self.seq = 0  # the next status gets it (the starting ones too)
        #: the last status sent: (ok, state, reason), when, and when the next periodic one is due (:meth:`due`)
        self.sent: tuple[bool, str, str] | None = None
        self.sent_at, self.next_at = -math.inf, -math.inf

    def assess(self, f: HostFacts, now: float) -> Assessment:
        """What stands in the way of driving at ``now``: cheap enough for every tick (:meth:`due` compares it with
        the last status sent)."""
        h = f.health
        pose_age = now - f.last_pose
        problems = []
        if not h.ok:
            problems.append(h.text)
        if pose_age > self.max_telemetry_age:
            problems.append("no telemetry yet" if math.isinf(pose_age) else f"no telemetry for {pose_age:.1f} s")
        if f.estopped:
            problems.insert(0, f"estop latched by {f.estop_source or 'unknown'}")
        if f.unsaved:
            problems.insert(0, f.unsaved)
        if f.conflict:
            problems.append(f.conflict)
        if not f.engaged and not f.estopped and not f.unsaved:
            if self.operator_engages and h.connected and not h.ok:
                problems.insert(0, f"waiting for the operator: {h.text.split(': ', 1)[-1]} "
                                   f"(or scmbridge engage --robot {self.robot})")
            else:
                problems.insert(0, f"waiting for engage (scmbridge engage --robot {self.robot})")
        state, reason = node_state(f.estopped or bool(f.unsaved), h, pose_age, problems, bool(f.unsaved),
                                   engaged=f.engaged, dry_run=f.dry_run, max_telemetry_age=self.max_telemetry_age)
        fresh = f.measured if pose_age <= self.max_telemetry_age else None
        return Assessment(tuple(problems), state, reason, pose_age, f.dry_run, f.engaged, fresh)

    def due(self, a: Assessment, now: float) -> bool:
        """Whether a status should go out at ``now``: each ``STATUS_EVERY_S``, and at once (at most
        ``STATUS_MAX_HZ`` a second) when ``ok``, the state or the typed reason changed since the last one sent. The
        station judges the robot's fitness on this status: an engage, a release or a restart reaches it in the tick
        that made it, not up to a second later (else a `mission resume` right after `engage` is refused)."""
        if now >= self.next_at:  # the periodic ones keep their own grid, whatever went out between them
            self.next_at = now + STATUS_EVERY_S
            return True
        return a.key != self.sent and now - self.sent_at >= 1.0 / STATUS_MAX_HZ

    def build(self, now: float, a: Assessment, *, counters: dict[str, int], late: Sequence[float] = (),
              failsafe: FailsafeReport | None = None, driving_reason: str = "") -> M.Status:
        """The status at ``now`` for assessment ``a`` (counted as sent): ``counters`` (:func:`host_counters`),
        ``late``: s each recent periodic tick came after its deadline (the loop's jitter), ``failsafe``: what the
        vehicle does alone when the link is lost, ``driving_reason``: the last decision's (said while driving)."""
        lat = {"telemetry_age": min(a.pose_age, 1e6) * 1e3}
        if len(late) > 2:
            dev = np.asarray(late) * 1e3
            lat.update({"jitter_p50": float(np.percentile(dev, 50)), "jitter_p99": float(np.percentile(dev, 99)),
                        "jitter_max": float(dev.max())})
        if failsafe is not None and (failsafe.drive_on_s is None or failsafe.drive_on_s > self.max_drive_on):
            lat["failsafe_drive_on"] = min(1e9, 1e3 * (failsafe.drive_on_s or 1e6))
        text = f"link {self.link}: " + ("; ".join(a.problems) if a.problems else applying(driving_reason))
        if a.dry_run:
            text = "DRY RUN (nothing is sent to the vehicle): " + text
        if self.unauthenticated:  # said whatever else is cut (the text's limit is 1024)
            text = text[:1024 - len(UNAUTHENTICATED)] + UNAUTHENTICATED
        msg = M.Status(stamp=now, seq=self.seq, node="driver", ok=a.ok, state=a.state, reason=a.reason,
                       rates_hz={"loop": 1.0 / self.period}, latencies_ms=lat, counters=counters, text=text[:1024],
                       host=machine(), engaged=a.engaged,
                       measured=None if a.measured is None else [_bounded(x) for x in a.measured])
        self.seq += 1
        self.sent, self.sent_at = a.key, now
        return msg

    def starting(self, now: float, reason: M.Reason, text: str) -> M.Status:
        """A status while the link is not open yet (state ``starting``; ``reason`` ``starting`` or ``link_down``)."""
        msg = M.Status(stamp=now, seq=self.seq, node="driver", ok=False, state="starting", reason=reason,
                       text=text[:1024])
        self.seq += 1
        return msg
