"""The one protocol every vehicle link implements.

A driver owns the wire to one vehicle. It never decides *what* to send (the driver host checks freshness,
finiteness and hard limits, and owns the deadman); it only turns an already-checked learner command (v, omega)
into the link's own frames and turns the vehicle's telemetry back into poses.

All times are the driver host's monotonic seconds, so that the pose stamps and the applied-command echo the station
pairs with each other come from one clock: passed in (``now``) where the protocol has them, and otherwise read from
the clock the driver was built with (a :class:`bridge.core.clock.Clock`, the station's kind: :data:`SYSTEM`, the
host's, by default: no driver uses the time module itself). A driver that waits (its ``open``, ``engage``, ``close``)
sets its deadlines on that clock and waits with its :meth:`~bridge.core.clock.Clock.wait`, so a test on a fake clock
(tests/fakeclock.py) drives it without real time. ``close`` is given the host's ``now`` where the host has it.

:class:`LinkBase` is the frame every built-in link shares: the health it reports, its counters (one dataclass names
them: the counts kept and the detail reported cannot disagree), its waits (``open``, ``engage``, ``close`` step the
time only through :meth:`LinkBase._pause`), the "zero until slower than ``stop_speed``, then close" loop
(:meth:`LinkBase._stop_until_still`) and one health verdict per tick (:meth:`LinkBase._verdict`: ``poll``, ``health``
and ``send`` at one ``now`` judge the link once).
"""

from __future__ import annotations

import inspect
import threading
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, Literal, Protocol, runtime_checkable

from bridge.core.clock import SYSTEM, Clock

__all__ = ["SYSTEM", "Clock"]


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

    def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0,
              now: float | None = None) -> None:
        """Stop the vehicle, wait (at most ``stop_timeout``) until it reports less than ``stop_speed``, then (if
        ``disarm``: it was engaged by this host) disarm it or idle its axes, and release the link. Idempotent.
        ``now``: the host's time (None: the link reads its clock once, a caller without a tick)."""


def close_link(driver: Driver, now: float, **kw: Any) -> None:
    """``driver.close(**kw)`` with the host's ``now`` where the link takes one: the project's links do, a lab's own
    link written against the earlier protocol (``close`` without ``now``) is still closed, so it still stops the
    vehicle at shutdown rather than failing there with a TypeError."""
    params = inspect.signature(driver.close).parameters
    takes_now = "now" in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    if takes_now:
        driver.close(**kw, now=now)
    else:
        driver.close(**kw)


def link_unauthenticated(config: object) -> str:
    """Why anyone on the network can command the vehicle through a link with this configuration, in words ("" when
    the link authenticates what it obeys, or has nothing to say about it: a CAN bus is a wire inside the robot). A
    link's configuration says it by an ``unauthenticated()`` method (the UDP link's ``insecure``, MAVLink without
    signing); the driver host's status (counter ``unauthenticated_link``), its start log and ``scmbridge doctor``
    repeat it, so a person sees it where they look, not only in a log line at open."""
    method = getattr(config, "unauthenticated", None)
    return method() if callable(method) else ""


