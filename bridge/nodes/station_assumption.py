"""The station's check of the method's assumption (docs/ARCHITECTURE.md section 6, "Outside the method's
assumption"): a learner that cannot turn in place, measured to turn no tighter than a curvature the mission's path
needs (:mod:`transfer.feasibility`), is not driven into the bend it cannot follow. The check runs on the first
running tick after a start (and after a new mission's path): it pauses the mission, typed ``outside_assumption``,
with a status text naming the path's bend and what the vehicle turns; a person who resumes drives on (the
operator wins; the corridor still stops the vehicle where it leaves).

What was measured comes from the station's configuration (``[transfer] turn_reach``, written by ``scmbridge demo
--sitl``'s identification, :mod:`bridge.tools.demo_identify`); nothing measured, nothing checked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from transfer.feasibility import Outside, Reach, outside_assumption


@dataclass
class AssumptionCheck:
    """See the module docstring. ``armed``: the next running tick checks (a start, a new path)."""

    reach: Reach | None
    armed: bool = True

    @classmethod
    def from_config(cls, turn_reach: list[float], needs_speed: bool) -> AssumptionCheck:
        """From ``[transfer] turn_reach`` ([right, left, speed]; empty: nothing measured) of a learner that needs
        speed to turn (one that turns in place turns any curvature)."""
        if not needs_speed or len(turn_reach) != 3:
            return cls(None)
        right, left, speed = (float(x) for x in turn_reach)
        return cls(Reach(right=right, left=left, speed=speed))

    def arm(self) -> None:
        """A start or a new path: the next running tick checks it."""
        self.armed = True

    def check(self, points: np.ndarray, corridor_m: float, from_s: float) -> Outside | None:
        """On a running tick: the path's bend this vehicle cannot follow from arc length ``from_s`` on (once per
        arming), else None."""
        if not self.armed or self.reach is None:
            return None
        self.armed = False
        return outside_assumption(points, self.reach, corridor_m, from_s)


__all__ = ["AssumptionCheck"]
