"""The one protocol every vehicle link implements.

A driver owns the wire to one vehicle. It never decides *what* to send (the driver host checks freshness,
finiteness and hard limits, and owns the deadman); it only turns an already-checked learner command (v, omega)
into the link's own frames and turns the vehicle's telemetry back into poses.

All times are the driver host's monotonic seconds, so that the pose stamps and the applied-command echo the station
pairs with each other come from one clock: passed in (``now``) where the protocol has them, and otherwise read from
the clock the driver was built with (a :data:`Clock`, ``time.monotonic`` by default; a driver's only direct use of
the time module is that default). A driver that waits (its ``open``, ``engage``, ``close``) sets its deadlines on that
clock and sleeps with the :data:`Sleep` it was given, so a test on a fake clock drives it without real time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Literal, Protocol, runtime_checkable

#: a monotonic clock in seconds (``time.monotonic``, or a test's fake)
Clock = Callable[[], float]
#: a wait of so many seconds on that clock (``time.sleep``, or a test's fake that advances its clock)
Sleep = Callable[[float], None]


class DriverError(RuntimeError):
    """The link cannot do what was asked (not connected, vehicle refused to arm, bus down...)."""


@dataclass(frozen=True, slots=True)
class Pose:
    """One telemetry sample in the ENU unicycle frame (x east, y north, theta counter-clockwise from x)."""

    stamp: float  # driver-host monotonic seconds when the sample was received / computed
    x: float
    y: float
    theta: float
    v: float | None = None  # body forward speed, m/s, where the link reports it
    omega: float | None = None  # yaw rate, rad/s, counter-clockwise positive


class LinkDetail(Protocol):
    """What one link knows beyond :class:`LinkHealth`'s common fields: a frozen dataclass of its own per link (axis
    states for CAN, mode and arming for MAVLink, stream refusals for UDP)."""

    def status_counters(self) -> dict[str, int]:
        """Its counts (whole numbers, not negative), which the driver host's status carries as ``link_<name>``."""
        ...


def whole_numbers(detail: object) -> dict[str, int]:
    """The fields of a dataclass that hold a whole number (or a flag) not below zero, by name: what
    :meth:`LinkDetail.status_counters` usually returns."""
    out: dict[str, int] = {}
    for f in fields(detail):
        value = getattr(detail, f.name)
        if isinstance(value, (int, bool)) and int(value) >= 0:
            out[f.name] = int(value)
    return out


#: why a link is (not) fit to drive, in one word that code decides on (:attr:`LinkHealth.reason`): ``ok``;
#: ``closed`` (not opened yet, or closed); ``link_down`` (no connection to the vehicle: a CAN bus down, no MAVLink
#: heartbeat); ``operator`` (a person has the vehicle: MAVLink, it left GUIDED); ``rebooted`` (MAVLink: the vehicle
#: rebooted and is not in GUIDED); ``disarmed`` (MAVLink: GUIDED, not armed); ``no_telemetry`` (no fresh pose from the
#: vehicle: MAVLink's LOCAL_POSITION_NED, the UDP robot's state); ``not_engaged`` (CAN: the axes idle); ``arming``
#: (CAN: waiting for both axes in closed loop); ``fault`` (CAN: a latched controller fault); ``no_heartbeat`` (CAN: a
#: controller's heartbeat lost); ``odometry`` (CAN: implausible encoder estimates rejected)
LinkReason = Literal["ok", "closed", "link_down", "operator", "rebooted", "disarmed", "no_telemetry", "not_engaged",
                     "arming", "fault", "no_heartbeat", "odometry"]