def counter_names(counters: type, *, besides: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The names of a counters dataclass's counts, in order: its fields whose default is the whole number 0, less
    ``besides`` (counts another piece keeps: the CAN axes' faults). The one source of a link's counter names."""
    out = []
    for f in fields(counters):
        if f.default is not MISSING and type(f.default) is int and f.default == 0 and f.name not in besides:
            out.append(f.name)
    return tuple(out)


#: a link's verdict at one moment: (ok, reason, text)
Verdict = tuple[bool, LinkReason, str]


class LinkBase:
    """What every built-in link keeps the same way (see the module docstring). A link sets :attr:`COUNTERS` (the
    dataclass its detail reports its counts in) and :meth:`_judge_link` (why it is, or is not, fit at ``now``: pure);
    everything else here is shared.

    ``counts`` holds each count of :attr:`COUNTERS` by name (less :attr:`COUNTED_ELSEWHERE`), created from the
    dataclass, so a count added there is kept and reported without writing its name twice. The verdict is judged
    at most once per ``now`` while nothing changed the link (:meth:`_verdict`); whatever changes what
    :meth:`_judge_link` reads calls :meth:`_changed` (a frame, a send failure, a bus reopened) so the next verdict
    judges again. Its helpers are protected (a leading underscore): they are the links' frame, not their API."""

    #: the link's counters dataclass: the names of its counts
    COUNTERS: type
    #: counts of COUNTERS kept by another piece (and merged in :meth:`counters`)
    COUNTED_ELSEWHERE: tuple[str, ...] = ()

    def __init__(self, clock: Clock = SYSTEM) -> None:
        self.clock = clock
        self._idle = threading.Event()  # never set: what a bounded wait with nothing to wake it waits on
        self._health = LinkHealth()
        self.counts: dict[str, int] = dict.fromkeys(counter_names(self.COUNTERS, besides=self.COUNTED_ELSEWHERE), 0)
        self._judged_at: tuple[float, Verdict] | None = None
        self.judged = 0  # verdicts judged (not answered from the one already judged at that moment)

    # ------------------------------------------------------------------------------------------- time
    def _pause(self, dt: float) -> float:
        """Wait ``dt`` s on the link's clock (a bounded wait of ``open``, ``engage`` or ``close``) and return the time
        after it: the only way such a wait learns the time moved."""
        self.clock.wait(self._idle, dt)
        return self.clock()

    # ------------------------------------------------------------------------------------------- health
    def _judge_link(self, now: float) -> Verdict:
        """Why the link is (not) fit to drive at ``now`` from what it last heard: ``(ok, reason, text)``. Pure."""
        raise NotImplementedError

    def _changed(self) -> None:
        """What :meth:`_judge_link` reads changed: the next :meth:`_verdict` judges again, even at the same ``now``."""
        self._judged_at = None

    def _verdict(self, now: float) -> Verdict:
        """The verdict at ``now``: judged once per moment and change (a tick's ``poll``, ``health`` and ``send``
        share it)."""
        cached = self._judged_at
        if cached is not None and cached[0] == now:
            return cached[1]
        v = self._judge_link(now)
        self.judged += 1
        self._judged_at = (now, v)
        return v

    @property
    def counters(self) -> dict[str, int]:
        """Every count of :attr:`COUNTERS` by name (a copy); a link whose pieces keep some merges theirs in."""
        return dict(self.counts)

    def _counter_snapshot(self, **extra: Any) -> Any:
        """The counts as a :attr:`COUNTERS` instance (``extra``: the detail's fields that are not counts)."""
        return self.COUNTERS(**self.counters, **extra)

    def _closed_health(self) -> None:
        h = self._health
        h.connected = h.ok = False
        h.text, h.reason = "closed", "closed"
        self._changed()

    # ------------------------------------------------------------------------------------------- close
    def _stop_until_still(self, now: float, stop_speed: float, stop_timeout: float, period: float,
                         speed: Callable[[float], float | None]) -> bool:
        """Closing: a stop at ``now`` and every ``period`` after it until ``speed(now)`` (the vehicle's reported
        speed, m/s; None: not known yet) is below ``stop_speed``, at most ``stop_timeout``; then one stop more.
        True if it reported stopped. The link's ``stop`` and ``speed`` do the I/O; the time moves by :meth:`pause`."""
        t_end = now + stop_timeout
        still = False
        while now < t_end:
            self.stop(now)
            now = self._pause(min(period, max(0.0, t_end - now)))
            reported = speed(now)
            if reported is not None and abs(reported) < stop_speed:
                still = True
                break
        self.stop(now)
        return still

    def stop(self, now: float) -> None:  # (every link has one: the Driver protocol's)
        raise NotImplementedError
