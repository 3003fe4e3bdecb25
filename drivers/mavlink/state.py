"""What the vehicle last told us (mode, arming, the times of its last HEARTBEAT and position, its STATUSTEXTs), and
the pure judgement of whether it accepts set-points now: the one place the link's ``ok`` and its reason come from."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

from drivers.base import LinkReason


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
