"""What the vehicle last told us (mode, arming, the times of its last HEARTBEAT and position, its STATUSTEXTs), and
the link's pure decisions on it: whether it accepts set-points now (:func:`judge`, the one place the link's ``ok`` and
its reason come from), what a new judgement changes (:func:`change`), when a set-point goes out
(:class:`SetpointPacer`) and what the vehicle does if this host dies (:func:`failsafe_report`). Pure: times are
arguments; the driver (:mod:`.driver`) does the I/O and reads its clock."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

from drivers.base import FailsafeReport, LinkReason

#: the vehicle's own failsafe settings read at open (Rover/Parameters.cpp, GCS failsafe in Rover/failsafe.cpp)
FAILSAFE_PARAMS = ("FS_GCS_ENABLE", "FS_GCS_TIMEOUT", "FS_ACTION", "FS_TIMEOUT")
#: Rover stops a GUIDED velocity target not renewed for this long (Rover/mode_guided.cpp), s
GUIDED_TIMEOUT_S = 3.0


@dataclass(frozen=True, slots=True)
class RoverModes:
    """ArduPilot Rover's custom mode numbers (from pymavlink's table): GUIDED, INITIALISING and every name."""

    guided: int
    initialising: int
    names: Mapping[int, str]

    def name(self, custom_mode: int | None) -> str:
        """``"HOLD"`` for 4, ``"mode 99"`` for a number Rover does not have, ``"unknown"`` before a HEARTBEAT."""
        if custom_mode is None:
            return "unknown"
        return self.names.get(custom_mode, f"mode {custom_mode}")


@dataclass
class Vehicle:
    """What the vehicle last told us; times are the driver host's monotonic seconds of receipt."""

    custom_mode: int | None = None
    armed: bool = False
    hb_time: float | None = None  # the last HEARTBEAT
    pos_time: float | None = None  # the last LOCAL_POSITION_NED
    boot_ms: int = 0  # the vehicle's time since boot in its last message
    rebooted: bool = False  # its clock went back: it forgot our message intervals (cleared once it drives again)
    #: it has been in GUIDED since this driver opened: only then did an operator take it (a vehicle found in MANUAL
    #: at start was never ours)
    guided_seen: bool = False
    texts: deque[tuple[float, str]] = field(default_factory=deque)  # (receive time, STATUSTEXT), bounded
    text_count: int = 0

    def heard(self, custom_mode: int, armed: bool, now: float, guided: int) -> None:
        """A HEARTBEAT received at ``now``: its mode and arming (``guided``: GUIDED's mode number)."""
        self.custom_mode = int(custom_mode)
        self.guided_seen = self.guided_seen or self.custom_mode == guided
        self.armed = bool(armed)
        self.hb_time = now

    def boot(self, boot_ms: int) -> bool:
        """The vehicle's time since boot in a message; True when it went back by more than a second: the vehicle
        rebooted, and forgot the message intervals we asked for."""
        went_back = boot_ms + 1000 < self.boot_ms
        self.rebooted = self.rebooted or went_back
        self.boot_ms = int(boot_ms)
        return went_back

    def note(self) -> str:
        """What the vehicle said lately, for an error text (``"; vehicle said: ..."``; "" when it said nothing)."""
        return f"; vehicle said: {'; '.join(t for _, t in self.texts)}" if self.texts else ""

    def said_since(self, since: float) -> list[str]:
        """The STATUSTEXTs received at or after ``since``."""
        return [t for ts, t in self.texts if ts >= since]


@dataclass(frozen=True, slots=True)
class LinkView:
    """The driver's side of the judgement: whether it is opened or closed and how its connection stands."""

    opened: bool  # open() succeeded: from then on the mode and arming are the operator's
    closed: bool
    connection: bool  # a pymavlink connection is open
    connected_at: float  # when it was opened: the vehicle counts as heard only once it speaks on it
    lost_reason: str  # why the last connection was dropped
    url: str


@dataclass(frozen=True, slots=True)
class Verdict:
    """Whether the vehicle accepts set-points at one moment, and why not: typed for code (``reason``, the link's
    :data:`drivers.base.LinkReason`) and in words a person can act on (``text``)."""

    connected: bool  # a fresh HEARTBEAT on the current connection
    ok: bool  # GUIDED, armed, heard from and streaming its position
    text: str  # for people
    reason: LinkReason  # for code: closed, link_down, operator, rebooted, disarmed, no_telemetry or ok


NOT_OPENED = Verdict(False, False, "not opened", "closed")


def position_fresh(v: Vehicle, now: float, position_timeout: float) -> bool:
    """A LOCAL_POSITION_NED within ``position_timeout`` of ``now`` (ArduPilot sends none without an EKF origin)."""
    return v.pos_time is not None and now - v.pos_time <= position_timeout


