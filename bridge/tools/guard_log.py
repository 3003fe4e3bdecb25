"""When and where the station's guards stopped a run, from its status (docs/ARCHITECTURE.md section 6): the demo's
summary and ``scmbridge report`` (which replays a recording through the demo's monitor) both say it.

A guard's pause shows on the station's status as its typed reason (``left_corridor``, ``fence``, ``pose_jump``,
``outside_assumption``), its words and the pose's distance from the path (``off_path_m``). :class:`GuardLog` keeps
one entry per pause (a new entry when the reason appears again after the mission drove on), with the latest pose at
that moment: the driver host's stamp, so the summary can say the time from the run's first command on the same
clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

#: the station's reasons that are a guard's pause (bridge.nodes.station_guards)
GUARD_REASONS = ("left_corridor", "fence", "pose_jump", "outside_assumption")


@dataclass
class GuardLog:
    """The guards' pauses seen on a station's status, in order."""

    stops: list[dict[str, Any]] = field(default_factory=list)
    _in: str | None = None  # the guard reason of the last station status (None: not a guard's pause)

    @property
    def stopped(self) -> bool:
        """The station's last status is a guard's pause (a demo with no person to resume it is over)."""
        return self._in is not None

    def note(self, st: Any, pose: tuple[float, float, float, float] | None) -> None:
        """A station status ``st`` (a :class:`bridge.core.wire.Status`) and the latest pose ``(stamp, x, y,
        theta)`` (None: none yet)."""
        reason = st.reason if st.reason in GUARD_REASONS else None
        if reason is not None and reason != self._in:
            self.stops.append({"reason": reason, "stamp": None if pose is None else pose[0],
                               "x": None if pose is None else round(pose[1], 3),
                               "y": None if pose is None else round(pose[2], 3),
                               "off_path_m": None if st.off_path_m is None else round(st.off_path_m, 3),
                               "text": st.text})
        self._in = reason

    def summary(self, t0: float) -> list[dict[str, Any]]:
        """The pauses for a run summary: ``t_s`` from ``t0`` (the run's first command, the driver host's clock)."""
        out = []
        for s in self.stops:
            entry = {k: v for k, v in s.items() if k != "stamp"}
            entry["t_s"] = None if s["stamp"] is None else round(s["stamp"] - t0, 1)
            out.append(entry)
        return out


__all__ = ["GUARD_REASONS", "GuardLog"]
