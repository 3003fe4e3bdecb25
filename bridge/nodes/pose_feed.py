"""The driver host's poses as it publishes them on ``scm/<robot>/state``, pure (times are arguments; no Zenoh, no
lock: the host calls :meth:`PoseFeed.offer_mocap` and :meth:`PoseFeed.take_mocap` under its own lock, docs/
ARCHITECTURE.md section 4, "Threads and clocks").

All of the host's stamps are its own monotonic clock, so the station pairs ``applied`` with ``state`` on one
clock. A link's poses already are (the drivers put the vehicle's stamps on it); a motion-capture bridge's samples
(``pose_source = "mocap"``) carry the bridge's own clock and are put on this host's with the sliding-window minimum
of ``receipt - stamp`` (:class:`bridge.core.clock.ClockOffset`). The feed numbers what it publishes in its own
``(epoch, seq)`` stream and remembers when it last published a pose (the telemetry's age, which stops the vehicle).
"""

from __future__ import annotations

import math

import msgspec

from bridge.core import wire as M
from bridge.core.clock import ClockOffset
from drivers.base import Pose

#: poses this far apart (s) give the measured speeds of a link that reports none (one pose to the next is noise)
MEASURE_WINDOW_S = 0.1


class PoseFeed:
    """One host's pose stream. ``source``: the link's name, or ``"mocap"`` (the poses come from motion capture and
    the link's poses are dropped; the link is still read: its frames carry the vehicle's health). ``epoch``: this
    host start's (:func:`bridge.core.wire.new_epoch`)."""

    def __init__(self, source: str, epoch: int, mocap_window_s: float = 5.0) -> None:
        self.source, self.epoch = source, epoch
        self.seq = 0  # the next pose published gets it
        self.last_pose = -math.inf  # when a pose was last published (the host's clock)
        self.mocap_clock = ClockOffset(mocap_window_s)
        self.mocap: list[M.LearnerState] = []  # restamped samples waiting for the loop
        #: the vehicle's latest measured body speeds (v m/s, omega rad/s), None before any; :meth:`published`
        self.measured: tuple[float, float] | None = None
        self.anchor: M.LearnerState | None = None  # the pose the next finite difference is taken from

    @property
    def mocap_source(self) -> bool:
        return self.source == "mocap"

    def offer_mocap(self, st: M.LearnerState, now: float) -> str:
        """A motion-capture sample received at ``now``: its stamp put on this host's clock and kept for the next
        :meth:`take_mocap`. Returns the clock's verdict (:meth:`ClockOffset.judge`): ``ok``, ``restarted`` (a
        confirmed step of the bridge's clock restarted the estimate) or another word for a sample dropped (stamped
        ahead of any possible delivery: forged, or a clock step not yet confirmed)."""
        t, verdict = self.mocap_clock.judge(st.stamp, now)
        if t is not None and t > 0:
            self.mocap.append(msgspec.structs.replace(st, stamp=t))
        return verdict

    def take_mocap(self) -> list[M.LearnerState]:
        """The motion-capture samples kept since the last call (and forget them)."""
        samples, self.mocap = self.mocap, []
        return samples

    def states(self, link: list[Pose], samples: list[M.LearnerState]) -> list[M.LearnerState]:
        """This tick's poses to publish, numbered from :attr:`seq` on: the motion-capture ``samples`` in stamp order
        (for a mocap source), else the link's poses."""
        if self.mocap_source:
            return [msgspec.structs.replace(s, seq=self.seq + i, epoch=self.epoch, source="mocap")
                    for i, s in enumerate(sorted(samples, key=lambda s: s.stamp))]
        return [M.LearnerState(stamp=p.stamp, seq=self.seq + i, x=p.x, y=p.y, theta=p.theta, v=p.v, omega=p.omega,
                               source=self.source, epoch=self.epoch) for i, p in enumerate(link)]

    def published(self, now: float, st: M.LearnerState | None = None) -> None:
        """A pose went out at ``now``: the next one is numbered after it, and the telemetry is fresh; ``st`` (the pose)
        is measured (:attr:`measured`)."""
        self.seq += 1
        self.last_pose = max(self.last_pose, now)
        if st is not None:
            self._measure(st)

    def _measure(self, st: M.LearnerState) -> None:
        """The vehicle's body speeds from its poses: the speeds the link reports where it does, else the motion
        between this pose and one at least :data:`MEASURE_WINDOW_S` older (signed along the heading)."""
        a = self.anchor
        v, omega = st.v, st.omega
        if a is None:
            self.anchor = st
        elif st.stamp - a.stamp >= MEASURE_WINDOW_S:
            dt = st.stamp - a.stamp
            dx, dy = st.x - a.x, st.y - a.y
            along = dx * math.cos(a.theta) + dy * math.sin(a.theta)
            fd_v = math.copysign(math.hypot(dx, dy), along if along != 0 else 1.0) / dt
            fd_omega = math.remainder(st.theta - a.theta, math.tau) / dt
            v = fd_v if v is None else v
            omega = fd_omega if omega is None else omega
            self.anchor = st
        elif st.stamp < a.stamp:  # a restamped stream went back: start again
            self.anchor = st
        if v is not None and omega is not None and math.isfinite(v) and math.isfinite(omega):
            self.measured = (float(v), float(omega))

    def age(self, now: float) -> float:
        """s since a pose was last published (inf before the first)."""
        return now - self.last_pose