@dataclass(slots=True)
class LinkHealth:
    """What a driver reports about its link; counters only grow.

    ``ok`` is the truth the whole system acts on: True only while the link is up *and* the vehicle accepts and
    executes velocity commands (MAVLink: heartbeat fresh, GUIDED, armed, position ready; CAN: both controllers'
    heartbeats fresh, closed loop, no axis error; UDP: the robot's state fresh). When it is False, ``text`` says why
    in words a person can act on (``"operator took control: mode HOLD"``, ``"left axis error: ..."``), the driver
    host stops, and the station stops pairing and planning for that robot. ``reason`` says it in one typed word
    (:data:`LinkReason`, the first cause when there are several), and only it is decided on: ``operator`` means a
    person has the vehicle (the host reports reason ``operator``, not ``fault``, and a MAVLink host disengages); a
    link sets it wherever it sets ``text``, which is for people and may be reworded freely.
    ``detail``: the link's own typed detail (None: nothing beyond these fields).
    """

    connected: bool = False
    ok: bool = False
    text: str = "not opened"
    frames_sent: int = 0
    frames_received: int = 0
    malformed: int = 0  # frames/messages that failed to decode or validate, dropped
    errors: int = 0  # link-level errors (send failures, vehicle faults)
    detail: LinkDetail | None = None
    reason: LinkReason = "closed"  # last, so a positional construction of the fields above keeps its meaning


@dataclass(frozen=True, slots=True)
class FailsafeReport:
    """What the vehicle does by itself when the driver host dies: ``drive_on_s``, the longest it may keep
    executing the last command (None: unknown), in words in ``text``, with the settings read from it."""

    drive_on_s: float | None
    text: str
    params: dict[str, float] = field(default_factory=dict)


@runtime_checkable
class Driver(Protocol):
    """A vehicle link. Construction takes the link's config mapping and does no I/O; ``open`` connects."""

    name: str

    def open(self, now: float) -> None:
        """Connect and read the vehicle's state (may block, bounded). Never arms it, changes its mode or puts an
        axis in closed loop: a restarted driver host must not take a vehicle back from a person."""

    def engage(self, now: float, clear_faults: bool = False) -> None:
        """A person's act (``scmbridge engage``): bring the vehicle to accept velocity commands (MAVLink: GUIDED and
        armed; CAN: closed loop). Raises :class:`DriverError` with the reason if it cannot; ``clear_faults``: the
        person also asks to clear what the controllers latched."""

    def failsafe(self) -> FailsafeReport:
        """What the vehicle does by itself if this host dies (read at open where the link allows)."""

    def send(self, v: float, omega: float, now: float) -> None:
        """Command forward speed ``v`` (m/s) and yaw rate ``omega`` (rad/s, CCW+). Inputs are already checked.

        The driver host calls it only while ``health().ok``; a driver still never sends a set-point the vehicle's
        state forbids (the operator took control, an axis is in error) and never changes the vehicle's mode,
        re-arms it or clears its faults by itself."""

    def stop(self, now: float) -> None:
        """Command zero velocity now (deadman, estop, shutdown). Must be safe to call at any time."""

    def poll(self, now: float) -> list[Pose]:
        """Read what arrived since the last call, without blocking long; return new poses, oldest first."""

    def health(self, now: float) -> LinkHealth:
        """The link's state at ``now`` as of the last ``poll``/``send`` (a new snapshot, with the link's typed
        detail), for the driver host's decisions and ``status``. Pure: it changes nothing and reads no clock, so
        asking never alters what the link does; what time changes (a latch, a phase, a count) happens in ``poll``
        and ``send``."""

    def clear_faults(self, now: float) -> None:
        """An explicit operator action (an estop release, ``scmbridge estop --release``): clear what the vehicle's
        controllers latched (axis errors) and bring them back to accepting commands. Never called automatically;
        a link with nothing to clear (MAVLink: the operator changes the mode) does nothing."""

    def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0) -> None:
        """Stop the vehicle, wait (at most ``stop_timeout``) until it reports less than ``stop_speed``, then (if
        ``disarm``: it was engaged by this host) disarm it or idle its axes, and release the link. Idempotent."""


def link_unauthenticated(config: object) -> str:
    """Why anyone on the network can command the vehicle through a link with this configuration, in words ("" when
    the link authenticates what it obeys, or has nothing to say about it: a CAN bus is a wire inside the robot). A
    link's configuration says it by an ``unauthenticated()`` method (the UDP link's ``insecure``, MAVLink without
    signing); the driver host's status (counter ``unauthenticated_link``), its start log and ``scmbridge doctor``
    repeat it, so a person sees it where they look, not only in a log line at open."""
    method = getattr(config, "unauthenticated", None)
    return method() if callable(method) else ""