def judge(v: Vehicle, link: LinkView, now: float, modes: RoverModes, heartbeat_timeout: float,
          position_timeout: float) -> Verdict:
    """The vehicle at ``now`` from what it last said. Pure: reads no clock and changes nothing."""
    hb_age = math.inf if v.hb_time is None else now - v.hb_time
    connected = (link.connection and hb_age <= heartbeat_timeout and v.hb_time is not None
                 and v.hb_time >= link.connected_at)
    if link.closed:
        return Verdict(False, False, "closed", "closed")
    if not link.opened:
        return Verdict(connected, False, "not opened", "closed")
    if not connected:
        if not link.connection:
            text = f"connection lost ({link.lost_reason}), re-opening {link.url}; no heartbeat for {hb_age:.1f} s"
        else:
            text = f"no heartbeat for {hb_age:.1f} s"
        return Verdict(False, False, text, "link_down")
    if v.custom_mode != modes.guided:
        who = ("vehicle rebooted" if v.rebooted else "operator took control" if v.guided_seen
               else "not in GUIDED (the operator's)")
        why: LinkReason = "rebooted" if v.rebooted else "operator"
        return Verdict(True, False, f"{who}: mode {modes.name(v.custom_mode)}{'' if v.armed else ', disarmed'}", why)
    if not v.armed:
        return Verdict(True, False, "vehicle disarmed in GUIDED: waiting for the operator to arm it", "disarmed")
    if not position_fresh(v, now, position_timeout):
        age = math.inf if v.pos_time is None else now - v.pos_time
        return Verdict(True, False, f"no LOCAL_POSITION_NED for {age:.1f} s (EKF origin lost?)", "no_telemetry")
    return Verdict(True, True, "driving: GUIDED, armed", "ok")


@dataclass(frozen=True, slots=True)
class Change:
    """What a new judgement changes against the one before: whether to say so (its reason changed), whether the link
    was lost (count it) and whether the vehicle's HEARTBEATs came back (reset the reconnect backoff and ask for the
    telemetry streams again: a rebooted autopilot forgot them; never the mode or arming)."""

    said: bool
    lost: bool
    back: bool


def change(before: Verdict, after: Verdict, link_up: bool) -> Change:
    """The :class:`Change` from ``before`` to ``after`` for a link that was up (``link_up``) or not."""
    lost = after.reason == "link_down" and link_up
    return Change(said=after.reason != before.reason, lost=lost, back=not lost and after.connected and not link_up)


class SetpointPacer:
    """When a set-point goes out: an unchanged command every ``period`` s (ArduPilot stops after GUID_TIMEOUT, 3 s,
    without one); a changed one at once, but never sooner than ``min_gap`` s after the last (the radio's budget,
    ``max_setpoint_hz``); a stop after motion always at once. Pure: times are arguments."""

    def __init__(self, period: float, min_gap: float) -> None:
        self.period, self.min_gap = period, min_gap
        self.last: tuple[float, float] | None = None  # the last (v, omega) sent
        self.last_time = -math.inf
        self.deferred = 0  # changed commands held back by ``min_gap`` (only grows)

    def due(self, cmd: tuple[float, float], now: float) -> bool:
        """Whether ``cmd`` goes out at ``now`` (a changed command held back is counted)."""
        if cmd == (0.0, 0.0) and self.last not in (None, (0.0, 0.0)):
            return True
        gap = now - self.last_time
        if cmd != self.last:
            if gap >= self.min_gap:
                return True
            self.deferred += 1
            return False
        return gap >= self.period

    def sent(self, cmd: tuple[float, float], now: float) -> None:
        """``cmd`` went out at ``now``."""
        self.last, self.last_time = cmd, now


def failsafe_report(params: Mapping[str, float]) -> FailsafeReport:
    """What the vehicle does on its own when this host dies (stops sending set-points and heartbeats), from the
    failsafe parameters it answered (:data:`FAILSAFE_PARAMS`): GUIDED stops after :data:`GUIDED_TIMEOUT_S` without a
    target, sooner when the GCS failsafe is on with an action."""
    p = params
    gcs = p.get("FS_GCS_ENABLE")
    known = ", ".join(f"{k}={p[k]:g}" for k in FAILSAFE_PARAMS if k in p) or "no failsafe parameter answered"
    drive_on = GUIDED_TIMEOUT_S  # Rover/mode_guided.cpp: no new target for 3 s -> stop (not a parameter)
    if gcs and p.get("FS_ACTION", 0) and "FS_GCS_TIMEOUT" in p:
        drive_on = min(drive_on, p["FS_GCS_TIMEOUT"] + p.get("FS_TIMEOUT", 0.0))
    text = (f"if the host dies the vehicle drives on for up to {drive_on:g} s (GUIDED stops after "
            f"{GUIDED_TIMEOUT_S:g} s without a target; {known})")
    return FailsafeReport(drive_on_s=drive_on, text=text, params=dict(p))
